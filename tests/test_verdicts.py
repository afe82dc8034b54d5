"""Verdicts under both rules (``cpl_keras.evaluation.verdicts``), on
synthetic predictions whose answers are known."""

import numpy as np
import pytest

from cpl_keras.camera import PARAMETERS
from cpl_keras.evaluation import EvaluationError
from cpl_keras.evaluation import verdicts as v

N = 400


def labels(seed, n=N):
    """Test labels shaped like cvgl's: fx = fy, b = tx, u0 = v0 = 56."""
    rng = np.random.default_rng(100 + seed)
    focal, base = rng.uniform(40, 60, n), rng.uniform(80, 100, n)
    return {"fx": focal, "fy": focal.copy(), "u0": np.full(n, 56.0), "v0": np.full(n, 56.0),
            "baseline": base, "disparity": rng.uniform(100, 900, n), "tx": base.copy(),
            "ty": rng.uniform(1, 4, n), "tz": rng.uniform(10, 40, n),
            "pitch": rng.uniform(0.1, 0.7, n)}


def row(seed, error, noise=False, indices=None):
    """One run of ``seed``: every prediction off by ``error`` x |y| (NMAE =
    ``error`` exactly), or by a random multiple of it (``noise``)."""
    truth = labels(seed)
    rng = np.random.default_rng(1000 * seed + int(error * 1e6))
    pred = {}
    for name, y in truth.items():
        size = rng.exponential(1.0, N) if noise else np.ones(N)
        sign = rng.choice([-1.0, 1.0], N) if noise else np.ones(N)
        pred[name] = y + error * np.abs(y) * size * sign
    return {"indices": np.arange(N) if indices is None else indices, "truth": truth,
            "pred": pred, "defined": {k: np.ones(N, bool) for k in truth}}


def rows(errors, noise=False):
    return {s: row(s, e, noise) for s, e in enumerate(errors)}


def by_column(result):
    return {c.column: c for c in result}


def test_a_clearly_better_is_decided_by_both_rules():
    result = v.compare(rows((0.010, 0.011, 0.012), noise=True),
                       rows((0.050, 0.052, 0.048), noise=True), resamples=300)
    assert [c.column for c in result] == list(v.COLUMNS)
    for c in result:
        assert (c.spread_rule, c.bootstrap_rule, c.verdict) == (v.A_LOWER,) * 3, c
        assert len(c.per_seed) == 3 and all(i.high < 0 for i in c.per_seed)
    # The other way round, B is lower.
    assert {c.verdict for c in v.compare(rows((0.05, 0.052, 0.048), noise=True),
                                         rows((0.01, 0.011, 0.012), noise=True),
                                         resamples=300)} == {v.B_LOWER}


def test_seeds_that_disagree_leave_the_bootstrap_undecided():
    result = v.compare(rows((0.01, 0.05, 0.01)), rows((0.05, 0.01, 0.05)), resamples=200)
    for c in result:
        assert [i.answer for i in c.per_seed] == [v.A_LOWER, v.B_LOWER, v.A_LOWER]
        assert c.bootstrap_rule == v.UNDECIDED and c.verdict == v.UNDECIDED


def test_rules_that_disagree_leave_the_column_undecided():
    # Every seed's interval is below 0, but A's seeds spread wider than the gap.
    result = v.compare(rows((0.002, 0.08, 0.002)), rows((0.05, 0.09, 0.05)), resamples=200)
    for c in result:
        assert (c.bootstrap_rule, c.spread_rule, c.verdict) == \
            (v.A_LOWER, v.UNDECIDED, v.UNDECIDED)
    # The means are apart beyond the spread, but seed 1 is a tie.
    result = v.compare(rows((0.010, 0.011, 0.012)), rows((0.030, 0.011, 0.031)), resamples=200)
    for c in result:
        assert [i.answer for i in c.per_seed] == [v.A_LOWER, v.UNDECIDED, v.A_LOWER]
        assert (c.spread_rule, c.bootstrap_rule, c.verdict) == \
            (v.A_LOWER, v.UNDECIDED, v.UNDECIDED)


