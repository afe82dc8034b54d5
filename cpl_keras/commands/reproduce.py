"""The reproduction's command line (``python -m cpl_keras.reproduce``,
installed: ``cpl-reproduce``): its options, their checks, and the run."""

from __future__ import annotations

import os

from cpl_keras import cli
from cpl_keras.data.storage import DatasetError
from cpl_keras.datasets import SPLITS
from cpl_keras.models.variants import BACKBONES
from cpl_keras.reproduce.pipeline import rebuild, rebuild_command, reproduce
from cpl_keras.reproduce.plan import GPU_SIZED_PAIRS, cpu_cost, gpu_sized, has_accelerator
from cpl_keras.reproduce.presets import PRESETS, PROG, REAL_ROOTS, default_folders, settings

# ---------------------------------------------------------------------------
# Command line
# ---------------------------------------------------------------------------
#: What ``--help`` says the command does.
DESCRIPTION = ("Reproduce the paper's tables: generate the datasets, train every run, and write "
               "Tables 1 and 2 with REPORT.md (docs/evaluation.md).")
#: Options that set the scale (not allowed with --from-predictions).
SCALE_OPTIONS = ("quick", "preset", "pairs", "random_pairs", "epochs", "patience", "backbone",
                 "image_size", "crops", "chessboard_crops", "seeds", "random_seeds", "workers",
                 "data_dir", "runs_dir", "geometric_max", "jobs", "run_budget",
                 "allow_cpu", "partial", "release_dir", "split", "backbone_weights") + REAL_ROOTS


def add_arguments(parser):
    """The reproduction's options, as an argument group of ``parser``; every
    number is checked when parsed (``cli.positive_int``)."""
    group = parser.add_argument_group("reproduce (cpl_keras/reproduce/)")
    _add_scale_arguments(group)
    _add_run_arguments(group)
    _add_folder_arguments(group)
    return group


def _add_scale_arguments(group):
    """The scale: a named one (--preset, --quick) and the values that override
    it (pairs, epochs, patience, towers, image size, crops, seeds)."""
    positive, non_negative = cli.positive_int, cli.non_negative_int
    group.add_argument("--preset", choices=tuple(PRESETS), metavar="NAME",
                       help=f"a named scale: {', '.join(PRESETS)} (docs/evaluation.md, "
                       "Presets; default: the paper's); the flags below override its values")
    group.add_argument("--quick", action="store_true", help="tiny settings (minutes)")
    group.add_argument("--pairs", type=positive, metavar="N",
                       help="cvgl-protocol pairs (paper: 123017)")
    group.add_argument("--random-pairs", type=positive, metavar="N", help="random-protocol pairs")
    group.add_argument("--epochs", type=positive, metavar="N",
                       help="maximum epochs per run (paper: 200)")
    group.add_argument("--patience", type=non_negative, metavar="N",
                       help="early stopping patience (paper: 5)")
    group.add_argument("--backbone", choices=BACKBONES, metavar="NAME",
                       help=f"the towers: {', '.join(BACKBONES)} (paper: inception_v3)")
    group.add_argument("--image-size", type=positive, metavar="PX",
                       help="square image side of every dataset (paper: 112)")
    group.add_argument("--crops", type=positive, metavar="N", help="Middlebury crops for Table 2")
    group.add_argument("--chessboard-crops", type=positive, metavar="N",
                       help="crops per OpenCV chessboard pair for Table 2")
    group.add_argument("--seeds", type=positive, metavar="N",
                       help="cvgl runs per variant, seeds SEED, SEED+1, ...")
    group.add_argument("--random-seeds", type=positive, metavar="N",
                       help="random-protocol runs per variant")
    group.add_argument("--split", choices=SPLITS, metavar="NAME",
                       help=f"the cvgl runs' split: {', '.join(SPLITS)} (default: the preset's)")
    group.add_argument("--backbone-weights", metavar="W",
                       help="the towers' initial weights: imagenet, FILE or none (random; "
                       "train.py --backbone-weights)")


def _add_run_arguments(group):
    """How the runs are made: --workers, --run-budget, --allow-cpu, --jobs,
    --partial, and the first --seed."""
    group.add_argument("--workers", type=cli.worker_count, metavar="N",
                       help="data generation processes (default: every core)")
    group.add_argument("--run-budget", type=cli.positive_float, metavar="SECONDS",
                       help="training seconds per run (train.py --time-budget)")
    group.add_argument("--allow-cpu", action="store_true",
                       help="run settings sized for a GPU (InceptionV3 towers on "
                       f"{GPU_SIZED_PAIRS:,}+ pairs) on a machine without one")
    group.add_argument("--jobs", type=cli.positive_int, metavar="N",
                       help="training runs at once, each its own process (default 1)")
    group.add_argument("--partial", action="store_true",
                       help="train nothing: the tables and REPORT.md of the seeds finished so "
                       "far, into OUT/partial/")
    group.add_argument("--seed", type=cli.non_negative_int, default=0, metavar="SEED",
                       help="seed of the datasets and of the first run (default 0)")


