"""Where MTL-CPL-A's training-loss jumps sit, from its committed logs: each
epoch's loss split into Eq. 9's terms as far as log.csv tells them.

    python analyses/loss_jumps.py          # paper_results/fair-fight/loss-jumps.md

MTL-CPL-A's objective is ``sum_i alpha_i L_i + s_i`` over the 13 targets
(``cpl_keras.models.losses``; ``alpha_i = exp(-s_i)``), where ``L_i`` is
1/13 of: for the ten parameters, the parameter's own absolute error plus
the error, in metres, of the point it moves alone (Eq. 7); for X, Y, Z, the
camera graph's point (every predicted value in it) against the truth. A
log.csv row holds the epoch's mean loss, each output's training MAE (the
ten parameters' own errors and the graph's X, Y, Z) and each alpha_i at the
epoch's end. So an epoch's loss is split into: ``sum s_i``; the X, Y, Z
terms, ``sum alpha_k MAE_k / 13``; the parameters' own errors, ``sum
alpha_p MAE_p / 13``; and the rest, the ten parameters' point errors
(which the log does not hold one by one) together with the error of
taking the end-of-epoch alpha_i for the whole epoch. Every epoch whose loss
rose by more than ``--rise`` over the epoch before is listed with the rise
of each part. The range arm (fixed alpha_i) is split the same way, for
contrast. Per pair, nothing is logged: which pairs, and which value they
predicted, the logs cannot tell.
"""

from __future__ import annotations

import argparse
import math
import os

from cpl_keras.camera import PARAMETERS, TARGETS
from cpl_keras.runs import read_log

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RUNS = "paper_results/fair-fight/inception/runs"
OUT = "paper_results/fair-fight/loss-jumps.md"
COMMAND = "python analyses/loss_jumps.py"
#: The runs split, in the page's order: (name, log under RUNS).
ARMS = (("MTL-CPL-A", "cvgl_cpl-a-s{seed}_log.csv"),
        ("MTL-CPL-A (range weights)", "cvgl_cpl-a-range-s{seed}_log.csv"))
SEEDS = (0, 1, 2)
#: A jump: a rise of the epoch's mean loss by more than this over the epoch before.
RISE = 5.0


def parts(row):
    """One log row's loss split: ``loss``, ``s`` (sum of s_i), ``points``
    (the X, Y, Z terms), ``own`` (the parameters' own errors), ``rest``."""
    alpha = {k: row[f"alpha_{k}"] for k in TARGETS}
    s = sum(-math.log(alpha[k]) for k in TARGETS)
    points = sum(alpha[k] * row[f"{k}_mae"] for k in ("X", "Y", "Z")) / len(TARGETS)
    own = sum(alpha[p] * row[f"{p}_mae"] for p in PARAMETERS) / len(TARGETS)
    return {"loss": row["loss"], "s": s, "points": points, "own": own,
            "rest": row["loss"] - s - points - own}


def jumps(rows, rise=RISE):
    """The epochs of ``rows`` (read_log's) whose loss rose by more than
    ``rise``: each with its parts, their rises and the MAEs beside them."""
    found = []
    for before, row in zip(rows, rows[1:]):
        now, then = parts(row), parts(before)
        if now["loss"] - then["loss"] <= rise:
            continue
        found.append({"epoch": int(row["epoch"]), **now,
                      "rises": {k: now[k] - then[k] for k in now},
                      "mae": {k: row[f"{k}_mae"] for k in ("X", "Y", "Z", "fx", "baseline",
                                                            "disparity")},
                      "mae_before": {k: before[f"{k}_mae"] for k in ("X", "disparity")}})
    return found


def compute(root=REPO, rise=RISE):
    """Per run: its largest rise of the loss from one epoch to the next and its jumps."""
    out = []
    for name, pattern in ARMS:
        for seed in SEEDS:
            rows = read_log(os.path.join(root, RUNS, pattern.format(seed=seed)))
            rises = [b["loss"] - a["loss"] for a, b in zip(rows, rows[1:])]
            out.append({"run": name, "seed": seed, "epochs": len(rows),
                        "largest_rise": max(rises), "jumps": jumps(rows, rise)})
    return out


def render(found, rise=RISE):
    """The page's Markdown."""
    from cpl_keras import files

    md = [files.generated_line(COMMAND), "",
          "# MTL-CPL-A's training-loss jumps, term by term (InceptionV3, fair fight)", "",
          __doc__.split("\n\n")[2].replace("\n", " ").replace("``", "`").strip(), "",
          f"Runs: `{RUNS}/`. A jump: the epoch's mean loss more than {rise:g} above the "
          "epoch before's.", "",
          "| run | seed | epochs | largest rise | jumps |", "|---|---|---|---|---|"]
    for run in found:
        md.append(f"| {run['run']} | {run['seed']} | {run['epochs']} | "
                  f"{run['largest_rise']:.1f} | "
                  f"{', '.join(str(j['epoch']) for j in run['jumps']) or 'none'} |")
    md += ["", "Each jump: the loss and its rise, split (rise of each part); the MAEs of the "
           "graph's X, Y, Z (m) and of fx (px), b (m) and d (px) in that epoch (X and d in the "
           "epoch before in brackets).", "",
           "| run | seed | epoch | loss (rise) | X, Y, Z terms | parameters' point errors "
           "and rest | own errors | sum s_i | X | Y | Z | fx | b | d |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for run in found:
        for j in run["jumps"]:
            r, m = j["rises"], j["mae"]
            md.append(f"| {run['run']} | {run['seed']} | {j['epoch']} | {j['loss']:.1f} "
                      f"(+{r['loss']:.1f}) | {j['points']:.1f} ({r['points']:+.1f}) | "
                      f"{j['rest']:.1f} ({r['rest']:+.1f}) | {j['own']:.2f} ({r['own']:+.2f}) "
                      f"| {j['s']:.1f} ({r['s']:+.1f}) | {m['X']:,.1f} "
                      f"({j['mae_before']['X']:,.1f}) | {m['Y']:,.1f} | {m['Z']:,.1f} | "
                      f"{m['fx']:.1f} | {m['baseline']:.3f} | {m['disparity']:.0f} "
                      f"({j['mae_before']['disparity']:.0f}) |")
    return "\n".join(md) + "\n"


def regenerate(page_path):
    """The committed page, again from the committed logs."""
    return render(compute())


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default=os.path.join(REPO, OUT))
    args = parser.parse_args(argv)
    from cpl_keras import files

    files.write_text(args.out, render(compute()))
    print(args.out)
    return 0


if __name__ == "__main__":
    from cpl_keras import cli

    cli.run(main, "analyses/loss_jumps.py")