def test_the_bootstrap_is_paired_seeded_and_matches_the_nmae():
    a, b = rows((0.02, 0.021, 0.019), noise=True), rows((0.021, 0.02, 0.02), noise=True)
    first, again = v.compare(a, b, resamples=200), v.compare(a, b, resamples=200)
    assert first == again
    other = v.compare(a, b, resamples=200, bootstrap_seed=1)
    assert [c.per_seed for c in other] != [c.per_seed for c in first]
    fx = by_column(first)["fx"].per_seed[0]
    y, p = a[0]["truth"]["fx"], a[0]["pred"]["fx"]
    assert fx.nmae_a == pytest.approx(np.mean(np.abs(p - y)) / np.mean(np.abs(y)), rel=1e-12)
    assert fx.low <= fx.nmae_a - fx.nmae_b <= fx.high
    # Identical rows: every paired resample's difference is exactly 0.
    same = v.compare(a, a, resamples=50)
    assert all(i.low == i.high == 0.0 and i.answer == v.UNDECIDED
               for c in same for i in c.per_seed)


def test_same_quantities_from_the_labels():
    truths = [labels(s) for s in range(3)]
    same = v.same_quantities(truths)
    assert same == {"identical": [["fx", "fy"], ["b", "tx"]],
                    "constant": {"u0": 56.0, "v0": 56.0}}
    truths[2]["fy"] = truths[2]["fy"] + 1e-6
    truths[1]["v0"] = truths[1]["v0"] + np.linspace(0, 1, N)
    same = v.same_quantities(truths)
    assert same == {"identical": [["b", "tx"]], "constant": {"u0": 56.0}}


def test_different_test_pairs_raise_one_line():
    a, b = rows((0.01, 0.01)), rows((0.02, 0.02))
    b[1]["indices"] = np.arange(N) + 1
    with pytest.raises(EvaluationError, match="seed 1") as error:
        v.compare(a, b, resamples=20)
    assert "\n" not in str(error.value)
    b[1]["indices"] = np.arange(N - 1)
    with pytest.raises(EvaluationError, match="different test pairs"):
        v.seed_intervals(1, a[1], b[1], resamples=20)
    with pytest.raises(EvaluationError, match="different seeds"):
        v.compare(a, {0: b[0]}, resamples=20)


def test_one_seed_is_refused_in_one_line():
    """The seed-spread rule needs a spread: one seed a side is refused."""
    with pytest.raises(EvaluationError, match="2 or more seeds") as error:
        v.compare(rows((0.01,)), rows((0.02,)), resamples=20)
    assert "\n" not in str(error.value)


def test_the_script_refuses_a_folder_of_one_seed(tmp_path):
    """analyses/verdicts.py on a reproduction's partial/ folder after its
    first seed (one seed's predictions, a table without per_seed values):
    one line naming what is missing, exit 2, no verdicts written."""
    import json
    import os
    import shutil
    import subprocess
    import sys

    from helpers import REPO

    source = os.path.join(REPO, "paper_results", "compact-2000")
    (tmp_path / "runs").mkdir()
    for variant in ("cpl-a", "baseline"):
        name = f"cvgl_{variant}-s0_predictions.npz"
        shutil.copy(os.path.join(source, "runs", name), tmp_path / "runs" / name)
    with open(os.path.join(source, "table1_cvgl.json")) as f:
        table = json.load(f)
    for row in table["rows"].values():
        row.pop("per_seed", None)
    (tmp_path / "table1_cvgl.json").write_text(json.dumps(table))
    result = subprocess.run([sys.executable, os.path.join(REPO, "analyses", "verdicts.py"),
                             "--folder", str(tmp_path), "--resamples", "20"],
                            capture_output=True, text=True, timeout=120,
                            env=dict(os.environ, KERAS_BACKEND="jax", PYTHONPATH=REPO))
    assert result.returncode == 2, result.stderr[-2000:]
    assert result.stderr.count("\n") == 1 and "Traceback" not in result.stderr
    assert "2 or more seeds" in result.stderr and "seed(s) [0]" in result.stderr
    assert sorted(os.listdir(tmp_path)) == ["runs", "table1_cvgl.json"]


