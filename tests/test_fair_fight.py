"""``analyses/fair_fight.py``: the protocol's runs and its verdict rule."""

import dataclasses
import os

import pytest
from helpers import load_script

from cpl_keras.evaluation import verdicts as v


def _script():
    return load_script("analyses/fair_fight.py")


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
    script = _script()
    base = v.ColumnVerdict(column="fx", parameter="fx", mean_a=0, spread_a=0, mean_b=0,
                           spread_b=0, spread_rule=v.UNDECIDED, bootstrap_rule=v.UNDECIDED,
                           verdict=v.UNDECIDED, per_seed=())
    columns = lambda *answers: [dataclasses.replace(base, verdict=a) for a in answers]  # noqa: E731
    assert script.protocol_verdict(columns(v.A_LOWER, v.UNDECIDED)) == "A lower"
    assert script.protocol_verdict(columns(v.B_LOWER, v.B_LOWER)) == "B lower"
    assert script.protocol_verdict(columns(v.A_LOWER, v.B_LOWER)) == "mixed"
    assert script.protocol_verdict(columns(v.UNDECIDED)) == "not decided"


def test_two_commands_side_by_side_share_the_runs(tmp_path):
    script = _script()
    run_dir = str(tmp_path / "runs" / "baseline-s0")
    assert script.claim(run_dir)  # (this process's claim)
    (tmp_path / "runs" / "baseline-s0.claim").write_text("999999999")  # (a process gone)
    assert script.claim(run_dir)  # (a stale claim is taken over)
    (tmp_path / "runs" / "baseline-s0.claim").write_text(str(os.getppid()))  # (alive)
    assert not script.claim(run_dir)
