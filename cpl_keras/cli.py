"""What every command line of the package shares.

* ``Parser``: argparse with one error format, ``<prog>: error: <one line>``
  on stderr and exit status 2 (no usage block);
* ``one_line(error)``: the first line of an exception's message (its type's
  name when it has none);
* ``fail(prog, error)``: print that error line, return 2 (for ``main``);
* ``command_line(prog, argv)``: the command as it was typed, quoted, for the
  files a command writes (config.json, tables, dataset metadata);
* ``positive_int``, ``non_negative_int``, ``positive_float``: argparse types
  whose errors name the flag (``argument --seed: must be ...``);
* ``check_output_file(path)``, ``make_parent(path)``: an output file's path
  checked without writing anything (its missing folders may be created:
  their nearest existing ancestor is a writable folder), then its folders
  created just before it is written;
* ``interruptible()``, ``check_interrupt()``, ``interrupted(prog, resume)``:
  Ctrl-C (SIGINT). Inside ``interruptible()`` one SIGINT raises ``Interrupted``
  in the main thread and is remembered, so that a library that swallows the
  exception still stops at the next ``check_interrupt()`` (training checks
  between batches); the command then prints one line (with how to resume) and
  exits 130.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import shlex
import signal
import sys
import threading


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


# ---------------------------------------------------------------------------
# Numeric arguments (checked when parsed, before anything is written)
# ---------------------------------------------------------------------------
def _integer(text, minimum, what):
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be {what}, got {text!r}") from None
    if value < minimum:
        raise argparse.ArgumentTypeError(f"must be {what}, got {value}")
    return value


def positive_int(text):
    """argparse type: an integer >= 1."""
    return _integer(text, 1, "a positive integer")


def non_negative_int(text):
    """argparse type: an integer >= 0."""
    return _integer(text, 0, "a non-negative integer")


def positive_float(text):
    """argparse type: a finite number > 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
    return value


# ---------------------------------------------------------------------------
# Output files
# ---------------------------------------------------------------------------
def check_output_file(path):
    """``path`` as a string if a file can be written there, missing folders
    included; ValueError (one line) otherwise. Writes nothing."""
    if not isinstance(path, (str, os.PathLike)) or not os.fspath(path):
        raise ValueError(f"output path must be a non-empty path, got {path!r}")
    path = os.fspath(path)
    if os.path.isdir(path):
        raise ValueError(f"output path is a directory: {path}")
    directory = os.path.dirname(os.path.abspath(path))
    ancestor = directory
    while not os.path.exists(ancestor):
        ancestor = os.path.dirname(ancestor)
    if not os.path.isdir(ancestor):
        raise ValueError(f"cannot create the output directory {directory}: {ancestor} is a file")
    if not os.access(ancestor, os.W_OK):
        what = "output directory" if ancestor == directory else "directory"
        raise ValueError(f"{what} is not writable: {ancestor}")
    return path


def make_parent(path):
    """Create the missing folders above the output file ``path``."""
    os.makedirs(os.path.dirname(os.path.abspath(os.fspath(path))), exist_ok=True)


# ---------------------------------------------------------------------------
# Ctrl-C
# ---------------------------------------------------------------------------
#: Exit status of a command stopped by Ctrl-C (128 + SIGINT, as a shell reports it).
INTERRUPTED = 130


class Interrupted(KeyboardInterrupt):
    """Ctrl-C (SIGINT) during a command run inside ``interruptible()``."""


_pending = threading.Event()


def check_interrupt():
    """Raise ``Interrupted`` when a SIGINT arrived inside ``interruptible()``
    (for loops that a swallowed exception would otherwise carry on)."""
    if _pending.is_set():
        raise Interrupted()


@contextlib.contextmanager
def interruptible():
    """Within the block, SIGINT raises ``Interrupted`` (a ``KeyboardInterrupt``)
    and is remembered for ``check_interrupt()``. Outside the main thread it
    does nothing (signal handlers can be set there only), nor in a process
    started with SIGINT ignored."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        _pending.set()
        raise Interrupted()

    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        # started with Ctrl-C ignored (nohup, a background job of a script)
        yield
        return
    def unraisable(report, chain=sys.unraisablehook):
        # A SIGINT that lands in a callback whose exceptions Python ignores
        # (a garbage-collection callback of JAX, say) would print a
        # traceback and be lost; it stays pending for check_interrupt().
        if not isinstance(report.exc_value, Interrupted):
            chain(report)

    _pending.clear()
    previous = signal.signal(signal.SIGINT, handler)
    previous_hook, sys.unraisablehook = sys.unraisablehook, unraisable
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        sys.unraisablehook = previous_hook
        _pending.clear()


def interrupted(prog, resume=None, note=None):
    """Print ``<prog>: interrupted`` on one line on stderr, with how to resume
    (``resume``: the command) or another ``note``; return 130."""
    line = f"{prog}: interrupted"
    if resume:
        line += f"; to resume, run the same command again: {resume}"
    elif note:
        line += f"; {note}"
    print(line, file=sys.stderr, flush=True)
    return INTERRUPTED
