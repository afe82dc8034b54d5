"""The figures docs/data.md quotes about the generated labels, measured again.

    python analyses/data_figures.py                 # 200 pairs per protocol, seed 0, 112 px
    python analyses/data_figures.py --pairs 300 --out-dir data/figures

Generates (or reuses) one dataset per protocol with ``generate_dataset`` and
prints, per protocol, a Markdown row: how often the release's pixel (the
image centre) sees the sky, the pairs that needed the projection-pixel
fallback, the label points' distance from the right camera, the median
|X|, the true disparity's range and median, and the share of labels whose
projection pixel lies on the principal row or column.

Produces: the table on stdout, the one docs/data.md quotes ("Measured
(generator 3.0) by a committed script"); the datasets it makes go to
``--out-dir`` (runs/data_figures/, not committed).
"""

from __future__ import annotations

import argparse
import os

import numpy as np


def figures(path):
    """The row of one dataset file."""
    from cpl_keras import camera
    from cpl_keras.data.storage import StereoFile

    with StereoFile(path) as f:
        labels, meta = f.labels, f.metadata
    n = len(labels["fx"])
    sky = int(np.sum(labels["sky_at_release_pixel"]))
    fallback = int(np.sum(labels["projection_fallback"]))
    xCam, yCam, zCam = camera.world_to_camera(
        labels["X"], labels["Y"], labels["Z"], labels["pitch"], labels["tx"], labels["ty"],
        labels["tz"])
    distance = np.sqrt(xCam ** 2 + yCam ** 2 + zCam ** 2)
    u, v, _ = camera.world_to_image(
        labels["X"], labels["Y"], labels["Z"], labels["fx"], labels["fy"], labels["u0"],
        labels["v0"], labels["baseline"], labels["pitch"], labels["tx"], labels["ty"],
        labels["tz"])
    on_row = float(np.mean(np.abs(v - labels["v0"]) < 0.5))
    on_column = float(np.mean(np.abs(u - labels["u0"]) < 0.5))
    d = np.asarray(labels["disparity"])
    return (f"| `{meta.get('protocol')}` | {sky} of {n} ({100 * sky / n:.1f} %) | {fallback} | "
            f"median {np.median(distance):.1f} m, max {distance.max():.1f} m, "
            f"{int(np.sum(distance > 200))} beyond 200 m | {np.median(np.abs(labels['X'])):.1f} m | "
            f"{d.min():.3g}..{d.max():.4g} px (median {np.median(d):.0f}) | "
            f"{100 * on_row:.1f} % / {100 * on_column:.1f} % |")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=200, help="pairs per protocol (default 200)")
    parser.add_argument("--seed", type=int, default=0, help="seed (default 0)")
    parser.add_argument("--image-size", type=int, default=112, help="image side (default 112)")
    parser.add_argument("--out-dir", default=os.path.join("runs", "data_figures"),
                        help="where the datasets go (default runs/data_figures)")
    args = parser.parse_args(argv)
    from cpl_keras.data.generate import GENERATOR_VERSION, generate_dataset

    os.makedirs(args.out_dir, exist_ok=True)
    print(f"| {args.pairs} pairs, {args.image_size} px, seed {args.seed}, generator "
          f"{GENERATOR_VERSION} | release's pixel sees the sky | fallback pairs | label points "
          f"from the right camera | median abs(X) | true disparity | on the principal row / "
          f"column |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for protocol in ("cvgl", "random"):
        path = os.path.join(args.out_dir, f"{protocol}_{args.pairs}_{args.image_size}px_"
                                          f"s{args.seed}_v{GENERATOR_VERSION}.h5")
        if not os.path.exists(path):
            generate_dataset(path, protocol=protocol, pairs=args.pairs, seed=args.seed,
                             image_size=args.image_size, progress=False)
        print(figures(path))
    return 0


if __name__ == "__main__":
    from cpl_keras import cli

    cli.run(main, 'analyses/data_figures.py')
