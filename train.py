"""Train one of the paper's networks.

    python train.py --variant cpl-a                      # demonstration run
    python train.py --variant cpl-a --data data/cvgl-123017.h5  # full-scale training

Without ``--data`` a small dataset is generated on first use into the cache
directory (``$CPL_KERAS_CACHE``, default ``~/.cache/cpl_keras``) and a short
demonstration run is made. Killed runs resume when the same command is run
again. The command itself is cpl_keras/commands/train.py (installed:
``cpl-train``). See docs/training.md.
"""

from __future__ import annotations

from cpl_keras import cli  # (first, and light: the Ctrl-C guard starts at once)

PROG = "train.py"


def main(argv=None):
    # (imported inside cli.run's Ctrl-C guard)
    from cpl_keras.commands import train

    return train.main(argv, prog=PROG)


def next_step(variant, demo_file):
    from cpl_keras.commands import train

    return train.next_step(variant, demo_file, prog=PROG)


def __getattr__(name):
    # the command's other names (DEMO, build_parser, ...), from its module
    from cpl_keras.commands import train

    return getattr(train, name)


if __name__ == "__main__":
    cli.run(main, PROG)
