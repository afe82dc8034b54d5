"""Two variants' test gap, setting by setting (towers, data): does it shrink,
vanish or grow?

    D2=data/reproduce-inception-2000-ema/cvgl_2000_112px_s0_v3.0.h5
    I2=paper_results/inception-2000-ema/runs C2=paper_results/compact-2000-ema/runs
    python analyses/variant_gaps.py \\
        --setting "InceptionV3, 2,000 pairs=$D2,$I2/cvgl_cpl-a-s0,$I2/cvgl_baseline-s0" \\
        --setting "compact, 2,000 pairs=$D2,$C2/cvgl_cpl-a-s0,$C2/cvgl_baseline-s0" \\
        --out runs/gaps.md

Each ``--setting NAME=DATA,RUN_A,RUN_B`` is one seed's pair of runs on one
dataset file (their shared test split; a run directory, published or not,
read through its stored predictions when it has them). Settings may differ
in data, towers and seed; within one, A and B must share the test split.
Writes a Markdown page (and the same as JSON beside it): per setting, each
run's test NMAE; A's NMAE minus B's with its paired bootstrap interval (95 %,
2,000 resamples of the test pairs, ``cpl_keras.evaluation.verdicts.
seed_intervals``, as ``paired_runs.py`` and ``verdicts.py`` draw them) and
the side it decides; and A's NMAE over B's, which stays comparable when
more data lowers both. ``regenerate`` rebuilds a committed page from its
JSON and the command on its first line (no dataset needed).
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def setting(text):
    """``NAME=DATA,RUN_A,RUN_B`` -> ``(name, data, run_a, run_b)``."""
    name, sep, paths = text.partition("=")
    parts = paths.split(",")
    if not sep or not name or len(parts) != 3 or not all(parts):
        raise argparse.ArgumentTypeError(f"expected NAME=DATA,RUN_A,RUN_B, got {text!r}")
    return (name, *parts)


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--setting", action="append", required=True, type=setting,
                        metavar="NAME=DATA,RUN_A,RUN_B", help="one setting (repeatable)")
    parser.add_argument("--a", default="MTL-CPL-A", help="what RUN_A is (the page's words)")
    parser.add_argument("--b", default="MTL-Baseline", help="what RUN_B is")
    parser.add_argument("--out", required=True, help="the Markdown page to write (.md)")
    parser.add_argument("--resamples", type=int, default=2000)
    args = parser.parse_args(argv)
    if not args.out.endswith(".md"):
        parser.error(f"--out must end in .md, got {args.out}")
    if args.resamples < 100:
        parser.error(f"--resamples must be at least 100, got {args.resamples}")
    return args


def gap(raw_a, raw_b, seed, resamples):
    """Per column: A's and B's NMAE, A minus B with its interval and side,
    and A over B."""
    from cpl_keras.evaluation.verdicts import (A_LOWER, B_LOWER, COLUMN_PARAMETER, COLUMNS,
                                               seed_intervals)

    intervals = seed_intervals(seed, raw_a, raw_b, resamples=resamples)
    side = {A_LOWER: "lower", B_LOWER: "higher"}
    out = {}
    for column in COLUMNS:
        i = intervals[COLUMN_PARAMETER[column]]
        out[column] = {"a": i.nmae_a, "b": i.nmae_b, "gap": i.nmae_a - i.nmae_b,
                       "low": i.low, "high": i.high, "answer": side.get(i.answer, "="),
                       "ratio": i.nmae_a / i.nmae_b if i.nmae_b > 0 else None}
    return out


def by_depth(raw_a, raw_b, parts=3):
    """A's MAE over B's per column in ``parts`` equal parts of the test pairs,
    by the depth of the ground-truth point (xCam = fx b / d, Eq. 4a): the
    camera projection terms weigh a parameter's error by the point it moves,
    and that point moves more the farther it is."""
    import numpy as np

    from cpl_keras import camera
    from cpl_keras.evaluation.verdicts import COLUMN_PARAMETER

    truth = {k: np.asarray(v, np.float64) for k, v in raw_a["truth"].items()}
    depth = camera.depth_from_disparity(truth["fx"], truth["baseline"], truth["disparity"])
    order = np.argsort(depth, kind="stable")
    groups = np.array_split(order, parts)
    out = {"depth_m": [[float(depth[g].min()), float(depth[g].max())] for g in groups],
           "pairs": [len(g) for g in groups], "ratio": {}}
    for column, name in COLUMN_PARAMETER.items():
        err_a = np.abs(np.asarray(raw_a["pred"][name], np.float64) - truth[name])
        err_b = np.abs(np.asarray(raw_b["pred"][name], np.float64) - truth[name])
        out["ratio"][column] = [float(err_a[g].mean() / err_b[g].mean())
                                if err_b[g].mean() > 0 else None for g in groups]
    return out


def run_record(path, config):
    return {"run": os.path.relpath(os.path.abspath(path), REPO), "command": config.command,
            "epochs_run": config.epochs_run, "best_epoch": config.best_epoch,
            "wall_time_s": config.wall_time_s}


def compare(settings, resamples):
    """The page's content, setting by setting."""
    from cpl_keras.evaluation.forward_pass import paired_outputs

    result = {}
    for name, data, run_a, run_b in settings:
        (raw_a, config_a), (raw_b, config_b) = (paired_outputs(run_a, data),
                                                paired_outputs(run_b, data))
        result[name] = {"data": os.path.basename(data), "seed": config_a.training.seed,
                        "test_pairs": len(raw_a["indices"]),
                        "a": run_record(run_a, config_a), "b": run_record(run_b, config_b),
                        "columns": gap(raw_a, raw_b, config_a.training.seed, resamples),
                        "by_depth": by_depth(raw_a, raw_b)}
    return result


