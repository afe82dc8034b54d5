"""Inspect the Lambda camera graph of a model.

    python -m cpl_keras.graph --variant cpl-a [--backbone small]
        [--image-size 112] [--as-released] [--out runs/camera_graph.png]

Prints every camera-graph layer with its op, its inputs and the paper
equation it implements, and draws the graph (PNG, SVG or PDF by the file
extension, drawn with matplotlib, so no graphviz is needed).
"""

from __future__ import annotations

import os

from cpl_keras import camera, cli, files, models
from cpl_keras.models import BACKBONES, variants

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


# ---------------------------------------------------------------------------
# Layout: layered, every edge routed in the gaps between the boxes
# ---------------------------------------------------------------------------
#: Label size (points), box padding, the gaps between columns (where edges
#: bend) and between boxes of a column, and the lane an edge takes through a
#: column it crosses (inches).
FONT_SIZE = 7.5
PAD_X, PAD_Y = 0.08, 0.05
COLUMN_GAP = 0.55
ROW_GAP = 0.14
LANE = 0.09
#: Samples per curve between two columns.
CURVE_SAMPLES = 16


def node_label(name, ops):
    """A box's text: the layer, its op and equation; or what feeds the graph."""
    if name in ops:
        return f"{name}\n{ops[name]['op']}  (Eq. {ops[name]['equation']})"
    return f"{name}\n({'gate' if name.endswith('_gate') else 'head'})"


def _text_size(fontsize=FONT_SIZE):
    """A function giving a label's width and height in inches (matplotlib's
    font metrics, so that the boxes fit the drawn text)."""
    from matplotlib.backends.backend_agg import RendererAgg
    from matplotlib.font_manager import FontProperties

    renderer, prop = RendererAgg(1, 1, 72), FontProperties(size=fontsize)

    def measure(label):
        lines = label.split("\n")
        width = max(renderer.get_text_width_height_descent(line, prop, ismath=False)[0]
                    for line in lines)
        return width / 72, fontsize * (1.2 * (len(lines) - 1) + 1.15) / 72
    return measure


def _ranks(names, preds, succs):
    """A column per node: outputs (no consumers) in the last column, every
    other node moved, as far as its inputs and consumers allow, towards the
    side with more edges (each move shortens the edges in total)."""
    rank = {}
    for name in names:  # (names are in topological order)
        rank[name] = 1 + max((rank[p] for p in preds[name]), default=-1)
    last = max(rank.values())
    for name in names:
        if not succs[name]:
            rank[name] = last
    changed = True
    while changed:
        changed = False
        for name in reversed(names):
            if not succs[name]:
                continue
            low = 1 + max((rank[p] for p in preds[name]), default=-1)
            high = min(rank[s] for s in succs[name]) - 1
            pull = len(succs[name]) - len(preds[name])
            target = high if pull > 0 else low if pull < 0 else rank[name]
            if target != rank[name]:
                rank[name], changed = target, True
    return rank


def _crossings(layers, links):
    position = {item: k for layer in layers for k, item in enumerate(layer)}
    count = 0
    for r in range(len(layers) - 1):
        segs = [(position[a], position[b]) for a, b in links if a in layers[r] and b in layers[r + 1]]
        count += sum(1 for i, (a1, b1) in enumerate(segs) for a2, b2 in segs[i + 1:]
                     if (a1 - a2) * (b1 - b2) < 0)
    return count


def _order(layers, links, sweeps=12):
    """Order each column by the mean position of its neighbours (barycentre
    sweeps), keeping the order with the fewest crossings."""
    preds, succs = {}, {}
    for a, b in links:
        succs.setdefault(a, []).append(b)
        preds.setdefault(b, []).append(a)
    layers = [list(layer) for layer in layers]
    best, best_count = [list(layer) for layer in layers], _crossings(layers, links)
    for sweep in range(sweeps):
        down = sweep % 2 == 0
        indices = range(1, len(layers)) if down else range(len(layers) - 2, -1, -1)
        for r in indices:
            near = layers[r - 1] if down else layers[r + 1]
            where = {item: k for k, item in enumerate(near)}
            neighbours = preds if down else succs

            def key(item, k, where=where, neighbours=neighbours):
                found = [where[n] for n in neighbours.get(item, ()) if n in where]
                return (sum(found) / len(found) if found else k, k)
            layers[r] = [item for k, item in sorted(enumerate(layers[r]),
                                                    key=lambda pair: key(pair[1], pair[0]))]
        count = _transpose(layers, links)
        if count < best_count:
            best, best_count = [list(layer) for layer in layers], count
    return best


