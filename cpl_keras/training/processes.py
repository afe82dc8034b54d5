"""Where and when the processes of a training run write: the trainer's one
seam to ``cpl_keras.distributed``.

A run trains in one process (``SingleProcess``) or in a group of processes
that train one model together (``Group``: process 0 writes the run
directory, the others keep the same state in memory). The trainer and its
checkpointing callback (``RunState``) ask the same few things of either:

* ``writes``: whether this process writes the run directory (and prints
  the epoch lines);
* ``write(what, function, *args)``: ``function(*args)`` on the process that
  writes, then a barrier named ``what``: every process goes on once it is
  written;
* ``alone()``: around the writing process's own saves of the model or its
  weights, which must not wait for the other processes;
* ``decide(what, value)``: the writing process's ``value``, on every process
  (its clock decides the time budget for the whole group);
* ``agree(what, fingerprint, *args)``: ``fingerprint(*args)`` must be the
  same on every process (``DistributedError`` in one line, naming the first
  value that differs);
* ``failures()``: around training: a collective that fails because a
  partner stopped or died ends in one line;
* ``part``: this process's share of every batch (``StereoSequence``'s
  ``process``), None for all of it.

In one process each of these is trivial.
"""

from __future__ import annotations

import contextlib

from cpl_keras import distributed
from cpl_keras.errors import Error
from cpl_keras.training.planning import TrainingError


class SingleProcess:
    """A run trained by this process alone: it writes, and waits for nobody."""

    writes = True
    count = 1

    def part(self, batch):
        """The whole ``batch``: this process trains on all of it."""
        return batch

    def global_batch(self, inputs):
        """``inputs`` unchanged: this process's batch is the whole batch."""
        return inputs

    def write(self, what, function, *args):
        """``function(*args)``."""
        return function(*args)

    def alone(self):
        """Nothing to do."""
        return contextlib.nullcontext()

    def decide(self, what, value):
        """``value``."""
        return value

    def agree(self, what, fingerprint, *args):
        """Nothing to agree on (``fingerprint`` is not called)."""

    def failures(self):
        """Nothing to translate."""
        return contextlib.nullcontext()


class Group:
    """A run trained by the processes of ``group`` (a joined
    ``distributed.ProcessGroup``) together."""

    def __init__(self, group):
        self.group = group
        self.writes = group.chief
        self.count = group.num_processes

    def part(self, batch):
        """This process's share of a global ``batch`` (``distributed.local_part``)."""
        return distributed.local_part(batch, self.group.process_id, self.group.num_processes)

    def global_batch(self, inputs):
        """This process's ``inputs`` as the group's global arrays
        (``distributed.global_batch``), for BatchNorm's statistics of the whole batch."""
        return distributed.global_batch(inputs)

    def write(self, what, function, *args):
        """``function(*args)`` on process 0 (its result; None on the
        others), then every process waits for the others (``what``)."""
        result = function(*args) if self.writes else None
        distributed.barrier(what)
        return result

    def alone(self):
        """New variables are this process's own within the block
        (``distributed.alone``)."""
        return distributed.alone()

    def decide(self, what, value):
        """Process 0's ``value``, on every process."""
        return distributed.broadcast(what, value)

    def agree(self, what, fingerprint, *args):
        """``DistributedError`` (one line) unless ``fingerprint(*args)``, a
        dict of JSON values, is the same on every process."""
        distributed.check_same(what, fingerprint(*args))

    @contextlib.contextmanager
    def failures(self):
        """An exception of a collective within the block (a partner's
        connection reset) becomes ``distributed.group_failure``'s one line;
        the package's own errors are one line already."""
        try:
            yield
        except Error:
            raise
        except Exception as error:
            raise distributed.group_failure(error) from None


def join_processes(data_parallel):
    """The processes of this run: the group of Keras's
    ``KERAS_DISTRIBUTION_*`` variables, joined (``distributed.join``; before
    any device is counted), or ``SingleProcess`` where they are not set."""
    group = distributed.group_from_environment()
    if group is None:
        return SingleProcess()
    if not data_parallel:
        raise TrainingError(f"{distributed.ENVIRONMENT[0]} and the others are set: training "
                            f"over several processes needs --data-parallel (data_parallel=True)")
    return Group(distributed.join(group))