def markdown(result, a, b, command):
    """The page of ``result`` (``compare``'s, or its JSON) written by ``command``."""
    from cpl_keras import files
    from cpl_keras.evaluation.verdicts import COLUMNS

    head = "| " + " | ".join(COLUMNS) + " |"
    rule = "|---" * (len(COLUMNS) + 1) + "|---|"
    lines = [files.generated_line(command), "",
             f"# {a} against {b}, setting by setting", "", "```", command, "```", "",
             "Test NMAE per column (lower is better); epochs run (kept):", "",
             "| setting | run | epochs (kept) " + head, "|---" + rule]
    for name, s in result.items():
        for key, label in (("a", a), ("b", b)):
            lines.append(f"| {name} | {label} | {s[key]['epochs_run']} ({s[key]['best_epoch']}) | "
                         + " | ".join(f"{s['columns'][c][key]:.3f}" for c in COLUMNS) + " |")
    lines += ["", f"{a}'s NMAE minus {b}'s, with the paired bootstrap's 95 % interval over "
              f"the setting's test pairs: `lower` or `higher` ({a} lower or higher) where "
              "the interval excludes 0, else `=`.", "",
              "| setting | seed, test pairs " + head + " lower / higher |", "|---" + rule]
    for name, s in result.items():
        cells = [s["columns"][c] for c in COLUMNS]
        answers = [cell["answer"] for cell in cells]
        lines.append(f"| {name} | {s['seed']}, {s['test_pairs']:,} | " + " | ".join(
            f"{cell['gap']:+.3f} {cell['answer']} [{cell['low']:+.3f}, {cell['high']:+.3f}]"
            for cell in cells) + f" | {answers.count('lower')} / {answers.count('higher')} |")
    lines += ["", f"{a}'s NMAE over {b}'s (below 1: {a} lower):", "",
              "| setting " + head, "|---" * (len(COLUMNS) + 1) + "|"]
    for name, s in result.items():
        lines.append(f"| {name} | " + " | ".join(
            "-" if s["columns"][c]["ratio"] is None else f"{s['columns'][c]['ratio']:.2f}"
            for c in COLUMNS) + " |")
    return "\n".join(lines + depth_lines(result, a, b)) + "\n"


def depth_lines(result, a, b):
    from cpl_keras.evaluation.verdicts import COLUMNS

    lines = ["", f"{a}'s MAE over {b}'s in thirds of each setting's test pairs by the depth "
             "of the ground-truth point (xCam = fx b / d, Eq. 4a; near, middle, far):", "",
             "| setting | depth (m), pairs | " + " | ".join(COLUMNS) + " |",
             "|---|---" + "|---" * len(COLUMNS) + "|"]
    for name, s in result.items():
        d = s["by_depth"]
        for i, ((low, high), pairs) in enumerate(zip(d["depth_m"], d["pairs"])):
            lines.append(f"| {name} | {low:.1f}-{high:.1f}, {pairs} | " + " | ".join(
                "-" if d["ratio"][c][i] is None else f"{d['ratio'][c][i]:.2f}"
                for c in COLUMNS) + " |")
    return lines


def command_line(args):
    return " ".join(["python analyses/variant_gaps.py"]
                    + [f'--setting "{n}={d},{ra},{rb}"' for n, d, ra, rb in args.setting]
                    + ([f'--a "{args.a}"'] if args.a != "MTL-CPL-A" else [])
                    + ([f'--b "{args.b}"'] if args.b != "MTL-Baseline" else [])
                    + [f"--out {args.out}"])


def regenerate(page_path):
    """The committed page ``page_path`` as this script writes it, from its
    JSON beside it and the command on its first line (``--a``, ``--b``)."""
    from cpl_keras import files

    command, payload = files.page_source(page_path)
    args = parse_args(shlex.split(command)[2:])
    return markdown(payload, args.a, args.b,
                    command)


def main(argv=None):
    from cpl_keras import files

    args = parse_args(argv)
    result = compare(args.setting, args.resamples)
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    files.write_page(args.out, markdown(result, args.a, args.b, command_line(args)), result)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.path.insert(0, REPO)
    from cpl_keras import cli

    cli.run(main, "analyses/variant_gaps.py")
