"""Message authentication on the bus, the Python side of cpp/plant/lcm/signing.h
(the same bytes): with a shared key, every message carries

    payload | link id (1 byte) | timestamp (6 bytes, big-endian, 10 us units since
    the epoch) | HMAC-SHA256(key, channel | 0x00 | payload | link id | timestamp)[:16]

and a receiver refuses a bad or missing MAC ("bad signature"), a timestamp not
above its link's last ("replay") or older than the window ("old timestamp")."""

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


def new_key() -> bytes:
    """A fresh 256-bit key (one per launched plant and run)."""
    return secrets.token_bytes(32)


def load_key(path: str | os.PathLike) -> bytes:
    """The key in ``path`` (hex text); ValueError naming the file if others
    can read or write it, or it is no key."""
    path = Path(path)
    try:
        mode = path.stat().st_mode
        text = path.read_text()
    except OSError as e:
        raise ValueError(f"{path}: cannot read the key file ({e.strerror})") from None
    if mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise ValueError(f"{path}: the key file is readable or writable by others (chmod 600 it)")
    try:
        key = bytes.fromhex("".join(text.split()))
    except ValueError:
        raise ValueError(f"{path}: not hex") from None
    if len(key) < MIN_KEY_BYTES:
        raise ValueError(f"{path}: a key is at least {2 * MIN_KEY_BYTES} hex digits")
    return key


def _mac(key: bytes, channel: str, payload: bytes, link_and_time: bytes) -> bytes:
    data = channel.encode() + b"\0" + payload + link_and_time
    return hmac.new(key, data, hashlib.sha256).digest()[:MAC_BYTES]


class Auth:
    """Signs what one link publishes and checks what it receives."""

    def __init__(self, key: bytes, window_us: int = WINDOW_US) -> None:
        self.key, self.window_ticks = key, window_us // TICK_US
        self.link_id = secrets.randbelow(255) + 1  # the plant signs as link 0
        self._last_sent = 0
        self._last_seen: dict[int, int] = {}

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
        if ts <= self._last_seen.get(link, 0):
            return None, "replay"
        now_us = time.time_ns() // 1000 if now_us is None else now_us
        if ts < now_us // TICK_US - self.window_ticks:
            return None, "old timestamp"
        self._last_seen[link] = ts
        return payload, ""
