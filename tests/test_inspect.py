"""The camera-graph CLI (cpl_keras.graph) prints the graph and draws it."""

import subprocess
import sys

import pytest

from cpl_keras import build_model
from cpl_keras.graph import camera_graph, main


def test_camera_graph_lists_every_equation():
    graph = camera_graph(build_model("cpl-u", backbone="small", image_size=32))
    by_name = {g["name"]: g for g in graph}
    assert by_name["xCam"]["op"] == "div" and by_name["xCam"]["equation"] == "4a"
    assert by_name["xCam"]["inputs"] == ["fx_times_baseline", "disparity"]
    assert by_name["Y"]["inputs"] == ["yCam", "ty"] and by_name["Y"]["equation"] == "5b"
    assert {g["op"] for g in graph} == {"add", "sub", "mul", "div", "neg", "sin", "cos"}
    assert len(graph) == 21


def test_released_cpl_a_graph_has_the_gates():
    graph = camera_graph(build_model("cpl-a", backbone="small", image_size=32, as_released=True))
    by_name = {g["name"]: g for g in graph}
    assert by_name["X"]["inputs"] == ["X_projected", "X_gate"]
    assert by_name["X"]["equation"] == "release"


def test_cli_prints_the_table_and_writes_the_diagram(tmp_path, capsys):
    out = tmp_path / "new" / "graph.png"  # (missing folders are made)
    assert main(["--variant", "cpl-a", "--image-size", "32", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "xCam = fx * b / d" in text and "4a" in text
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    svg = tmp_path / "graph.svg"
    assert main(["--variant", "cpl-u", "--image-size", "32", "--out", str(svg)]) == 0
    assert b"<svg" in svg.read_bytes()[:2000]


def test_cli_bad_arguments_exit_2_without_output(tmp_path):
    out = tmp_path / "graph.png"
    for args in (["--variant", "baseline"], ["--variant", "cpl-u", "--out", str(tmp_path / "g.txt")],
                 ["--variant", "cpl-u", "--image-size", "8"]):
        result = subprocess.run([sys.executable, "-m", "cpl_keras.graph", *args, "--out", str(out)]
                                if "--out" not in args else [sys.executable, "-m", "cpl_keras.graph", *args],
                                capture_output=True, text=True, timeout=600)
        assert result.returncode == 2
        assert result.stderr.startswith("python -m cpl_keras.graph: error: ") and "Traceback" not in result.stderr
        assert len(result.stderr.strip().splitlines()) == 1
    assert not out.exists()


# ---------------------------------------------------------------------------
# The drawing: every edge visibly ends at its own box
# ---------------------------------------------------------------------------
def _passes_through(p, q, box, inset=1e-6):
    """Whether the segment p-q enters the interior of ``box`` (x0, y0, x1, y1)
    shrunk by ``inset`` (Liang-Barsky clipping)."""
    x0, y0, x1, y1 = box[0] + inset, box[1] + inset, box[2] - inset, box[3] - inset
    (px, py), (qx, qy) = p, q
    dx, dy = qx - px, qy - py
    low, high = 0.0, 1.0
    for step, room in ((-dx, px - x0), (dx, x1 - px), (-dy, py - y0), (dy, y1 - py)):
        if step == 0:
            if room < 0:
                return False
            continue
        t = room / step
        if step < 0:
            low = max(low, t)
        else:
            high = min(high, t)
        if low > high:
            return False
    return True


def _boxes_crossed(points, boxes, skip=()):
    return sorted({name for name, box in boxes.items() if name not in skip
                   for p, q in zip(points, points[1:]) if _passes_through(p, q, box)})


def _straight_edges_of_the_first_drawing(graph, boxes):
    """The first drawing's geometry (one column per depth, heads in the first,
    2.3 x 0.62 inches a cell, straight lines from box to box), with these boxes."""
    depth = {}
    for node in graph:
        for name in node["inputs"]:
            depth.setdefault(name, 0)
        depth[node["name"]] = 1 + max(depth[i] for i in node["inputs"])
    columns = {}
    for name, d in depth.items():
        columns.setdefault(d, []).append(name)
    moved = {}
    for d, names in columns.items():
        for k, name in enumerate(names):
            x0, y0, x1, y1 = boxes[name]
            cx, cy = 2.3 * d, 0.62 * (k - (len(names) - 1) / 2)
            moved[name] = (cx - (x1 - x0) / 2, cy - (y1 - y0) / 2, cx + (x1 - x0) / 2, cy + (y1 - y0) / 2)
    edges = {(s, g["name"]): [(moved[s][2], (moved[s][1] + moved[s][3]) / 2),
                              (moved[g["name"]][0], (moved[g["name"]][1] + moved[g["name"]][3]) / 2)]
             for g in graph for s in g["inputs"]}
    return moved, edges


@pytest.mark.parametrize("as_released", [False, True])
def test_every_edge_ends_at_its_own_box_and_passes_through_none(as_released):
    from cpl_keras.graph import layout

    graph = camera_graph(build_model("cpl-a", backbone="small", image_size=32,
                                     as_released=as_released))
    placed = layout(graph)
    boxes = placed["boxes"]
    assert {(e["source"], e["target"]) for e in placed["edges"]} == {
        (s, g["name"]) for g in graph for s in g["inputs"]}
    assert len(placed["edges"]) == sum(len(set(g["inputs"])) for g in graph)
    names = list(boxes)
    for i, a in enumerate(names):  # no two boxes overlap
        for b in names[i + 1:]:
            A, B = boxes[a], boxes[b]
            assert A[2] <= B[0] or B[2] <= A[0] or A[3] <= B[1] or B[3] <= A[1], (a, b)
    for edge in placed["edges"]:
        points = edge["points"]
        source, target = boxes[edge["source"]], boxes[edge["target"]]
        # it leaves from the source's right side and ends on the target's left side ...
        assert points[0][0] == source[2] and source[1] < points[0][1] < source[3]
        assert points[-1][0] == target[0] and target[1] < points[-1][1] < target[3]
        # ... arriving from the left, and enters no box on its way, its own included
        assert points[-2][0] < points[-1][0]
        assert _boxes_crossed(points, boxes) == [], edge
    # two inputs of one box end at two different points
    ends = [(e["target"], e["points"][-1]) for e in placed["edges"]]
    assert len(set(ends)) == len(ends)


def test_the_check_catches_the_first_drawings_edges():
    """The first drawing's straight edges ran behind other boxes (disparity ->
    xCam and fy -> xCam_over_fy behind fx_times_baseline): the check above
    finds them."""
    from cpl_keras.graph import layout

    graph = camera_graph(build_model("cpl-a", backbone="small", image_size=32))
    boxes, edges = _straight_edges_of_the_first_drawing(graph, layout(graph)["boxes"])
    crossed = {edge: _boxes_crossed(points, boxes, skip=edge) for edge, points in edges.items()}
    assert "fx_times_baseline" in crossed["fy", "xCam_over_fy"]
    assert "fx_times_baseline" in crossed["disparity", "xCam"]
