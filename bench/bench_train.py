"""Training throughput of the faithful model, next to a matmul's GFLOP/s.

    python bench/bench_train.py                       # JAX, 2 InceptionV3 towers, 112x112, batch 16
    python bench/bench_train.py --compare-tensorflow  # also the TensorFlow backend, if installed
    python bench/bench_train.py --data d.h5 --workers 2   # through the HDF5 input pipeline
    python bench/bench_backends.py                    # JAX, TensorFlow and PyTorch side by side

Reports training samples/s, the FLOPs of one training step (XLA's cost
analysis of the compiled step, JAX backend) and so the achieved GFLOP/s, and
the GFLOP/s of a large float32 matmul measured in the same process: the
machine's practical peak for dense float32 work. One JSON line per backend
goes to stdout (``--json`` writes them to a file as well).
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
import time


def parse_args(argv=None):
    from cpl_keras import cli

    parser = cli.Parser(prog="bench/bench_train.py", description=__doc__.splitlines()[0])
    parser.add_argument("--backend", default=os.environ.get("KERAS_BACKEND", "jax"),
                        choices=("jax", "tensorflow", "torch"))
    parser.add_argument("--variant", default="baseline")
    parser.add_argument("--backbone", default="inception_v3")
    parser.add_argument("--image-size", type=cli.positive_int, default=112)
    parser.add_argument("--batch-size", type=cli.positive_int, default=16)
    parser.add_argument("--steps", type=cli.positive_int, default=12, help="timed training steps")
    parser.add_argument("--repeats", type=cli.positive_int, default=2,
                        help="timed runs; the best is kept")
    parser.add_argument("--steps-per-execution", type=cli.positive_int, default=1)
    parser.add_argument("--dtype-policy", default="float32",
                        help="Keras dtype policy for the model, e.g. mixed_bfloat16")
    parser.add_argument("--plain-conv", action="store_true",
                        help="keep every convolution a plain Conv2D (no PatchConv2D), "
                             "to measure what the patches gain")
    parser.add_argument("--no-jit", action="store_true", help="compile with jit_compile=False")
    parser.add_argument("--data", help="read batches from this HDF5 file (StereoSequence)")
    parser.add_argument("--workers", type=cli.positive_int, default=1,
                        help="StereoSequence threads")
    parser.add_argument("--in-memory", default="auto", choices=("auto", "on", "off"),
                        help="with --data: StereoSequence keeps the images in memory "
                             "(auto: when they fit its limit) or streams every batch (off)")
    parser.add_argument("--matmul-size", type=cli.positive_int, default=4096)
    parser.add_argument("--compare-tensorflow", action="store_true",
                        help="also run this benchmark under the TensorFlow backend, if installed")
    parser.add_argument("--flops-per-step", type=cli.positive_float,
                        help="FLOPs of one training step, for backends that cannot count them")
    parser.add_argument("--predict-repeats", type=cli.positive_int, default=2,
                        help="timed predict passes over the same samples; the best is kept")
    parser.add_argument("--json", help="append the result lines to this file")
    return parser.parse_args(argv)


def matmul_gflops(size, repeats=5):
    """GFLOP/s of a float32 (size x size) @ (size x size) matmul (2 n^3 FLOPs)."""
    import numpy as np
    from keras import ops

    a = ops.convert_to_tensor(np.random.default_rng(0).standard_normal((size, size), np.float32))
    b = ops.convert_to_tensor(np.random.default_rng(1).standard_normal((size, size), np.float32))
    ops.convert_to_numpy(ops.matmul(a, b)[0, 0])  # warm up / compile
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        ops.convert_to_numpy(ops.matmul(a, b)[0, 0])
        best = min(best, time.perf_counter() - start)
    return 2.0 * size**3 / best / 1e9


def train_step_flops(model, x, y):
    """FLOPs of one compiled training step (JAX backend: XLA cost analysis)."""
    import jax

    state = (
        [v.value for v in model.trainable_variables],
        [v.value for v in model.non_trainable_variables],
        [v.value for v in model.optimizer.variables],
        [v.value for v in model.metrics_variables],
    )
    compiled = jax.jit(model.train_step).lower(state, (x, y)).compile()
    analysis = compiled.cost_analysis()
    if isinstance(analysis, (list, tuple)):
        analysis = analysis[0]
    return float(analysis.get("flops", float("nan")))


def run(args):
    import keras
    import numpy as np

    from cpl_keras import build_model, compile_model
    from cpl_keras.camera import TARGETS

    keras.config.set_dtype_policy(args.dtype_policy)
    if args.plain_conv:
        from cpl_keras.models import backbones, fast_layers

        backbones.with_faster_layers = lambda tower: tower
        # Deep-Homo's PatchConv2D and ViewMaxPooling2D, for the rest of the process
        fast_layers.xla_layers_only().__enter__()
    model = build_model(args.variant, backbone=args.backbone, image_size=args.image_size, seed=0)
    compile_model(model, jit_compile=not args.no_jit and "auto",
                  steps_per_execution=args.steps_per_execution)
    batch = args.batch_size
    rng = np.random.default_rng(0)
    n = batch * args.steps
    shape = (args.image_size, args.image_size, 3)
    if args.data:
        from cpl_keras.datasets import targets_from_labels
        from cpl_keras.training.sequence import StereoSequence
        from cpl_keras.data.storage import StereoFile

        with StereoFile(args.data) as f:
            targets = targets_from_labels(f.labels)
            count = f.num_pairs
        data = StereoSequence(args.data, np.arange(min(n, count)), targets, batch_size=batch,
                              shuffle=True, workers=args.workers,
                              in_memory={"auto": "auto", "on": True, "off": False}[args.in_memory])
        fit_kwargs = {}
        n = min(n, count)
        x, y = data[0]
    else:
        x = {name: rng.uniform(0, 255, (n,) + shape).astype(np.float32)
             for name in ("left_image", "right_image")}
        y = {name: rng.standard_normal((n, 1)).astype(np.float32) for name in TARGETS}
        data = x
        fit_kwargs = {"y": y, "batch_size": batch, "shuffle": False}

    start = time.perf_counter()
    model.fit(data, epochs=1, verbose=0, **fit_kwargs)  # compiles
    compile_s = time.perf_counter() - start
    best = float("inf")
    for _ in range(args.repeats):
        start = time.perf_counter()
        model.fit(data, epochs=1, verbose=0, **fit_kwargs)
        best = min(best, time.perf_counter() - start)
    samples_per_s = n / best

    model.predict(x, batch_size=batch, verbose=0)  # compiles the predict function
    predict_best = float("inf")
    for _ in range(args.predict_repeats):
        start = time.perf_counter()
        model.predict(x, batch_size=batch, verbose=0)
        predict_best = min(predict_best, time.perf_counter() - start)
    predict_n = len(next(iter(x.values())))

    result = {
        "backend": keras.backend.backend(), "variant": args.variant, "backbone": args.backbone,
        "image_size": args.image_size, "batch_size": batch, "timed_samples": n,
        "steps_per_execution": args.steps_per_execution, "jit": not args.no_jit,
        "dtype_policy": args.dtype_policy, "plain_conv": args.plain_conv,
        "input": f"hdf5, workers={args.workers}, in_memory={data.in_memory}" if args.data
        else "in-memory arrays",
        "num_parameters": int(model.count_params()),
        "first_epoch_s": round(compile_s, 2),
        "samples_per_s": round(samples_per_s, 2),
        "predict_pairs_per_s": round(predict_n / predict_best, 2),
        "load_average": [round(v, 2) for v in os.getloadavg()],
        "matmul_size": args.matmul_size,
        "matmul_gflops": round(matmul_gflops(args.matmul_size), 1),
        "cpu_count": os.cpu_count(),
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
    }
    flops = args.flops_per_step
    if keras.backend.backend() == "jax":
        xb = {k: v[:batch] for k, v in x.items()}
        yb = {k: v[:batch] for k, v in y.items()}
        flops = train_step_flops(model, xb, yb)
    if flops:
        result["gflop_per_step"] = round(flops / 1e9, 2)
        result["achieved_gflops"] = round(flops / 1e9 * samples_per_s / batch, 1)
        result["fraction_of_matmul"] = round(result["achieved_gflops"] / result["matmul_gflops"], 3)
    return result


def main(argv=None):
    args = parse_args(argv)
    os.environ["KERAS_BACKEND"] = args.backend
    results = [run(args)]
    if args.compare_tensorflow and args.backend == "jax":
        if importlib.util.find_spec("tensorflow") is None:
            print("tensorflow is not installed: no TensorFlow comparison", file=sys.stderr)
        else:
            argv_tf = [a for a in (argv if argv is not None else sys.argv[1:])
                       if a != "--compare-tensorflow"]
            env = dict(os.environ, KERAS_BACKEND="tensorflow")
            out = subprocess.run([sys.executable, os.path.abspath(__file__), "--backend",
                                  "tensorflow", *argv_tf], env=env, capture_output=True,
                                 text=True, check=True).stdout
            results.append(json.loads(out.strip().splitlines()[-1]))
    for result in results:
        line = json.dumps(result)
        print(line)
        if args.json:
            with open(args.json, "a") as f:
                f.write(line + "\n")


if __name__ == "__main__":
    from cpl_keras import cli

    cli.run(main, 'bench/bench_train.py')
