"""Where one training step's time goes (JAX backend, XLA:CPU): a per-op profile.

    python bench/profile_step.py                      # faithful model: 2 InceptionV3 towers, 112x112, batch 16
    python bench/profile_step.py --backbone small_resnet --steps 20
    XLA_FLAGS=--xla_cpu_use_onednn=true python bench/profile_step.py

Compiles the model's training step (``model.train_step`` under ``jax.jit``,
the same function ``fit`` runs), times ``--steps`` steps, then records them
with the JAX profiler. Every op XLA:CPU executes (a "thunk": a fused group of
HLO instructions) leaves one event named after its HLO instruction; the
instruction's metadata says which layer and which pass it came from
(``jvp(...)``: the forward pass, ``transpose(jvp(...))``: the backward pass,
``adam``: the optimizer). The script adds up the events' durations by pass
and by kind of layer and prints two markdown tables: the categories, and the
most expensive single ops.

Event durations are the time an op held one of XLA's threads; ops run side by
side on the cores, so their sum is compared with the step's wall time x the
number of cores ("core occupancy"): what is left is time when a core waited
(dependencies, dispatch, Python) or ran work that left no event (the helper
threads of an op that splits itself).
"""

from __future__ import annotations

import argparse
import collections
import glob
import os
import re
import tempfile
import time


#: Keras layer class -> the kind the tables report.
LAYER_KINDS = {
    "Conv2D": "convolution", "PatchConv2D": "convolution (PatchConv2D layers)",
    "BatchNormalization": "BatchNorm",
    "BatchNormalizationLagFree": "BatchNorm", "Dense": "dense",
    "MaxPooling2D": "pooling", "AveragePooling2D": "pooling",
    "GlobalAveragePooling2D": "pooling", "Activation": "activation", "ReLU": "activation",
    "Concatenate": "concatenate", "Add": "add", "Lambda": "camera graph / Lambda",
}

_INSTRUCTION = re.compile(r"^\s*(?:ROOT\s+)?%?([\w.\-]+) = (\S+) ([\w\-]+)\(")
_OP_NAME = re.compile(r'op_name="([^"]*)"')
_COMPUTATION = re.compile(r"^(?:ENTRY\s+)?%?([\w.\-]+) .*\{\s*$")
_CALLS = re.compile(r"calls=%?([\w.\-]+)")


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variant", default="baseline")
    parser.add_argument("--backbone", default="inception_v3")
    parser.add_argument("--image-size", type=int, default=112)
    parser.add_argument("--batch-size", type=int, default=16)
    parser.add_argument("--steps", type=int, default=4, help="timed and profiled training steps")
    parser.add_argument("--top", type=int, default=12, help="single ops listed")
    parser.add_argument("--dtype-policy", default="float32")
    parser.add_argument("--plain-conv", action="store_true",
                        help="keep every convolution a plain Conv2D (no PatchConv2D)")
    return parser.parse_args(argv)


def layer_classes(model):
    """Layer name -> class name, through nested models (the towers)."""
    classes = {}
    for layer in model.layers:
        classes[layer.name] = type(layer).__name__
        if hasattr(layer, "layers"):
            classes.update(layer_classes(layer))
    return classes


def classify(op_name, classes):
    """(pass, layer kind) of an HLO instruction from its ``op_name`` metadata."""
    if "transpose(jvp(" in op_name:
        phase = "backward"
    elif "jvp(" in op_name:
        phase = "forward"
    elif "/adam/" in op_name or op_name.endswith("/adam"):
        return "optimizer", "Adam update"
    else:
        phase = "other"
    if "compile_loss" in op_name:
        return phase, "loss"
    for segment in reversed(op_name.split("/")):
        segment = re.sub(r"^(transpose\()?(jvp\()?|\)+$", "", segment)
        if segment in classes:
            name = classes[segment]
            return phase, LAYER_KINDS.get(name, name)
    return phase, "other"


def instruction_table(hlo_text):
    """HLO instruction name -> (opcode, shape, op_name, computation) of a compiled module.

    A fusion without metadata of its own takes the ``op_name`` of the first
    instruction inside it that has one; one whose instructions have none but
    hold a convolution (XLA's filter-gradient convolutions) is reported as
    opcode ``convolution-fusion``.
    """
    table = {}
    calls = {}
    first_op_name = {}
    has_convolution = set()
    computation = None
    for line in hlo_text.splitlines():
        match = _COMPUTATION.match(line)
        if match and "=" not in line.split("{")[0]:
            computation = match.group(1)
            continue
        match = _INSTRUCTION.match(line)
        if match:
            op_name = _OP_NAME.search(line)
            op_name = op_name.group(1) if op_name else ""
            table[match.group(1)] = (match.group(3), match.group(2), op_name, computation)
            if op_name:
                first_op_name.setdefault(computation, op_name)
            if match.group(3) == "convolution":
                has_convolution.add(computation)
            called = _CALLS.search(line)
            if called:
                calls[match.group(1)] = called.group(1)
    for name, (opcode, shape, op_name, computation) in table.items():
        if not op_name and name in calls:
            op_name = first_op_name.get(calls[name], "")
            if not op_name and calls[name] in has_convolution:
                opcode = "convolution-fusion"
            table[name] = (opcode, shape, op_name, computation)
    return table


