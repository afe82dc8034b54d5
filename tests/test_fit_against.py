"""analyses/fit_against.py: a run's training MAE over a reference run's,
epoch by epoch, and its Eq. 9 weights, from two log.csv files."""

import csv
import json

import pytest
from helpers import load_script


def _script():
    return load_script("analyses/fit_against.py")


def _write_log(path, header, rows):
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(header)
        writer.writerows(rows)


def test_ratios_crossing_and_weights_against_the_reference(tmp_path, capsys):
    script = _script()
    runs = tmp_path / "runs"
    runs.mkdir()
    # the run (a camera-projection variant: <target>_mae and alpha_<target>),
    # published (RUN_log.csv); its MAE of b 4, 3, 2, 1 against the reference's
    # 2 at every epoch: below it from epoch 4 only
    _write_log(str(runs / "cpl") + "_log.csv", ["epoch", "baseline_mae", "alpha_baseline"],
               [[e, 5 - e, 0.1 * e] for e in range(1, 5)])
    # the reference (MTL-Baseline: <target>_loss), a run directory, 5 epochs
    (runs / "base").mkdir()
    _write_log(runs / "base" / "log.csv", ["epoch", "baseline_loss"],
               [[e, 2.0] for e in range(1, 6)])
    out = tmp_path / "page.md"
    assert script.main(["--pair", f"A={runs / 'cpl'},{runs / 'base'}", "--targets", "baseline",
                        "--epochs", "1", "3", "--out", str(out)]) == 0
    result = json.loads((tmp_path / "page.json").read_text())["A"]["baseline"]
    assert result["ratio"] == {"1": 2.0, "3": 1.0}
    assert (result["last_epoch"], result["ratio_last"]) == (4, 0.5)
    assert (result["first_below"], result["epochs_below"], result["epochs_compared"]) == (4, 1, 4)
    assert result["alpha"] == {"1": pytest.approx(0.1), "3": pytest.approx(0.3),
                               "4": pytest.approx(0.4)}
    assert "| baseline | 2.00 | 1.00 | 4 | 0.50 | 4 | 1 of 4 | 0.100 | 0.300 | 0.400 |" \
        in out.read_text()

    # a log with neither column is one line, exit 2, and nothing written
    capsys.readouterr()
    assert script.main(["--pair", f"B={runs / 'cpl'},{runs / 'base'}", "--targets", "pitch",
                        "--out", str(tmp_path / "bad.md")]) == 2
    err = capsys.readouterr().err
    assert "neither pitch_mae nor pitch_loss" in err and err.count("\n") == 1
    assert not (tmp_path / "bad.md").exists()
