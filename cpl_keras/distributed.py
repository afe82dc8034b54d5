"""Training over several processes: one model, every process's devices.

Keras 3 on JAX trains one model over the devices of several processes (one
per host, say): ``jax.distributed`` connects them (``join``: what
``keras.distribution.initialize()`` does, with timeouts) and
``keras.distribution.DataParallel`` shards each global batch over all of
their devices, BatchNorm statistics included. What this module adds is the
project's side of it (the trainer reaches it through one object,
``cpl_keras.training.processes``):

* ``ProcessGroup`` and ``group_from_environment``: the group a process
  belongs to, from Keras's own variables (set on every process)::

      KERAS_DISTRIBUTION_JOB_ADDRESSES=host0:port   # process 0's address
      KERAS_DISTRIBUTION_NUM_PROCESSES=N
      KERAS_DISTRIBUTION_PROCESS_ID=i               # 0 .. N-1

  (``train.py --coordinator/--num-processes/--process-id`` set them).
* ``join(group)``: connect before any device is counted; from then on a
  process whose partner stops (Ctrl-C, SIGTERM, a kill) ends too, with one
  line, within seconds (``PEER_TIMEOUT_S`` for a partner that vanished
  without a word), instead of waiting forever in a collective.
* ``local_part``: each process's share of a global batch (each reads it
  from its own copy of the dataset file); ``check_same``: a value every
  process must agree on (the dataset, the split, the step counts, the
  resume point), checked before training so that a mismatch fails at once;
  ``broadcast``, ``barrier``: process 0 decides and writes, the others
  follow.
* ``global_batch``: a process-local batch as the global array a jitted
  function of the model's variables takes (the BatchNorm recompute);
  ``refuse_prediction``: ``model.predict`` fails under a multi-process
  distribution ("spans non-addressable devices"), so prediction runs after
  training, in one process (``evaluate.py``).

Only the JAX backend trains over several processes here (Keras's
``DataParallel`` across processes is JAX's). Upstream reports to respect:
keras-team/keras#18560 (multi-process tracking), openxla/xla#16430
(collectives with forced host devices).
"""

from __future__ import annotations

import atexit
import contextlib
import dataclasses
import json
import os
import signal
import sys
import threading
import time

import numpy as np

from cpl_keras import cli, files
from cpl_keras.errors import Error

#: Keras's variables that put a process in a group (``keras.distribution.initialize``).
ENVIRONMENT = ("KERAS_DISTRIBUTION_JOB_ADDRESSES", "KERAS_DISTRIBUTION_NUM_PROCESSES",
               "KERAS_DISTRIBUTION_PROCESS_ID")
#: Seconds without a heartbeat after which a partner counts as gone
#: (environment: ``CPL_KERAS_PEER_TIMEOUT_S``).
PEER_TIMEOUT_S = 30.0
#: Seconds between a process's heartbeats (and its look at the others').
BEAT_S = 1.0
#: Seconds the processes wait for each other to connect.
CONNECT_S = 300
#: Seconds a barrier or an agreement waits (a partner that died is caught
#: sooner, by the heartbeats).
WAIT_S = 3600
#: Seconds process 0 waits, once its partners have said that they are
#: leaving, before it ends (``_leave``).
LEAVE_MARGIN_S = 0.5
#: Exit status of a process whose partner failed (not interrupted).
PARTNER_FAILED = 1


class DistributedError(Error):
    """A process group that cannot form or whose processes disagree (one line)."""


@dataclasses.dataclass(frozen=True)
class ProcessGroup:
    """The processes that train one model together."""

    # host:port of process 0, where the group's coordination service listens
    coordinator: str
    # how many processes the group has
    num_processes: int
    # this process's index, 0 .. num_processes - 1 (0 writes the run directory)
    process_id: int

    @property
    def chief(self):
        """Whether this process writes the run directory (process 0)."""
        return self.process_id == 0


def group_from_environment(environ=None):
    """The ``ProcessGroup`` that Keras's ``KERAS_DISTRIBUTION_*`` variables
    describe, or None when none is set. ``DistributedError`` (one line) when
    only some are set or a value is malformed."""
    environ = os.environ if environ is None else environ
    values = {name: environ.get(name, "").strip() for name in ENVIRONMENT}
    given = [name for name, value in values.items() if value]
    if not given:
        return None
    if len(given) < len(ENVIRONMENT):
        missing = ", ".join(name for name in ENVIRONMENT if name not in given)
        raise DistributedError(f"{', '.join(given)} set but not {missing}: a process group "
                               f"needs all three")
    coordinator = values[ENVIRONMENT[0]].split(",")[0].strip()
    host, _, port = coordinator.rpartition(":")
    if not host or not port.isdigit():
        raise DistributedError(f"{ENVIRONMENT[0]} must start with process 0's host:port, "
                               f"got {values[ENVIRONMENT[0]]!r}")
    try:
        count, index = int(values[ENVIRONMENT[1]]), int(values[ENVIRONMENT[2]])
    except ValueError:
        raise DistributedError(f"{ENVIRONMENT[1]} and {ENVIRONMENT[2]} must be integers, got "
                               f"{values[ENVIRONMENT[1]]!r} and "
                               f"{values[ENVIRONMENT[2]]!r}") from None
    if count < 1 or not 0 <= index < count:
        raise DistributedError(f"{ENVIRONMENT[2]}={index} is not a process of "
                               f"{ENVIRONMENT[1]}={count} (0 .. {count - 1})")
    return ProcessGroup(coordinator, count, index)


