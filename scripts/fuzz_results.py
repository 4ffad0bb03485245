#!/usr/bin/env python3
"""Summarise scripts/fuzz.sh runs into a committed result file.

    FUZZ_RUNS=10000000 bash scripts/fuzz.sh 0 fuzz_policy ...   # one target at a time
    .venv/bin/python scripts/fuzz_results.py --out docs/results/fuzz.csv fuzz_policy ...

Reads each target's libFuzzer log (build-fuzz/<target>.log, written by
scripts/fuzz.sh with -print_final_stats=1) and writes one row per target: the
receivers whose decoder it runs, the inputs executed, exec/s, the wall time,
libFuzzer's peak RSS (its own process: ASan's shadow memory included, not a
receiver's) and the crashes found (a sanitizer report, a deadly signal, a
failed property or a leak, each of which ends the run). scripts/render_results.py
renders the file into docs/deploy.md.
"""

from __future__ import annotations

import argparse
import platform
import re
import subprocess
import sys
from datetime import date
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
# target -> what it decodes, and which receivers run that decoder
COVERS = {
    "fuzz_valve_command": "`wire::Decode<valve_command_t>`: the plant; lcm_echo",
    "fuzz_plant_control": "`wire::Decode<plant_control_t>`: the plant; lcm_echo",
    "fuzz_messages": "the plant's command handling (decode; ValvesFromCommand)",
    "fuzz_plant_state": "`wire::Decode<plant_state_t>`: the policy node",
    "fuzz_policy": "`wire::Decode<policy_t>`: the policy node's pushes",
    "fuzz_policy_ack": "`wire::Decode<policy_ack_t>`",
    "fuzz_policy_v2": "`DecodePolicyV2`: the policy node's history-window pushes",
    "fuzz_signed": "`signing::Verifier` then every `wire::Decode`: the keyed plant; node; lcm_echo",
    "fuzz_py_wire": "`decode_state`; `decode_ack`; `Auth.verify`: the Python links; ftc.replay; "
                    "the push tool",
    "fuzz_scenario": "the scenario file parser",
}
CRASH = re.compile(r"ERROR: (AddressSanitizer|UndefinedBehaviorSanitizer|LeakSanitizer|"
                   r"libFuzzer)|deadly signal|runtime error:|Uncaught Python exception")


def summarise(target: str, log: Path) -> list[str]:
    text = log.read_text(errors="replace")

    def stat(name: str) -> str:
        found = re.findall(rf"^stat::{name}:\s*(\d+)", text, re.M)
        return found[-1] if found else ""

    done = re.findall(r"^Done (\d+) runs in (\d+) second", text, re.M)
    crashes = len(CRASH.findall(text))
    return [target, COVERS.get(target, "?"), stat("number_of_executed_units"),
            stat("average_exec_per_sec"), done[-1][1] if done else "", stat("peak_rss_mb"),
            str(crashes), "yes" if done and not crashes else "no"]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("targets", nargs="+", help="fuzz targets (their logs in --logs)")
    parser.add_argument("--logs", type=Path, default=REPO / "build-fuzz",
                        help="where scripts/fuzz.sh wrote <target>.log")
    parser.add_argument("--out", type=Path, required=True, help="the result file to write")
    parser.add_argument("--command", default="FUZZ_RUNS=10000000 nice -n 10 bash scripts/fuzz.sh "
                        "0 TARGET, one target at a time",
                        help="the command that ran them (for the provenance line)")
    args = parser.parse_args(argv)
    missing = [t for t in args.targets if not (args.logs / f"{t}.log").is_file()]
    if missing:
        parser.error(f"no log for {', '.join(missing)} in {args.logs} (run scripts/fuzz.sh first)")
    rows = [summarise(t, args.logs / f"{t}.log") for t in args.targets]
    commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=REPO, capture_output=True,
                            text=True).stdout.strip() or "?"
    cpu = next((line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text()
                .splitlines() if line.startswith("model name")), platform.processor())
    head = ["target", "decoder_and_receivers", "inputs", "exec_per_s", "wall_s",
            "fuzzer_peak_rss_mb", "crashes", "completed"]
    lines = [f"# what: libFuzzer (C++ with ASan and UBSan; Python with atheris) on every bus "
             "decoder, each run to its inputs' count; peak RSS is the fuzzer's own process",
             f"# command: {args.command}", f"# commit: {commit}",
             f"# date: {date.today().isoformat()}", f"# machine: {cpu}, 2 cores shared with other "
             "work", ",".join(head)]
    lines += [",".join(f'"{c}"' if "," in c else c for c in r) for r in rows]
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines[-len(rows) - 1:]))
    return 0 if all(r[-1] == "yes" for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
