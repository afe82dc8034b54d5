"""Training throughput of the two-tower MTL model per backbone, in one process.

    python bench/bench_backbones.py                           # 112x112, batch 16, default candidates
    python bench/bench_backbones.py --backbones inception_v3 small mobilenet_v3_small

Every model is the MTL-Baseline shape: input scaling to [-1, 1], two towers
(one per image, no weight sharing), flatten, concatenate, the 13 regression
heads Dense(120)-Dense(84)-Dense(1) and the summed per-output MAE, Adam 1e-3
(what ``cpl_keras.compile_model`` does for the ``baseline`` variant). It is
built as a plain ``keras.Model`` here so that candidate towers that are not
registered in ``cpl_keras.models.backbones`` can be measured the same way.

All models are built and compiled first; then the timed rounds alternate
between them (round r times ``--steps`` training steps of every backbone in
turn, then ``--steps`` predict calls), so a load change on a shared machine
hits every candidate alike. Reported: parameters, flattened features per
tower, the first training step (XLA compilation included), the median
training step and, measured alternately with it, the median training step of
the 13 heads alone on random features of the same size (the heads' first
Dense(120) takes all the flattened features, so it is a large part of a
compact model's step), training and predict samples/s, the ratio of training
samples/s to InceptionV3's (when measured) and the load average before and
after. ``--json`` writes the rows as JSON lines.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time

os.environ.setdefault("KERAS_BACKEND", "jax")


# --- candidate towers that are not registered backbones (for comparison only) ---

def _mobilenet_v3_small(alpha=1.0, minimalistic=False):
    def make(height, width, name):
        import keras

        return keras.applications.MobileNetV3Small(
            input_shape=(height, width, 3), alpha=alpha, minimalistic=minimalistic,
            include_top=False, weights=None, include_preprocessing=False, name=name,
        )
    return make


def _mobilenet_v2(alpha):
    def make(height, width, name):
        import keras

        return keras.applications.MobileNetV2(
            input_shape=(height, width, 3), alpha=alpha, include_top=False, weights=None,
            name=name,
        )
    return make


def _efficientnet_b0(height, width, name):
    # EfficientNet (v1) always adds its own Rescaling(1/255) + Normalization:
    # measured for speed only, it would rescale the already-scaled inputs.
    import keras

    return keras.applications.EfficientNetB0(
        input_shape=(height, width, 3), include_top=False, weights=None, name=name,
    )


def _small_resnet(widths):
    def make(height, width, name):
        from cpl_keras.models.backbones import small_resnet_tower

        return small_resnet_tower(height, width, name, widths=widths)
    return make


EXTRA_CANDIDATES = {
    "small_resnet_32_64_128_128": _small_resnet((32, 64, 128, 128)),
    "mobilenet_v3_small": _mobilenet_v3_small(),
    "mobilenet_v3_small_minimalistic": _mobilenet_v3_small(minimalistic=True),
    "mobilenet_v3_small_0.75": _mobilenet_v3_small(alpha=0.75),
    "mobilenet_v2_0.35": _mobilenet_v2(0.35),
    "efficientnet_b0": _efficientnet_b0,
}


def tower_factory(name):
    from cpl_keras.models import backbones

    if name in backbones.BACKBONES:
        return backbones.TOWERS[name]
    if name in EXTRA_CANDIDATES:
        return EXTRA_CANDIDATES[name]
    raise SystemExit(f"bench_backbones.py: error: unknown backbone {name!r}; choose from "
                     f"{', '.join(list(backbones.BACKBONES) + list(EXTRA_CANDIDATES))}")


def build(name, size):
    """Two towers -> flatten -> concat -> 13 heads, compiled with summed MAE and Adam."""
    import keras

    from cpl_keras.camera import TARGETS
    from cpl_keras.layers import regression_head

    make_tower = tower_factory(name)
    keras.utils.set_random_seed(0)
    left = keras.Input((size, size, 3), name="left_image")
    right = keras.Input((size, size, 3), name="right_image")
    scale = keras.layers.Rescaling(1.0 / 127.5, offset=-1.0, name="input_scaling")
    left_tower = make_tower(size, size, f"left_{name}")
    right_tower = make_tower(size, size, f"right_{name}")
    features = keras.layers.Concatenate(name="stereo_features")([
        keras.layers.Flatten(name="left_flatten")(left_tower(scale(left))),
        keras.layers.Flatten(name="right_flatten")(right_tower(scale(right))),
    ])
    outputs = [regression_head(features, target) for target in TARGETS]
    model = keras.Model({"left_image": left, "right_image": right}, outputs, name=name)
    model.compile(optimizer=keras.optimizers.Adam(1e-3),
                  loss={target: "mae" for target in TARGETS})
    per_tower = int(features.shape[-1]) // 2
    # the 13 heads alone, on the concatenated features: their share of the step
    head_input = keras.Input((2 * per_tower,), name="stereo_features")
    heads = keras.Model(head_input, [regression_head(head_input, t) for t in TARGETS],
                        name=f"{name}_heads")
    heads.compile(optimizer=keras.optimizers.Adam(1e-3), loss=["mae"] * len(TARGETS))
    return model, heads, per_tower, left_tower.count_params()


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--image-size", type=int, default=112)
    parser.add_argument("--batch-size", type=int, default=16)
    parser.add_argument("--steps", type=int, default=3,
                        help="timed training (and predict) steps per backbone per round")
    parser.add_argument("--repeats", type=int, default=3, help="alternating timed rounds")
    parser.add_argument("--backbones", nargs="+",
                        default=["inception_v3", "small", "small_resnet", "mobilenet_v3_small"])
    parser.add_argument("--json", help="append one JSON line per backbone to this file")
    return parser.parse_args(argv)


def main(argv=None):
    args = parse_args(argv)
    import numpy as np

    from cpl_keras.camera import TARGETS

    for name in args.backbones:
        tower_factory(name)  # fail early on an unknown name
    batch, size = args.batch_size, args.image_size
    rng = np.random.default_rng(0)
    x = {k: rng.uniform(0, 255, (batch, size, size, 3)).astype(np.float32)
         for k in ("left_image", "right_image")}
    y = {t: rng.standard_normal((batch, 1)).astype(np.float32) for t in TARGETS}
    load_start = os.getloadavg()

    models, rows = {}, {}
    for name in args.backbones:
        start = time.perf_counter()
        model, heads, per_tower, tower_params = build(name, size)
        build_s = time.perf_counter() - start
        start = time.perf_counter()
        model.train_on_batch(x, y)  # compiles the training step
        first_step_s = time.perf_counter() - start
        start = time.perf_counter()
        model.predict_on_batch(x)  # compiles the predict step
        first_predict_s = time.perf_counter() - start
        features = rng.standard_normal((batch, 2 * per_tower)).astype(np.float32)
        head_y = [y[t] for t in TARGETS]
        heads.train_on_batch(features, head_y)
        models[name] = (model, heads, features, head_y)
        rows[name] = {
            "backbone": name, "parameters": int(model.count_params()),
            "tower_parameters": int(tower_params), "features_per_tower": per_tower,
            "build_s": round(build_s, 2), "first_step_s": round(first_step_s, 2),
            "first_predict_s": round(first_predict_s, 2), "train_step_s": [],
            "predict_step_s": [], "heads_step_s": [],
            "heads_parameters": int(heads.count_params()),
        }
        print(f"built {name}: {model.count_params():,} parameters, first step "
              f"{first_step_s:.1f} s, load {os.getloadavg()[0]:.2f}", file=sys.stderr, flush=True)

    for round_ in range(args.repeats):
        for name, (model, heads, features, head_y) in models.items():
            for _ in range(args.steps):
                start = time.perf_counter()
                model.train_on_batch(x, y)  # returns numpy losses: synchronous
                rows[name]["train_step_s"].append(time.perf_counter() - start)
            for _ in range(args.steps):
                start = time.perf_counter()
                heads.train_on_batch(features, head_y)
                rows[name]["heads_step_s"].append(time.perf_counter() - start)
        for name, (model, *_) in models.items():
            for _ in range(args.steps):
                start = time.perf_counter()
                np.asarray(model.predict_on_batch(x)[0])
                rows[name]["predict_step_s"].append(time.perf_counter() - start)
        print(f"round {round_ + 1}/{args.repeats} done, load {os.getloadavg()[0]:.2f}",
              file=sys.stderr, flush=True)
    load_end = os.getloadavg()

    reference = None
    for row in rows.values():
        row["train_samples_per_s"] = round(batch / statistics.median(row["train_step_s"]), 2)
        row["predict_samples_per_s"] = round(batch / statistics.median(row["predict_step_s"]), 2)
        row["train_step_ms"] = round(1000 * statistics.median(row["train_step_s"]), 1)
        row["heads_step_ms"] = round(1000 * statistics.median(row["heads_step_s"]), 1)
        if row["backbone"] == "inception_v3":
            reference = row["train_samples_per_s"]
    load = "{:.2f} {:.2f} {:.2f} -> {:.2f} {:.2f} {:.2f}".format(*load_start, *load_end)
    print(f"\nimage {size}x{size}, batch {batch}, {args.repeats} rounds x {args.steps} steps "
          f"(medians), load average (1, 5, 15 min) {load}, {os.cpu_count()} CPUs\n")
    print("| backbone | parameters (heads) | features/tower | first step s | train step ms "
          "(heads alone) | train samples/s | predict samples/s | x InceptionV3 |")
    print("|---|---|---|---|---|---|---|---|")
    for row in rows.values():
        row["ratio_to_inception_v3"] = (round(row["train_samples_per_s"] / reference, 1)
                                        if reference else None)
        row.update(image_size=size, batch_size=batch, load_average=load,
                   train_step_s=[round(t, 4) for t in row["train_step_s"]],
                   predict_step_s=[round(t, 4) for t in row["predict_step_s"]],
                   heads_step_s=[round(t, 4) for t in row["heads_step_s"]])
        ratio = f"{row['ratio_to_inception_v3']:.1f}x" if reference else "-"
        print(f"| `{row['backbone']}` | {row['parameters']:,} ({row['heads_parameters']:,}) "
              f"| {row['features_per_tower']:,} | {row['first_step_s']:.1f} "
              f"| {row['train_step_ms']:.0f} ({row['heads_step_ms']:.0f}) "
              f"| {row['train_samples_per_s']:.1f} "
              f"| {row['predict_samples_per_s']:.1f} | {ratio} |")
        if args.json:
            with open(args.json, "a") as f:
                f.write(json.dumps(row) + "\n")


if __name__ == "__main__":
    from cpl_keras import cli

    cli.run(main, 'bench/bench_backbones.py')
