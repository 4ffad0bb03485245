"""``--overwrite``: results replaced deliberately, and still never lost by accident.

The old results are moved aside into ``DIR/.replaced`` (a rename: nothing is
copied or deleted) once the new run has passed its checks and holds the
directory's lock. They are deleted only when the new results have proved
themselves (:meth:`Replacement.commit`: an interval run's first checkpoint,
an orchestrator's completed run list), and moved back if the new run fails
before that (:meth:`Replacement.restore`). A holder killed in between leaves
``.replaced`` behind: whoever next holds the directory commits it once the
results beside it have proved themselves (``proven``), and a next
``--overwrite`` before that keeps the original and discards the unproven
partial results it replaces. Every move is a rename within the directory,
and a stash is complete before it counts: it is built under a temporary
name and renamed to ``.replaced`` last.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Callable, Iterable

from ftc.common.errors import StorageError

STASH = ".replaced"
BUILDING = ".replacing"  # a stash being built (or taken apart): never the original


class Replacement:
    """The replacement of the results in ``directory``. ``entries``: which of
    its entries are results (names, or a function of the directory giving
    them); the lock files and the stash itself never are. ``proven``: whether
    the results now in the directory have proved themselves (an interval
    run's checkpoint, an orchestrator's finished run)."""

    def __init__(self, directory: Path | str,
                 entries: Iterable[str] | Callable[[Path], Iterable[str]],
                 proven: Callable[[Path], bool]) -> None:
        self.directory = Path(directory)
        self.stash = self.directory / STASH
        self._building = self.directory / BUILDING
        self._entries = entries
        self._proven = proven

    def _present(self) -> list[str]:
        names = self._entries(self.directory) if callable(self._entries) else self._entries
        return [n for n in names if not n.startswith(".replac") and not n.endswith(".lock")
                and os.path.lexists(self.directory / n)]

    def pending(self) -> bool:
        """Whether replaced results wait in the stash."""
        return self.stash.is_dir()

    def stash_old(self) -> list[str]:
        """Move the present results into the stash; returns their names. With a
        stash already there, the results beside it either proved themselves
        (the stash is deleted, then they are stashed) or are the partial ones
        of an --overwrite that never finished (they are removed; the stash,
        the original, stays)."""
        try:
            self._settle_building()
            if self.stash.is_dir():
                if not self._proven(self.directory):
                    for name in self._present():
                        _remove(self.directory / name)
                    return sorted(os.listdir(self.stash))
                self.commit()
            present = self._present()
            if present:
                self._building.mkdir()
                for name in present:
                    os.rename(self.directory / name, self._building / name)
                os.rename(self._building, self.stash)  # complete: now it counts
            return present
        except OSError as e:
            raise StorageError(f"cannot move the results of {self.directory} aside into "
                               f"{self.stash}: {e.strerror or e}") from None

    def settle(self) -> None:
        """Commit a stash whose replacement has proved itself (a resumed run's
        holder calls it: the one whose --overwrite was killed never did)."""
        if self.stash.is_dir() and self._proven(self.directory):
            self.commit()

    def commit(self) -> None:
        """The new results stand: the replaced ones are deleted (renamed out of
        the way first, so that a cut-short deletion leaves no half stash)."""
        if self.stash.is_dir():
            trash = self.directory / f".replaced-deleting-{os.getpid()}"
            os.rename(self.stash, trash)
            shutil.rmtree(trash, ignore_errors=True)

    def restore(self) -> None:
        """The new run failed before it proved itself: its results are removed
        and the replaced ones moved back."""
        if not self.stash.is_dir():
            return
        try:
            for name in self._present():
                _remove(self.directory / name)
            os.rename(self.stash, self._building)  # taken apart from here on
            self._settle_building()
        except OSError as e:
            raise StorageError(f"cannot move the replaced results back from {self.stash}: "
                               f"{e.strerror or e}") from None

    def _settle_building(self) -> None:
        """A stash cut short while being built or taken apart: its entries go
        back (the results they were are the newest complete ones)."""
        if not self._building.is_dir():
            return
        for name in os.listdir(self._building):
            target = self.directory / name
            if not os.path.lexists(target):
                os.rename(self._building / name, target)
            else:
                _remove(self._building / name)
        self._building.rmdir()


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    else:
        path.unlink(missing_ok=True)
