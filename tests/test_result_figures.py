"""``analyses/validation_curves.py`` and ``analyses/collapsed_pitch.py``:
two figures of paper_results/, their numbers from the committed files."""

import json
import shutil

from helpers import REPO, load_script


def _tampered(script, tmp_path, monkeypatch, change):
    """The script's committed JSON copied into ``tmp_path``, ``change``d, and
    the script pointed at the copy."""
    out = tmp_path / "figure"
    shutil.copy(script.OUT + ".json", str(out) + ".json")
    with open(str(out) + ".json") as f:
        payload = json.load(f)
    change(payload)
    with open(str(out) + ".json", "w") as f:
        json.dump(payload, f)
    monkeypatch.setattr(script, "OUT", str(out))


def test_the_committed_validation_curves_are_what_the_logs_give(capsys, tmp_path, monkeypatch):
    script = load_script("analyses/validation_curves.py")
    assert script.OUT.startswith(REPO)
    assert script.main(["--check"]) == 0, capsys.readouterr().err
    result = script.compute()
    for towers in ("InceptionV3", "compact"):
        for runs in result["towers"][towers]["variants"].values():
            assert sorted(runs) == ["0", "1", "2"]
            for run in runs.values():
                assert run["kept_epoch"] == run["lowest_epoch"] < run["last_epoch"]

    def change(payload):
        run = payload["towers"]["InceptionV3"]["variants"]["MTL-CPL-A"]["0"]
        run["kept_epoch"] += 1

    _tampered(script, tmp_path, monkeypatch, change)
    assert script.main(["--check"]) == 1
    assert "differs" in capsys.readouterr().err


def test_the_committed_collapsed_pitch_is_what_the_predictions_give(capsys, tmp_path,
                                                                    monkeypatch):
    script = load_script("analyses/collapsed_pitch.py")
    assert script.main(["--check"]) == 0, capsys.readouterr().err
    # the numbers are those of the collapsed-heads page, whose definition it imports
    with open(f"{REPO}/paper_results/inception-2000-ablations/collapsed-heads.json") as f:
        page = json.load(f)
    with open(script.OUT + ".json") as f:
        runs = json.load(f)["runs"]
    for row in ("MTL-CPL-A", "MTL-Baseline"):
        for seed, entry in runs[row].items():
            cell = page[f"InceptionV3 {row}, seed {seed}"]["columns"]["pitch"]
            assert entry["pairs"] == cell["pairs"]
            assert abs(entry["share"] - cell["share"]) < 1e-4
            if "error_share" in cell:
                assert abs(entry["error_share"] - cell["error_share"]) < 1e-4

    def change(payload):
        payload["runs"]["MTL-CPL-A"]["1"]["error_share"] = 0.5

    _tampered(script, tmp_path, monkeypatch, change)
    assert script.main(["--check"]) == 1
    assert "differs" in capsys.readouterr().err
