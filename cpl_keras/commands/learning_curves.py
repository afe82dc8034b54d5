"""``python -m cpl_keras.learning_curves`` (``cpl-learning-curves``): validation
NMAE against epochs for run directories, or the experiment that trains them
(``cpl_keras.learning_curves``)."""

from __future__ import annotations

from cpl_keras import cli
from cpl_keras.learning_curves import CurveError, markdown, run_experiment, write_outputs
from cpl_keras.learning_curves import __doc__ as LIBRARY_DOC


def main(argv=None):
    parser = cli.Parser(prog="python -m cpl_keras.learning_curves",
                        description=LIBRARY_DOC.split("\n\n")[0])
    parser.add_argument("runs", nargs="*", help="run directories")
    parser.add_argument("--out", type=cli.path, required=True, help="output folder (created if missing)")
    parser.add_argument("--experiment", action="store_true",
                        help="make the datasets and train the four runs first")
    parser.add_argument("--pairs", type=int, default=8000,
                        help="--experiment: cvgl pairs of its dataset (default 8000)")
    parser.add_argument("--backbone", default="small_resnet",
                        help="--experiment: the towers (default small_resnet)")
    parser.add_argument("--only", action="append",
                        help="with --experiment: train only this run (repeatable; e.g. "
                        "cvgl-cpl-a-small_resnet), so runs can share the machine in parallel")
    parser.add_argument("--keep-earlier", action="store_true",
                        help="keep the rows of runs drawn into --out before that are not "
                        "given now")
    parser.add_argument("--at-epoch", type=cli.positive_int,
                        help="also tabulate every run's validation NMAE after this many epochs")
    parser.add_argument("--data-dir", default="data",
                        help="--experiment: where its dataset goes (default data)")
    parser.add_argument("--runs-dir", default="runs/learning",
                        help="--experiment: where its runs go (default runs/learning)")
    args = parser.parse_args(argv)
    try:
        if args.experiment:
            rows = run_experiment(data_dir=args.data_dir, runs_dir=args.runs_dir,
                                  out_dir=args.out, pairs=args.pairs, backbone=args.backbone,
                                  only=args.only)
        elif args.runs:
            rows = write_outputs(args.runs, args.out, keep_earlier=args.keep_earlier,
                                 at_epoch=args.at_epoch,
                                 command=cli.command_line(parser.prog, argv))
        else:
            parser.error("give run directories or --experiment")
    except (CurveError, OSError, ValueError) as error:
        return cli.fail(parser.prog, error)
    print(markdown(rows))
    return 0


if __name__ == "__main__":
    cli.run(main, "python -m cpl_keras.learning_curves")
