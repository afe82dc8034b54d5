"""``python -m cpl_keras.data.import_cvgl`` (``cpl-import-cvgl``): the
authors' released CVGL files, or their real sets' files, as one dataset file
of the project (``cpl_keras.data.import_cvgl``)."""

from __future__ import annotations

import sys

from cpl_keras import cli
from cpl_keras.data.import_cvgl import PROG, import_release
from cpl_keras.data.release_files import SUFFIXES
from cpl_keras.data.storage import StereoFile


def _parser():
    p = cli.Parser(prog=PROG, description="Import the authors' released CVGL data (the folder "
                   "of 15 flat .npy files, or the raw Town*/*episode* folders) into one HDF5 "
                   "dataset file; docs/data.md, 'The paper's own data'.")
    p.add_argument("release_dir", type=cli.path, help="the release's folder (either layout)")
    p.add_argument("--out", type=cli.path, required=True, help="the dataset file to write (.h5)")
    p.add_argument("--suffix", default="", choices=SUFFIXES,
                   help="the set's file-name suffix: none for CVGL (default), r for "
                   "Tsinghua-Daimler, r_cs for Cityscapes (flat files)")
    p.add_argument("--seed", type=cli.non_negative_int, default=0,
                   help="raw episodes: the seed of the one shuffle of their frames (the "
                   "release's was unseeded; default 0); the flat files keep their order")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def main(argv=None):
    args = _parser().parse_args(argv)
    try:
        with cli.interruptible():
            path = import_release(args.release_dir, args.out, args.suffix, args.seed,
                                  progress=not args.no_progress,
                                  command_line=cli.command_line(PROG, argv))
    except KeyboardInterrupt:
        return cli.interrupted(PROG, note=f"{args.out} was not finished (run the same command "
                               "to continue it)")
    except (ValueError, OSError) as error:
        return cli.fail(PROG, error)
    with StereoFile(path) as f:
        n, meta = f.num_pairs, f.metadata
    print(path)
    sys.stderr.write(f"summary: {n} pairs of {meta['source']} ({meta['layout']} layout); "
                     f"not derivable from the release: {', '.join(meta['underived_labels'])}: "
                     "train and evaluate with --as-released\n")
    return 0


if __name__ == "__main__":
    cli.run(main, PROG)
