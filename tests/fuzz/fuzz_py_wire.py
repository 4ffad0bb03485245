"""libFuzzer target (atheris) for the Python receivers' decoding: what the
controllers' links (ftc.plant.lcm_link), ftc.replay (ftc.plant.log) and the
push tool (ftc.control.run.policy_weights) run on every buffer they take.
Properties checked on every input:

* decode_state and decode_ack never raise, and refuse with a reason or accept:
  a state that is exactly one message of the plant's shape (it re-encodes to
  as many bytes; booleans make the bytes themselves not canonical), an ack
  whose reason is at most MAX_REASON characters and that re-encodes;
* Auth.verify refuses bytes not signed with the key as a bad signature, never
  raising; the input signed with the key verifies once, to itself, then is a
  replay.

Run by scripts/fuzz.sh (target fuzz_py_wire); needs atheris (pip).
"""

import sys

import atheris

with atheris.instrument_imports(include=["ftc.plant.wire", "ftc.plant.signing"]):
    from ftc.plant import signing, wire

from ftc.common.constants import NUM_ENGINES, NUM_TANKS

KEY = bytes(range(32))
NOW_US = 1_700_000_000_000_000  # a fixed clock: the signer's timestamps rise from it
RECEIVER = signing.Auth(KEY, not_before_us=0)
SENDER = signing.Auth(KEY)


def test_one_input(data: bytes) -> None:
    msg, why = wire.decode_state(data)
    if (msg is None) == (why is None):
        raise AssertionError(f"decode_state: {msg!r}, {why!r}")
    if msg is not None:
        if (msg.num_tanks, msg.num_engines) != (NUM_TANKS, NUM_ENGINES):
            raise AssertionError("a state of another shape accepted")
        if len(msg.encode()) != len(data):
            raise AssertionError("an accepted state is not exactly the buffer")
    ack, why = wire.decode_ack(data)
    if (ack is None) == (why is None):
        raise AssertionError(f"decode_ack: {ack!r}, {why!r}")
    if ack is not None:
        # (lcm-gen decodes the reason's bytes with errors replaced, so an
        # accepted ack re-encodes, but not always to as many bytes)
        ack.encode()
        if len(ack.reason) > ack.MAX_REASON:
            raise AssertionError("an accepted ack's reason is over MAX_REASON")
    if RECEIVER.verify("FUZZ_STATE", data, NOW_US) != (None, "bad signature"):
        raise AssertionError("unsigned bytes passed the check")
    signed = SENDER.sign("FUZZ_STATE", data, NOW_US)
    if RECEIVER.verify("FUZZ_STATE", signed, NOW_US) != (data, ""):
        raise AssertionError("the signed input did not verify to itself")
    if RECEIVER.verify("FUZZ_STATE", signed, NOW_US)[1] != "replay":
        raise AssertionError("the signed input verified twice")


if __name__ == "__main__":
    atheris.Setup(sys.argv, test_one_input)
    atheris.Fuzz()
