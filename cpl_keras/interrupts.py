"""Ctrl-C (SIGINT) and SIGTERM for the commands: one line, exit 130, no
half-written file, no crash in the interpreter's teardown.

* ``interruptible()``, ``check_interrupt()``, ``interrupted(prog, resume)``:
  Ctrl-C (SIGINT). Inside ``interruptible()`` one SIGINT raises ``Interrupted``
  in the main thread and is remembered, so that a library that swallows the
  exception still stops at the next ``check_interrupt()`` (training checks
  between batches); the command then prints one line (with how to resume) and
  exits 130. An exception that a Ctrl-C caused (what it stopped half-way
  raised something else) ends the command the same way.
* ``run(main, prog)``: every command's one exit path (``if __name__ ==
  "__main__": cli.run(main, PROG)``): ``main()``'s exit status, or after a
  Ctrl-C that ``main`` did not handle one line and 130. An interrupted
  process ends at once (``os._exit``) without the interpreter's teardown:
  that teardown, with XLA's compilation threads still at work, is where a
  Ctrl-C used to end in a segmentation fault (exit 139).

(``python -m cpl_keras.X``'s Ctrl-C guard before X's imports, until ``run``
takes over, is the package's first statement: ``cpl_keras/__init__.py``.)
"""

from __future__ import annotations

import _thread
import contextlib
import gc
import os
import signal
import sys
import threading
import time

from cpl_keras import files
from cpl_keras.errors import Error, fail

# ---------------------------------------------------------------------------
# Ctrl-C
# ---------------------------------------------------------------------------
#: Exit status of a command stopped by Ctrl-C (128 + SIGINT, as a shell reports it).
INTERRUPTED = 130
#: Exit status of a command stopped by SIGTERM (128 + SIGTERM), outside a
#: process group (whose SIGTERM is its partners' Ctrl-C: ``terminate``).
TERMINATED = 143


class Interrupted(KeyboardInterrupt):
    """Ctrl-C (SIGINT) during a command run inside ``interruptible()``."""


_pending = threading.Event()
#: Set when the stop that is pending came by SIGTERM (``_sigterm``): the
#: command's line says so and it exits ``TERMINATED``.
_terminated = threading.Event()
#: Whether this process has claimed its "interrupted" line (``interrupted``):
#: set under ``_claim`` by the one caller that prints it.
_announced = threading.Event()
#: Set once that line has been printed (the other callers wait for it).
_printed = threading.Event()
_claim = threading.Lock()
#: Seconds ``run`` gives a command to end by itself after a Ctrl-C before it
#: ends the process (``_watchdog``).
GRACE_S = 5.0
#: Seconds between deliveries of a Ctrl-C that could not be raised yet.
REDELIVER_S = 0.2
#: Seconds a caller of ``interrupted`` that did not claim the line waits for
#: the one that did to print it.
LINE_WAIT_S = 5.0


def check_interrupt():
    """Raise ``Interrupted`` when a SIGINT arrived inside ``interruptible()``
    (for loops that a swallowed exception would otherwise carry on)."""
    if _pending.is_set():
        raise Interrupted()


def _in_import(frame):
    """Whether ``frame`` (where the main thread was when a signal came) is
    inside an import: an exception raised there can leave a native module
    half initialised (jaxlib then crashed with a segmentation fault)."""
    while frame is not None:
        if frame.f_code.co_filename.startswith("<frozen importlib"):
            return True
        frame = frame.f_back
    return False


def _handler(signum, frame):
    """SIGINT: remembered for ``check_interrupt()``, raised as ``Interrupted``
    unless the main thread is inside an import (then ``run``'s watchdog
    delivers it again a moment later)."""
    _pending.set()
    if not _in_import(frame):
        raise Interrupted()


def _sigterm(signum, frame):
    """SIGTERM (a ``kill``, a scheduler) in a command run by ``run``: the
    same stop as Ctrl-C (the last completed epoch kept, one line), said as a
    termination, exit ``TERMINATED``."""
    _terminated.set()
    _handler(signal.SIGINT, frame)


def _unraisable(report, chain):
    # A SIGINT that lands in a callback whose exceptions Python ignores
    # (a garbage-collection callback of JAX, say) would print a traceback
    # and be lost; it stays pending for check_interrupt() (and ``run``'s
    # watchdog delivers it again).
    if not isinstance(report.exc_value, Interrupted):
        chain(report)