def _transpose(layers, links):
    """Swap neighbours within a column while that removes crossings (in
    place); returns the crossings left."""
    count = _crossings(layers, links)
    improved = True
    while improved:
        improved = False
        for layer in layers:
            for k in range(len(layer) - 1):
                layer[k], layer[k + 1] = layer[k + 1], layer[k]
                swapped = _crossings(layers, links)
                if swapped < count:
                    count, improved = swapped, True
                else:
                    layer[k], layer[k + 1] = layer[k + 1], layer[k]
    return count


def _place(desired, gaps):
    """Positions as close as possible (least squares) to ``desired``, in
    order, consecutive ones at least ``gaps`` apart (pool adjacent violators)."""
    offsets = [0.0]
    for gap in gaps:
        offsets.append(offsets[-1] + gap)
    blocks = []  # [mean of (desired - offset), count]
    for value, offset in zip(desired, offsets):
        blocks.append([value - offset, 1])
        while len(blocks) > 1 and blocks[-2][0] > blocks[-1][0]:
            (m2, n2), (m1, n1) = blocks.pop(), blocks.pop()
            blocks.append([(m1 * n1 + m2 * n2) / (n1 + n2), n1 + n2])
    flat = [mean for mean, count in blocks for _ in range(count)]
    return [value + offset for value, offset in zip(flat, offsets)]


def _curve(start, end, samples=CURVE_SAMPLES):
    """A cubic Bezier from ``start`` to ``end`` leaving and arriving
    horizontally; it stays within their x range (its control points do)."""
    (x0, y0), (x1, y1) = start, end
    if y0 == y1:
        return [end]
    k = (x1 - x0) / 2
    controls = ((x0, y0), (x0 + k, y0), (x1 - k, y1), (x1, y1))
    points = []
    for i in range(1, samples + 1):
        t = i / samples
        weights = ((1 - t) ** 3, 3 * t * (1 - t) ** 2, 3 * t ** 2 * (1 - t), t ** 3)
        points.append((sum(w * c[0] for w, c in zip(weights, controls)),
                       sum(w * c[1] for w, c in zip(weights, controls))))
    return points


def layout(graph, measure=None):
    """Where everything of the drawing goes, in inches, y downwards.

    Columns of boxes (a node's column: see ``_ranks``); an edge that spans
    several columns passes each column in a lane of its own, and bends only
    in the gaps between columns, so it touches no box but its two ends: it
    leaves its source from the middle of the right side and ends on the left
    side of its target (one port per input, top to bottom in the order the
    edges arrive).

    Returns a dict: ``boxes`` (name -> (x0, y0, x1, y1)), ``labels`` (name ->
    text), ``edges`` (list of dicts: ``source``, ``target``, ``detached``,
    ``points``: the polyline that is drawn) and ``size`` (width, height).
    """
    measure = measure or _text_size()
    ops = {g["name"]: g for g in graph}
    edges = [(src, g["name"]) for g in graph for src in dict.fromkeys(g["inputs"])]
    detached = {(src, g["name"]) for g in graph for src in g["detached"]}
    names = list(dict.fromkeys([i for g in graph for i in g["inputs"] if i not in ops]
                               + [g["name"] for g in graph]))
    preds = {n: [] for n in names}
    succs = {n: [] for n in names}
    for s, t in edges:
        preds[t].append(s)
        succs[s].append(t)
    rank = _ranks(names, preds, succs)
    layers, chains, links = _lanes(names, edges, rank)
    layers = _order(layers, links)

    labels = {name: node_label(name, ops) for name in names}
    size = _sizes(names, labels, layers, measure)
    y = _rows(layers, links, size)
    left, centre, right = _columns(layers, size)
    boxes = {name: (centre[rank[name]] - size[name][0] / 2, y[name] - size[name][1] / 2,
                    centre[rank[name]] + size[name][0] / 2, y[name] + size[name][1] / 2)
             for name in names}
    port = _ports(names, preds, chains, y, boxes)
    routed = [{"source": s, "target": t, "detached": (s, t) in detached,
               "points": _route(chains[s, t], rank[s], y, boxes, port[s, t], left, right)}
              for s, t in edges]
    height = max(b[3] for b in boxes.values())
    return {"boxes": boxes, "labels": labels, "edges": routed, "size": (right[-1], height),
            "kinds": {n: "op" if n in ops else "input" for n in names}}


