"""Errors that a user can act on, as opposed to bugs.

The command line prints one of these as a single line and exits with its ``exit_code``
(2: the input, a checkpoint or a resume was refused; 3: training diverged); anything else is a
bug and keeps its traceback. Configuration checks raise ``ValueError`` naming the field, its
value and the allowed range; the command line treats those as user errors too, as long as they
are raised while the command's arguments are checked, before any work.
"""

from __future__ import annotations


class RunError(Exception):
    """A run refused or stopped for a reason the user can act on."""

    exit_code = 2


class CheckpointError(RunError):
    """A checkpoint that cannot be read as written: missing part, truncated, bad digest, or one
    that does not belong to this run."""


class TooLargeError(RunError):
    """The requested program does not fit in the memory of the devices present."""


class DivergedError(RunError):
    """A run's loss, gradients or parameters became non-finite; the last good checkpoint is
    kept."""

    exit_code = 3
