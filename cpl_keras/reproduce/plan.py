"""Which training runs a reproduction's settings make (``run_jobs``), and
what they would cost on a machine without an accelerator (``cpu_cost``)."""

from __future__ import annotations

from typing import NamedTuple

from cpl_keras.reproduce.presets import RELEASED_RUN, TABLE1


def run_stems(config, protocol="cvgl"):
    """The runs of the settings (a ``Settings``) on ``protocol``, by name stem
    (the variant, or ``RELEASED_RUN``)."""
    stems = list(config.variants)
    if protocol == "cvgl" and config.released:
        stems.append(RELEASED_RUN)
    return tuple(stems)


class Job(NamedTuple):
    """One training run of the settings (``run_jobs``)."""

    # the Table 1 version it belongs to (``TABLE1``'s key: "cvgl", "random", ...)
    key: str
    # the dataset's protocol, and the split the run is trained on
    protocol: str
    split: str
    # the run's seed (the split's, the initialisation's and the batches' order)
    seed: int
    # the variant trained, and whether as released (the release's heads and targets)
    variant: str
    released: bool
    # the run directory's name inside ``<runs dir>/<key>/``: ``cpl-a``, ``cpl-u-s1``
    name: str


def run_jobs(config, seed):
    """Every training run of the settings (a ``Settings``), a ``Job`` each. The runs of ``seeded_variants``
    (None: all) are trained on every seed of a table, the others on its first
    seed only; a table trained over several seeds names its runs
    ``<stem>-s<seed>`` (``cpl-u-s1``, ``deep-homo-s0``, ``cpl-a-released-s0``).
    Within a table, the ``first_variants`` train on every seed before the
    other runs start (seed by seed in each group)."""
    seeded, first = config.seeded_variants, config.first_variants
    jobs = []
    for key in config.tables:
        protocol, split, seeds_key = TABLE1[key]
        split = config.split or split
        count = getattr(config, seeds_key)
        stems = run_stems(config, protocol)
        groups = [[s for s in stems if s in first], [s for s in stems if s not in first]]
        for group in groups:
            for run_seed in range(seed, seed + count):
                for stem in group:
                    if run_seed != seed and seeded is not None and stem not in seeded:
                        continue
                    released = stem == RELEASED_RUN or config.data == "release"
                    variant = "cpl-a" if stem == RELEASED_RUN else stem
                    name = stem + (f"-s{run_seed}" if count > 1 else "")
                    jobs.append(Job(key, protocol, split, run_seed, variant, released, name))
    return jobs


#: Settings sized for a GPU: InceptionV3 towers on this many pairs or more.
GPU_SIZED_PAIRS = 10000
#: The faithful model's training rate on a 2-core CPU (paper_results/notes/backends.md).
CPU_SAMPLES_PER_S = 12


def gpu_sized(config):
    """Whether ``config`` (a ``Settings``) trains InceptionV3 towers on GPU-sized data."""
    return config.backbone == "inception_v3" and config.pairs >= GPU_SIZED_PAIRS


def has_accelerator():
    """Whether JAX sees a GPU or TPU (imported here, after the arguments are checked)."""
    import jax

    return jax.default_backend() != "cpu"


def cpu_cost(config, seed=0):
    """The one line that refuses GPU-sized settings on a CPU, with their cost."""
    train = config.pairs * (1 - 0.3) * (1 - 0.1)
    epoch_h = train / CPU_SAMPLES_PER_S / 3600
    count = len(run_jobs(config, seed))
    return (f"these settings are sized for a GPU ({config.pairs:,} pairs, InceptionV3 "
            f"towers, {count} runs) and JAX sees no GPU here: one epoch of one run would take "
            f"about {epoch_h:.1f} h on this CPU (~{CPU_SAMPLES_PER_S} samples/s); pass "
            f"--allow-cpu to go on, or use --preset cpu or cpu-8000")
