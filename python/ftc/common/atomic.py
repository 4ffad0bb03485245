"""Atomic file writes, the only ones in the package: write to a temporary file
in the target's directory, then ``os.replace`` it over the target, so a reader
(or a run killed at any moment) sees either the old file or the complete new
one, never a partial one. A write that fails (disk full, unwritable directory)
removes its temporary file and raises :class:`StorageError` naming the path.
The file gets the mode any other tool would give it (0666 less the umask), not
the 0600 of a temporary file, so a group sharing a results directory reads it."""

from __future__ import annotations

import csv
import io
import json
import os
import tempfile
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

from ftc.common.errors import StorageError


def current_umask() -> int:
    """The process's umask, read without changing it (Linux's /proc; elsewhere
    the set-and-restore of os.umask)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _atomic(path: Path | str, write: Callable[[Any], None], binary: bool) -> None:
    path = Path(path)
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
        os.fchmod(fd, 0o666 & ~current_umask())
        with os.fdopen(fd, "wb" if binary else "w", **({} if binary else {"newline": ""})) as f:
            write(f)
            f.flush()
        os.replace(tmp, path)
        tmp = None
    except OSError as e:
        raise StorageError(f"cannot write {path}: {e.strerror or e}") from None
    except RuntimeError as e:  # torch.save reports a failed write as RuntimeError
        raise StorageError(f"cannot write {path}: {str(e).splitlines()[0]}") from None
    finally:
        if tmp is not None and os.path.exists(tmp):
            os.unlink(tmp)


def atomic_write_text(path: Path | str, text: str) -> None:
    """Write ``text`` to ``path`` atomically (creating its directory)."""
    _atomic(path, lambda f: f.write(text), binary=False)


def atomic_write_bytes(path: Path | str, data: bytes) -> None:
    _atomic(path, lambda f: f.write(data), binary=True)


def atomic_write_csv(path: Path | str, header: Sequence[str], rows: Iterable[Sequence],
                     lineterminator: str = "\r\n") -> None:
    """Write a CSV file (header, then rows) atomically (csv's default line ends)."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator=lineterminator)
    writer.writerow(header)
    writer.writerows(rows)
    atomic_write_text(path, buf.getvalue())


def _json_default(o: Any) -> Any:
    """numpy scalars and arrays as numbers and lists; anything else (paths) as text."""
    if hasattr(o, "tolist"):
        return o.tolist()
    return str(o)


def atomic_write_json(path: Path | str, obj: Any, indent: int | None = 2) -> None:
    """Write ``obj`` as JSON (numpy values as lists, paths as strings) atomically."""
    atomic_write_text(path, json.dumps(obj, indent=indent, default=_json_default) + "\n")


def atomic_torch_save(path: Path | str, obj: Any) -> None:
    """``torch.save`` atomically (checkpoints, cached policies)."""
    import torch

    _atomic(path, lambda f: torch.save(obj, f), binary=True)
