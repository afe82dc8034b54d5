"""How strongly each term of Eq. 7 weighs a relative error under the fair
fight's range weights (alpha_i = 1 / mean|y_i|, fixed), to first order, at
a pair made of the training means.

    python analyses/range_sensitivity.py    # paper_results/fair-fight/range-sensitivity.md

Each parameter's term is its own absolute error plus the error, in metres,
of the point it moves alone (``cpl_keras.models.losses``). For an error
delta = eps * mean|y_p| (a relative error eps, as NMAE counts it) the
range-weighted term moves by ``alpha_p (|delta| + |J_p delta|_1) = eps (1 +
|J_p|_1)``, J_p the derivative of the point (X, Y, Z) with respect to p:
the own error is balanced (1 for every parameter), the point's part is not
(|J_p|_1 in m/px for fx, fy, u0, v0 and the disparity, m/rad for the pitch,
m/m for b, tx, ty, tz). The pair: every parameter at its training mean
(each seed's ``train_stats.json`` of the range arm's runs) and the pixel
that projects the mean point (X, Y, Z) there; the disparity either the one
that point implies or its training mean (a mean of ratios is not a ratio
of means, so the two differ), the derivatives by central differences.
"""

from __future__ import annotations

import argparse
import os

import numpy as np

from cpl_keras import camera

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RUNS = os.path.join("paper_results", "fair-fight", "inception", "runs")
OUT = os.path.join("paper_results", "fair-fight", "range-sensitivity.md")
COMMAND = "python analyses/range_sensitivity.py"
SEEDS = (0, 1, 2)
#: Each parameter's unit, for the point part's unit (metres per it).
UNITS = {"fx": "px", "fy": "px", "u0": "px", "v0": "px", "baseline": "m", "disparity": "px",
         "tx": "m", "ty": "m", "tz": "m", "pitch": "rad"}


def point_sensitivities(params, u, v, step=1e-6):
    """``{p: |dP/dp|_1}``: how far, in metres summed over X, Y, Z, the point
    of pixel (u, v) moves per unit of each parameter (central differences)."""
    out = {}
    for p in camera.PARAMETERS:
        h = step * max(1.0, abs(params[p]))
        ends = [np.array(camera.image_to_world(**dict(params, **{p: params[p] + sign * h}),
                                               u=u, v=v), np.float64) for sign in (1, -1)]
        out[p] = float(np.abs((ends[0] - ends[1]) / (2 * h)).sum())
    return out


def reference_pairs(mean):
    """``{label: (params, u, v)}``: the training means ``mean`` (train_stats'),
    the pixel projecting the mean point, the disparity implied or the mean."""
    params = {p: float(mean[p]) for p in camera.PARAMETERS}
    u, v, implied = camera.world_to_image(
        mean["X"], mean["Y"], mean["Z"], *(params[k] for k in (
            "fx", "fy", "u0", "v0", "baseline", "pitch", "tx", "ty", "tz")))
    return {f"disparity implied by the mean point ({float(implied):.0f} px)":
            (dict(params, disparity=float(implied)), float(u), float(v)),
            f"disparity at its mean ({params['disparity']:.0f} px)": (params, float(u), float(v))}


def compute(root=REPO):
    """Per seed and reference pair: each term's response to a relative error, ``1 + |J_p|_1``."""
    from cpl_keras import files

    found = []
    for seed in SEEDS:
        stats = files.read_json(os.path.join(root, RUNS, f"cvgl_cpl-a-range-s{seed}",
                                             "train_stats.json"))
        for label, (params, u, v) in reference_pairs(stats["mean"]).items():
            point = point_sensitivities(params, u, v)
            found.append({"seed": seed, "pair": label,
                          "term": {p: 1.0 + point[p] for p in camera.PARAMETERS}})
    return found


def render(found):
    from cpl_keras import files

    names = camera.PARAMETERS
    md = [files.generated_line(COMMAND), "",
          "# The range weights' terms, to first order: how much each weighs a relative error",
          "", " ".join(__doc__.split("\n\n")[2].split()).replace("``", "`"), "",
          "Each cell: `1 + |J_p|_1`, the range-weighted term's change per unit of relative "
          "error (the point part's unit: metres per "
          + ", ".join(f"{UNITS[p]} ({p})" for p in names) + "). The last column: the "
          "pitch's over the largest other's.", "",
          "| seed | pair | " + " | ".join(names) + " | pitch / next |",
          "|---|---|" + "---|" * (len(names) + 1)]
    for row in found:
        term = row["term"]
        others = max(term[p] for p in names if p != "pitch")
        md.append(f"| {row['seed']} | {row['pair']} | "
                  + " | ".join(f"{term[p]:.2f}" for p in names)
                  + f" | {term['pitch'] / others:.1f} |")
    return "\n".join(md) + "\n"


def regenerate(page_path):
    """The committed page, again from the committed training statistics."""
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

    cli.run(main, "analyses/range_sensitivity.py")
