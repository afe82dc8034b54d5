"""What generating a dataset will take on this machine, now: the disk from a
generated file's bytes per pair, the time from a sample of pairs rendered
as the generator renders them, by its worker processes all at once, under
whatever else the machine is running.

The demonstration's estimate once rendered 16 pairs on one core (0.15 s)
and divided by the cores: it said 9-11 minutes for a dataset that took
about 18 on a machine shared with other jobs, whose load a process alone
on one core barely meets.
"""

from __future__ import annotations

import contextlib
import os
import time

from cpl_keras.data.blocks import iter_blocks
from cpl_keras.data.storage import StereoFile

#: The least time a sample is timed for (seconds, after every worker's
#: first block): long enough for the scheduler's share of the cores.
SAMPLE_SECONDS = 3.0
#: The most pairs a sample renders (it stops at ``SAMPLE_SECONDS`` first).
MAX_SAMPLE_PAIRS = 4096


def sample_rate(protocol, pairs, image_size, workers, seconds=SAMPLE_SECONDS):
    """Pairs a second that ``workers`` processes render now: pairs of a
    ``pairs``-pair dataset (from its last ``MAX_SAMPLE_PAIRS``) rendered as
    the generator does (``iter_blocks``), timed from the arrival of the
    workers' first blocks (each holds its process's start and set-up: the
    towns and their materials, about ten pairs' time) until ``seconds`` have
    passed or the pairs run out. Returns ``(rate, pairs timed, seconds
    timed)``; a sample of no more blocks than workers is timed whole."""
    begin = time.perf_counter()
    start, timed, arrived, total, now = None, 0, 0, 0, begin
    blocks = iter_blocks(protocol, 0, pairs, image_size, workers,
                         max(0, pairs - MAX_SAMPLE_PAIRS))
    with contextlib.closing(blocks):
        for _, (left, _, _) in blocks:
            now, arrived, total = time.perf_counter(), arrived + 1, total + len(left)
            if arrived <= workers:
                start = now
                continue
            timed += len(left)
            if now - start >= seconds:
                break
    if not timed:
        return total / max(now - begin, 1e-9), total, now - begin
    return timed / max(now - start, 1e-9), timed, now - start


def load_average():
    """This machine's load over the last minute (processes running or waiting
    for a core), or None where it is not known."""
    try:
        return os.getloadavg()[0]
    except (OSError, AttributeError):
        return None


def estimate_cost(pairs, sample_file, protocol="cvgl", workers=None, seconds=SAMPLE_SECONDS):
    """What generating ``pairs`` pairs will take, measured here and now: disk
    from the bytes per pair of ``sample_file`` (a generated file of the same
    image size; the images are gzip-compressed, so this varies a little with
    the scenes), time from ``sample_rate`` with ``workers`` processes
    (default: every core, the generator's). Returns a dict:
    ``bytes_per_pair``, ``bytes``, ``seconds``, ``workers``,
    ``pairs_per_second``, ``seconds_per_pair`` (one worker's),
    ``sampled_pairs`` and ``sample_seconds`` (what was timed), ``load`` (the
    load average after it, or None), ``cpus``, ``image_size``."""
    with StereoFile(sample_file) as data:
        sample_pairs = data.num_pairs
        image_size = data.image_shape[0]
    bytes_per_pair = os.path.getsize(sample_file) / sample_pairs
    workers = workers or os.cpu_count() or 1
    rate, sampled, elapsed = sample_rate(protocol, pairs, image_size, workers, seconds)
    return {"bytes_per_pair": bytes_per_pair, "bytes": bytes_per_pair * pairs,
            "seconds": pairs / rate, "workers": workers, "pairs_per_second": rate,
            "seconds_per_pair": workers / rate, "sampled_pairs": sampled,
            "sample_seconds": elapsed, "load": load_average(), "cpus": os.cpu_count() or 1,
            "image_size": image_size}