def _lanes(names, edges, rank):
    """The columns' items: the nodes, and one lane item per column an edge
    passes through. Returns the columns, each edge's chain of items (source,
    lanes, target) and the links between consecutive items of the chains."""
    layers = [[] for _ in range(max(rank.values()) + 1)]
    for name in names:
        layers[rank[name]].append(name)
    chains, links = {}, []
    for s, t in edges:
        chain = [s] + [("lane", s, t, r) for r in range(rank[s] + 1, rank[t])] + [t]
        for r, item in enumerate(chain[1:-1], rank[s] + 1):
            layers[r].append(item)
        links += list(zip(chain, chain[1:]))
        chains[s, t] = chain
    return layers, chains, links


def _sizes(names, labels, layers, measure):
    """Width and height of every item: a node's box fits its label, a lane is
    ``LANE`` high and has no width."""
    size = {}
    for name in names:
        w, h = measure(labels[name])
        size[name] = (w + 2 * PAD_X, h + 2 * PAD_Y)
    for layer in layers:
        for item in layer:
            size.setdefault(item, (0.0, LANE))
    return size


def _gaps(layer, size):
    """The least distances between the centres of consecutive items of a column."""
    def gap(a, b):
        real = sum(isinstance(i, str) for i in (a, b))
        return (size[a][1] + size[b][1]) / 2 + (ROW_GAP if real == 2 else ROW_GAP / 2)
    return [gap(a, b) for a, b in zip(layer, layer[1:])]


def _rows(layers, links, size):
    """Every item's y (its centre), the top of the drawing at 0: the items
    start stacked, then each is pulled towards its neighbours (sweeps to and
    fro over the columns), their gaps kept."""
    y = {}
    for layer in layers:
        y.update(zip(layer, _place([0.0] * len(layer), _gaps(layer, size))))
    neighbours = {}
    for a, b in links:
        neighbours.setdefault(a, []).append(b)
        neighbours.setdefault(b, []).append(a)
    for sweep in range(24):
        order = range(len(layers)) if sweep % 2 == 0 else range(len(layers) - 1, -1, -1)
        for r in order:
            layer = layers[r]
            desired = [sum(y[n] for n in neighbours.get(i, ())) / len(neighbours[i])
                       if neighbours.get(i) else y[i] for i in layer]
            y.update(zip(layer, _place(desired, _gaps(layer, size))))
    top = min(y[i] - size[i][1] / 2 for i in y)
    return {i: v - top for i, v in y.items()}


def _columns(layers, size):
    """The left side, centre and right side (x) of every column: as wide as
    its widest box, ``COLUMN_GAP`` between them."""
    widths = [max(size[i][0] for i in layer) if layer else 0.0 for layer in layers]
    left, x = [], 0.0
    for width in widths:
        left.append(x)
        x += width + COLUMN_GAP
    centre = [lx + w / 2 for lx, w in zip(left, widths)]
    right = [lx + w for lx, w in zip(left, widths)]
    return left, centre, right


def _ports(names, preds, chains, y, boxes):
    """Where each edge ends on its target's left side (y): a target's inputs
    end top to bottom in the order they arrive."""
    port = {}
    for name in names:
        incoming = sorted(preds[name], key=lambda s: (y[chains[s, name][-2]], preds[name].index(s)))
        x0, y0, x1, y1 = boxes[name]
        for k, s in enumerate(incoming):
            port[s, name] = y0 + (y1 - y0) * (k + 1) / (len(incoming) + 1)
    return port


def _route(chain, first, y, boxes, arrive_at, left, right):
    """The polyline of the edge along ``chain`` (its source, in column
    ``first``, its lanes, its target, where it ends at height ``arrive_at``):
    straight through each column, curved in the gaps between them."""
    s, t = chain[0], chain[-1]
    points = [(boxes[s][2], y[s])]
    if boxes[s][2] < right[first]:
        points.append((right[first], y[s]))
    for r, item in enumerate(chain[1:], first + 1):
        arrive = arrive_at if item == t else y[item]
        points += _curve(points[-1], (left[r], arrive))
        if item == t:  # (exactly on the box's side)
            if boxes[t][0] > left[r] + 1e-9:
                points.append((boxes[t][0], arrive))
            else:
                points[-1] = (boxes[t][0], arrive)
        else:
            points.append((right[r], arrive))
    return points


