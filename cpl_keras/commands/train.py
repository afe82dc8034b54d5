"""``train.py`` and ``cpl-train``: train one of the paper's networks.

Without ``--data`` a small dataset is generated on first use into the cache
directory (``$CPL_KERAS_CACHE``, default ``~/.cache/cpl_keras``) and a short
demonstration run is made. Killed runs resume when the same command is run
again. ``main(argv, prog)``: ``prog`` is the name in the command's lines
and in the command it records (``train.py`` from the repository,
``cpl-train`` installed). See docs/training.md.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys

from cpl_keras import cli, distributed
from cpl_keras.training_options import AUGMENTATIONS
from cpl_keras.cache import cache_dir, enable_compile_cache
from cpl_keras.data.estimate import estimate_cost
from cpl_keras.data.generate import cached_dataset
from cpl_keras.data.storage import DatasetError
from cpl_keras.datasets import SPLITS
from cpl_keras.errors import Error
from cpl_keras.models import BACKBONES, VARIANTS
from cpl_keras.models.options import ADAPTIVE_WEIGHTS, DISPARITY_HEADS, ModelOptions
from cpl_keras.models.variants import DISENTANGLE, HEAD_ACTIVATIONS, POINT_ERRORS
from cpl_keras.training import summary_line, train
from cpl_keras.training_options import RECIPES, TrainingOptions, recipe, split_fields

#: The demonstration run (no --data): dataset and training settings chosen to
#: finish in a minute or so on a laptop CPU (README.md). Its 256 training
#: steps are too few for the default average of the weights (momentum 0.99,
#: about 100 steps): that lagging average scored the demonstration's test
#: pairs worse on every column than the weights as trained, and momentum 0.9
#: (about 10 steps) as well as them (docs/training.md).
DEMO = {"pairs": 800, "image_size": 112, "epochs": 8, "backbone": "small", "seed": 0,
        "weight_ema": 0.9}


#: The name the command goes by (``train.py`` passes its own).
PROG = "cpl-train"


def disparity_ceiling(text):
    """argparse type of --disparity-ceiling: auto, none or a positive number."""
    if text in ("auto", "none"):
        return text
    return cli.positive_float(text)


#: The options ``--help`` leaves out, by what they are about: docs/training.md's
#: options table has every option (``--help``'s epilog says so and names these).
MORE_OPTIONS = {
    "the heads and losses": ("--disentangle", "--point-errors",
                             "--exp-disparity-head", "--head-activation", "--head-norm",
                             "--disparity-head", "--linear-pitch-head", "--linear-focal-head",
                             "--alpha-rate", "--adaptive-weights", "--disparity-ceiling",
                             "--weight-decay", "--clip-norm", "--target-scaling"),
    "validation": ("--monitor", "--bn-statistics", "--bn-recompute-batches"),
    "diagnostics": ("--term-gradients", "--head-units"),
    "a process group": ("--coordinator", "--num-processes", "--process-id"),
    "speed": ("--steps-per-execution",),
}
HIDDEN = argparse.SUPPRESS


def build_parser(prog=PROG):
    """The command's parser; its options in the order ``--help`` lists them,
    the ones it leaves out (``MORE_OPTIONS``) named in its epilog."""
    more = "; ".join(f"{topic}: {', '.join(flags)}" for topic, flags in MORE_OPTIONS.items())
    parser = cli.Parser(
        prog=prog,
        description="Train a camera calibration network (Butt & Taj) on a stereo dataset; "
        "without --data, a short demonstration.",
        epilog="Every option, with its default and meaning: docs/training.md, section "
        f"Options; not listed above, {more}.",
    )
    _add_run_arguments(parser)
    _add_group_arguments(parser)
    _add_loop_arguments(parser)
    _add_head_arguments(parser)
    _add_validation_arguments(parser)
    _add_extra_arguments(parser)
    _add_output_arguments(parser)
    return parser


def _add_run_arguments(parser):
    """The run (--variant .. --data-parallel): the network and its towers
    (--backbone, --backbone-weights), the dataset and its split, the
    schedule, the run directory, the seed, data parallelism."""
    parser.add_argument("--variant", required=True, choices=VARIANTS, metavar="V",
                        help=f"the network: {', '.join(VARIANTS)} (cpl-a: the paper's)")
    parser.add_argument("--data", metavar="FILE",
                        help="dataset (.h5) of the data generator (default: a demonstration)")
    parser.add_argument("--epochs", type=cli.positive_int, metavar="N",
                        help="maximum epochs (default 200; the demonstration 8)")
    parser.add_argument("--batch-size", type=cli.positive_int, default=16, metavar="N",
                        help="pairs per training step (default 16, the paper's)")
    parser.add_argument("--lr", type=cli.positive_float, metavar="LR", dest="learning_rate",
                        help="learning rate (default 1e-3; deep-homo 1.5e-3)")
    parser.add_argument("--image-size", type=cli.positive_int, metavar="PX",
                        help="the dataset's image side, checked (default: its own)")
    parser.add_argument("--backbone", choices=BACKBONES, metavar="NAME",
                        help=f"the towers: {', '.join(BACKBONES)} (default inception_v3)")
    parser.add_argument("--backbone-weights", type=cli.path, metavar="W",
                        help="imagenet or FILE: InceptionV3's ImageNet weights (default: random)")
    parser.add_argument("--split", choices=SPLITS, default="paper", metavar="NAME",
                        help=f"{', '.join(SPLITS)} (default paper)")
    parser.add_argument("--as-released", action="store_true",
                        help="reproduce the released code (labels, loss, val = test)")
    parser.add_argument("--run-dir", type=cli.path, metavar="DIR",
                        help="default runs/<variant>-<split>-s<seed>")
    parser.add_argument("--seed", type=cli.non_negative_int, metavar="N",
                        help="seed of split, shuffling and weights (default 0)")
    parser.add_argument("--data-parallel", action="store_true",
                        help="data parallelism over every device, or a process group's")


def _add_loop_arguments(parser):
    """The training loop: --patience, --workers, --steps-per-execution."""
    parser.add_argument("--patience", type=cli.non_negative_int, default=5, metavar="N",
                        help="early stopping patience (default 5)")
    parser.add_argument("--workers", type=cli.worker_count, default=1, metavar="N",
                        help="data reading threads (default 1)")
    parser.add_argument("--steps-per-execution", type=cli.positive_int, default=1, help=HIDDEN)


def _add_head_arguments(parser):
    """The model's knobs (``ModelOptions``, one field each; None: the
    record's default): --recipe, --disentangle, --point-errors,
    --exp-disparity-head, --head-activation, --head-norm, --disparity-head,
    --linear-pitch-head, --linear-focal-head, --alpha-rate, --adaptive-weights,
    --disparity-ceiling; and the optimiser's (``TrainingOptions``):
    --weight-decay, --clip-norm."""
    parser.add_argument("--recipe", choices=tuple(RECIPES), metavar="NAME",
                        help="paper (default) or sound: a named set of the model's options")
    parser.add_argument("--disentangle", choices=DISENTANGLE, help=HIDDEN)
    parser.add_argument("--point-errors", choices=POINT_ERRORS, help=HIDDEN)
    parser.add_argument("--exp-disparity-head", action="store_true", default=None, help=HIDDEN)
    parser.add_argument("--head-activation", choices=HEAD_ACTIVATIONS, help=HIDDEN)
    parser.add_argument("--head-norm", action="store_true", default=None, help=HIDDEN)
    parser.add_argument("--disparity-head", choices=DISPARITY_HEADS, help=HIDDEN)
    parser.add_argument("--linear-pitch-head", action="store_false", default=None,
                        dest="bounded_pitch_head", help=HIDDEN)
    parser.add_argument("--linear-focal-head", action="store_false", default=None,
                        dest="positive_focal_head", help=HIDDEN)
    parser.add_argument("--alpha-rate", type=cli.non_negative_float, help=HIDDEN)
    parser.add_argument("--adaptive-weights", choices=ADAPTIVE_WEIGHTS, help=HIDDEN)
    parser.add_argument("--disparity-ceiling", type=disparity_ceiling, help=HIDDEN)
    parser.add_argument("--weight-decay", type=cli.non_negative_float, help=HIDDEN)
    parser.add_argument("--clip-norm", type=cli.positive_float, help=HIDDEN)


def _add_validation_arguments(parser):
    """Each epoch's validation and the weights it keeps: --bn-statistics,
    --bn-recompute-batches, --monitor, --weight-ema."""
    parser.add_argument("--bn-statistics", choices=("fixed", "epoch"), help=HIDDEN)
    parser.add_argument("--bn-recompute-batches", type=cli.non_negative_int, help=HIDDEN)
    parser.add_argument("--monitor", choices=("nmae", "loss"), help=HIDDEN)
    parser.add_argument("--weight-ema", type=cli.momentum, metavar="M",
                        help="validate and keep a moving average of the weights (default 0.99, "
                        "the demonstration 0.9; 0: the paper's, the weights as trained)")


def _add_extra_arguments(parser):
    """Additions to the paper's training, off by default: --target-scaling,
    --time-budget, --augment."""
    parser.add_argument("--target-scaling", choices=("none", "std"), default="none", help=HIDDEN)
    parser.add_argument("--time-budget", type=cli.positive_float, metavar="SECONDS",
                        dest="time_budget_s",
                        help="seconds of training: no epoch starts that would overrun them")
    parser.add_argument("--augment", choices=("none",) + AUGMENTATIONS, metavar="NAME",
                        help=f"none (default) or {', '.join(AUGMENTATIONS)}: "
                        "augmented training pixels, exact labels")


def _add_output_arguments(parser):
    """What a run prints and logs beyond its results: --term-gradients,
    --head-units, --quiet."""
    parser.add_argument("--term-gradients", action="store_true", help=HIDDEN)
    parser.add_argument("--head-units", action="store_true", help=HIDDEN)
    parser.add_argument("--quiet", action="store_true",
                        help="no per-epoch lines or progress bar (the summary line stays)")


def _add_group_arguments(parser):
    """--coordinator, --num-processes, --process-id (``_check_group_arguments``;
    or Keras's KERAS_DISTRIBUTION_* variables, which they set)."""
    parser.add_argument("--coordinator", metavar="HOST:PORT", help=HIDDEN)
    parser.add_argument("--num-processes", type=cli.positive_int, help=HIDDEN)
    parser.add_argument("--process-id", type=cli.non_negative_int, help=HIDDEN)


def demo_dataset():
    """The demonstration dataset, generated on first use."""
    try:
        return cached_dataset(
            cache_dir(), protocol="cvgl", pairs=DEMO["pairs"], seed=DEMO["seed"],
            image_size=DEMO["image_size"], prefix="demo-",
            log=lambda line: print(f"Demonstration dataset: {line}", file=sys.stderr))
    except (OSError, ValueError) as error:
        raise DatasetError(f"cannot generate the demonstration dataset: {error}") from None


#: The paper's number of cvgl pairs.
FULL_PAIRS = 123017
#: Where the demonstration's full-scale command puts them: a name of its own
#: (docs/data.md's data/cvgl.h5 has 10,000 pairs, and the generator refuses
#: to put other settings over it).
FULL_DATA = f"data/cvgl-{FULL_PAIRS}.h5"


def next_step(variant, demo_file, prog=PROG):
    """What to run after the demonstration, with what the dataset will cost
    (measured on ``demo_file``, and by rendering a sample of pairs now with
    the generator's workers: ``cpl_keras.data.estimate``)."""
    text = (
        f"This was a demonstration ({DEMO['pairs']} pairs, the 'small' backbone, "
        f"{DEMO['epochs']} epochs). Full-scale training (InceptionV3 towers, up to 200 "
        "epochs with early stopping):\n"
        f"  python -m cpl_keras.data.generate --protocol cvgl --pairs {FULL_PAIRS} "
        f"--out {FULL_DATA}\n"
        f"  {cli.command_line(prog, ['--variant', variant, '--data', FULL_DATA])}"
    )
    try:
        cost = estimate_cost(FULL_PAIRS, demo_file)
    except (OSError, ValueError):
        return text
    workers = cost["workers"]
    load = "" if cost["load"] is None else f" (load {cost['load']:.1f} on {cost['cpus']} cores)"
    return text + (
        f"\nThe dataset takes about {cost['bytes'] / 1e9:.1f} GB of disk "
        f"({cost['bytes_per_pair'] / 1e3:.1f} KB a pair at {cost['image_size']} px, measured "
        f"on the demonstration file) and about {_duration(cost['seconds'])} to generate with "
        f"{workers} worker process{'es' if workers > 1 else ''}: an estimate from "
        f"{cost['sampled_pairs']} pairs sampled just now ({cost['pairs_per_second']:.0f} pairs/s "
        f"over {cost['sample_seconds']:.1f} s) at this machine's present load{load}; more "
        "load, more time."
    )


def _duration(seconds):
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def main(argv=None, prog=PROG):
    parser = build_parser(prog)
    args = parser.parse_args(argv)
    demo = args.data is None
    _check_group_arguments(parser, args, demo)
    seed = args.seed if args.seed is not None else DEMO["seed"]
    epochs = args.epochs if args.epochs is not None else (DEMO["epochs"] if demo else 200)
    backbone = args.backbone or (DEMO["backbone"] if demo else "inception_v3")
    run_dir = args.run_dir or os.path.join(
        "runs", ("demo-" if demo else "") + f"{args.variant}-{args.split}-s{seed}"
        + ("-released" if args.as_released else "")
    )
    command = cli.command_line(prog, argv)
    enable_compile_cache()

    try:
        with cli.interruptible():
            return _train(args, demo, seed, epochs, backbone, run_dir, command, prog)
    except KeyboardInterrupt:  # cli.Interrupted, or a Ctrl-C outside the block
        # a kill's state: the last completed epoch is checkpointed; the same
        # command resumes after it
        return cli.interrupted(prog, resume=command)


def _check_group_arguments(parser, args, demo):
    """--coordinator, --num-processes and --process-id: all three or none
    (then Keras's variables, which they set, may describe the group)."""
    flags = (args.coordinator, args.num_processes, args.process_id)
    if any(flag is not None for flag in flags):
        if any(flag is None for flag in flags):
            parser.error("--coordinator, --num-processes and --process-id go together")
        distributed.set_environment(*flags)
    try:
        group = distributed.group_from_environment()
    except distributed.DistributedError as error:
        parser.error(str(error))
    if group is not None and not args.data_parallel:
        parser.error("a process group (--coordinator or KERAS_DISTRIBUTION_*) trains with "
                     "--data-parallel")
    if group is not None and demo:
        parser.error("a process group trains on --data (each process its own copy)")


def _weight_ema(args, demo):
    """--weight-ema as given; unset, the demonstration's own (``DEMO``) or
    training's default (None)."""
    if args.weight_ema is None and demo and not args.as_released:
        return DEMO["weight_ema"]
    return args.weight_ema


def records(args, demo, seed, epochs, backbone):
    """The run's two records, ``(ModelOptions, TrainingOptions)``, as the
    command line gives them: the recipe's fields, then every option given
    (an argparse destination named as a field of either record; "none"
    where an option offers it is the field's None), the demonstration's
    defaults where it runs. Checked before a dataset is made."""
    fields = recipe(args.recipe or "paper")
    names = {field.name for field in dataclasses.fields(ModelOptions)} | {
        field.name for field in dataclasses.fields(TrainingOptions)}
    fields.update({name: None if value == "none" else value
                   for name, value in vars(args).items()
                   if name in names - {"variant", "target_scaling"} and value is not None})
    fields.update(backbone=backbone, seed=seed, epochs=epochs,
                  weight_ema=_weight_ema(args, demo), target_scaling=args.target_scaling)
    model, training = split_fields(fields)
    return ModelOptions(**model), TrainingOptions(**training)


def _train(args, demo, seed, epochs, backbone, run_dir, command, prog):
    try:
        model, training = records(args, demo, seed, epochs, backbone)
        data = demo_dataset() if demo else args.data
        summary = train(
            data, variant=args.variant, run_dir=run_dir, model=model, training=training,
            steps_per_execution=args.steps_per_execution, verbose=0 if args.quiet else 1,
            command=command, return_model=False, term_gradients=args.term_gradients,
            head_units=args.head_units,
        )
    except (Error, OSError) as error:  # (DatasetError, TrainingError, RunError, ...)
        return cli.fail(prog, error)
    if summary.finished_before:
        # nothing trained, no file changed
        print(f"already {summary.config.status}, left as it is: {summary_line(summary)}")
        return 0
    if summary.config.status == "failed":
        # diverged: the run directory says so (and keeps the best weights so
        # far); the next run into it replaces it
        return cli.fail(prog, summary_line(summary))
    print(summary_line(summary))
    if demo:
        print(next_step(args.variant, data, prog))
    return 0

