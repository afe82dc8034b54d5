"""Build a real-data HDF5 file for Table 2.

Usage::

    python -m cpl_keras.real.build middlebury --out data/middlebury.h5 [--crops 500]
    python -m cpl_keras.real.build tsinghua --root DIR --out data/tdcb.h5 [--split test]
    python -m cpl_keras.real.build cityscapes --root DIR --out data/cityscapes.h5

Options: ``--image-size`` (112), ``--seed`` (0), ``--right {warp,released}``
and ``--labels {rig,vehicle}`` (Tsinghua-Daimler / Cityscapes only),
``--limit N`` (first N images). Bad input prints one line and exits with
status 2; the output file appears only when complete.
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys

from cpl_keras.real import LABEL_MODES


class _Parser(argparse.ArgumentParser):
    def error(self, message):
        print(f"error: {message}", file=sys.stderr)
        raise SystemExit(2)


def parse_args(argv=None):
    parser = _Parser(prog="python -m cpl_keras.real.build", description=__doc__.split("\n")[0])
    parser.add_argument("source", choices=("middlebury", "tsinghua", "cityscapes"))
    parser.add_argument("--out", required=True, help="output HDF5 file")
    parser.add_argument("--root", help="dataset root (tsinghua, cityscapes)")
    parser.add_argument("--split", help="split folder under leftImg8bit/ (e.g. test)")
    parser.add_argument("--image-size", type=int, default=112)
    parser.add_argument("--crops", type=int, default=500, help="middlebury: number of crops")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--right", choices=("warp", "released"), default="warp")
    parser.add_argument("--labels", choices=LABEL_MODES, default="rig")
    parser.add_argument("--limit", type=int, help="use only the first N images")
    return parser.parse_args(argv)


def main(argv=None):
    args = parse_args(argv)
    command = "python -m cpl_keras.real.build " + shlex.join(
        sys.argv[1:] if argv is None else list(argv))
    out_dir = os.path.dirname(os.path.abspath(args.out))
    try:
        if not os.path.isdir(out_dir):
            raise ValueError(f"output directory does not exist: {out_dir}")
        if os.path.isdir(args.out):
            raise ValueError(f"output path is a directory: {args.out}")
        if args.source == "middlebury":
            from cpl_keras.real.middlebury import build_middlebury

            path = build_middlebury(args.out, crops=args.crops, image_size=args.image_size,
                                    seed=args.seed, command=command)
        else:
            if not args.root:
                raise ValueError(f"--root is required for {args.source}")
            if not os.path.isdir(args.root):
                raise ValueError(f"dataset root not found: {args.root}")
            from cpl_keras.real.tsinghua import build_stereo_dataset

            path = build_stereo_dataset(
                args.root, args.out, dataset=args.source, split=args.split,
                image_size=args.image_size, right=args.right, labels=args.labels,
                seed=args.seed, limit=args.limit, command=command)
    except (ValueError, OSError) as error:
        message = str(error).splitlines()[0] if str(error) else type(error).__name__
        print(f"error: {message}", file=sys.stderr)
        return 2
    print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
