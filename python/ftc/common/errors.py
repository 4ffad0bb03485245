"""Errors that end a run, and the exit codes every command line uses.

    0  success
    1  a failure at run time not covered below
    2  bad input: a flag, a scenario file, a --resume directory whose config or
       checkpoint is corrupt or from another configuration, a plug-in's action
       that is not six valves of 0 or 1
    3  the plant stopped answering
    4  a non-finite number (observation, loss, gradient, weights)
    5  storage: a file could not be written (disk full, unwritable path)
"""

from __future__ import annotations

EXIT_OK = 0
EXIT_FAILURE = 1
EXIT_USAGE = 2
EXIT_PLANT_GONE = 3
EXIT_NON_FINITE = 4
EXIT_STORAGE = 5


class RunError(RuntimeError):
    """A run stopped; ``exit_code`` is what the command line exits with."""

    exit_code = EXIT_FAILURE


class UsageError(RunError):
    """Bad input (a flag, a file), found before or while the run starts."""

    exit_code = EXIT_USAGE


class CheckpointError(RunError):
    """A --resume directory's checkpoint or config is corrupt or does not match."""

    exit_code = EXIT_USAGE


class PlantLostError(RunError):
    """The plant stopped answering during the run."""

    exit_code = EXIT_PLANT_GONE


class NonFiniteError(RunError):
    """A non-finite observation, loss, gradient or weight."""

    exit_code = EXIT_NON_FINITE


class StorageError(RunError):
    """A result could not be written (disk full, unwritable path); nothing partial is left."""

    exit_code = EXIT_STORAGE
