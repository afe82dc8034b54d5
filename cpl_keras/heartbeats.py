"""A process group's partners, watched (``cpl_keras.distributed.join``
starts it): a process whose partner stops ends too, within seconds, with
one line, instead of waiting forever in a collective.

* Heartbeats: every ``BEAT_S`` each process counts up its own key in the
  group's coordination service and reads its partners'. A partner whose
  count has not moved for ``peer_timeout_s()`` (killed without a word), or
  a coordinator that no longer answers, ends this process with
  ``PARTNER_FAILED``.
* A stop: Ctrl-C or SIGTERM in one process (SIGTERM is Ctrl-C here) sets
  the group's stop key; the others read it and end with status 130.
* Leaving: process 0 hosts the coordination service, and JAX aborts a
  partner whose service vanishes while it still runs (a stack trace, exit
  -6) before it can print its line. So a partner says that it leaves, just
  before it ends (``cli.exit_now``), and after a stop process 0 waits for
  that word from every partner: process 0 leaves last.
"""

from __future__ import annotations

import atexit
import contextlib
import os
import signal
import sys
import threading
import time

from cpl_keras import cli, files

#: Seconds without a heartbeat after which a partner counts as gone
#: (environment: ``CPL_KERAS_PEER_TIMEOUT_S``).
PEER_TIMEOUT_S = 30.0
#: Seconds between a process's heartbeats (and its look at the others').
BEAT_S = 1.0
#: Seconds process 0 waits, once its partners have said that they are
#: leaving, before it ends (``_leave``).
LEAVE_MARGIN_S = 0.5
#: Exit status of a process whose partner failed (not interrupted).
PARTNER_FAILED = 1

#: The group watched and its coordination client (``start``); whether it is
#: stopping (a stop said by this process or read from a partner).
_watched = {"group": None, "client": None, "stopping": False}
#: Set at exit: the heartbeat thread ends (``_stop_watching``).
_stopping = threading.Event()


def start(group, client, prog):
    """Watch ``group``'s partners through ``client`` (JAX's coordination
    client) from now on; ``prog`` names this command in its last line.
    SIGTERM then stops the process as Ctrl-C does (JAX's own preemption
    handler, which would swallow it, is off: ``distributed.join``)."""
    _watched.update(group=group, client=client)
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, cli.terminate)
        cli.on_interrupt(_announce_stop)
    cli.before_exit(_leave)
    watcher = threading.Thread(target=_watch, args=(group, prog), daemon=True,
                               name="cpl_keras-partners")
    watcher.start()
    atexit.register(_stop_watching, watcher)


def _stop_watching(watcher):
    """At exit, before JAX leaves the group: end the heartbeat thread. A
    daemon thread still inside a call to the coordination service when the
    interpreter finalises is unwound out of C++ and aborts the process; and
    once process 0 has left, its partners' thread would take the service's
    end for a failure."""
    _stopping.set()
    watcher.join(timeout=10 * BEAT_S)


def peer_timeout_s():
    """``PEER_TIMEOUT_S``, or ``CPL_KERAS_PEER_TIMEOUT_S`` when set."""
    try:
        return float(os.environ.get("CPL_KERAS_PEER_TIMEOUT_S", PEER_TIMEOUT_S))
    except ValueError:
        return PEER_TIMEOUT_S


def _announce_stop(reason="interrupted"):
    """Tell the partners that this process is stopping (they stop too),
    unless one has already said so (its message stays)."""
    client, group = _watched["client"], _watched["group"]
    _watched["stopping"] = True
    if client is None or group is None:
        return
    try:
        client.key_value_set("cpl_keras/stop", f"process {group.process_id} {reason}",
                             allow_overwrite=False)
    except Exception:  # (a partner's message is there, or the coordinator is gone)
        pass


def _leave():
    """Just before this process ends at once (``cli.exit_now``): a partner
    says that it is leaving; process 0, once the group is stopping, waits
    until every partner has said so (or, one killed without a word, for
    ``peer_timeout_s()``). Process 0 hosts the coordination service, and a
    partner whose service vanishes while it still runs is aborted by JAX (a
    stack trace, exit -6) before it can print its line: so process 0 leaves
    last."""
    client, group = _watched["client"], _watched["group"]
    if client is None or group is None:
        return
    if not group.chief:
        with contextlib.suppress(Exception):  # (process 0 may be gone already)
            client.key_value_set(f"cpl_keras/left/{group.process_id}", "1",
                                 allow_overwrite=True)
        return
    if not _watched["stopping"]:
        return
    _stopping.set()  # (the heartbeat thread no longer takes a partner's end for a failure)
    waiting = set(range(1, group.num_processes))
    deadline = time.monotonic() + peer_timeout_s()
    while waiting and time.monotonic() < deadline:
        waiting = {p for p in waiting if _try_get(client, f"cpl_keras/left/{p}") is None}
        time.sleep(BEAT_S / 20)
    time.sleep(LEAVE_MARGIN_S)  # (from a partner's word to its end: microseconds)


def _watch(group, prog):
    """Heartbeats: every ``BEAT_S`` this process counts up its own key and
    reads its partners'. A partner that says it stopped (Ctrl-C, SIGTERM)
    ends this process with status 130; one whose count has not moved for
    ``peer_timeout_s()``, or a coordinator that no longer answers, with
    ``PARTNER_FAILED``. Either way with one line on stderr and the
    temporary files of unfinished writes removed."""
    client, beat, timeout = _watched["client"], 0, peer_timeout_s()
    seen = {p: (None, time.monotonic()) for p in range(group.num_processes)
            if p != group.process_id}
    while not _stopping.is_set():
        beat += 1
        try:
            client.key_value_set(f"cpl_keras/alive/{group.process_id}", str(beat),
                                 allow_overwrite=True)
            stop = _try_get(client, "cpl_keras/stop")
            if stop and not stop.startswith(f"process {group.process_id} "):
                _watched["stopping"] = True
                _end(prog, f"interrupted: {stop}; to resume, run the same command on every "
                           f"process", 130)
            now = time.monotonic()
            for peer, (last, since) in seen.items():
                value = _try_get(client, f"cpl_keras/alive/{peer}")
                if value != last:
                    seen[peer] = (value, now)
                elif now - since > timeout and not _watched["stopping"]:
                    _end(prog, f"error: process {peer} of {group.num_processes} gave no sign of "
                               f"life for {timeout:g} s; ending this one too (run the same "
                               f"command on every process to resume)", PARTNER_FAILED)
        except Exception as error:  # the coordination service is gone: process 0 ended
            if _stopping.is_set():
                return
            if group.chief:
                _end(prog, f"error: the process group's coordination failed "
                           f"({str(error).strip().splitlines()[0][:120]})", PARTNER_FAILED)
            _end(prog, f"error: lost process 0 at {group.coordinator}; ending this one too "
                       f"(run the same command on every process to resume)", PARTNER_FAILED)
        _stopping.wait(BEAT_S)


def _try_get(client, key):
    """The value of ``key`` in the coordination service, or None when unset."""
    try:
        return client.key_value_try_get(key)
    except Exception as error:  # NOT_FOUND is an exception; anything else goes up
        if "not found" in str(error).lower() or "NOT_FOUND" in str(error):
            return None
        raise


def _end(prog, message, status):
    """End this process at once with ``<prog>: <message>`` (one line)."""
    files.remove_unfinished()
    if status == cli.INTERRUPTED:
        cli.interrupted(prog, note=message.removeprefix("interrupted: "))
    else:
        print(f"{prog}: {message}", file=sys.stderr, flush=True)
    cli.exit_now(status)