def set_environment(coordinator, num_processes, process_id, environ=None):
    """Keras's variables for a group (what ``train.py --coordinator ...`` does)."""
    environ = os.environ if environ is None else environ
    for name, value in zip(ENVIRONMENT, (coordinator, num_processes, process_id)):
        environ[name] = str(value)


# ---------------------------------------------------------------------------
# Joining a group
# ---------------------------------------------------------------------------
_state = {"group": None, "client": None, "calls": 0, "stopping": False}
#: Set at exit: the heartbeat thread ends (``_stop_watching``).
_stopping = threading.Event()


def current():
    """The group this process has joined (``join``), or None."""
    return _state["group"]


def is_chief():
    """True outside a group, and in its process 0."""
    group = current()
    return group is None or group.chief


def join(group, prog="train.py"):
    """Connect this process to ``group`` (before any device is counted) and
    watch its partners; returns ``group``. A second call is a no-op.

    JAX's preemption service would swallow SIGTERM: it is switched off, and
    SIGTERM then ends the process as Ctrl-C does (``cli``). The partners'
    heartbeats are watched by a thread (``_watch``)."""
    if current() is not None:
        return current()
    import keras

    if keras.backend.backend() != "jax":
        raise DistributedError(f"training over several processes needs the JAX backend "
                               f"(KERAS_BACKEND={keras.backend.backend()})")
    import jax
    # (private: JAX exposes no public handle on the coordination service's
    # key-value store and barriers, which the heartbeats need outside the
    # devices' collectives; tests/test_private_apis.py checks it is there)
    from jax._src import distributed as jax_distributed

    jax.config.update("jax_enable_preemption_service", False)
    # (the CPU devices' collectives between processes; GPUs bring their own)
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    try:
        jax.distributed.initialize(
            coordinator_address=group.coordinator, num_processes=group.num_processes,
            process_id=group.process_id, initialization_timeout=CONNECT_S,
            heartbeat_timeout_seconds=int(2 * peer_timeout_s()) + 10)
    except (RuntimeError, ValueError) as error:
        raise DistributedError(f"cannot join the process group at {group.coordinator} as "
                               f"process {group.process_id} of {group.num_processes}: "
                               f"{str(error).strip().splitlines()[0]}") from None
    _state.update(group=group, client=jax_distributed.global_state.client)
    # (private: the second half of keras.distribution.initialize, one random
    # seed for every process, whose first half cannot pass the timeouts above
    # to jax.distributed.initialize; tests/test_private_apis.py checks it)
    from keras.src.backend.jax.distribution_lib import initialize_rng

    initialize_rng()
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, cli.terminate)
        cli.on_interrupt(_announce_stop)
    cli.before_exit(_leave)
    watcher = threading.Thread(target=_watch, args=(group, prog), daemon=True,
                               name="cpl_keras-partners")
    watcher.start()
    atexit.register(_stop_watching, watcher)
    return group


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
    client, group = _state["client"], current()
    _state["stopping"] = True
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
    client, group = _state["client"], current()
    if client is None or group is None:
        return
    if not group.chief:
        with contextlib.suppress(Exception):  # (process 0 may be gone already)
            client.key_value_set(f"cpl_keras/left/{group.process_id}", "1",
                                 allow_overwrite=True)
        return
    if not _state["stopping"]:
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
    client, beat, timeout = _state["client"], 0, peer_timeout_s()
    seen = {p: (None, time.monotonic()) for p in range(group.num_processes)
            if p != group.process_id}
    while not _stopping.is_set():
        beat += 1
        try:
            client.key_value_set(f"cpl_keras/alive/{group.process_id}", str(beat),
                                 allow_overwrite=True)
            stop = _try_get(client, "cpl_keras/stop")
            if stop and not stop.startswith(f"process {group.process_id} "):
                _state["stopping"] = True
                _end(prog, f"interrupted: {stop}; to resume, run the same command on every "
                           f"process", 130)
            now = time.monotonic()
            for peer, (last, since) in seen.items():
                value = _try_get(client, f"cpl_keras/alive/{peer}")
                if value != last:
                    seen[peer] = (value, now)
                elif now - since > timeout and not _state["stopping"]:
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


