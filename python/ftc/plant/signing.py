"""Message authentication on the bus, the Python side of cpp/plant/lcm/signing.h
(the same bytes): with a shared key, every message carries

    payload | link id (1 byte) | timestamp (6 bytes, big-endian, 10 us units since
    the epoch) | HMAC-SHA256(key, channel | 0x00 | payload | link id | timestamp)[:16]

and a receiver refuses a bad or missing MAC ("bad signature"), a timestamp not
above its link's last ("replay") or older than the window ("old timestamp").
A receiver's links start at its own start: what was signed before this process
started (recorded off the bus, replayed to a restarted receiver with the same
key within the window) is a replay too."""

from __future__ import annotations

import hashlib
import hmac
import os
import secrets
import stat
import time
from pathlib import Path

MAC_BYTES = 16
TRAILER_BYTES = 1 + 6 + MAC_BYTES
TICK_US = 10
MIN_KEY_BYTES = 16
WINDOW_US = 30_000_000
# the environment variable a launched plant takes its per-run key from (hex)
KEY_VARIABLE = "FTC_BUS_KEY"
# when this process started (imported the module, before any link subscribed)
STARTED_US = time.time_ns() // 1000


def new_key() -> bytes:
    """A fresh 256-bit key (one per launched plant and run)."""
    return secrets.token_bytes(32)


MAX_KEY_FILE_BYTES = 4096  # a 256-bit key is 64 hex digits and a newline


def load_key(path: str | os.PathLike) -> bytes:
    """The key in ``path`` (hex text); ValueError naming the file if others
    can read or write it, it is not a regular file of at most
    MAX_KEY_FILE_BYTES (a directory, a FIFO that would block, a device that
    never ends), or it is no key. Opened without blocking and checked on the
    open descriptor, so the file checked is the file read."""
    path = Path(path)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as e:
        raise ValueError(f"{path}: cannot read the key file ({e.strerror})") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise ValueError(f"{path}: the key file is not a regular file")
        if st.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
            raise ValueError(f"{path}: the key file is readable or writable by others "
                             "(chmod 600 it)")
        if st.st_size > MAX_KEY_FILE_BYTES:
            raise ValueError(f"{path}: the key file has {st.st_size} bytes (a key file has at "
                             f"most {MAX_KEY_FILE_BYTES})")
        raw = os.read(fd, MAX_KEY_FILE_BYTES + 1)
    except OSError as e:
        raise ValueError(f"{path}: cannot read the key file ({e.strerror})") from None
    finally:
        os.close(fd)
    try:
        key = bytes.fromhex("".join(raw.decode("ascii").split()))
    except ValueError:  # (UnicodeDecodeError included)
        raise ValueError(f"{path}: not hex") from None
    if len(key) < MIN_KEY_BYTES:
        raise ValueError(f"{path}: a key is at least {2 * MIN_KEY_BYTES} hex digits")
    return key


def _mac(key: bytes, channel: str, payload: bytes, link_and_time: bytes) -> bytes:
    data = channel.encode() + b"\0" + payload + link_and_time
    return hmac.new(key, data, hashlib.sha256).digest()[:MAC_BYTES]


class Auth:
    """Signs what one link publishes and checks what it receives."""

    def __init__(self, key: bytes, window_us: int = WINDOW_US,
                 not_before_us: int = STARTED_US) -> None:
        """not_before_us: every link's floor (a timestamp at or below it is a
        replay); default the process's start."""
        self.key, self.window_ticks = key, window_us // TICK_US
        self.link_id = secrets.randbelow(255) + 1  # the plant signs as link 0
        self._last_sent = 0
        self._last_seen: dict[int, int] = {}
        self._floor = max(0, not_before_us // TICK_US - 1)

    def sign(self, channel: str, payload: bytes, now_us: int | None = None) -> bytes:
        now_us = time.time_ns() // 1000 if now_us is None else now_us
        ts = max(now_us // TICK_US, self._last_sent + 1)
        self._last_sent = ts
        tail = bytes([self.link_id]) + ts.to_bytes(6, "big")
        return payload + tail + _mac(self.key, channel, payload, tail)

    def verify(self, channel: str, data: bytes,
               now_us: int | None = None) -> tuple[bytes | None, str]:
        """(payload, "") or (None, the cause: "bad signature", "replay", "old timestamp")."""
        if len(data) < TRAILER_BYTES:
            return None, "bad signature"
        n = len(data) - TRAILER_BYTES
        payload, tail, mac = data[:n], data[n:n + 7], data[n + 7:]
        if not hmac.compare_digest(_mac(self.key, channel, payload, tail), mac):
            return None, "bad signature"
        link, ts = tail[0], int.from_bytes(tail[1:], "big")
        if ts <= self._last_seen.get(link, self._floor):
            return None, "replay"
        now_us = time.time_ns() // 1000 if now_us is None else now_us
        if ts < now_us // TICK_US - self.window_ticks:
            return None, "old timestamp"
        self._last_seen[link] = ts
        return payload, ""
