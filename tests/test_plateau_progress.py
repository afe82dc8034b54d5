"""``analyses/plateau_progress.py``: the plateau amendment's runs as they
stand, from their ledgers, run directories and published records."""

import glob
import json
import os
import shutil

import numpy as np
import pytest
from helpers import REPO, load_script

from cpl_keras import camera
from cpl_keras.training.state import TrainingState, write_state
from cpl_keras.training_options import TrainingError

CPU = {"cpu": "AMD EPYC", "cpu_count": 2}
FIGHT = os.path.join(REPO, "paper_results", "fair-fight")


def _log(path, values):
    """A log.csv of the monitor alone, epochs numbered from 1."""
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w") as f:
        f.write("epoch,val_nmae\n" + "".join(f"{i + 1},{v}\n" for i, v in enumerate(values)))


def _halved_errors(out, arm, seed):
    """The committed 50-epoch record's test predictions of ``arm`` and
    ``seed`` copied into ``out``'s 50-epoch runs, and into its plateau record
    with every error halved."""
    rows = load_script("analyses/fair_fight_rows.py")
    name = f"cvgl_{arm}-s{seed}"
    source = os.path.join(FIGHT, "inception", "runs", name)
    (stored,) = glob.glob(os.path.join(source, "predictions", "*.npz"))
    with np.load(stored, allow_pickle=False) as found:
        arrays = {k: found[k] for k in found.files}
    fifty = out / "inception" / "runs" / name
    os.makedirs(fifty / "predictions", exist_ok=True)
    np.savez(fifty / "predictions" / os.path.basename(stored), **arrays)
    shutil.copy(os.path.join(source, "config.json"), fifty / "config.json")
    _, _, truth = rows.truths(seed)
    outputs = [str(x) for x in arrays["outputs"]]
    pred = arrays["pred"].astype(np.float64)
    for p in camera.PARAMETERS:
        i = outputs.index(p)
        pred[:, i] = truth[p] + (pred[:, i] - truth[p]) / 2
    os.makedirs(out / "inception-plateau" / "runs" / name / "predictions", exist_ok=True)
    np.savez(out / "inception-plateau" / "runs" / name / "predictions"
             / os.path.basename(stored), **dict(arrays, pred=pred))


@pytest.fixture
def plateau(tmp_path):
    """A home and an out folder: MTL-Baseline seed 0 training (25 epochs,
    best at 20), MTL-CPL-A seed 0 published (63 epochs, stopped by
    patience), MTL-Baseline seed 1 lost (a start, no run directory)."""
    script, starts = load_script("analyses/plateau_progress.py"), load_script(
        "analyses/run_starts.py")
    home, out = tmp_path / "home", tmp_path / "out"
    runs = out / "inception-plateau" / "runs"
    run_dir = home / "fair-fight-plateau" / "inception" / "baseline-s0"
    starts.record_start(str(runs / "cvgl_baseline-s0"), str(run_dir), machine=CPU, gpu_names=[])
    os.makedirs(run_dir / "backup")
    write_state(str(run_dir), TrainingState(epoch=25, best=0.05, best_epoch=19, wait=5))
    _log(run_dir / "log.csv", [1 / e for e in range(1, 21)] + [0.06] * 5)
    starts.record_start(str(runs / "cvgl_baseline-s0"), str(run_dir), machine=CPU, gpu_names=[])
    # its 50-epoch run: the same first 20 epochs, then another value
    _log(out / "inception" / "runs" / "cvgl_baseline-s0" / "log.csv",
         [1 / e for e in range(1, 21)] + [0.07] * 30)
    record = runs / "cvgl_cpl-a-s0"
    _log(record / "log.csv", [2.0 - 0.01 * e for e in range(63)])
    _halved_errors(out, "cpl-a", 0)
    (record / "config.json").write_text(json.dumps(
        {"epochs_run": 63, "best_epoch": 43, "best_score": 2.0 - 0.01 * 42,
         "stopped": "no improvement for 20 epochs"}))
    starts.record_start(str(runs / "cvgl_baseline-s1"), str(tmp_path / "gone"), machine=CPU,
                        gpu_names=[])
    return script, home, out, run_dir


