"""``python -m cpl_keras.data.generate`` (``cpl-generate``): render a synthetic
stereo dataset to one HDF5 file (``cpl_keras.data.generate``)."""

from __future__ import annotations

import sys

from cpl_keras import cli
from cpl_keras.cli import Parser
from cpl_keras.data.generate import (
    PROG, check_arguments, check_output_path, generate_file, summary_text,
)
from cpl_keras.data.preview import write_preview
from cpl_keras.data.writer import pairs_kept
from cpl_keras.data.protocols import PROTOCOLS


def _parser():
    p = Parser(
        prog=PROG,
        description="Render a synthetic CVGL-style stereo dataset to one HDF5 file.",
    )
    p.add_argument("--protocol", default="cvgl", choices=PROTOCOLS,
                   help="cvgl: the paper's 50 rigs; random: realistic rigs; cameras: random "
                   "rigs with real cameras' aspect ratios squashed to the square input; "
                   "wild: the cameras rigs under a sun, haze and white balance drawn per "
                   "rig (default cvgl)")
    p.add_argument("--pairs", type=int, required=True, help="number of stereo pairs")
    p.add_argument("--out", type=cli.path, help="output HDF5 file (may be left out with --preview)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--image-size", type=int, default=112, help="square image side (default 112)")
    p.add_argument("--workers", type=cli.worker_count, default=None,
                   help="worker processes (default and most: all cores)")
    p.add_argument("--preview", help="also write a PNG contact sheet of a few pairs")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--restart", action="store_true",
                   help="discard the OUT.partial file of an interrupted run and start again "
                   "(by default it is continued; one of other arguments is refused)")
    p.add_argument("--force", action="store_true",
                   help="replace a dataset already at OUT made with other settings (by default "
                   "it is refused; one made with these settings is left as it is)")
    return p


def _main(args, command_line):
    try:
        check_arguments(args.protocol, args.pairs, args.seed, args.image_size, args.workers)
        if args.out is not None:
            check_output_path(args.out)
        if args.preview is not None:
            check_output_path(args.preview)
        if args.out is not None:
            path = generate_file(args.out, args.protocol, args.pairs, args.seed, args.image_size,
                             args.workers, not args.no_progress, command_line,
                             restart=args.restart, force=args.force,
                             log=lambda line: print(line, file=sys.stderr, flush=True))
            print(path)
            sys.stderr.write(f"summary: {summary_text(path)}\n")
        if args.preview is not None:
            print(write_preview(args.preview, args.protocol, args.pairs, args.seed,
                                args.image_size))
    except (ValueError, OSError) as error:
        return cli.fail(PROG, " ".join(str(error).split()))
    return 0


def main(argv=None):
    parser = _parser()
    args = parser.parse_args(argv)
    if args.out is None and args.preview is None:
        parser.error("give --out (the dataset) and/or --preview (a contact sheet)")

    command_line = cli.command_line(PROG, argv)
    try:
        with cli.interruptible():
            return _main(args, command_line)
    except KeyboardInterrupt:  # cli.Interrupted, or a Ctrl-C outside the block
        note, kept = None, pairs_kept(args.out + ".partial") if args.out is not None else 0
        if kept:
            note = (f"{args.out}.partial keeps the first {kept} of {args.pairs} pairs; the same "
                    "command continues it")
        elif args.out is not None:
            note = f"{args.out} was not written; the same command starts again from the first pair"
        return cli.interrupted(PROG, note=note)


if __name__ == "__main__":
    cli.run(main, PROG)
