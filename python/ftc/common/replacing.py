"""``--overwrite``: results replaced deliberately, and still never lost by accident.

The old results are moved aside into ``DIR/.replaced`` (a rename: nothing is
copied or deleted) once the new run has passed its checks and holds the
directory's lock. They are deleted only when the new results have proved
themselves (:meth:`Replacement.commit`: an interval run's first checkpoint,
an orchestrator's completed run list), and moved back if the new run fails
before that (:meth:`Replacement.restore`). A holder killed in between leaves
``.replaced`` behind; the next ``--overwrite`` keeps that original and
discards the partial results it replaces, and the next finished checkpoint
of a resumed run commits it.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Callable, Iterable

from ftc.common.errors import StorageError

STASH = ".replaced"


class Replacement:
    """The replacement of the results in ``directory``. ``entries``: which of
    its entries are results (names, or a function of the directory giving
    them); the lock files and the stash itself never are."""

    def __init__(self, directory: Path | str,
                 entries: Iterable[str] | Callable[[Path], Iterable[str]]) -> None:
        self.directory = Path(directory)
        self.stash = self.directory / STASH
        self._entries = entries

    def _present(self) -> list[str]:
        names = self._entries(self.directory) if callable(self._entries) else self._entries
        return [n for n in names if n != STASH and not n.endswith(".lock")
                and os.path.lexists(self.directory / n)]

    def stash_old(self) -> list[str]:
        """Move the present results into the stash; returns their names. With a
        stash already there (an earlier --overwrite that never finished), that
        original is kept and the partial results beside it are removed."""
        try:
            if self.stash.is_dir():
                for name in self._present():
                    _remove(self.directory / name)
                return sorted(os.listdir(self.stash))
            present = self._present()
            if present:
                self.stash.mkdir()
                for name in present:
                    os.rename(self.directory / name, self.stash / name)
            return present
        except OSError as e:
            raise StorageError(f"cannot move the results of {self.directory} aside into "
                               f"{self.stash}: {e.strerror or e}") from None

    def commit(self) -> None:
        """The new results stand: the replaced ones are deleted."""
        if self.stash.is_dir():
            shutil.rmtree(self.stash, ignore_errors=True)

    def restore(self) -> None:
        """The new run failed before it proved itself: its results are removed
        and the replaced ones moved back."""
        if not self.stash.is_dir():
            return
        try:
            for name in self._present():
                _remove(self.directory / name)
            for name in os.listdir(self.stash):
                os.rename(self.stash / name, self.directory / name)
            self.stash.rmdir()
        except OSError as e:
            raise StorageError(f"cannot move the replaced results back from {self.stash}: "
                               f"{e.strerror or e}") from None


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    else:
        path.unlink(missing_ok=True)
