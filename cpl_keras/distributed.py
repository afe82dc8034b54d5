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
  line, within seconds, instead of waiting forever in a collective
  (``cpl_keras.heartbeats``).
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

import contextlib
import dataclasses
import json
import os
import time

import numpy as np

from cpl_keras import heartbeats
from cpl_keras.errors import Error

#: Keras's variables that put a process in a group (``keras.distribution.initialize``).
ENVIRONMENT = ("KERAS_DISTRIBUTION_JOB_ADDRESSES", "KERAS_DISTRIBUTION_NUM_PROCESSES",
               "KERAS_DISTRIBUTION_PROCESS_ID")
#: Seconds the processes wait for each other to connect.
CONNECT_S = 300
#: Seconds a barrier or an agreement waits (a partner that died is caught
#: sooner, by the heartbeats).
WAIT_S = 3600


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
_state = {"group": None, "client": None, "calls": 0}


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
    SIGTERM then ends the process as Ctrl-C does (``cli``). The partners
    are watched from then on (``heartbeats.start``)."""
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
            heartbeat_timeout_seconds=int(2 * heartbeats.peer_timeout_s()) + 10)
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
    heartbeats.start(group, _state["client"], prog)
    return group


def group_failure(error):
    """The one-line ``DistributedError`` of an exception that a collective
    raised (a partner's connection reset, say). First, ``peer_timeout_s()``
    and a little more are left to the heartbeat thread, which ends the
    process with the line that names the partner that stopped or died."""
    deadline = time.monotonic() + heartbeats.peer_timeout_s() + 3 * heartbeats.BEAT_S
    while time.monotonic() < deadline:
        time.sleep(heartbeats.BEAT_S / 4)
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


def refuse_prediction():
    """``DistributedError`` inside a group of several processes, where
    ``model.predict`` cannot run (its outputs span non-addressable devices)."""
    group = current()
    if group is not None and group.num_processes > 1:
        raise DistributedError("prediction runs in one process: evaluate the run with "
                               "evaluate.py after training, outside the process group")