def test_every_column_is_a_parameter():
    assert [v.COLUMN_PARAMETER[c] for c in v.COLUMNS] == list(PARAMETERS)


def test_welch_p_of_the_seeds():
    """Welch's two-sided p: means 2 and 5, SD 1 each, 3 seeds a side (t =
    -3.67 on 4 degrees of freedom); undefined for one seed a side."""
    assert v.welch_p([1.0, 2.0, 3.0], [4.0, 5.0, 6.0]) == pytest.approx(0.0213, abs=2e-4)
    assert np.isnan(v.welch_p([1.0], [2.0]))
    assert np.isnan(v.welch_p([1.0, 1.0], [2.0, 2.0]))


def test_the_rig_bootstrap_counts_a_rig_once():
    """Three rigs of 2,000 pairs: A is 1 % off on two and 20 % on the third,
    B 10 % everywhere. Resampling pairs decides for A (its pairs agree
    within each rig); resampling whole rigs does not (three draws), and the
    rigs are found from the labels alone."""
    def rig_row(errors):
        truth, pred = {}, {}
        for name in PARAMETERS:
            y = np.concatenate([np.full(2000, 10.0 + 5 * r) for r in range(3)])
            if name == "disparity":
                y = np.random.default_rng(0).uniform(100, 200, 6000)
            truth[name] = y
            pred[name] = y + np.repeat(errors, 2000) * np.abs(y)
        return {"indices": np.arange(6000), "truth": truth, "pred": pred}

    a, b = rig_row(np.array([0.01, 0.01, 0.2])), rig_row(np.array([0.1, 0.1, 0.1]))
    assert len(set(v.rig_keys(a["truth"]))) == 3
    assert v.seed_intervals(0, a, b, resamples=500)["fx"].answer == v.A_LOWER
    assert v.rig_intervals(0, a, b, resamples=500)["fx"] == v.UNDECIDED
    far = rig_row(np.array([0.01, 0.01, 0.02]))
    assert v.rig_intervals(0, far, b, resamples=500)["fx"] == v.A_LOWER


def test_paired_runs_arguments_and_page():
    """analyses/paired_runs.py: two references and at least one more run,
    NAME=RUN_DIR each; the page lists each run's NMAEs and, per other run
    and reference, the interval and the side it decides."""
    from helpers import load_script

    script = load_script("analyses/paired_runs.py")
    for bad in (["--data", "d.h5", "--run", "A=a", "--run", "B=b", "--out", "o.md"],
                ["--data", "d.h5", "--run", "A", "--run", "B=b", "--run", "C=c", "--out", "o.md"],
                ["--data", "d.h5", "--run", "A=a", "--run", "B=b", "--run", "C=c", "--out", "o"]):
        with pytest.raises(SystemExit):
            script.parse_args(bad)
    args = script.parse_args(["--data", "d.h5", "--run", "A=a", "--run", "B=b", "--run", "C=c",
                              "--out", "o.md"])
    assert args.runs == [("A", "a"), ("B", "b"), ("C", "c")]
    nmae = {c: 0.1 for c in v.COLUMNS}
    result = {"seed": 0, "data": "d.h5", "references": ["A", "B"],
              "runs": {n: {"epochs_run": 3, "best_epoch": 2, "nmae": nmae} for n in "ABC"},
              "intervals": {f"C - {r}": {c: {"low": 0.01, "high": 0.02, "answer": "higher"}
                                         for c in v.COLUMNS} for r in "AB"}}
    page = script.markdown(result, "python analyses/paired_runs.py ...")
    assert "| C | 3 (2) | " + " | ".join(["0.100"] * 10) + " |" in page
    assert page.count("higher [+0.010, +0.020]") == 20 and "| 0 / 10 |" in page
