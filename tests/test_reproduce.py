"""The one-command reproduction pipeline, in its quick mode (as CI runs it)."""

import json
import os
import subprocess
import sys

import pytest


def run(*args, cwd=None):
    return subprocess.run([sys.executable, "evaluate.py", *args], capture_output=True, text=True,
                          cwd=cwd)


@pytest.mark.slow
def test_quick_reproduction_end_to_end(tmp_path):
    out, data, runs = tmp_path / "out", tmp_path / "data", tmp_path / "runs"
    result = run("--reproduce", "--quick", "--out", str(out), "--data-dir", str(data),
                 "--runs-dir", str(runs))
    assert result.returncode == 0, result.stderr[-3000:]
    report = (out / "REPORT.md").read_text()
    for heading in ("Table 1, paper protocol", "Table 1, unseen rigs", "Table 2, real data",
                    "Training runs", "MTL-CPL-A (as released)", "Geometric"):
        assert heading in report
    for stem in ("table1_cvgl", "table1_random", "table2_middlebury"):
        table = json.loads((out / f"{stem}.json").read_text())
        assert {"Average", "Deep-Homo", "MTL-CPL-U", "MTL-Baseline", "MTL-CPL-A"} <= set(table["rows"])
        assert (out / f"{stem}_fov.png").read_bytes()[:4] == b"\x89PNG"
    cvgl = json.loads((out / "table1_cvgl.json").read_text())
    assert cvgl["rows"]["MTL-CPL-A (as released)"]["as_released"] is True
    summary = json.loads((out / "reproduce.json").read_text())
    assert len(summary["runs"]) == 9
    assert all(r["epochs_run"] == 1 and r["split"] in ("paper", "held-out-config") for r in summary["runs"])
    assert (out / "runs" / "random_cpl-a_log.csv").exists()
    # no machine's absolute paths in the results (but in the command as typed):
    # paths are relative to out/
    command = summary["command"]
    for name in os.listdir(out):
        if name.endswith((".md", ".json", ".csv")):
            text = (out / name).read_text().replace(json.dumps(command)[1:-1], "")
            assert str(tmp_path) not in text.replace(command, ""), name
    assert (out / cvgl["runs"][0] / "config.json").exists()
    # run again: every stage is reused (the tables too, despite relative paths)
    again = run("--reproduce", "--quick", "--out", str(out), "--data-dir", str(data),
                "--runs-dir", str(runs))
    assert again.returncode == 0 and "evaluating" not in again.stderr, again.stderr[-3000:]


def test_reproduce_bad_arguments_exit_2(tmp_path):
    for args in (["--reproduce", "--pairs", "0"], ["--reproduce", "--table", "1"], ["--quick"]):
        result = run(*args, "--out", str(tmp_path / "out"), "--data-dir", str(tmp_path / "d"))
        assert result.returncode == 2, args
        assert result.stderr.startswith("evaluate.py: error: ") and "Traceback" not in result.stderr
    # the reproduction's own entry point, same error format under its own name
    result = subprocess.run([sys.executable, "-m", "cpl_keras.reproduce", "--pairs", "0",
                             "--out", str(tmp_path / "out")], capture_output=True, text=True)
    assert result.returncode == 2
    assert result.stderr.startswith("python -m cpl_keras.reproduce: error: pairs must be positive")
    assert not (tmp_path / "out" / "REPORT.md").exists()
