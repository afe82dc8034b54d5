"""``python -m cpl_keras.real.build`` (``cpl-real-build``): build the real stereo
sets of Table 2 (``cpl_keras.real.build``)."""

from __future__ import annotations

import sys

from cpl_keras import cli
from cpl_keras.real import LABEL_MODES
from cpl_keras.real.build import OPTIONS, PROG, SOURCES, build_all, build_one
from cpl_keras.real.build import __doc__ as LIBRARY_DOC

#: The sources that are one rig (all the others: ``all``).
RIGS = tuple(source for source in SOURCES if source != "all")


def parse_args(argv=None):
    parser = cli.Parser(prog=PROG, description=LIBRARY_DOC.split("\n")[0])
    parser.add_argument("source", choices=SOURCES, metavar="SOURCE",
                        help=f"the real rig to build ({', '.join(RIGS)}), or all (every "
                        "shipped rig and every root given) into --out-dir")
    parser.add_argument("--out", type=cli.path, help="output HDF5 file (every source but all)")
    parser.add_argument("--out-dir", type=cli.path, help="output folder (all)")
    parser.add_argument("--root", help="dataset root (kitti, tsinghua, cityscapes; "
                        "chessboard: a folder of left*/right* pairs; oakd: of *_left.png/*_right.png "
                        "pairs and their calibration; default the shipped ones)")
    for name in ("kitti", "kitti-raw", "tsinghua", "cityscapes"):
        parser.add_argument(f"--{name}", help=f"all: {name} root")
    parser.add_argument("--split", help="split folder (tsinghua/cityscapes: under leftImg8bit/; "
                        "kitti: e.g. training)")
    parser.add_argument("--layout", choices=("stereo", "raw"), default="stereo",
                        help="kitti: stereo 2015 / scene flow, or raw")
    parser.add_argument("--image-size", type=int, default=112,
                        help="square side the pairs are resized to, intrinsics transformed "
                        "exactly (default 112)")
    parser.add_argument("--crops", type=cli.positive_int, help="chessboard, oakd: crops per pair (20); "
                        "middlebury: number of crops (500)")
    parser.add_argument("--seed", type=int, default=0,
                        help="seed of the crops and projection pixels (default 0)")
    parser.add_argument("--right", choices=("warp", "released"), default="warp",
                        help="tsinghua: the right image as the left one forward-warped with "
                        "its disparity (warp, default) or as the release made it (released)")
    parser.add_argument("--labels", choices=LABEL_MODES, default="rig",
                        help="tsinghua: the right camera's pose in the left camera's frame "
                        "(rig, default) or the dataset's vehicle-frame pose (vehicle)")
    parser.add_argument("--kitti-calib", metavar="DIR",
                        help="kitti: where the calibration files are when they are not beside "
                        "the images (the data_scene_flow_calib archive, or the raw data's "
                        "<date>_calib archives, unpacked there)")
    parser.add_argument("--limit", type=cli.positive_int,
                        help="use only the first N images (default: all)")
    parser.add_argument("--force", action="store_true", help="all: rebuild existing files")
    args = parser.parse_args(argv)
    if args.source == "all":
        if not args.out_dir:
            parser.error("all needs --out-dir DIR")
    elif not args.out:
        parser.error(f"{args.source} needs --out FILE")
    return args


def main(argv=None):
    args = parse_args(argv)
    command = cli.command_line(PROG, argv)

    def report(line):
        print(line, file=sys.stderr)

    try:
        options = {name: getattr(args, name) for name in OPTIONS}
        if args.source == "all":
            roots = {name: getattr(args, name) for name in ("kitti", "kitti_raw", "tsinghua",
                                                            "cityscapes")}
            paths = build_all(args.out_dir, roots=roots, force=args.force, command=command,
                              report=report, **options)
        else:
            paths = [build_one(args.source, args.out, root=args.root, command=command,
                               report=report, **options)]
    except (ValueError, OSError) as error:
        return cli.fail(PROG, error)
    print("\n".join(paths))
    return 0


if __name__ == "__main__":
    cli.run(main, PROG)