@contextlib.contextmanager
def interruptible():
    """Within the block, SIGINT raises ``Interrupted`` (a ``KeyboardInterrupt``)
    and is remembered for ``check_interrupt()``; any other exception that
    ends the block once a Ctrl-C has come is taken for the Ctrl-C (raised as
    ``Interrupted`` from it). Outside the main thread it does nothing
    (signal handlers can be set there only), nor in a process started with
    SIGINT ignored."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        # started with Ctrl-C ignored (nohup, a background job of a script)
        yield
        return

    def unraisable(report, chain=sys.unraisablehook):
        _unraisable(report, chain)

    outermost = signal.getsignal(signal.SIGINT) is not _handler
    if outermost:
        _pending.clear()
        _announced.clear()  # (a new command in this process: its own line)
        _printed.clear()
    # (a block inside another, train.py's inside ``run``'s, keeps a Ctrl-C
    # that came before it pending)
    previous = signal.signal(signal.SIGINT, _handler)
    previous_hook, sys.unraisablehook = sys.unraisablehook, unraisable
    try:
        yield
    except Exception as error:
        if _pending.is_set():
            # A Ctrl-C came first: this is what it stopped half-way (Keras
            # raised TypeError from a variable whose initialiser it had
            # cleared; its traceback, then Python's teardown, crashed).
            raise Interrupted() from error
        raise
    finally:
        signal.signal(signal.SIGINT, previous)
        sys.unraisablehook = previous_hook
        if outermost:
            _pending.clear()


def _watchdog(prog, note):
    """``run``'s guard thread. After a Ctrl-C it delivers the interrupt to the
    main thread again every ``REDELIVER_S`` while the command runs (one that
    a callback swallowed, or that came during an import), and after
    ``GRACE_S`` (a main thread stuck in a long native call, such as an XLA
    compilation) it ends the process itself: the command's line, the
    temporary files of unfinished atomic writes removed, exit 130."""
    while True:
        _pending.wait()
        deadline = time.monotonic() + GRACE_S
        while _pending.is_set() and time.monotonic() < deadline:
            time.sleep(REDELIVER_S)
            if _pending.is_set() and not _announced.is_set():
                _thread.interrupt_main()  # (not once the command is ending)
        if _pending.is_set():
            break
    files.remove_unfinished()
    interrupted(prog, note=note)  # (prints nothing when the command has)
    _exit_interrupted()


def _exit_interrupted():
    """End the process now with status 130 (143 after SIGTERM), stdout and
    stderr flushed."""
    exit_now(TERMINATED if _terminated.is_set() else INTERRUPTED)


#: Called (with no argument) just before this process ends at once
#: (``exit_now``): ``before_exit``.
_exit_hooks = []


def before_exit(callback):
    """Call ``callback()`` just before this process ends at once
    (``exit_now``), after its output is flushed: a process of a group tells
    its partners that it is leaving, and process 0 waits for them there
    (``cpl_keras.distributed``)."""
    _exit_hooks.append(callback)


def exit_now(status):
    """End the process now with ``status``, stdout and stderr flushed, the
    ``before_exit`` callbacks called, and without the interpreter's
    teardown: every way a command of the package ends at once goes here."""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    for callback in _exit_hooks:
        try:
            callback()
        except Exception:  # (the process ends all the same)
            pass
    os._exit(status)


def run(main, prog, note=None):
    """Run a command's ``main()`` and end the process with its exit status:
    the one exit path of every command of the package and of bench/.

    A ``KeyboardInterrupt`` that ``main`` let through prints
    ``interrupted(prog, note=note)``'s line; an ``errors.Error`` or
    ``OSError`` (a missing or malformed file, a bad argument) its one-line
    message, exit status 2; a ``SystemExit`` (argparse's ``--help`` and
    errors) its status. Whenever the status is 130 (an interruption,
    handled here or by ``main``), further Ctrl-Cs are ignored and the
    process ends with ``os._exit(130)`` once stdout and stderr are flushed
    (once ``main`` has returned, whatever its status, a Ctrl-C is ignored:
    the command's work is done):
    Python's teardown would wait on, or crash in, the XLA work a compiling
    command still has in flight (a segmentation fault, exit 139). Files are
    written atomically (``cpl_keras.files``), so an interrupted command has
    none half-written to clean up. A Ctrl-C is delivered again while the
    command runs on, and ``GRACE_S`` after it the process ends all the same
    (``_watchdog``). Any other status leaves through ``sys.exit``."""
    if threading.current_thread() is threading.main_thread() and \
            signal.getsignal(signal.SIGINT) is not signal.SIG_IGN:
        threading.Thread(target=_watchdog, args=(prog, note), daemon=True,
                         name="cpl_keras-ctrl-c").start()
    if threading.current_thread() is threading.main_thread() and \
            signal.getsignal(signal.SIGTERM) is signal.SIG_DFL:
        _terminated.clear()
        signal.signal(signal.SIGTERM, _sigterm)
    try:
        with interruptible():
            status = main()
    except KeyboardInterrupt:
        status = _end_interrupted(prog, note)
    except (Error, OSError) as error:  # (a missing or bad file: one line, 2; a
        status = fail(prog, error)       # reader gone from the pipe: silence, 141)
    except SystemExit as done:  # (argparse's --help and errors: the same way out)
        status = _exit_status(done)
    # The command is done: a Ctrl-C from here on, in the interpreter's
    # teardown, would end a finished command by SIGINT (exit -2, no line).
    _ignore_interrupts()
    if status in (INTERRUPTED, TERMINATED):
        gc.collect()  # (a process pool's semaphores released, not warned of as leaked)
        _exit_interrupted()
    if files.teardown_unsafe():  # (a file library left in a failed state)
        gc.collect()  # (what else the command let go of is released first)
        exit_now(status)
    sys.exit(status)


def _exit_status(done):
    """The exit status of the ``SystemExit`` ``done`` as Python gives it (a message: 1)."""
    if done.code is None or isinstance(done.code, int):
        return done.code or 0
    print(done.code, file=sys.stderr)
    return 1


def _end_interrupted(prog, note):
    """``run``'s answer to a ``KeyboardInterrupt``: Ctrl-C ignored from here
    on, the line printed unless the command or the watchdog has (a further
    Ctrl-C that lands before it is ignored is absorbed); returns 130."""
    while True:
        try:
            _ignore_interrupts()
            return interrupted(prog, note=note)
        except KeyboardInterrupt:
            continue


def _ignore_interrupts():
    """From here on a Ctrl-C is ignored (the process is already ending), and
    a SIGTERM ends it as the system does."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        if signal.getsignal(signal.SIGTERM) is _sigterm:
            signal.signal(signal.SIGTERM, signal.SIG_DFL)


#: Called (with no argument) when this process is interrupted, before its
#: line: ``on_interrupt``.
_interrupt_hooks = []


def on_interrupt(callback):
    """Call ``callback()`` when this process is interrupted (``interrupted``):
    a process of a group tells its partners (``cpl_keras.distributed``)."""
    _interrupt_hooks.append(callback)


def terminate(signum, frame):
    """A SIGTERM handler that stops the command as Ctrl-C does (set by a
    process of a group, whose partners must hear of it: a scheduler's
    SIGTERM then ends the whole group within seconds)."""
    _handler(signal.SIGINT, frame)


def interrupted(prog, resume=None, note=None):
    """Print ``<prog>: interrupted`` on one line on stderr (after SIGTERM
    ``<prog>: terminated (SIGTERM)``), with how to resume (``resume``: the
    command) or another ``note``; return 130 (143).

    The line is printed once per command, whichever path ends it: the first
    caller claims it (under a lock), calls the ``on_interrupt`` callbacks and
    prints; a later or concurrent caller (``run``'s watchdog beside the main
    thread, say) prints nothing and waits, up to ``LINE_WAIT_S``, until the
    first caller's line is out, so that a caller that then ends the process
    cannot cut it off."""
    with _claim:
        first = not _announced.is_set()
        _announced.set()
    status = TERMINATED if _terminated.is_set() else INTERRUPTED
    if not first:
        _printed.wait(LINE_WAIT_S)
        return status
    line = f"{prog}: " + ("terminated (SIGTERM)" if status == TERMINATED else "interrupted")
    if resume:
        line += f"; to resume, run the same command again: {resume}"
    elif note:
        line += f"; {note}"
    try:
        for callback in _interrupt_hooks:
            callback()
    finally:
        # (one write: stderr writes through, so print's line and its newline
        # were two, and another thread's output, -X importtime's in the main
        # thread, came between them)
        sys.stderr.write(line + "\n")
        sys.stderr.flush()
        _printed.set()
    return status
