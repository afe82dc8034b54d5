"""The package's one error type for problems a user can fix: a missing or
malformed file, a bad argument, a run directory that does not fit. Each
module's own error (``DatasetError``, ``RunError``, ``TrainingError``, ...)
derives from ``Error``; its message is one line that names the problem, and
a command line prints it as ``<prog>: error: <message>`` and exits with
status 2 (``cli.fail``). ``Error`` is a ``ValueError``, so code that catches
``ValueError`` keeps working. Like ``cpl_keras.files``, this module imports
nothing of the package."""

from __future__ import annotations


class Error(ValueError):
    """A problem the user can fix, said in one line."""
