"""Inspect the Lambda camera graph of a model.

    python -m cpl_keras.graph --variant cpl-a [--backbone small]
        [--image-size 112] [--as-released] [--out camera_graph.png]

Prints every camera-graph layer with its op, its inputs and the paper
equation it implements, and draws the graph (PNG, SVG or PDF by the file
extension, drawn with matplotlib, so no graphviz is needed).
(``python -m cpl_keras.inspect``, the module's former name, still works.)
"""

from __future__ import annotations

import os
import sys

from cpl_keras import camera, cli, runs

PROG = "python -m cpl_keras.graph"

GATE_EQUATION = ("release", "per-sample sigmoid gate (the released CPL-A)")


def camera_graph(model):
    """The camera-graph layers of ``model`` in topological order.

    Returns a list of dicts with ``name``, ``op``, ``inputs`` (names of the
    layers feeding it), ``detached`` (those of the inputs read through
    ``stop_gradient``: the exact disentangling of Eq. 7) and ``equation``
    (paper equation number, formula).
    """
    from cpl_keras.layers import OP_NAMES, is_camera_layer, stop_gradient

    def source(tensor):
        """The layer behind ``tensor``, seen through a stop_gradient Lambda."""
        layer = tensor._keras_history.operation
        if getattr(layer, "function", None) is stop_gradient:
            return layer._inbound_nodes[0].input_tensors[0]._keras_history.operation.name, True
        return layer.name, False

    graph = []
    for layer in model.layers:
        if not is_camera_layer(layer):
            continue
        node = layer._inbound_nodes[0]
        sources = [source(t) for t in node.input_tensors]
        inputs = [name for name, _ in sources]
        base = layer.name.replace("_projected", "")
        gated = layer.name in ("X", "Y", "Z") and any(i.endswith("_gate") for i in inputs)
        equation = GATE_EQUATION if gated else camera.EQUATIONS.get(base, ("", ""))
        graph.append({
            "name": layer.name, "op": OP_NAMES[layer.function], "inputs": inputs,
            "detached": [name for name, detached in sources if detached],
            "equation": equation[0], "formula": equation[1],
        })
    return graph


def format_table(graph):
    rows = [("layer", "op", "inputs", "Eq.", "computes")]
    rows += [(g["name"], g["op"], ", ".join(g["inputs"]), g["equation"], g["formula"]) for g in graph]
    widths = [max(len(r[i]) for r in rows) for i in range(4)]
    lines = []
    for k, row in enumerate(rows):
        lines.append("  ".join(cell.ljust(w) for cell, w in zip(row, widths)) + "  " + row[4])
        if k == 0:
            lines.append("-" * (sum(widths) + 2 * len(widths) + len(rows[0][4])))
    return "\n".join(lines)


def draw_graph(graph, path, title):
    """Draw the camera graph left to right, one column per depth."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    depth = {}
    for node in graph:  # topological order: inputs are known or heads
        for name in node["inputs"]:
            depth.setdefault(name, 0)
        depth[node["name"]] = 1 + max(depth[i] for i in node["inputs"])
    columns = {}
    for name, d in depth.items():
        columns.setdefault(d, []).append(name)
    ops = {g["name"]: g for g in graph}
    tallest = max(len(c) for c in columns.values())
    fig_w, fig_h = 2.3 * (max(columns) + 1), 0.62 * tallest + 1.2
    fig, ax = plt.subplots(figsize=(fig_w, fig_h))
    position = {}
    for d, names in columns.items():
        for k, name in enumerate(names):
            position[name] = (d, (tallest - 1) / 2 - k + (len(names) - 1) / 2)
    boxes = {}
    for name, (x, y) in position.items():
        if name in ops:
            colour = "#fde9c9" if name in ("X", "Y", "Z", "xCam", "yCam", "zCam") else "#e8eef9"
            label = f"{name}\n{ops[name]['op']}  (Eq. {ops[name]['equation']})"
        else:
            colour, label = "#d9f2d9", f"{name}\n(head)"
        boxes[name] = ax.text(x, y, label, ha="center", va="center", fontsize=7.5, zorder=3,
                              bbox=dict(boxstyle="round,pad=0.35", fc=colour, ec="#44546a", lw=0.8))
    for node in graph:
        for name in node["inputs"]:
            # from the right edge of the input's box to the left edge of this one
            ax.annotate("", xy=(0.0, 0.5), xycoords=boxes[node["name"]],
                        xytext=(1.0, 0.5), textcoords=boxes[name], zorder=1,
                        arrowprops=dict(arrowstyle="->", color="#7a869a", lw=0.8,
                                        shrinkA=4, shrinkB=4))
    ax.set_xlim(-0.6, max(columns) + 0.6)
    ax.set_ylim(-0.8, tallest - 0.2)
    ax.axis("off")
    ax.set_title(title, fontsize=10)
    fig.tight_layout()
    runs.save_figure(fig, path, dpi=130)


def main(argv=None, prog=PROG):
    from cpl_keras.models import BACKBONES, variants

    with_graph = [spec.name for spec in variants.SPECS if spec.camera_graph]
    parser = cli.Parser(prog=prog, description="Show the Lambda camera graph of a model.")
    parser.add_argument("--variant", default="cpl-a",
                        help=f"{' or '.join(with_graph)} (default cpl-a)")
    parser.add_argument("--backbone", default="small",
                        help=f"{', '.join(BACKBONES)} (default small: the graph is the same, "
                        "it builds fast)")
    parser.add_argument("--image-size", type=int, default=112)
    parser.add_argument("--as-released", action="store_true", help="the released code's graph")
    parser.add_argument("--out", default="camera_graph.png", help="diagram file (.png, .svg or .pdf)")
    args = parser.parse_args(argv)
    try:
        if args.variant not in with_graph:
            raise ValueError(f"only {' and '.join(with_graph)} have a camera graph, "
                             f"not {args.variant!r}")
        if os.path.splitext(args.out)[1].lower() not in (".png", ".svg", ".pdf"):
            raise ValueError(f"--out must end in .png, .svg or .pdf: {args.out}")
        directory = os.path.dirname(os.path.abspath(args.out))
        if not os.path.isdir(directory):
            raise ValueError(f"output directory does not exist: {directory}")
        from cpl_keras.models import build_model

        model = build_model(args.variant, backbone=args.backbone,
                            image_size=args.image_size, as_released=args.as_released)
    except ValueError as error:
        return cli.fail(prog, error)
    graph = camera_graph(model)
    mode = "as released" if args.as_released else "as the paper writes it"
    print(f"Camera graph of {args.variant} ({mode}): {len(graph)} Lambda layers, "
          f"loss '{model.loss_mode}'")
    print(format_table(graph))
    detached = sorted({name for g in graph for name in g["detached"]})
    if detached:
        print(f"The graph reads {', '.join(detached)} through stop_gradient: the X, Y, Z terms "
              "of the loss train only the pixel heads u, v (exact disentangling of Eq. 7).")
    try:
        draw_graph(graph, args.out, f"{args.variant} camera graph ({mode}): Eqs. 4a-5c as Lambda layers")
    except OSError as error:
        return cli.fail(prog, f"cannot write {args.out}: {error.strerror or error}")
    print(f"diagram written to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
