"""What every command line of the package shares.

* ``Parser``: argparse with one error format, ``<prog>: error: <one line>``
  on stderr and exit status 2 (no usage block), and a ``--help`` at most
  ``HELP_WIDTH`` characters wide whose usage line is short (``HelpFormatter``);
* ``one_line(error)``: the first line of an exception's message (its type's
  name when it has none);
* ``fail(prog, error)``: print that error line, return 2 (for ``main``);
* ``command_line(prog, argv)``: the command as it was typed, quoted, for the
  files a command writes (config.json, tables, dataset metadata);
* ``positive_int``, ``non_negative_int``, ``positive_float``: argparse types
  whose errors name the flag (``argument --seed: must be ...``);
* ``check_output_file(path)``, ``check_output_dir(path)``, ``make_parent(path)``:
  an output's path checked before the work, writing nothing (missing folders
  can be made, its device has space left; ``OutputError`` otherwise), then
  its folders created just before it is written;
* ``ProgressBar``: pairs done, their rate and the time left, on stderr;
* ``check_room(what, path, disk, memory)``: a command's estimate of the disk
  space and memory it needs, checked against what this machine has before
  any work (one line naming both, ``size_text`` for the sizes);
* the Ctrl-C machinery (``interruptible``, ``interrupted``, ``run``, ...):
  ``cpl_keras.interrupts``, its names also here.
"""

from __future__ import annotations

import argparse
import math
import os
import shlex
import shutil
import sys
import textwrap
import time

from cpl_keras.errors import Error, fail, one_line  # noqa: F401  (one_line: also here)
from cpl_keras.interrupts import (  # noqa: F401  (the commands reach them as cli.*)
    INTERRUPTED, Interrupted, before_exit, check_interrupt, exit_now,
    interrupted, interruptible, on_interrupt, run, terminate,
)


#: The widest line of a command's ``--help``, however wide the terminal.
HELP_WIDTH = 100


class HelpFormatter(argparse.HelpFormatter):
    """``--help`` as wide as the terminal up to ``HELP_WIDTH`` characters,
    with a usage line of the required arguments and ``[options]`` (each
    option is listed below it; the whole list made usage blocks of up to 17
    lines), its text wrapped between words only (``--time-budget`` was cut
    after ``--time-``)."""

    def __init__(self, prog, indent_increment=2, max_help_position=24, width=None):
        if width is None:
            width = min(shutil.get_terminal_size().columns - 2, HELP_WIDTH)
        super().__init__(prog, indent_increment, max_help_position, width)

    def add_usage(self, usage, actions, groups, prefix=None):
        if usage is None:  # (a flag and its value on one line: a no-break space between)
            words = [f"{action.option_strings[0]}\xa0"
                     f"{self._format_args(action, action.dest.upper())}"
                     if action.option_strings else self._format_args(action, action.dest)
                     for action in actions if action.required or not action.option_strings]
            indent = " " * len(f"usage: {self._prog} ")
            usage = "%(prog)s " + textwrap.fill(
                " ".join(words + ["[options]"]), self._width, initial_indent=indent,
                subsequent_indent=indent, break_on_hyphens=False)[len(indent):].replace("\xa0", " ")
        super().add_usage(usage, actions, groups, prefix)

    def _split_lines(self, text, width):  # (a flag is never cut at its hyphens)
        return textwrap.wrap(" ".join(text.split()), width, break_on_hyphens=False)

    def _fill_text(self, text, width, indent):
        return textwrap.fill(" ".join(text.split()), width, initial_indent=indent,
                             subsequent_indent=indent, break_on_hyphens=False)