def _add_folder_arguments(group):
    """Where things are: the real sets' roots (Table 2), the datasets' and
    runs' folders, the discussion, and a reproduction to rebuild
    (--from-predictions)."""
    group.add_argument("--release-dir", metavar="DIR",
                       help="the authors' released files (--preset paper-release)")
    for flag, name in (("--kitti", "KITTI stereo 2015"), ("--kitti-raw", "KITTI raw"),
                       ("--tsinghua", "Tsinghua-Daimler Cyclist"), ("--cityscapes", "Cityscapes")):
        group.add_argument(flag, metavar="DIR", help=f"Table 2: the {name} root")
    group.add_argument("--data-dir", metavar="DIR", help="where the datasets go (default "
                       "data/reproduce[-PRESET]; --quick: data/quick)")
    group.add_argument("--runs-dir", metavar="DIR", help="where the runs go (default "
                       "runs/reproduce[-PRESET]; --quick: runs/quick)")
    group.add_argument("--discussion", metavar="FILE",
                       help="Markdown appended to REPORT.md as the comparison with the paper "
                       "(default: OUT/discussion.md, if there)")
    group.add_argument("--from-predictions", metavar="DIR",
                       help="rebuild the tables and REPORT.md in DIR from its published "
                       "predictions alone")


def resolve_args(parser, args):
    """Check the reproduction's options (``parser.error``: one line, exit 2,
    before anything is written) and fill in the folders and the settings
    (``args.config``: a ``Settings``)."""
    if args.from_predictions is not None:
        given = [name for name in SCALE_OPTIONS if getattr(args, name, None) not in (None, False)]
        if given:
            parser.error(f"--from-predictions rebuilds the tables of DIR as they were made; "
                         f"drop --{given[0].replace('_', '-')}")
        if args.out is not None and os.path.abspath(args.out) != \
                os.path.abspath(args.from_predictions):
            parser.error("--from-predictions DIR writes into DIR; drop --out")
        if args.discussion is not None and not os.path.isfile(args.discussion):
            parser.error(f"--discussion: file not found: {args.discussion}")
        args.out = args.from_predictions
        args.config = None
        return args
    try:
        args.config = settings(
            args.quick, args.preset, pairs=args.pairs, random_pairs=args.random_pairs,
            epochs=args.epochs, patience=args.patience, backbone=args.backbone,
            image_size=args.image_size, crops=args.crops, chessboard_crops=args.chessboard_crops,
            geometric_max=args.geometric_max, seeds=args.seeds, random_seeds=args.random_seeds,
            workers=args.workers, run_budget_s=args.run_budget, split=args.split,
            backbone_weights=args.backbone_weights)
    except ValueError as error:
        parser.error(str(error))
    _check_release_dir(parser, args)
    if gpu_sized(args.config) and not args.allow_cpu and not has_accelerator():
        parser.error(cpu_cost(args.config, args.seed))
    out, data_dir, runs_dir = default_folders(args.config.preset)
    args.out = args.out or out
    args.data_dir = args.data_dir or data_dir
    args.runs_dir = args.runs_dir or runs_dir
    if args.discussion is None:
        args.discussion = os.path.join(args.out, "discussion.md")
    for name in REAL_ROOTS:
        root = getattr(args, name)
        if root is not None and not os.path.isdir(root):
            parser.error(f"--{name.replace('_', '-')}: dataset root not found: {root}")
    return args


def _check_release_dir(parser, args):
    """``--release-dir`` given exactly where the settings read the release's files."""
    wanted = args.config.data == "release"
    if wanted and args.release_dir is None:
        parser.error(f"--preset {args.config.preset} trains on the authors' released files: "
                     "give their folder with --release-dir DIR (docs/data.md)")
    if args.release_dir is not None and not wanted:
        parser.error("--release-dir is read by --preset paper-release only")
    if args.release_dir is not None and not os.path.isdir(args.release_dir):
        parser.error(f"--release-dir: folder not found: {args.release_dir}")


def run(args, command, prog=PROG):
    """Run the reproduction (or the rebuild) for resolved ``args``; the exit status."""
    try:
        if args.from_predictions is not None:
            report = rebuild(args.out, rebuild_command(args.out), args.discussion)
        else:
            with cli.interruptible():
                report = reproduce(
                    out_dir=args.out, data_dir=args.data_dir, runs_dir=args.runs_dir,
                    config=args.config, seed=args.seed, command=command,
                    discussion_file=args.discussion,
                    real_roots={name: getattr(args, name) for name in REAL_ROOTS},
                    jobs=args.jobs or 1, partial=args.partial,
                    release_dir=getattr(args, "release_dir", None))
    except KeyboardInterrupt:  # every stage is resumable: the same command goes on
        return cli.interrupted(prog, resume=command)
    except (ValueError, DatasetError, OSError) as error:  # EvaluationError is a ValueError
        return cli.fail(prog, error)
    print(f"report: {report}")
    return 0


def parse_args(argv=None):
    """The command line, checked and resolved (``resolve_args``); a bad one
    ends the process with one line and exit status 2."""
    parser = cli.Parser(prog=PROG, description=DESCRIPTION)
    parser.add_argument("--out", type=cli.path, metavar="OUT",
                        help="output folder (default paper_results/ of the current "
                             "directory, or the preset's own under it)")
    parser.add_argument("--geometric-max", type=cli.positive_int, metavar="N",
                        help="the Geometric baseline on the first N evaluation pairs only")
    add_arguments(parser)
    return resolve_args(parser, parser.parse_args(argv))


def main(argv=None):
    return run(parse_args(argv), cli.command_line(PROG, argv), PROG)


if __name__ == "__main__":
    cli.run(main, PROG)

