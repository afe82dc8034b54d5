"""``analyses/fair_fight.py``: the protocol's runs and its verdict rule."""

import dataclasses
import json
import os

import pytest
from helpers import REPO, load_script

from cpl_keras.evaluation import verdicts as v


def _script():
    return load_script("analyses/fair_fight.py")


def _page():
    return load_script("analyses/fair_fight_verdicts.py")


def test_every_arm_trains_under_one_recipe_for_the_same_epochs(capsys, tmp_path):
    data = tmp_path / "d.h5"
    data.write_bytes(b"")
    assert _script().main(["--towers", "inception", "--seeds", "0", "1", "--data", str(data),
                           "--dry-run"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 6  # 3 arms x 2 seeds, each seed's arms together
    for line in lines:
        words = line.split()
        assert words[words.index("--epochs") + 1] == words[words.index("--patience") + 1] == "50"
        assert words[words.index("--recipe") + 1] == "sound"
        assert words[words.index("--backbone") + 1] == "inception_v3"
    assert [line.split("--variant ")[1].split()[0] for line in lines[:3]] == [
        "baseline", "cpl-a", "cpl-a"]
    assert "--adaptive-weights range" in lines[2] and "--adaptive-weights" not in lines[1]
    with pytest.raises(SystemExit) as stop:
        _script().main(["--towers", "compact", "--data", str(tmp_path / "none.h5")])
    assert stop.value.code == 2


def test_the_protocol_verdict_of_a_pair():
    script = _page()
    base = v.ColumnVerdict(column="fx", parameter="fx", mean_a=0, spread_a=0, mean_b=0,
                           spread_b=0, spread_rule=v.UNDECIDED, bootstrap_rule=v.UNDECIDED,
                           verdict=v.UNDECIDED, per_seed=())
    columns = lambda *answers: [dataclasses.replace(base, verdict=a) for a in answers]  # noqa: E731
    assert script.protocol_verdict(columns(v.A_LOWER, v.UNDECIDED)) == "A lower"
    assert script.protocol_verdict(columns(v.B_LOWER, v.B_LOWER)) == "B lower"
    assert script.protocol_verdict(columns(v.A_LOWER, v.B_LOWER)) == "mixed"
    assert script.protocol_verdict(columns(v.UNDECIDED)) == "not decided"

    # (the page: the protocol's verdict once every seed is in; "so far" before)
    with open(os.path.join(REPO, "paper_results/fair-fight/compact/verdicts.json")) as f:
        result = json.load(f)
    pair = result["pairs"]["MTL-CPL-A vs MTL-Baseline"]
    assert pair["seeds"] == script.PROTOCOL_SEEDS
    assert "**The protocol's verdict: " in script.verdicts_markdown("compact", result)
    pair["seeds"] = [0, 1]
    text = script.verdicts_markdown("compact", result)
    line = next(x for x in text.splitlines() if "(A = MTL-CPL-A, seeds 0, 1" in x)
    assert line.startswith("**So far: ") and "not the protocol's verdict" in line


def test_two_commands_side_by_side_share_the_runs(tmp_path):
    script = _script()
    run_dir = str(tmp_path / "runs" / "baseline-s0")
    assert script.claim(run_dir)  # (this process's claim)
    (tmp_path / "runs" / "baseline-s0.claim").write_text("999999999")  # (a process gone)
    assert script.claim(run_dir)  # (a stale claim is taken over)
    (tmp_path / "runs" / "baseline-s0.claim").write_text(str(os.getppid()))  # (alive)
    assert not script.claim(run_dir)


def _log(path, monitor, dead_pitch=None, epochs=50):
    """A log.csv of ``epochs`` epochs: every column's validation NMAE is
    ``monitor(epoch, column)``, val_nmae their sum; ``dead_pitch(epoch)``."""
    from cpl_keras.camera import PARAMETERS

    header = ["epoch", "val_nmae"] + [f"val_nmae_{p}" for p in PARAMETERS]
    header += ["dead_pitch"] if dead_pitch else []
    lines = [",".join(header)]
    for e in range(1, epochs + 1):
        cols = [monitor(e, p) for p in PARAMETERS]
        row = [str(e), repr(sum(cols))] + [repr(c) for c in cols]
        lines.append(",".join(row + ([repr(dead_pitch(e))] if dead_pitch else [])))
    path.write_text("\n".join(lines) + "\n")
    return str(path)


def test_validation_at_equal_epochs_and_collapsed_heads_of_a_pair(tmp_path):
    script = _page()
    # A: 1/e on every column but the disparity (2/e); B: 1.5/e everywhere; seed 1's B
    # ran 40 epochs only, so the epoch 50 is left out of the means
    a = {s: _log(tmp_path / f"a{s}.csv", lambda e, p: (2.0 if p == "disparity" else 1.0) / e)
         for s in (0, 1)}
    b = {0: _log(tmp_path / "b0.csv", lambda e, p: 1.5 / e),
         1: _log(tmp_path / "b1.csv", lambda e, p: 1.5 / e, epochs=40),
         2: _log(tmp_path / "b2.csv", lambda e, p: 0.0)}  # (a seed A lacks: not read)
    found = script.equal_epochs(a, b)
    assert found["seeds"] == [0, 1]
    assert sorted(found["a"], key=int) == ["10", "20", "30", "40"]
    assert found["a"]["10"]["fx"] == pytest.approx(0.1)
    assert found["b"]["40"]["disparity"] == pytest.approx(1.5 / 40)
    assert found["a"]["20"]["val_nmae"] == pytest.approx(11 / 20)
    assert found["monitor_a_lower"] == {"0": {"epochs": 50, "a_lower": 50},
                                        "1": {"epochs": 40, "a_lower": 40}}
    text = "\n".join(script.equal_epochs_markdown(found))
    assert "means over seeds 0, 1" in text
    assert "| 9 (fx, fy, u0, v0, baseline, tx, ty, tz, pitch) |" in text
    assert "| 1 (disparity) |" in text
    assert "seed 0: 50 of 50; seed 1: 40 of 40" in text
    # the heads: the share at the kept epoch, the last epoch's beside it where it differs
    log = _log(tmp_path / "h.csv", lambda e, p: 1.0, dead_pitch=lambda e: 0.5 if e < 50 else 1.0)
    shares = script.head_shares(log, kept_epoch=30)
    assert shares["kept"]["pitch"] == 0.5 and shares["last"]["pitch"] == 1.0
    assert shares["kept"]["fx"] is None  # (a log without that head's column)
    runs = [{"arm": "cpl-a", "seed": 0, "best_epoch": 30, "dead_heads": shares}]
    row = script.heads_markdown(runs)[-2]
    assert row.startswith("| MTL-CPL-A | 0 | 30 | - |") and row.endswith("| 0.50 (1.00) |")


def test_each_arm_beside_the_average_row(tmp_path):
    import numpy as np

    from cpl_keras.camera import PARAMETERS

    script = _page()
    # two seeds of 4 test pairs; u0 is constant (the Average row is exact there)
    truth = {s: {p: np.array([1.0, 2.0, 3.0, 4.0]) + s for p in PARAMETERS} for s in (0, 1)}
    for s in (0, 1):
        truth[s]["u0"] = np.full(4, 56.0)
    mean = {s: {p: float(truth[s][p].mean()) for p in PARAMETERS} for s in (0, 1)}
    points = {"X": 1.0, "Y": 1.0, "Z": 1.0}  # (train_stats.json has every target)
    # A is off by 0.1 everywhere; B (seed 0 only) predicts the training mean
    rows = {"cpl-a": {s: {"truth": truth[s], "pred": {p: truth[s][p] + 0.1 for p in PARAMETERS}}
                      for s in (0, 1)},
            "baseline": {0: {"truth": truth[0],
                             "pred": {p: np.full(4, mean[0][p]) for p in PARAMETERS}}}}
    statistics = {(arm, s): {"mean": {**mean[s], **points}} for arm in rows for s in rows[arm]}
    found = script.beside_average(rows, statistics)
    # the Average row: MAE 1.0 on a column 1..4 (mean |y| 2.5), 1.0 on 2..5 (mean 3.5)
    assert found["average"]["seeds"] == [0, 1]
    assert found["average"]["nmae"]["fx"] == pytest.approx((1 / 2.5 + 1 / 3.5) / 2)
    assert found["average"]["nmae"]["u0"] == 0.0
    a = found["arms"]["cpl-a"]
    assert a["seeds"] == [0, 1]
    assert a["nmae"]["fx"] == pytest.approx((0.1 / 2.5 + 0.1 / 3.5) / 2)
    assert a["nmae"]["sum"] == pytest.approx(sum(a["nmae"][p] for p in PARAMETERS))
    b = found["arms"]["baseline"]  # (its ratio: against the Average over seed 0 alone)
    assert b["seeds"] == [0] and b["average_nmae"]["fx"] == pytest.approx(1 / 2.5)
    lines = script.average_markdown(found)

    def cells(start):
        return [c.strip() for c in next(x for x in lines if x.startswith(start)).split("|")]

    header, row = cells("| row |"), cells("| MTL-Baseline / Average |")
    assert row[header.index("fx")] == "1.00" and row[header.index("u0")] == "-"
    assert "exact: u0, constant in the labels" in "\n".join(lines)
    assert cells("| MTL-CPL-A / Average |")[header.index("fy")] == "0.10"
    # the arms of a seed share a split: training means that disagree are refused
    statistics[("baseline", 0)] = {"mean": {**mean[0], **points, "fx": mean[0]["fx"] + 1.0}}
    with pytest.raises(ValueError, match="seed 0: the training means"):
        script.beside_average(rows, statistics)


def test_the_plateau_amendment_prints_its_six_runs_and_writes_nothing(capsys, tmp_path):
    """``--plateau --dry-run``: InceptionV3 MTL-Baseline and MTL-CPL-A, seeds
    0-2, patience 20 and at most 200 epochs, under the same recipe, run
    from ``--home`` with the dataset and run directories relative to it, so
    that a published record names no machine's path."""
    script = _script()
    home = tmp_path / "cpl-runs"
    (home / "data").mkdir(parents=True)
    (home / "data" / "cvgl_2000_112px_s0_v3.0.h5").write_bytes(b"")
    out = tmp_path / "results"
    assert script.main(["--plateau", "--towers", "inception", "--home", str(home),
                        "--out", str(out), "--dry-run"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 6
    for line, (seed, arm) in zip(lines, [(s, a) for s in (0, 1, 2)
                                         for a in ("baseline", "cpl-a")]):
        assert line.startswith(f"cd {home} && python ")
        words = line.split(" && ", 1)[1].split()
        assert words[1].endswith("train.py")
        value = {w: words[i + 1] for i, w in enumerate(words[:-1]) if w.startswith("--")}
        assert value["--epochs"] == "200" and value["--patience"] == "20"
        assert value["--recipe"] == "sound" and value["--backbone"] == "inception_v3"
        assert value["--variant"] == arm and value["--seed"] == str(seed)
        assert value["--split"] == "paper" and "--adaptive-weights" not in words
        assert value["--data"] == "data/cvgl_2000_112px_s0_v3.0.h5"
        assert value["--run-dir"] == f"fair-fight-plateau/inception/{arm}-s{seed}"
    assert not out.exists() and sorted(p.name for p in home.iterdir()) == ["data"]
    # the amendment is InceptionV3's, and its dataset must be in its home
    for argv in (["--towers", "compact", "--home", str(home)],
                 ["--towers", "inception", "--home", str(tmp_path)]):
        with pytest.raises(SystemExit) as stop:
            script.main(["--plateau", "--dry-run"] + argv)
        assert stop.value.code == 2


def test_the_plateau_ledger_counts_resumes_machines_and_a_run_lost_twice(tmp_path):
    """Each start of a plateau run is recorded beside its record: the epoch
    it went on from, the machine; a run directory missing after a start is
    a loss, started again once, never a third time."""
    from cpl_keras.training.state import TrainingState, write_state

    starts = load_script("analyses/run_starts.py")
    record, run_dir = str(tmp_path / "runs" / "cvgl_cpl-a-s0"), str(tmp_path / "home" / "r")
    cpu, gpu = {"cpu": "AMD EPYC", "cpu_count": 2}, {"cpu": "Xeon", "cpu_count": 16}
    starts.record_start(record, run_dir, machine=cpu, gpu_names=[])
    os.makedirs(os.path.join(run_dir, "backup"))
    write_state(run_dir, TrainingState(epoch=37))
    ledger = starts.record_start(record, run_dir, machine=cpu, gpu_names=[])
    assert [s["from_epoch"] for s in ledger["starts"]] == [0, 37]
    assert (ledger["resumed"], ledger["lost"], len(ledger["machines"])) == (1, 0, 1)
    import shutil

    shutil.rmtree(run_dir)  # (its machine gone): started again once, from epoch 0
    ledger = starts.record_start(record, run_dir, machine=gpu, gpu_names=["NVIDIA H100"])
    assert ledger["starts"][-1]["lost_before"] and ledger["lost"] == 1
    assert ledger["machines"][-1] == dict(gpu, gpus=["NVIDIA H100"])
    with pytest.raises(starts.LostTwice, match="lost twice"):
        starts.record_start(record, run_dir, machine=gpu, gpu_names=[])
    assert len(starts.read(record)["starts"]) == 3  # (the refused start is not recorded)
    os.makedirs(record)
    starts.copy_into(record)
    with open(os.path.join(record, "starts.json")) as f:
        assert json.load(f)["resumed"] == 1


def test_the_plateau_ledger_names_one_machine_one_way_whether_or_not_jax_is_imported(
        tmp_path, monkeypatch):
    """The devices JAX sees are listed by ``backend.machine`` only once the
    process has imported JAX: the ledger leaves them out, so a start in a
    process that published a run before (JAX imported) and one in a fresh
    process count one machine, and so do starts recorded with them before."""
    import sys
    import types

    from cpl_keras import backend

    if backend.keras_backend() != "jax":
        pytest.skip("the devices are listed on the JAX backend")
    starts = load_script("analyses/run_starts.py")
    jax = types.SimpleNamespace(devices=lambda: [types.SimpleNamespace(
        platform="cpu", device_kind="cpu")])  # (JAX imported, without its import time)
    monkeypatch.setitem(sys.modules, "jax", jax)
    assert backend.machine()["devices"] == ["cpu:cpu"]
    assert "devices" not in starts.this_machine()
    record, run_dir = str(tmp_path / "runs" / "cvgl_cpl-a-s0"), str(tmp_path / "r")
    starts.record_start(record, run_dir, gpu_names=[])
    monkeypatch.delitem(sys.modules, "jax")  # (a fresh process: no JAX yet)
    os.makedirs(os.path.join(run_dir, "backup"))
    from cpl_keras.training.state import TrainingState, write_state

    write_state(run_dir, TrainingState(epoch=84))
    ledger = starts.record_start(record, run_dir, gpu_names=[])
    assert len(ledger["machines"]) == 1 and "devices" not in ledger["machines"][0]
    older = dict(ledger["starts"][0]["machine"], devices=["cpu:cpu"])
    assert len(starts.summary([dict(ledger["starts"][0], machine=older),
                               ledger["starts"][1]])["machines"]) == 1


def test_the_plateau_page_names_its_amendment_ends_starts_and_the_fifty_epoch_verdict(tmp_path):
    """The amendment's verdicts page: its title and rules name
    protocol-plateau.md, each run says how it ended and how often it was
    started, each pair has its 50-epoch verdict beside it, and the range
    arm (not in the amendment) has no section; the protocol's own pages are
    untouched (None)."""
    import shutil

    page = _page()
    assert page.amendment(str(tmp_path), "inception", {}) is None
    committed = os.path.join(REPO, "paper_results", "fair-fight", "inception", "verdicts.json")
    os.makedirs(tmp_path / "inception")
    shutil.copy(committed, tmp_path / "inception" / "verdicts.json")
    record = tmp_path / "inception-plateau" / "runs" / "cvgl_baseline-s0"
    os.makedirs(record)
    machine = {"cpu": "AMD EPYC", "cpu_count": 2, "gpus": []}
    (record / "starts.json").write_text(json.dumps(
        {"starts": [{"start": i} for i in (1, 2, 3)], "resumed": 2, "machines": [machine]}))
    found = page.amendment(str(tmp_path), "inception-plateau",
                           {("baseline", 0): str(record), ("cpl-a", 0): str(tmp_path / "none")})
    title = "MTL-CPL-A vs MTL-Baseline"
    assert found["fifty_epochs"][title] == "B lower"
    assert found["starts"] == {"baseline-s0": {"starts": 3, "resumed": 2, "machines": 1},
                               "cpl-a-s0": {"starts": 0, "resumed": 0, "machines": 0}}
    with open(committed) as f:
        result = json.load(f)
    result["pairs"] = {title: result["pairs"][title]}
    result["amendment"] = found
    result["runs"] = [run for run in result["runs"] if run["arm"] != "cpl-a-range"]
    for run in result["runs"]:
        run["stopped"] = "early stopping: no improvement of val_nmae for 20 epochs"
    text = page.verdicts_markdown("inception-plateau", result)
    assert "# Fair fight, InceptionV3 to a plateau: verdicts" in text
    assert "[../protocol-plateau.md](../protocol-plateau.md)" in text
    assert "| MTL-Baseline | 0 | 50 (48) | early stopping: no improvement of val_nmae for 20 " \
           "epochs | 3 (2) | 8,346 |" in text
    assert "At 50 epochs (the same runs' first 50, [../inception/verdicts.md]" \
           "(../inception/verdicts.md)): B lower." in text
    assert text.count("\n### ") == 1 and "(range weights) (A)" not in text
