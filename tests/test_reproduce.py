"""The one-command reproduction pipeline, in its quick mode (as CI runs it)."""

import json
import subprocess
import sys


def run(*args, cwd=None):
    return subprocess.run([sys.executable, "evaluate.py", *args], capture_output=True, text=True,
                          cwd=cwd)


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


def test_reproduce_bad_arguments_exit_2(tmp_path):
    for args in (["--reproduce", "--pairs", "0"], ["--reproduce", "--table", "1"], ["--quick"]):
        result = run(*args, "--out", str(tmp_path / "out"), "--data-dir", str(tmp_path / "d"))
        assert result.returncode == 2, args
        assert result.stderr.startswith("error: ") and "Traceback" not in result.stderr
    assert not (tmp_path / "out" / "REPORT.md").exists()
