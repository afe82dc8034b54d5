"""The ledger of a long run's starts: how often it was resumed, on which
machines, and whether its run directory was lost (the plateau amendment,
paper_results/fair-fight/protocol-plateau.md).

The ledger is a JSON file in the work tree, beside the run's published
record (``<record>_starts.json``), written at each start before training,
so that a commit carries it even when the run directory stays on a machine
(outside the work tree). Each start adds one entry: the epochs the run had
completed before it (``backup/state.json``), the machine
(``backend.machine`` without the devices JAX sees, and the GPUs
``nvidia-smi`` lists) and whether the run directory had been lost (a ledger
with starts, no run directory here). A run lost twice is not started a
third time: ``LostTwice``. When the run is published the ledger
is copied into its record as ``starts.json``.
"""

from __future__ import annotations

import datetime
import os
import shutil
import subprocess

#: The ledger's name inside a published record.
IN_RECORD = "starts.json"


class LostTwice(Exception):
    """A run's directory was lost twice: publish what finished, do not start it again."""


def ledger_path(record):
    """The ledger of the run published (once it ends) at ``record``."""
    return record.rstrip(os.sep) + "_starts.json"


def gpus():
    """The GPUs ``nvidia-smi`` lists here (no JAX imported: it would take
    their memory), [] where there is none."""
    try:
        done = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"],
                              capture_output=True, text=True, timeout=20)
    except (OSError, subprocess.SubprocessError):
        return []
    return [line.strip() for line in done.stdout.splitlines() if line.strip()] \
        if done.returncode == 0 else []


def read(record):
    """The ledger of ``record``'s run: ``{"starts": [...]}``, empty if none."""
    from cpl_keras import files

    found = files.read_json(ledger_path(record), default={"starts": []})
    if not isinstance(found, dict) or not isinstance(found.get("starts"), list):
        raise ValueError(f"{ledger_path(record)} is not a ledger of starts")
    return found


def _identity(machine):
    """A recorded machine without ``devices`` (see ``this_machine``)."""
    return {k: v for k, v in machine.items() if k != "devices"}


def this_machine():
    """This machine as the ledger records it: ``backend.machine`` without
    ``devices``, which it lists only when this process has imported JAX (a
    start after a run published in the same process would otherwise name
    the same machine differently from a start in a fresh one); the GPUs are
    recorded apart (``gpus``)."""
    from cpl_keras import backend

    return _identity(backend.machine())


def summary(starts):
    """The ledger's counts: resumes (starts after the first that went on
    from a completed epoch), losses, and the machines, each once in order
    (a ``devices`` list some older starts carry is not part of a machine's
    identity: see ``this_machine``)."""
    machines = []
    for start in starts:
        machine = dict(_identity(start["machine"]), gpus=start.get("gpus", []))
        if machine not in machines:
            machines.append(machine)
    return {"starts": len(starts),
            "resumed": sum(1 for s in starts if s["from_epoch"] > 0),
            "lost": sum(1 for s in starts if s["lost_before"]),
            "machines": machines}


def record_start(record, run_dir, machine=None, gpu_names=None):
    """Add this start of the run in ``run_dir`` to ``record``'s ledger (and
    return the ledger). ``LostTwice`` when the run directory is missing here
    after a start that had already followed a loss."""
    from cpl_keras import files
    from cpl_keras.training.state import read_state

    ledger = read(record)
    starts = ledger["starts"]
    lost = bool(starts) and not os.path.isdir(run_dir)
    if lost and any(s["lost_before"] for s in starts):
        raise LostTwice(f"{os.path.basename(record)}: its run directory was lost twice "
                        f"({len(starts)} starts in {ledger_path(record)}): publish what "
                        "finished, say so, and do not start it a third time")
    from_epoch = 0 if lost else read_state(run_dir).epoch
    starts.append({"start": len(starts) + 1, "from_epoch": from_epoch, "lost_before": lost,
                   "utc": datetime.datetime.now(datetime.timezone.utc).isoformat(
                       timespec="seconds"),
                   "machine": machine if machine is not None else this_machine(),
                   "gpus": gpu_names if gpu_names is not None else gpus()})
    ledger.update(summary(starts), starts=starts)
    os.makedirs(os.path.dirname(os.path.abspath(record)), exist_ok=True)
    files.write_json(ledger_path(record), ledger)
    return ledger


def copy_into(record):
    """The ledger copied into the published ``record`` (``starts.json``)."""
    from cpl_keras import files

    with files.atomic_path(os.path.join(record, IN_RECORD)) as tmp:
        shutil.copyfile(ledger_path(record), tmp)
