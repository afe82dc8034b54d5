"""Inspect the Lambda camera graph of a model.

    python -m cpl_keras.graph --variant cpl-a [--backbone small]
        [--image-size 112] [--as-released] [--out runs/camera_graph.png]
        [--dot camera_graph.dot]

Prints every camera-graph layer with its op, its inputs and the paper
equation it implements, and draws the graph (PNG, SVG or PDF by the file
extension; laid out with networkx, drawn with matplotlib); ``--dot`` also
writes it as Graphviz text, to draw it with Graphviz.
"""

from __future__ import annotations

import itertools
import statistics

import networkx as nx

from cpl_keras import camera, files

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


# The graph as networkx sees it, and as Graphviz text.
#: Box colours: what feeds the graph, the camera coordinates and 3D point, the rest.
COLOURS = {"input": "#d9f2d9", "point": "#fde9c9", "op": "#e8eef9"}
POINT_LAYERS = ("X", "Y", "Z", "xCam", "yCam", "zCam")
DASHED_KEY = "dashed: read through stop_gradient (exact disentangling of Eq. 7)"


def to_networkx(graph):
    """``graph`` (``camera_graph``) as a ``networkx.DiGraph``: the layers and
    what feeds them (heads, gates) as nodes with a ``label`` (the layer, its
    op and equation; or head, gate) and a ``kind`` (``input``, ``point`` or
    ``op``), an edge per input with ``detached`` (read through ``stop_gradient``)."""
    ops = {g["name"]: g for g in graph}
    names = dict.fromkeys([i for g in graph for i in g["inputs"] if i not in ops]
                          + [g["name"] for g in graph])
    dg = nx.DiGraph()
    for name in names:
        kind = "input" if name not in ops else "point" if name in POINT_LAYERS else "op"
        label = (f"{name}\n{ops[name]['op']}  (Eq. {ops[name]['equation']})" if name in ops
                 else f"{name}\n({'gate' if name.endswith('_gate') else 'head'})")
        dg.add_node(name, label=label, kind=kind)
    for g in graph:
        for source in dict.fromkeys(g["inputs"]):
            dg.add_edge(source, g["name"], detached=source in g["detached"])
    return dg


def _quote(text):
    """``text`` as a Graphviz quoted string (a line break as ``\\n``)."""
    return '"' + text.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n") + '"'


def to_dot(graph, title):
    """The camera graph as Graphviz text (``dot -Tpng``): the figure's boxes,
    labels, colours and dashed edges, left to right."""
    dg = to_networkx(graph)
    lines = [f"// {DASHED_KEY}", "digraph camera_graph {",
             f"  graph [rankdir=LR, labelloc=t, label={_quote(title)}];",
             '  node [shape=box, style="rounded,filled", color="#44546a", fontsize=10];',
             '  edge [color="#7a869a"];']
    for name, data in dg.nodes(data=True):
        lines.append(f'  {_quote(name)} [label={_quote(data["label"])}, '
                     f'fillcolor="{COLOURS[data["kind"]]}"];')
    for source, target, data in dg.edges(data=True):
        style = " [style=dashed]" if data["detached"] else ""
        lines.append(f"  {_quote(source)} -> {_quote(target)}{style};")
    return "\n".join(lines + ["}"]) + "\n"


# The layout: columns (networkx's topological generations), the order within
# a column (barycentres), edges that skip columns in lanes of their own.
#: Label size (points), box padding, the gaps between columns (where edges
#: bend) and between boxes of a column, and the height of the lane an edge
#: takes through a column it passes (inches).
FONT_SIZE = 7.5
PAD_X, PAD_Y = 0.08, 0.05
COLUMN_GAP = 0.55
ROW_GAP = 0.14
LANE = 0.09
#: Sweeps of the barycentre ordering.
SWEEPS = 12


def _text_size(label):
    """A label's width and height in inches (matplotlib's font, so that the
    boxes fit the drawn text)."""
    from matplotlib.textpath import TextPath

    lines = label.split("\n")
    width = max(TextPath((0, 0), line, size=FONT_SIZE).get_extents().width for line in lines)
    return float(width) / 72, FONT_SIZE * (1.2 * (len(lines) - 1) + 1.15) / 72


