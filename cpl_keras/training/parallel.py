"""Several training runs at once, each in a process of its own.

``train_parallel(pending, processes)`` trains ``(label, data, options)``
runs (``options``: ``trainer.train``'s keyword arguments) ``processes`` at
a time, each in a fresh, spawned process (JAX does not survive a fork), the
slow variants first, and never two runs of one model at once while another
run could go instead: the second then loads the first's compiled programs
from the compile cache (``cpl_keras.cache``) instead of compiling them
too. Ctrl-C (or SIGINT to this process) interrupts every running run,
each of which resumes from its last completed epoch next time; a run
that fails stops the others and raises ``TrainingError``; a process
whose parent is gone ends itself. ``on_finished(label, options)``
is called, in this process, for every run that ends well (the
reproduction publishes it there). The runs are the same as runs trained
one after the other.
"""

from __future__ import annotations

import multiprocessing
import multiprocessing.connection
import os
import signal
import sys
import threading
import time

from cpl_keras import cli
from cpl_keras.cache import enable_compile_cache
from cpl_keras.errors import Error
from cpl_keras.models.variants import SLOW_VARIANTS
from cpl_keras.training import trainer
from cpl_keras.training.result import summary_line


def _log(message):
    print(message, file=sys.stderr, flush=True)


def _exit_with_parent(parent, every=2.0):
    """End this process (status 143, as by SIGTERM) once ``parent`` is gone:
    a parent killed outright leaves no training behind."""
    def watch():
        while os.getppid() == parent:
            time.sleep(every)
        os._exit(143)

    threading.Thread(target=watch, daemon=True, name="exit-with-parent").start()


def _train_job(data, options, parent, log, prog):
    """A training run in a process of its own: quiet; the exit status says
    how it ended (0 trained, 1 no epoch completed, 2 an error, printed on one
    line, 130 interrupted, 143 its parent gone; a killed run resumes from its
    last completed epoch)."""
    _exit_with_parent(parent)
    enable_compile_cache()
    try:
        with cli.interruptible():
            summary = trainer.train(data, verbose=0, **options)
    except KeyboardInterrupt:  # the last completed epoch is checkpointed
        sys.exit(130)
    except (Error, OSError) as error:
        print(f"{prog}: error: {options['run_dir']}: {error}", file=sys.stderr)
        sys.exit(2)
    log(summary_line(summary))
    sys.exit(0 if summary.config.best_epoch is not None else 1)


def _interrupt(running):
    """Ctrl-C: SIGINT to every running run, then wait for them (each
    checkpoints its last completed epoch), terminating any that hangs."""
    for _, _, process in running.values():
        if process.is_alive():
            os.kill(process.pid, signal.SIGINT)
    for _, _, process in running.values():
        process.join(timeout=60)
        if process.is_alive():
            process.terminate()


def model_key(options):
    """What makes two runs' compiled programs the same: the model (variant,
    as released, backbone) trained at the same batch size."""
    return tuple(options.get(k) for k in ("variant", "as_released", "backbone", "batch_size"))


def next_job(queue, running_keys):
    """The index in ``queue`` of the first job whose model (``model_key``) no
    running process has (its programs are being compiled there), or 0."""
    return next((i for i, (_, _, options) in enumerate(queue)
                 if model_key(options) not in running_keys), 0)


def train_parallel(pending, processes, *, on_finished=None, log=_log, prog="cpl_keras"):
    """Train the ``pending`` runs (``(label, data, options)``) ``processes``
    at a time (see the module doc). ``log(line)`` says what starts and ends
    (a module-level function: the processes call it too); ``prog`` starts
    their one-line errors."""
    context = multiprocessing.get_context("spawn")
    # the slow variants first, so that the short runs fill the other processes meanwhile
    queue = sorted(pending, key=lambda job: job[2]["variant"] not in SLOW_VARIANTS)
    running, failure = {}, None
    try:
        while (queue and failure is None) or running:
            while queue and failure is None and len(running) < processes:
                label, data, options = queue.pop(
                    next_job(queue, {model_key(o) for _, o, _ in running.values()}))
                log(f"training {label} ({options.get('backbone', 'inception_v3')}, up to "
                    f"{options.get('epochs', 200)} epochs; {processes} runs at a time)")
                process = context.Process(target=_train_job, name=label,
                                          args=(data, options, os.getpid(), log, prog))
                process.start()
                running[process.sentinel] = (label, options, process)
            for sentinel in multiprocessing.connection.wait(list(running), timeout=5):
                label, options, process = running.pop(sentinel)
                process.join()
                if process.exitcode == 0 and on_finished:
                    on_finished(label, options)
                if process.exitcode != 0 and failure is None:
                    failure = (f"{options['run_dir']}: training ended with exit status "
                               f"{process.exitcode}")
                    for _, _, other in running.values():
                        other.terminate()  # SIGTERM: resumes from its last epoch
    except KeyboardInterrupt:
        _interrupt(running)
        raise
    if failure is not None:
        raise trainer.TrainingError(failure)
