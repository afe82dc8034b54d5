"""``train.py`` and ``cpl-train``: train one of the paper's networks.

Without ``--data`` a small dataset is generated on first use into the cache
directory (``$CPL_KERAS_CACHE``, default ``~/.cache/cpl_keras``) and a short
demonstration run is made. Killed runs resume when the same command is run
again. ``main(argv, prog)``: ``prog`` is the name in the command's lines
and in the command it records (``train.py`` from the repository,
``cpl-train`` installed). See docs/training.md.
"""

from __future__ import annotations

import dataclasses
import os
import sys

from cpl_keras import cli, distributed
from cpl_keras.training.augment import AUGMENTATIONS
from cpl_keras.cache import cache_dir, enable_compile_cache
from cpl_keras.data.generate import cached_dataset, estimate_cost
from cpl_keras.data.storage import DatasetError
from cpl_keras.datasets import SPLITS
from cpl_keras.errors import Error
from cpl_keras.models import BACKBONES, VARIANTS
from cpl_keras.models.options import (
    ADAPTIVE_WEIGHTS, DISPARITY_HEADS, RECIPES, ModelOptions, recipe,
)
from cpl_keras.models.variants import DISENTANGLE, HEAD_ACTIVATIONS, POINT_ERRORS
from cpl_keras.training import summary_line, train

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