def columns(dg):
    """Every node's column: its topological generation; then the outputs (no
    consumers) moved to the last column, and every input, and every node
    with more consumers than inputs, as far right as its consumers allow
    (it shortens more edges than it lengthens)."""
    column = {n: k for k, generation in enumerate(nx.topological_generations(dg))
              for n in generation}
    last = max(column.values())
    column.update({n: last for n in dg if dg.out_degree(n) == 0})
    for n in reversed(list(nx.topological_sort(dg))):
        if dg.out_degree(n) > dg.in_degree(n):
            column[n] = min(column[s] for s in dg.successors(n)) - 1
    return column


def _with_lanes(dg, column):
    """``dg`` with every edge that skips columns split by a lane node
    ``("lane", source, target, column)`` per column it passes; returns the
    new graph, every node's column and every edge's chain of nodes."""
    expanded, chains = nx.DiGraph(), {}
    expanded.add_nodes_from(dg)
    column = dict(column)
    for s, t in dg.edges:
        lanes = [("lane", s, t, c) for c in range(column[s] + 1, column[t])]
        column.update({lane: lane[3] for lane in lanes})
        chains[s, t] = [s, *lanes, t]
        nx.add_path(expanded, chains[s, t])
    return expanded, column, chains


def _crossings(expanded, stacks):
    """How many pairs of edges cross between consecutive columns."""
    where = {n: k for stack in stacks for k, n in enumerate(stack)}
    spans = [[(where[a], where[b]) for a in stack for b in expanded.successors(a)] for stack in stacks]
    return sum((a1 - a2) * (b1 - b2) < 0 for gap in spans
               for (a1, b1), (a2, b2) in itertools.combinations(gap, 2))


def _order(expanded, column):
    """Each column's nodes top to bottom: sweeps to and fro, each sorting a
    column by the mean position of its nodes' neighbours in the column just
    swept; the order with the fewest crossings is kept."""
    stacks = [[] for _ in range(max(column.values()) + 1)]
    for n in expanded:
        stacks[column[n]].append(n)
    best = (_crossings(expanded, stacks), [list(s) for s in stacks])
    for sweep in range(SWEEPS):
        down = sweep % 2 == 0
        for c in range(1, len(stacks)) if down else range(len(stacks) - 2, -1, -1):
            where = {n: k for k, n in enumerate(stacks[c - 1 if down else c + 1])}
            near = expanded.predecessors if down else expanded.successors
            mean = {n: statistics.fmean([where[m] for m in near(n)] or [k])
                    for k, n in enumerate(stacks[c])}
            stacks[c].sort(key=mean.get)
        best = min(best, (_crossings(expanded, stacks), [list(s) for s in stacks]),
                   key=lambda pair: pair[0])
    return best[1]


def _rows(stacks, height):
    """Every node's y (its centre; y downwards): each column's nodes stacked
    in order, a lane taking less room than a box, the columns centred on one
    line (as ``networkx.multipartite_layout`` centres its layers)."""
    y = {}
    for stack in stacks:
        gaps = [(height[a] + height[b]) / 2 + ROW_GAP * (0.5 if tuple in (type(a), type(b)) else 1)
                for a, b in zip(stack, stack[1:])]
        centres = list(itertools.accumulate(gaps, initial=0.0))
        y.update({n: c - centres[-1] / 2 for n, c in zip(stack, centres)})
    top = min(v - height[n] / 2 for n, v in y.items())
    return {n: v - top for n, v in y.items()}


def layout(graph, measure=None):
    """Where everything of the drawing goes, in inches, y downwards: a dict
    of ``column`` (name -> column), ``boxes`` (name -> (x0, y0, x1, y1)),
    ``labels``, ``kinds`` (``to_networkx``'s), ``edges`` (dicts: ``source``,
    ``target``, ``detached``, ``path``: matplotlib's vertices and codes; an
    edge leaves the middle of its source's right side and ends on its
    target's left side, one point per input) and ``size`` (width, height).
    """
    measure = measure or _text_size
    dg = to_networkx(graph)
    column = columns(dg)
    expanded, where, chains = _with_lanes(dg, column)
    size = {n: (w + 2 * PAD_X, h + 2 * PAD_Y) for n, label in dg.nodes(data="label")
            for w, h in [measure(label)]}
    stacks = _order(expanded, where)
    y = _rows(stacks, {n: size[n][1] if n in size else LANE for n in expanded})
    widths = [max((size[n][0] for n in stack if n in size), default=0.0) for stack in stacks]
    left = list(itertools.accumulate((w + COLUMN_GAP for w in widths[:-1]), initial=0.0))
    right = [x + w for x, w in zip(left, widths)]
    boxes = {}
    for n, c in column.items():
        x0, half = left[c] + (widths[c] - size[n][0]) / 2, size[n][1] / 2
        boxes[n] = (x0, y[n] - half, x0 + size[n][0], y[n] + half)
    port = {}
    for t in dg:  # (a box's inputs end top to bottom in the order they arrive)
        incoming = sorted(dg.predecessors(t), key=lambda s, t=t: y[chains[s, t][-2]])
        x0, y0, x1, y1 = boxes[t]
        port.update({(s, t): y0 + (y1 - y0) * (k + 1) / (len(incoming) + 1)
                     for k, s in enumerate(incoming)})
    edges = [{"source": s, "target": t, "detached": detached,
              "path": _route(chains[s, t], where, y, boxes, port[s, t], left, right)}
             for s, t, detached in dg.edges(data="detached")]
    return {"column": column, "boxes": boxes, "labels": dict(dg.nodes(data="label")),
            "kinds": dict(dg.nodes(data="kind")), "edges": edges,
            "size": (right[-1], max(b[3] for b in boxes.values()))}