def test_each_run_reads_as_it_stands(plateau):
    script, home, out, run_dir = plateau
    found = {(r["arm"], r["seed"]): r for r in script.progress(str(home), str(out))["runs"]}
    assert len(found) == 6
    training = found[("baseline", 0)]
    assert training["status"] == "interrupted"  # (no live process claims it)
    assert (training["epochs"], training["best_epoch"], training["wait"]) == (25, 20, 5)
    assert training["best"] == pytest.approx(0.05)  # (the log's epoch 20, numbered from 1)
    assert (training["starts"], training["resumed"]) == (2, 1)
    assert training["at"] == {"10": pytest.approx(0.1), "20": pytest.approx(0.05)}
    assert training["repeats_fifty"] == {"epochs": 20, "of": 25}
    published = found[("cpl-a", 0)]
    assert (published["status"], published["epochs"], published["best_epoch"]) == (
        "published", 63, 43)
    assert published["best"] == pytest.approx(2.0 - 0.01 * 42)
    # A straight fall of 0.01 an epoch: 0.1 in 10 epochs over the window's mean.
    mean = sum(2.0 - 0.01 * e for e in range(53, 63)) / 10
    assert published["slope"] == pytest.approx(-0.1 / mean)
    assert published["repeats_fifty"] is None  # (no 50-epoch log of its own here)
    # Its test columns: the committed 50-epoch record's, as its verdicts
    # page scored them, and the plateau record's, every error halved.
    with open(os.path.join(FIGHT, "inception", "verdicts.json")) as f:
        pair = json.load(f)["pairs"]["MTL-CPL-A vs MTL-Baseline"]
    scored = {c["parameter"]: c["per_seed"][0] for c in pair["detail"]}
    assert scored and all(s["seed"] == 0 for s in scored.values())
    test = published["test"]
    assert test["fifty_best_epoch"] > 0
    for p, interval in scored.items():
        assert test["fifty"][p] == pytest.approx(interval["nmae_a"], rel=1e-6), p
        assert test["plateau"][p] == pytest.approx(interval["nmae_a"] / 2, rel=1e-5), p
    assert "test" not in training
    assert found[("baseline", 1)]["status"] == "lost"
    assert found[("cpl-a", 2)]["status"] == "not started"
    (run_dir.parent / "baseline-s0.claim").write_text(str(os.getpid()))
    assert script.run_progress("baseline", 0, str(home), str(out))["status"] == "training"


def test_the_page_is_written_and_regenerates_from_its_json(plateau, capsys):
    script, home, out, _ = plateau
    assert script.main(["--home", str(home), "--out", str(out)]) == 0
    page = out / "inception-plateau" / "progress.md"
    text = page.read_text()
    assert "3 of 6 runs started, 1 published" in text
    assert "| MTL-Baseline | 0 | interrupted | 25 | 0.050 (20) | 5 of 20 | +4 % | 20 of 25 | 2 (1) |" in text
    assert "| MTL-CPL-A | 0 | published (no improvement for 20 epochs) | 63 |" in text
    assert "| MTL-CPL-A | 0 | to a plateau (best epoch 43) |" in text
    assert "| MTL-CPL-A | 0 | 50 epochs (best epoch " in text
    assert script.regenerate(str(page)) == text
    assert script.main(["--home", str(home), "--out", str(out), "--print"]) == 0
    assert "| MTL-CPL-A | 2 | not started |" in capsys.readouterr().out


def test_a_corrupt_state_is_one_line_naming_the_file(plateau):
    script, home, out, run_dir = plateau
    (run_dir / "backup" / "state.json").write_text("{not json")
    with pytest.raises(TrainingError) as error:
        script.progress(str(home), str(out))
    assert "state.json" in str(error.value) and "\n" not in str(error.value)


def test_repeating_the_fifty_epoch_run_ignores_only_the_machines_columns():
    script = load_script("analyses/plateau_progress.py")
    old = [{"epoch": e, "loss": 1.0 / e, "wall_time_s": 10.0 * e} for e in range(1, 4)]
    new = [dict(row, wall_time_s=row["wall_time_s"] + 5, load_average=1.5) for row in old]
    assert script.repeats(new + [{"epoch": 4, "loss": 0.2}], old) == {"epochs": 3, "of": 3}
    new[1]["loss"] += 1e-12  # (a last digit)
    assert script.repeats(new, old) == {"epochs": 1, "of": 3}
    assert script.repeats(new, []) is None


def test_a_run_before_its_first_epoch_has_no_best_and_no_wait(plateau):
    script, home, out, run_dir = plateau
    fresh = run_dir.parent / "cpl-a-s1"
    starts = load_script("analyses/run_starts.py")
    starts.record_start(str(out / "inception-plateau" / "runs" / "cvgl_cpl-a-s1"), str(fresh),
                        machine=CPU, gpu_names=[])
    os.makedirs(fresh / "backup")
    write_state(str(fresh), TrainingState(epoch=0))
    (run_dir.parent / "cpl-a-s1.claim").write_text(str(os.getpid()))
    assert script.main(["--home", str(home), "--out", str(out)]) == 0
    text = (out / "inception-plateau" / "progress.md").read_text()
    assert "| MTL-CPL-A | 1 | training | 0 | - | - | - | - | 1 (0) |" in text
    assert "None" not in text


def test_the_pages_say_how_many_plateau_runs_are_published():
    """The index (its prose and its table) and the fair-fight README say how
    many of the six plateau runs are published, in words; the count is the
    published records in ``inception-plateau/runs`` (a page left behind by
    a publication fails here). Once all six are, the pages give the verdict,
    and no smaller count may stay on them."""
    import re

    runs = os.path.join(FIGHT, "inception-plateau", "runs")
    published = sum(os.path.isdir(os.path.join(runs, name)) for name in os.listdir(runs))
    words = ["none", "one", "two", "three", "four", "five", "six"]
    said = re.compile(r"\b(none|one|two|three|four|five|six) of (?:its )?six "
                      r"(?:runs )?(?:is |are )?published", re.IGNORECASE)
    for page, least in ((os.path.join(REPO, "paper_results", "README.md"), 2),
                        (os.path.join(FIGHT, "README.md"), 1)):
        with open(page, encoding="utf-8") as f:
            text = " ".join(f.read().split())
        counts = [m.lower() for m in said.findall(text)]
        assert set(counts) <= {words[published]}, (page, counts)
        assert published == 6 or len(counts) >= least, (page, counts)
        assert not re.search(r"none published|6 runs, none", text), page