class Parser(argparse.ArgumentParser):
    """An ArgumentParser whose errors are one line: ``<prog>: error: <message>``,
    exit 2; its help formatted by ``HelpFormatter``."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("formatter_class", HelpFormatter)
        super().__init__(*args, **kwargs)

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


def worker_count(text):
    """argparse type: a number of worker processes or threads, from 1 to
    this machine's CPUs (more would only crowd them: 100,000 started a storm
    of processes)."""
    value = _integer(text, 1, "a positive integer")
    cpus = os.cpu_count() or 1
    if value > cpus:
        raise argparse.ArgumentTypeError(f"must be at most {cpus}, the CPUs of this machine, "
                                         f"got {value}")
    return value


def non_negative_int(text):
    """argparse type: an integer >= 0."""
    return _integer(text, 0, "a non-negative integer")


def named_path(text):
    """``NAME=PATH`` as ``(name, path)``, both non-empty (the analyses'
    ``--run NAME=RUN_DIR``)."""
    name, sep, path = str(text).partition("=")
    if not sep or not name or not path:
        raise argparse.ArgumentTypeError(f"must be NAME=PATH, got {text!r}")
    return name, path


def path(text):
    """argparse type: a path, not empty (an empty one would name the working
    directory or a command's default)."""
    if not text.strip():
        raise argparse.ArgumentTypeError("must name a file or folder, got an empty path")
    return text


def positive_float(text):
    """argparse type: a finite number > 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
    return value


def non_negative_float(text):
    """argparse type: a finite number >= 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number >= 0, got {text!r}") from None
    if not (math.isfinite(value) and value >= 0):
        raise argparse.ArgumentTypeError(f"must be a number >= 0, got {text}")
    return value


def momentum(text):
    """argparse type: a number in [0, 1) (a moving average's momentum; 0: off)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number in [0, 1), got {text!r}") from None
    if not (math.isfinite(value) and 0 <= value < 1):
        raise argparse.ArgumentTypeError(f"must be a number in [0, 1), got {text}")
    return value


# ---------------------------------------------------------------------------
# Output files
# ---------------------------------------------------------------------------
class OutputError(Error):
    """An output path that cannot be written (one line naming it)."""


#: An output's device with less free space than this is full (a command's
#: tables, plots and exports take less).
MIN_FREE_BYTES = 1 << 20


def check_output_file(path):
    """``path`` as a string if a file can be written there, missing folders
    included, on a device with space left (``MIN_FREE_BYTES``);
    ``OutputError`` (one line) otherwise. Writes nothing."""
    if not isinstance(path, (str, os.PathLike)) or not os.fspath(path):
        raise OutputError(f"output path must be a non-empty path, got {path!r}")
    path = os.fspath(path)
    if os.path.isdir(path):
        raise OutputError(f"output path is a directory: {path}")
    _check_folder(os.path.dirname(os.path.abspath(path)))
    return path


def check_output_dir(path):
    """``path`` as a string if files can be written in the folder ``path``,
    made if missing, on a device with space left (``MIN_FREE_BYTES``);
    ``OutputError`` (one line) otherwise. Writes nothing."""
    path = os.fspath(path)
    if os.path.exists(path) and not os.path.isdir(path):
        raise OutputError(f"output directory is a file: {path}")
    _check_folder(os.path.abspath(path))
    return path


def _check_folder(directory):
    """``OutputError`` unless files can be written in ``directory`` or in
    the folders that would be made down to it."""
    ancestor = directory
    while not os.path.exists(ancestor):
        ancestor = os.path.dirname(ancestor)
    if not os.path.isdir(ancestor):
        raise OutputError(f"cannot create the output directory {directory}: {ancestor} is a file")
    if not os.access(ancestor, os.W_OK):
        what = "output directory" if ancestor == directory else "directory"
        raise OutputError(f"{what} is not writable: {ancestor}")
    try:
        device = os.statvfs(ancestor)
    except OSError:  # (no such call here: the writes will tell)
        return
    blocks = device.f_bfree if os.geteuid() == 0 else device.f_bavail
    free = blocks * device.f_frsize
    if free < MIN_FREE_BYTES:
        raise OutputError(f"no space left on the device of {ancestor}: {free // 1024} KiB free")


def make_parent(path):
    """Create the missing folders above the output file ``path``."""
    os.makedirs(os.path.dirname(os.path.abspath(os.fspath(path))), exist_ok=True)


def size_text(size):
    """A number of bytes in words: ``512 bytes``, ``75.3 KB``, ``9.3 GB``
    (decimal units, up to PB)."""
    if size < 1000:
        return f"{size:.0f} bytes"
    for unit in ("KB", "MB", "GB", "TB"):
        size /= 1000
        if size < 1000:
            return f"{size:.1f} {unit}"
    return f"{size / 1000:,.0f} PB"


def available_memory():
    """Bytes of memory a new allocation can have now (``MemAvailable`` of
    /proc/meminfo; elsewhere the free pages), or None when unknown."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, AttributeError):
        return None


def check_room(what, path, disk=0, memory=0):
    """Raise ValueError (one line) when ``what`` (a plural phrase, "500
    crops at 112 px") needs more disk space (``disk``: the fewest bytes its
    output file ``path`` can take, in the folder that holds or will hold
    it) or more memory (``memory`` bytes, an estimate) than this machine
    has free. Writes nothing."""
    folder = os.path.dirname(os.path.abspath(os.fspath(path)))
    while not os.path.isdir(folder):
        folder = os.path.dirname(folder)
    free = shutil.disk_usage(folder).free
    if disk > free:
        raise ValueError(f"{what} need at least {size_text(disk)} of disk; {size_text(free)} is "
                         f"free in {folder}")
    available = available_memory()
    if available is not None and memory > available:
        raise ValueError(f"{what} need about {size_text(memory)} of memory; "
                         f"{size_text(available)} is available")


class ProgressBar:
    """A command's progress bar on stderr (generation, import): pairs done
    of ``total`` (``done`` of them before this run, by the run it resumes),
    and the rate and time left measured on this run's own pairs."""

    def __init__(self, total, label, enabled, done=0):
        self.total, self.label, self.enabled = total, label, enabled
        self.start = time.perf_counter()
        self.done = self.initial = done
        self.open_line = False  # (a bar line not yet ended by a newline)

    def update(self, n):
        self.done += n
        if not self.enabled:
            return
        elapsed = time.perf_counter() - self.start
        rate = (self.done - self.initial) / max(elapsed, 1e-9)
        width = 30
        filled = int(width * self.done / self.total)
        eta = (self.total - self.done) / max(rate, 1e-9)
        # (the line's state first: a Ctrl-C lands just after the text as well)
        self.open_line = self.done < self.total
        sys.stderr.write(f"\r{self.label} [{'#' * filled}{'.' * (width - filled)}] "
                         f"{self.done}/{self.total} pairs {rate:6.1f} pairs/s ETA {eta:5.0f}s "
                         + ("" if self.open_line else "\n"))
        sys.stderr.flush()

    def close(self):
        """End the bar's line (an interruption's or error's line then starts
        on its own)."""
        if self.open_line:
            sys.stderr.write("\n")
            sys.stderr.flush()
            self.open_line = False