def group_failure(error):
    """The one-line ``DistributedError`` of an exception that a collective
    raised (a partner's connection reset, say). First, ``peer_timeout_s()``
    and a little more are left to the heartbeat thread, which ends the
    process with the line that names the partner that stopped or died."""
    deadline = time.monotonic() + peer_timeout_s() + 3 * BEAT_S
    while time.monotonic() < deadline:
        time.sleep(BEAT_S / 4)
    text = str(error).strip().splitlines()
    return DistributedError(f"the process group failed: {text[0] if text else type(error).__name__}")


# ---------------------------------------------------------------------------
# Agreeing
# ---------------------------------------------------------------------------
def _next_key(what):
    _state["calls"] += 1
    return f"cpl_keras/{_state['calls']}/{what}"


def gather(what, value):
    """Every process's ``value`` (JSON), in process order."""
    group, client = current(), _state["client"]
    if group is None:
        return [value]
    key = _next_key(what)
    client.key_value_set(f"{key}/{group.process_id}", json.dumps(value, sort_keys=True))
    return [json.loads(client.blocking_key_value_get(f"{key}/{p}", WAIT_S * 1000))
            for p in range(group.num_processes)]


def check_same(what, values):
    """Raise ``DistributedError`` (one line) unless every process has the
    same ``values`` (a dict of JSON values); names the first that differs."""
    everyone = gather(what, values)
    for name in values:
        seen = [v.get(name) for v in everyone]
        if any(s != seen[0] for s in seen):
            listed = ", ".join(f"{s!r} on process {p}" for p, s in enumerate(seen))
            raise DistributedError(f"the processes disagree on {what}: {name} is {listed}")


def broadcast(what, value):
    """Process 0's ``value`` (JSON), on every process."""
    group, client = current(), _state["client"]
    if group is None:
        return value
    key = _next_key(what)
    if group.chief:
        client.key_value_set(key, json.dumps(value))
        return value
    return json.loads(client.blocking_key_value_get(key, WAIT_S * 1000))


def barrier(what):
    """Wait until every process of the group gets here (no-op outside one)."""
    if current() is not None:
        _state["client"].wait_at_barrier(_next_key(what), WAIT_S * 1000)


# ---------------------------------------------------------------------------
# Batches
# ---------------------------------------------------------------------------
def local_part(batch, process_id, num_processes):
    """Process ``process_id``'s share of a global ``batch`` (any array whose
    first axis is the batch): the ``process_id``-th of ``num_processes``
    equal contiguous slices. The global batch must divide evenly."""
    size = len(batch)
    if size % num_processes:
        raise ValueError(f"a global batch of {size} does not split over {num_processes} "
                         f"processes")
    share = size // num_processes
    return batch[process_id * share:(process_id + 1) * share]


def global_batch(inputs):
    """``inputs`` (a process-local batch: an array or a dict of arrays) as
    the global arrays of the active distribution, for a jitted function of
    the model's variables; unchanged outside a group."""
    if current() is None:
        return inputs
    import jax
    import keras

    distribution = keras.distribution.distribution()

    def to_global(array):
        array = np.asarray(array)
        layout = distribution.get_data_layout(
            (array.shape[0] * current().num_processes,) + array.shape[1:])
        return jax.make_array_from_process_local_data(layout.backend_layout, array)

    if isinstance(inputs, dict):
        return {name: to_global(array) for name, array in inputs.items()}
    return to_global(inputs)


@contextlib.contextmanager
def alone():
    """Within the block, new variables are this process's own: for what
    process 0 does by itself, saving a model or its weights. (Keras's saving
    creates a variable, and under a multi-process distribution creating one
    is a collective that would wait for the other processes forever.)"""
    if current() is None:
        yield
        return
    import keras

    previous = keras.distribution.distribution()
    keras.distribution.set_distribution(None)
    try:
        yield
    finally:
        keras.distribution.set_distribution(previous)


def to_numpy(value):
    """A tensor as a NumPy array; a global array that spans other processes'
    devices must be replicated, and its local copy is read."""
    if getattr(value, "is_fully_addressable", True) is False:
        value = value.addressable_data(0)
    return np.asarray(value)


def refuse_prediction():
    """``DistributedError`` inside a group of several processes, where
    ``model.predict`` cannot run (its outputs span non-addressable devices)."""
    group = current()
    if group is not None and group.num_processes > 1:
        raise DistributedError("prediction runs in one process: evaluate the run with "
                               "evaluate.py after training, outside the process group")
