"""``python -m cpl_keras.data.mix`` (``cpl-mix``): mix dataset files into one
(``cpl_keras.data.mix``)."""

from __future__ import annotations

import sys

import numpy as np

from cpl_keras import cli
from cpl_keras.data.mix import PROG, mix_datasets
from cpl_keras.data.mix import __doc__ as LIBRARY_DOC
from cpl_keras.data.storage import StereoFile


def main(argv=None):
    parser = cli.Parser(prog=PROG, description=LIBRARY_DOC.split("\n")[0])
    parser.add_argument("sources", nargs="+", help="dataset files (.h5) to mix, in order")
    parser.add_argument("--out", type=cli.path, required=True, help="the mixed dataset file (.h5)")
    args = parser.parse_args(argv)
    try:
        cli.check_output_file(args.out)
        with cli.interruptible():
            cli.make_parent(args.out)
            path = mix_datasets(args.out, args.sources, command=cli.command_line(PROG, argv))
    except KeyboardInterrupt:
        return cli.interrupted(PROG, note=f"{args.out} was not written")
    except (ValueError, OSError) as error:
        return cli.fail(PROG, error)
    with StereoFile(path) as f:
        counts = np.bincount(f.labels["source_index"])
        rigs = f.metadata["rigs"]
    print(path)
    sys.stderr.write(f"summary: {int(counts.sum())} pairs from {len(counts)} files "
                     f"({', '.join(str(c) for c in counts)}); real rigs: "
                     f"{', '.join(rigs) or 'none'}\n")
    return 0


if __name__ == "__main__":
    cli.run(main, PROG)