def build_parser(prog=PROG):
    """The command's parser; its options in the order ``--help`` lists them."""
    parser = cli.Parser(
        prog=prog,
        description="Train a camera calibration network (Butt & Taj) on a stereo dataset.",
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
    parser.add_argument("--variant", required=True, choices=VARIANTS,
                        help="the network: baseline (MTL-Baseline, 13 heads, MAE), cpl-u "
                        "(camera projection loss, uniform), cpl-a (CPL with adaptive weights, "
                        "the paper's), deep-homo (the Deep-Homo comparison)")
    parser.add_argument("--data", help="dataset file (.h5) from the data generator; "
                        "default: a small demonstration dataset")
    parser.add_argument("--epochs", type=cli.positive_int, help="maximum epochs (default 200)")
    parser.add_argument("--batch-size", type=cli.positive_int, default=16,
                        help="pairs per training step (default 16, the paper's); at most the "
                        "training split")
    parser.add_argument("--lr", type=cli.positive_float, help="learning rate (default 1e-3, Deep-Homo 1.5e-3)")
    parser.add_argument("--image-size", type=cli.positive_int,
                        help="expected image side; must match the dataset (default: the dataset's)")
    parser.add_argument("--backbone", choices=BACKBONES,
                        help="tower backbone (default inception_v3, the paper's)")
    parser.add_argument("--backbone-weights", type=cli.path, metavar="imagenet|FILE",
                        help="both towers start from InceptionV3's ImageNet weights: imagenet "
                        "(Keras's file, from its cache or downloaded) or FILE, that file in "
                        "Keras's legacy .h5 or Keras 3 .weights.h5 layout (default: random "
                        "initialisation; inception_v3 only)")
    parser.add_argument("--split", choices=SPLITS, default="paper",
                        help="paper: the paper's frame-level 70/30 split (default); drive: "
                        "whole contiguous drives held out; held-out-config: whole rigs held out "
                        "(random protocol); released: the authors' release's own, the first 70 %% "
                        "of an imported release's rows train, the rest validation and test")
    parser.add_argument("--as-released", action="store_true",
                        help="reproduce the released code (labels, loss, val = test)")
    parser.add_argument("--run-dir", type=cli.path, help="run directory (default runs/<variant>-<split>-s<seed>)")
    parser.add_argument("--seed", type=cli.non_negative_int, help="seed of split, shuffling and weights (default 0)")
    parser.add_argument("--data-parallel", action="store_true",
                        help="data parallelism over all local devices, or over every "
                        "process's devices in a process group (docs/training.md)")


def _add_loop_arguments(parser):
    """The training loop: --patience, --workers, --steps-per-execution."""
    parser.add_argument("--patience", type=cli.non_negative_int, default=5, help="early stopping patience")
    parser.add_argument("--workers", type=cli.worker_count, default=1,
                        help="data reading threads (at most the CPUs)")
    parser.add_argument("--steps-per-execution", type=cli.positive_int, default=1,
                        help="training steps per compiled call (Keras's steps_per_execution; "
                        "default 1)")


def _add_head_arguments(parser):
    """The model's knobs (``ModelOptions``, one field each; None: the
    record's default): --recipe, --disentangle, --point-errors,
    --exp-disparity-head, --head-activation, --head-norm, --disparity-head,
    --linear-pitch-head, --linear-focal-head, --alpha-rate, --adaptive-weights,
    --disparity-ceiling, --weight-decay, --clip-norm."""
    parser.add_argument("--recipe", choices=tuple(RECIPES),
                        help="a named set of the options below: paper (default, changes "
                        "nothing) or sound (leaky heads of slope 0.01, --head-norm, the softplus "
                        "disparity head, --clip-norm 1; paper_results/fair-fight); an option "
                        "given as well overrides the recipe's")
    parser.add_argument("--disentangle", choices=DISENTANGLE,
                        help="CPL: the X, Y, Z terms of Eq. 7 train only the pixel heads "
                        "(exact, default) or every head the camera graph reads (partial)")
    parser.add_argument("--point-errors", choices=POINT_ERRORS,
                        help="CPL: Eq. 7's point errors in metres (default, the paper's) or "
                        "divided by each pair's true depth (relative; an ablation)")
    parser.add_argument("--exp-disparity-head", action="store_true", default=None,
                        help="MTL-Baseline: the CPL variants' disparity head, d = exp(z) up to "
                        "--disparity-ceiling, instead of a linear one (an ablation)")
    parser.add_argument("--head-activation", choices=HEAD_ACTIVATIONS,
                        help="the regression heads' hidden activation: relu (default, the "
                        "release's) or a leaky ReLU of slope 0.2 or 0.01 (ablations)")
    parser.add_argument("--head-norm", action="store_true", default=None,
                        help="a LayerNorm of the towers' features before the heads (not the "
                        "paper's)")
    parser.add_argument("--disparity-head", choices=DISPARITY_HEADS,
                        help="default: each variant's own (CPL exp, MTL-Baseline linear); "
                        "softplus: d = floor + softplus(z) starting at the training mean, for "
                        "every variant alike (not the paper's)")
    parser.add_argument("--linear-pitch-head", action="store_false", default=None,
                        dest="bounded_pitch_head",
                        help="an unbounded pitch head (the release's; default: clipped to +-pi/2)")
    parser.add_argument("--linear-focal-head", action="store_false", default=None,
                        dest="positive_focal_head",
                        help="CPL: linear fx, fy heads (the release's; default clipped at 1 px, "
                        "straight-through, since the camera graph divides by them)")
    parser.add_argument("--alpha-rate", type=cli.non_negative_float, help="MTL-CPL-A: how "
                        "many times an ordinary weight's pace the adaptive weights move (default "
                        "10; 1 = Eq. 9 as the paper trains it; 0 = frozen at the first batch's)")
    parser.add_argument("--adaptive-weights", choices=ADAPTIVE_WEIGHTS,
                        help="MTL-CPL-A: Eq. 9's weights learned (default, the paper's) or fixed "
                        "at 1 / mean|y_i| of the training split (range)")
    parser.add_argument("--disparity-ceiling", type=disparity_ceiling, metavar="auto|none|PX",
                        help="the positive disparity head's largest output (auto, default: "
                        "twice the largest training label; none: 1e5 px, the bound before; or "
                        "pixels)")
    parser.add_argument("--weight-decay", type=cli.non_negative_float,
                        help="decoupled weight decay (AdamW; default 0, the paper's Adam)")
    parser.add_argument("--clip-norm", type=cli.positive_float,
                        help="clip the gradient's global norm at this value (default: off, the "
                        "paper's)")


def _add_validation_arguments(parser):
    """Each epoch's validation and the weights it keeps: --bn-statistics,
    --bn-recompute-batches, --monitor, --weight-ema."""
    parser.add_argument("--bn-statistics", choices=("fixed", "epoch"),
                        help="BatchNorm statistics before each validation: fixed (default), the "
                        "same training pairs every epoch, population variance; epoch, the first "
                        "batches of each epoch's order (this project's default before)")
    parser.add_argument("--bn-recompute-batches", type=cli.non_negative_int,
                        help="training batches of that recompute (default 64 fixed, 16 epoch; "
                        "0 = Keras's moving averages, as released)")
    parser.add_argument("--monitor", choices=("nmae", "loss"),
                        help="what early stopping and the kept epoch follow: nmae (default), the "
                        "sum of the ten parameters' validation NMAEs; loss, the validation loss "
                        "(the paper's; as released)")
    parser.add_argument("--weight-ema", type=cli.momentum, metavar="M",
                        help="validate, keep and save a moving average of the weights, momentum "
                        "M (default 0.99, not the paper's; 0: the weights as trained, the "
                        "paper's; as released: 0)")


def _add_extra_arguments(parser):
    """Additions to the paper's training, off by default: --target-scaling,
    --time-budget, --augment."""
    parser.add_argument("--target-scaling", choices=("none", "std"), default="none",
                        help="MTL-Baseline: divide each output's MAE by the target's training "
                        "standard deviation (std; not the paper's) or not (none, default)")
    parser.add_argument("--time-budget", type=cli.positive_float, metavar="SECONDS",
                        help="seconds of training the run may take: no epoch is started that "
                        "would overrun them (judged by the last epoch's length); the run "
                        "then ends as finished with its best epoch (default: no limit)")
    parser.add_argument("--augment", choices=("none",) + AUGMENTATIONS, default="none",
                        help="photometric augmentation of the training batches (exposure, grey, "
                             "blur, noise, JPEG; labels unchanged; not the paper's, default none)")


def _add_output_arguments(parser):
    """What a run prints and logs beyond its results: --term-gradients,
    --head-units, --quiet."""
    parser.add_argument("--term-gradients", action="store_true",
                        help="log, every epoch, the gradient that each loss term sends into the "
                        "towers' shared features (grad_<target> in log.csv; a diagnostic, "
                        "training is unchanged; not with --data-parallel)")
    parser.add_argument("--head-units", action="store_true",
                        help="log, every epoch, each regression head's live first-layer units on "
                        "the same 64 training pairs (dead_<head>: share of pairs with every unit "
                        "at or below zero; units_<head>: units above zero for some pair; a "
                        "diagnostic, training is unchanged; not with --data-parallel)")
    parser.add_argument("--quiet", action="store_true",
                        help="no per-epoch lines or progress bar (the summary line stays)")


def _add_group_arguments(parser):
    """--coordinator, --num-processes, --process-id (``_check_group_arguments``)."""
    group = parser.add_argument_group(
        "process group (with --data-parallel; or Keras's KERAS_DISTRIBUTION_JOB_ADDRESSES, "
        "KERAS_DISTRIBUTION_NUM_PROCESSES, KERAS_DISTRIBUTION_PROCESS_ID)")
    group.add_argument("--coordinator", metavar="HOST:PORT",
                       help="process 0's address, the same on every process")
    group.add_argument("--num-processes", type=cli.positive_int, help="processes in the group")
    group.add_argument("--process-id", type=cli.non_negative_int,
                       help="this process's index, 0 .. N-1 (0 writes the run directory)")


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


def next_step(variant, demo_file, prog=PROG):
    """What to run after the demonstration, with what the dataset will cost
    (measured on ``demo_file`` and by rendering a few pairs now)."""
    text = (
        f"This was a demonstration ({DEMO['pairs']} pairs, the 'small' backbone, "
        f"{DEMO['epochs']} epochs). Full-scale training (InceptionV3 towers, up to 200 "
        "epochs with early stopping):\n"
        f"  python -m cpl_keras.data.generate --protocol cvgl --pairs {FULL_PAIRS} "
        "--out data/cvgl.h5\n"
        f"  {cli.command_line(prog, ['--variant', variant, '--data', 'data/cvgl.h5'])}"
    )
    try:
        cost = estimate_cost(FULL_PAIRS, demo_file)
    except (OSError, ValueError):
        return text
    return text + (
        f"\nThe dataset takes about {cost['bytes'] / 1e9:.1f} GB of disk "
        f"({cost['bytes_per_pair'] / 1e3:.1f} KB a pair at {cost['image_size']} px, measured "
        f"on the demonstration file) and about {_duration(cost['seconds'])} to generate on "
        f"{cost['workers']} core{'s' if cost['workers'] > 1 else ''} "
        f"({cost['seconds_per_pair']:.3f} s a pair on one core, measured just now)."
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


def model_fields(args, backbone):
    """The ``ModelOptions`` fields the command line gives: the recipe's,
    then every option given (an argparse destination named as a field)."""
    fields = dict(recipe(args.recipe or "paper"), backbone=backbone,
                  as_released=args.as_released)
    names = {field.name for field in dataclasses.fields(ModelOptions)}
    fields.update({name: value for name, value in vars(args).items()
                   if name in names - {"backbone", "as_released", "disparity_ceiling"}
                   and value is not None})
    if args.disparity_ceiling is not None:  # ("none": None, the bound of before)
        fields["disparity_ceiling"] = None if args.disparity_ceiling == "none" \
            else args.disparity_ceiling
    return fields


def _train(args, demo, seed, epochs, backbone, run_dir, command, prog):
    try:
        model = ModelOptions(**model_fields(args, backbone))  # (checked before a dataset is made)
        data = demo_dataset() if demo else args.data
        summary = train(
            data, variant=args.variant, run_dir=run_dir, model=model, epochs=epochs,
            batch_size=args.batch_size, learning_rate=args.lr, image_size=args.image_size,
            split=args.split, seed=seed, data_parallel=args.data_parallel,
            patience=args.patience, workers=args.workers,
            steps_per_execution=args.steps_per_execution,
            bn_recompute_batches=args.bn_recompute_batches, bn_statistics=args.bn_statistics,
            monitor=args.monitor, target_scaling=args.target_scaling,
            weight_ema=_weight_ema(args, demo), time_budget_s=args.time_budget,
            verbose=0 if args.quiet else 1,
            augment=None if args.augment == "none" else args.augment,
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

