"""The camera-graph CLI (cpl_keras.graph, alias cpl_keras.inspect) prints the graph and draws it."""

import subprocess
import sys

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
    out = tmp_path / "graph.png"
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
        result = subprocess.run([sys.executable, "-m", "cpl_keras.inspect", *args, "--out", str(out)]
                                if "--out" not in args else [sys.executable, "-m", "cpl_keras.inspect", *args],
                                capture_output=True, text=True)
        assert result.returncode == 2
        assert result.stderr.startswith("python -m cpl_keras.inspect: error: ") and "Traceback" not in result.stderr
        assert len(result.stderr.strip().splitlines()) == 1
    assert not out.exists()
