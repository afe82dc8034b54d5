"""The camera-graph CLI (cpl_keras.graph) prints the graph, draws it and
writes it as Graphviz text."""

import re
import subprocess
import sys
from pathlib import Path

import pytest

from cpl_keras import build_model
from cpl_keras.commands.graph import main
from cpl_keras.graph import camera_graph, layout, to_dot
from helpers import REPO


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
    dot = tmp_path / "other" / "graph.dot"
    assert main(["--variant", "cpl-a", "--image-size", "32", "--out", str(out),
                 "--dot", str(dot)]) == 0
    text = capsys.readouterr().out
    assert "xCam = fx * b / d" in text and "4a" in text
    assert text.endswith(f"diagram written to {out}\nGraphviz text written to {dot}\n")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert '"xCam_over_fy" -> "zCam";' in dot.read_text()
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["graph.dot", "graph.png", "new", "other"]
    # docs/method.md's command (at 112 px; the graph does not depend on the
    # size) writes the committed figure and text again byte for byte, so its
    # rerun leaves `git status` empty
    for made, committed in ((out, "camera_graph.png"), (dot, "camera_graph.dot")):
        assert made.read_bytes() == (Path(REPO) / "docs" / committed).read_bytes(), committed
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


def test_cli_bad_output_paths_exit_2_before_building(tmp_path, capsys):
    (tmp_path / "file").write_text("")
    out = tmp_path / "graph.png"
    for args, message in (
            (["--dot", str(out)], "--dot and --out name the same file"),
            (["--dot", str(tmp_path / "file" / "g.dot")], "is a file"),
            (["--dot", str(tmp_path)], "output path is a directory")):
        assert main(["--variant", "cpl-u", "--out", str(out), *args]) == 2
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) == 1, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]


# ---------------------------------------------------------------------------
# The graph's forms: Graphviz text and the drawing's layout
# ---------------------------------------------------------------------------
def _graph(as_released):
    return camera_graph(build_model("cpl-a", backbone="small", image_size=32,
                                    as_released=as_released))


def _edges(graph):
    return {(s, g["name"]) for g in graph for s in g["inputs"]}


@pytest.mark.parametrize("as_released", [False, True])
def test_dot_text_has_every_layer_and_edge(as_released):
    graph = _graph(as_released)
    text = to_dot(graph, 'a "title"')
    assert text.startswith("// dashed: ") and "\ndigraph camera_graph {\n" in text
    assert text.endswith("\n}\n") and 'label="a \\"title\\""' in text
    nodes = dict(re.findall(r'^  "(\w+)" \[label="([^"]*)"', text, re.M))
    edges = re.findall(r'^  "(\w+)" -> "(\w+)"( \[style=dashed\])?;$', text, re.M)
    layers = {g["name"]: g for g in graph}
    assert set(nodes) == set(layers) | {s for s, _ in _edges(graph)}
    for name, g in layers.items():
        assert nodes[name] == f"{name}\\n{g['op']}  (Eq. {g['equation']})"
    assert len(edges) == len(_edges(graph)) and {(s, t) for s, t, _ in edges} == _edges(graph)
    assert {(s, t) for s, t, dashed in edges if dashed} == {
        (s, g["name"]) for g in graph for s in g["detached"]}
    if not as_released:  # (the paper's form reads the parameters through stop_gradient)
        assert ("fx", "fx_times_baseline", " [style=dashed]") in edges


@pytest.mark.parametrize("as_released", [False, True])
def test_layout_puts_every_node_after_its_inputs(as_released):
    graph = _graph(as_released)
    placed = layout(graph)
    column, boxes = placed["column"], placed["boxes"]
    assert {(e["source"], e["target"]) for e in placed["edges"]} == _edges(graph)
    for s, t in _edges(graph):
        assert column[s] < column[t], (s, t)
        assert boxes[s][2] < boxes[t][0], (s, t)  # (and drawn to its left)
    assert {column[g["name"]] for g in graph if g["name"] in ("X", "Y", "Z")} == {max(column.values())}
    assert set(boxes) == set(column) and all(placed["labels"][g["name"]].startswith(g["name"] + "\n")
                                             for g in graph)
    names = list(boxes)
    for i, a in enumerate(names):  # no two boxes (labels) overlap
        for b in names[i + 1:]:
            A, B = boxes[a], boxes[b]
            assert A[2] <= B[0] or B[2] <= A[0] or A[3] <= B[1] or B[3] <= A[1], (a, b)
    for edge in placed["edges"]:  # each edge ends on its own target's left side
        x, y = edge["path"][0][-1]
        target = boxes[edge["target"]]
        assert x == target[0] and target[1] < y < target[3]
