"""The package's one error type for problems a user can fix: a missing or
malformed file, a bad argument, a run directory that does not fit. Each
module's own error (``DatasetError``, ``RunError``, ``TrainingError``, ...)
derives from ``Error``; its message is one line that names the problem, and
a command line prints it as ``<prog>: error: <message>`` and exits with
status 2 (``fail``, also ``cli.fail``). ``Error`` is a ``ValueError``, so code that catches
``ValueError`` keeps working. Like ``cpl_keras.files``, this module imports
nothing of the package."""

from __future__ import annotations

import os
import sys


class Error(ValueError):
    """A problem the user can fix, said in one line."""


def one_line(error):
    """The first line of ``error``'s message (an exception or a string)."""
    text = str(error).strip()
    if text:
        return text.splitlines()[0]
    return type(error).__name__ if isinstance(error, BaseException) else "error"


#: Exit status of a command whose output's reader went away (128 + SIGPIPE,
#: as a shell reports ``yes | head -1``).
READER_GONE = 141


def fail(prog, error):
    """Print ``<prog>: error: <one line>`` to stderr; return the exit status 2.
    A ``BrokenPipeError`` (``| head``: stdout's reader has gone) is not an
    error to report: nothing is printed, stdout is pointed at /dev/null (so
    that flushing it at exit does not fail again) and the status is
    ``READER_GONE``, as for any Unix tool."""
    if isinstance(error, BrokenPipeError):
        try:
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        except (OSError, ValueError):
            pass
        return READER_GONE
    print(f"{prog}: error: {one_line(error)}", file=sys.stderr)
    return 2
