"""What every command line of the package shares.

* ``Parser``: argparse with one error format, ``<prog>: error: <one line>``
  on stderr and exit status 2 (no usage block);
* ``one_line(error)``: the first line of an exception's message (its type's
  name when it has none);
* ``fail(prog, error)``: print that error line, return 2 (for ``main``);
* ``command_line(prog, argv)``: the command as it was typed, quoted, for the
  files a command writes (config.json, tables, dataset metadata).
"""

from __future__ import annotations

import argparse
import shlex
import sys


def one_line(error):
    """The first line of ``error``'s message (an exception or a string)."""
    text = str(error).strip()
    if text:
        return text.splitlines()[0]
    return type(error).__name__ if isinstance(error, BaseException) else "error"


def fail(prog, error):
    """Print ``<prog>: error: <one line>`` to stderr; return the exit status 2."""
    print(f"{prog}: error: {one_line(error)}", file=sys.stderr)
    return 2


class Parser(argparse.ArgumentParser):
    """An ArgumentParser whose errors are one line: ``<prog>: error: <message>``, exit 2."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {one_line(message)}\n")


def command_line(prog, argv=None):
    """The command line that ran ``prog`` with ``argv`` (default ``sys.argv[1:]``),
    shell-quoted; a script (``train.py``) is prefixed with ``python``."""
    args = list(sys.argv[1:] if argv is None else argv)
    head = f"python {prog}" if prog.endswith(".py") else prog
    return " ".join([head] + [shlex.quote(str(a)) for a in args])