def draw_graph(graph, path, title):
    """Draw the camera graph left to right (layout: ``layout``); an input
    read through ``stop_gradient`` is drawn dashed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import FancyBboxPatch

    placed = layout(graph)
    width, height = placed["size"]
    dashed = any(edge["detached"] for edge in placed["edges"])
    # inches around the drawing, above it for the title, below it for the key
    margin, head, foot = 0.2, 0.45, 0.25 if dashed else 0.0
    fig = plt.figure(figsize=(width + 2 * margin, height + 2 * margin + head + foot))
    ax = fig.add_axes([0, 0, 1, 1])
    ax.set_xlim(-margin, width + margin)
    ax.set_ylim(height + margin + foot, -margin - head)  # y downwards, as the layout's
    ax.axis("off")
    grey = "#7a869a"
    for edge in placed["edges"]:
        xs, ys = zip(*edge["points"])
        ax.plot(xs, ys, color=grey, lw=0.8, zorder=1, linestyle=(0, (3, 2)) if edge["detached"] else "-")
        x, y = edge["points"][-1]
        ax.annotate("", xy=(x, y), xytext=(x - 0.1, y), zorder=2,
                    arrowprops=dict(arrowstyle="-|>", color=grey, lw=0.8, shrinkA=0, shrinkB=0,
                                    mutation_scale=7))
    for name, (x0, y0, x1, y1) in placed["boxes"].items():
        if placed["kinds"][name] == "input":
            colour = "#d9f2d9"
        else:
            colour = "#fde9c9" if name in ("X", "Y", "Z", "xCam", "yCam", "zCam") else "#e8eef9"
        ax.add_patch(FancyBboxPatch((x0, y0), x1 - x0, y1 - y0, zorder=3, fc=colour, ec="#44546a",
                                    lw=0.8, boxstyle="round,pad=0,rounding_size=0.04"))
        ax.text((x0 + x1) / 2, (y0 + y1) / 2, placed["labels"][name], ha="center", va="center",
                fontsize=FONT_SIZE, zorder=4)
    ax.text(width / 2, -margin - head / 2, title, ha="center", va="center", fontsize=10)
    if dashed:
        ax.text(0, height + margin + foot / 2, "dashed: read through stop_gradient (exact "
                "disentangling of Eq. 7)", fontsize=FONT_SIZE, color="#44546a", va="center")
    files.save_figure(fig, path, dpi=130)


def main(argv=None, prog=PROG):
    with_graph = [spec.name for spec in variants.SPECS if spec.camera_graph]
    parser = cli.Parser(prog=prog, description="Show the Lambda camera graph of a model.")
    parser.add_argument("--variant", default="cpl-a",
                        help=f"{' or '.join(with_graph)} (default cpl-a)")
    parser.add_argument("--backbone", default="small",
                        help=f"{', '.join(BACKBONES)} (default small: the graph is the same, "
                        "it builds fast)")
    parser.add_argument("--image-size", type=int, default=112,
                        help="square input side of the model drawn (default 112)")
    parser.add_argument("--as-released", action="store_true", help="the released code's graph")
    parser.add_argument("--out", default=os.path.join("runs", "camera_graph.png"),
                        help="diagram file (.png, .svg or .pdf; default runs/camera_graph.png, "
                        "git-ignored; docs/camera_graph.png is made with --out)")
    args = parser.parse_args(argv)
    try:
        if args.variant not in with_graph:
            raise ValueError(f"only {' and '.join(with_graph)} have a camera graph, "
                             f"not {args.variant!r}")
        if os.path.splitext(args.out)[1].lower() not in (".png", ".svg", ".pdf"):
            raise ValueError(f"--out must end in .png, .svg or .pdf: {args.out}")
        directory = os.path.dirname(os.path.abspath(args.out))
        if os.path.exists(directory) and not os.path.isdir(directory):
            raise ValueError(f"not a directory: {directory}")
        model = models.build_model(args.variant, backbone=args.backbone,
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
        cli.make_parent(args.out)  # (runs/, the default's folder, may not exist yet)
        draw_graph(graph, args.out, f"{args.variant} camera graph ({mode}): Eqs. 4a-5c as Lambda layers")
    except OSError as error:
        return cli.fail(prog, f"cannot write {args.out}: {error.strerror or error}")
    print(f"diagram written to {args.out}")
    return 0


if __name__ == "__main__":
    cli.run(main, PROG)