def _route(chain, column, y, boxes, arrive, left, right):
    """The path of the edge along ``chain`` (matplotlib's vertices and codes):
    from its source straight to the right side of the source's column, then
    per column a curve in the gap (leaving and arriving horizontally) and a
    straight line through the column (a lane) or to the target's box, where
    it ends at height ``arrive``."""
    from matplotlib.path import Path

    s, t = chain[0], chain[-1]
    height = y[s]
    vertices, codes = [(boxes[s][2], height), (right[column[s]], height)], [Path.MOVETO, Path.LINETO]
    for n in chain[1:]:
        x0, x1 = vertices[-1][0], left[column[n]]
        to = arrive if n == t else y[n]
        vertices += [((x0 + x1) / 2, height), ((x0 + x1) / 2, to), (x1, to),
                     (boxes[t][0] if n == t else right[column[n]], to)]
        codes += [Path.CURVE4] * 3 + [Path.LINETO]
        height = to
    return vertices, codes


def draw_graph(graph, path, title):
    """Draw the camera graph left to right (layout: ``layout``); an input
    read through ``stop_gradient`` is drawn dashed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import FancyBboxPatch, PathPatch
    from matplotlib.path import Path

    placed = layout(graph)
    width, height = placed["size"]
    dashed = any(edge["detached"] for edge in placed["edges"])
    # inches around the drawing, above it for the title, below it for the key
    margin, head, foot = 0.2, 0.45, 0.25 if dashed else 0.0
    fig = plt.figure(figsize=(width + 2 * margin, height + 2 * margin + head + foot))
    ax = fig.add_axes([0, 0, 1, 1], xlim=(-margin, width + margin),
                      ylim=(height + margin + foot, -margin - head))  # y downwards, as the layout's
    ax.axis("off")
    grey = "#7a869a"
    for edge in placed["edges"]:
        ax.add_patch(PathPatch(Path(*edge["path"]), fill=False, ec=grey, lw=0.8, zorder=1,
                               linestyle=(0, (3, 2)) if edge["detached"] else "-"))
        x, y = edge["path"][0][-1]
        ax.annotate("", xy=(x, y), xytext=(x - 0.1, y), zorder=2,
                    arrowprops=dict(arrowstyle="-|>", color=grey, lw=0.8, shrinkA=0, shrinkB=0,
                                    mutation_scale=7))
    for name, (x0, y0, x1, y1) in placed["boxes"].items():
        ax.add_patch(FancyBboxPatch((x0, y0), x1 - x0, y1 - y0, zorder=3,
                                    fc=COLOURS[placed["kinds"][name]], ec="#44546a", lw=0.8,
                                    boxstyle="round,pad=0,rounding_size=0.04"))
        ax.text((x0 + x1) / 2, (y0 + y1) / 2, placed["labels"][name], ha="center", va="center",
                fontsize=FONT_SIZE, zorder=4)
    ax.text(width / 2, -margin - head / 2, title, ha="center", va="center", fontsize=10)
    if dashed:
        ax.text(0, height + margin + foot / 2, DASHED_KEY, fontsize=FONT_SIZE, color="#44546a",
                va="center")
    files.save_figure(fig, path, dpi=130)


if __name__ == "__main__":  # the command line: cpl_keras/commands/graph.py
    import runpy

    runpy.run_module("cpl_keras.commands.graph", run_name="__main__")
