"""analyses/head_units.py: when a head dies, from logs written with
train.py --head-units."""

import csv
import json

from helpers import assert_refuses_a_bare_log, load_script

HEADS = ("fx", "fy", "u0", "v0", "baseline", "disparity", "tx", "ty", "tz", "pitch")


def _log(path, epochs):
    """A log.csv whose pitch head loses units and dies at epoch 3, another
    head steady; ``epochs``: the 1-based epochs, the first without columns."""
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["epoch", "loss"] + [f"{k}_{h}" for h in HEADS for k in ("dead", "units")])
        for epoch in epochs:
            if epoch == epochs[0]:  # (logged before --head-units was added)
                writer.writerow([epoch, 1.0] + [""] * (2 * len(HEADS)))
                continue
            cells = []
            for head in HEADS:
                if head == "pitch":
                    cells += [{2: 0.0, 3: 0.5, 4: 1.0}[epoch], {2: 6, 3: 2, 4: 0}[epoch]]
                else:
                    cells += [0.0, 30]
            writer.writerow([epoch, 1.0] + cells)


def test_the_epoch_a_head_dies_and_its_units(tmp_path, capsys):
    """Per run and head: the first epoch with a dead share of 0.25 or more,
    the units first, last and fewest; --head lists every logged epoch; a
    log without the columns is one line, exit 2, and nothing written."""
    script = load_script("analyses/head_units.py")
    run = tmp_path / "runs" / "cvgl_cpl-a-s0"
    run.mkdir(parents=True)
    _log(str(run) + "_log.csv", [1, 2, 3, 4])  # (a published run's log beside its folder)
    out = tmp_path / "units.md"
    assert script.main(["--run", f"A={run}", "--head", "pitch", "--out", str(out)]) == 0
    summary = json.loads((tmp_path / "units.json").read_text())["A"]
    assert summary["epochs"] == [2, 3, 4]
    pitch, fx = summary["heads"]["pitch"], summary["heads"]["fx"]
    assert pitch["first_dead_epoch"] == 3 and fx["first_dead_epoch"] is None
    assert (pitch["units_first"], pitch["units_last"], pitch["units_fewest"]) == (6, 0, 0)
    text = out.read_text()
    assert "| dead 3; 6 -> 0 (min 0) |" in text and "| 3 | 0.50, 2 |" in text
    assert script.main(["--run", f"A={run}", "--dead-share", "1", "--out", str(out)]) == 0
    summary = json.loads((tmp_path / "units.json").read_text())["A"]
    assert summary["heads"]["pitch"]["first_dead_epoch"] == 4
    assert_refuses_a_bare_log(script, tmp_path, capsys, "no dead_<head>/units_<head> columns")