def thunk_events(trace_dir, names):
    """(name, duration in ns) of every executed op event in a JAX profiler trace."""
    from jax.profiler import ProfileData

    paths = glob.glob(os.path.join(trace_dir, "**", "*.xplane.pb"), recursive=True)
    if not paths:
        raise RuntimeError(f"{trace_dir}: the profiler wrote no trace")
    data = ProfileData.from_file(paths[0])
    events = []
    threads = set()
    for plane in data.planes:
        for line in plane.lines:
            for event in line.events:
                if event.name in names:
                    events.append((event.name, event.duration_ns))
                    threads.add(line.name)
    return events, threads


def run(args):
    os.environ.setdefault("KERAS_BACKEND", "jax")
    import jax
    import keras
    import numpy as np

    from cpl_keras import build_model, compile_model
    from cpl_keras.camera import TARGETS

    if keras.backend.backend() != "jax":
        raise SystemExit("profile_step.py profiles the JAX backend only")
    keras.config.set_dtype_policy(args.dtype_policy)
    if args.plain_conv:
        from cpl_keras.models import backbones, fast_layers

        backbones.with_faster_layers = lambda tower: tower
        # Deep-Homo's PatchConv2D and ViewMaxPooling2D, for the rest of the process
        fast_layers.xla_layers_only().__enter__()
    model = build_model(args.variant, backbone=args.backbone, image_size=args.image_size, seed=0)
    compile_model(model)
    rng = np.random.default_rng(0)
    shape = (args.batch_size, args.image_size, args.image_size, 3)
    x = {name: rng.uniform(0, 255, shape).astype(np.float32) for name in ("left_image", "right_image")}
    y = {name: rng.standard_normal((args.batch_size, 1)).astype(np.float32) for name in TARGETS}
    model.fit(x, y, batch_size=args.batch_size, epochs=1, verbose=0)  # builds the optimizer

    state = (
        [v.value for v in model.trainable_variables],
        [v.value for v in model.non_trainable_variables],
        [v.value for v in model.optimizer.variables],
        [v.value for v in model.metrics_variables],
    )
    compiled = jax.jit(model.train_step, donate_argnums=0).lower(state, (x, y)).compile()
    table = instruction_table(compiled.as_text())
    classes = layer_classes(model)

    def steps(state, n):
        for _ in range(n):
            logs, state = compiled(state, (x, y))
        jax.block_until_ready(logs)
        return state

    state = steps(state, 2)  # warm up
    start = time.perf_counter()
    state = steps(state, args.steps)
    step_s = (time.perf_counter() - start) / args.steps
    with tempfile.TemporaryDirectory() as trace_dir:
        with jax.profiler.trace(trace_dir):
            state = steps(state, args.steps)
        events, threads = thunk_events(trace_dir, table)

    per_category = collections.Counter()
    per_op = collections.Counter()
    for name, duration in events:
        opcode, shape, op_name, _ = table[name]
        phase, kind = classify(op_name, classes)
        if opcode == "convolution-fusion":  # XLA keeps no metadata for these
            phase, kind = "backward", "convolution (filter gradient, no layer name)"
        if kind == "convolution" and phase == "backward":
            kind = "convolution (gradient)"
        if opcode in ("copy", "transpose") and kind == "other":
            kind = "copy/transpose"
        per_category[(phase, kind)] += duration
        per_op[name] += duration
    total = sum(per_category.values())
    return {
        "step_s": step_s, "samples_per_s": args.batch_size / step_s,
        "busy_s": total / 1e9 / args.steps, "cores": os.cpu_count(),
        "categories": per_category, "ops": per_op, "table": table, "steps": args.steps,
        "load_average": os.getloadavg(), "xla_flags": os.environ.get("XLA_FLAGS", ""),
    }


def report(args, result):
    steps = result["steps"]
    total = sum(result["categories"].values())
    lines = [
        f"{args.variant}, {args.backbone} towers, {args.image_size}x{args.image_size}, "
        f"batch {args.batch_size}, dtype policy {args.dtype_policy}, "
        f"{'plain Conv2D only, ' if args.plain_conv else ''}"
        f"XLA_FLAGS={result['xla_flags'] or '(none)'}",
        f"step {result['step_s'] * 1e3:.0f} ms wall ({result['samples_per_s']:.2f} samples/s); "
        f"op time {result['busy_s'] * 1e3:.0f} ms per step on {result['cores']} cores: "
        f"core occupancy {result['busy_s'] / (result['step_s'] * result['cores']):.2f}; "
        f"load average {', '.join(f'{v:.2f}' for v in result['load_average'])}",
        "",
        "| pass | layer kind | ms per step | share of op time |",
        "|---|---|---|---|",
    ]
    for (phase, kind), duration in result["categories"].most_common():
        lines.append(f"| {phase} | {kind} | {duration / 1e6 / steps:.1f} | {duration / total:.1%} |")
    lines += ["", "| op | HLO opcode | output | layer | ms per step |", "|---|---|---|---|---|"]
    for name, duration in result["ops"].most_common(args.top):
        opcode, shape, op_name, _ = result["table"][name]
        layer = "/".join(op_name.split("/")[1:]) or "-"
        lines.append(f"| {name} | {opcode} | {shape.split('{')[0]} | {layer} | "
                     f"{duration / 1e6 / steps:.2f} |")
    return "\n".join(lines)


def main(argv=None):
    args = parse_args(argv)
    print(report(args, run(args)))


if __name__ == "__main__":
    from cpl_keras import cli

    cli.run(main, 'bench/profile_step.py')
