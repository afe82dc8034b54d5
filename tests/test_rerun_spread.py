"""``analyses/rerun_spread.py``: the spread between two trainings of one seed,
and the "lower on N" counts beyond twice it, from the committed files."""

import json
import os
from pathlib import Path

import numpy as np
import pytest
from helpers import REPO, load_script


def test_the_committed_spread_page_is_what_the_committed_files_give(capsys):
    script = load_script("analyses/rerun_spread.py")
    assert script.main(["--check"]) == 0, capsys.readouterr().err


def test_the_counts_follow_the_rule_and_the_check_can_fail(tmp_path, monkeypatch):
    """Each decided column is beyond exactly when its gap exceeds twice the larger
    of the two variants' own spreads for its towers and training, and beyond
    the widest exactly when it exceeds twice the larger of their widest
    spreads (every rerun with the towers, and InceptionV3 MTL-CPL-A's
    validation window)."""
    script = load_script("analyses/rerun_spread.py")
    result = script.compute()
    for towers, variants in result["widest"].items():
        for variant, widest in variants.items():
            found = [r["columns"] for r in result["reruns"]
                     if (r["towers"], r["variant"]) == (towers, variant)]
            found += [r["window"] for r in result["validation"]
                      if (r["towers"], r["variant"]) == (towers, variant)]
            assert widest == {c: max(f[c] for f in found) for c in widest}, (towers, variant)

    def follows(entry, key, threshold):
        return entry[key] == (entry["gap"] > threshold) or abs(entry["gap"] - threshold) < 1e-4

    for comparison in result["comparisons"]:
        spreads = result["spreads"][comparison["spreads"]]
        for column, entry in comparison["columns"].items():
            own = max(spreads["MTL-CPL-A"][column], spreads["MTL-Baseline"][column])
            assert follows(entry, "beyond_twice_spread", 2 * own), (comparison["setting"], column)
            widest = result["widest"][comparison["spreads"].split(",")[0]]
            wide = max(widest["MTL-CPL-A"][column], widest["MTL-Baseline"][column])
            assert follows(entry, "beyond_twice_widest", 2 * wide), column
        for side in ("A lower", "B lower"):
            mine = [e for e in comparison["columns"].values() if e["verdict"] == side]
            assert comparison["counts"][side] == {
                "decided": len(mine), "beyond": sum(e["beyond_twice_spread"] for e in mine),
                "beyond_widest": sum(e["beyond_twice_widest"] for e in mine)}
    # the fair fight's compact towers take their own spreads, measured under the recipe
    (fight,) = [c for c in result["comparisons"] if c["setting"] == "fair fight, compact"]
    assert fight["spreads"] == "compact, recipe"
    # a fair fight's row says "so far" exactly while its page lacks some of the
    # protocol's seeds (the page names them: ``protocol_seeds``)
    for comparison in result["comparisons"]:
        with open(os.path.join(script.RESULTS, comparison["verdicts"])) as f:
            page = json.load(f)
        if "protocol_seeds" in page:
            seeds = page["pairs"][script.PAIR]["seeds"]
            assert ("so far" in comparison["setting"]) == (seeds != page["protocol_seeds"])
    # a tampered JSON fails the check
    tampered = json.loads(json.dumps(result))
    tampered["spreads"]["compact, recipe"]["MTL-CPL-A"]["d"] += 0.001
    (tmp_path / "spread.json").write_text(json.dumps(tampered))
    (tmp_path / "spread.md").write_text(script.markdown(result))
    monkeypatch.setattr(script, "OUT", str(tmp_path / "spread"))
    assert script.main(["--check"]) == 1


COLUMNS = ("fx", "fy", "u0", "v0", "b", "d", "tx", "ty", "tz", "pitch")
PARAMETERS = ("fx", "fy", "u0", "v0", "baseline", "disparity", "tx", "ty", "tz", "pitch")


def _nmae(truth, pred):
    return np.mean(np.abs(pred - truth)) / np.mean(np.abs(truth))


def _outputs(record):
    (path,) = (Path(record) / "predictions").glob("*.npz")
    with np.load(path, allow_pickle=False) as stored:
        names = [str(n) for n in stored["outputs"]]
        return np.asarray(stored["indices"]), {n: stored["pred"][:, k].astype(np.float64)
                                               for k, n in enumerate(names)}


def test_each_variants_own_spread_under_the_recipe_is_its_published_rerun():
    """spread.json's compact rows under the fair fight's recipe are
    |NMAE(rerun) - NMAE(published)| recomputed here from the two published
    records' predictions and the truths of inception-2000-ema's seed-0 file
    (the same dataset, split and seed), per variant; the InceptionV3
    MTL-CPL-A spread is its validation difference at its kept epoch."""
    import csv

    from cpl_keras import prediction_files

    results = Path(REPO) / "paper_results"
    committed = json.loads((results / "spread.json").read_text())
    truth_file = prediction_files.load(
        str(results / "inception-2000-ema/runs/cvgl_baseline-s0_predictions.npz")).raw
    for arm, variant in (("cpl-a", "MTL-CPL-A"), ("baseline", "MTL-Baseline")):
        a_idx, a = _outputs(results / f"fair-fight/compact/runs/cvgl_{arm}-s0")
        assert np.array_equal(a_idx, truth_file.indices)
        rows = {r["rerun"].rsplit("/", 1)[1]: r["columns"] for r in committed["reruns"]
                if r["training"] == "recipe" and r["variant"] == variant}
        assert sorted(rows) == [f"cvgl_{arm}-o0-s0", f"cvgl_{arm}-s0"]
        for name, columns in rows.items():
            b_idx, b = _outputs(results / "fair-fight/compact-rerun/runs" / name)
            assert np.array_equal(a_idx, b_idx)
            for column, parameter in zip(COLUMNS, PARAMETERS):
                truth = np.asarray(truth_file.truth[parameter], np.float64)
                expected = abs(_nmae(truth, b[parameter]) - _nmae(truth, a[parameter]))
                assert columns[column] == pytest.approx(expected, abs=5e-5), (name, column)
        # the variant's own spread: per column the larger of its two reruns'
        own = committed["spreads"]["compact, recipe"][variant]
        assert own == {c: max(r[c] for r in rows.values()) for c in COLUMNS}

    def log(path):
        with open(path, newline="") as f:
            return {int(r["epoch"]): r for r in csv.DictReader(f)}

    published = log(results / "inception-2000-ema/runs/cvgl_cpl-a-s0_log.csv")
    other = log(results / "inception-2000-ablations/runs/cvgl_cpl-a-patience20-s0_log.csv")
    kept = json.loads((results / "inception-2000-ema/runs/cvgl_cpl-a-s0/config.json")
                      .read_text())["best_epoch"]
    own = committed["spreads"]["InceptionV3, defaults"]["MTL-CPL-A"]
    for column, name in zip(COLUMNS, PARAMETERS):
        key = f"val_nmae_{name}"
        expected = abs(float(published[kept][key]) - float(other[kept][key]))
        assert own[column] == pytest.approx(expected, abs=5e-5), column


def test_the_readme_counts_beyond_twice_the_spread_are_the_pages():
    """README's answer: each "(K beyond)" is spread.json's count for its row."""
    import re

    result = json.loads((Path(REPO) / "paper_results" / "spread.json").read_text())
    counts = {c["setting"]: c["counts"] for c in result["comparisons"]}
    rows = {"compact, 8,000 pairs, 3 seeds": ("compact, 8,000 pairs", "A lower"),
            "compact, 2,000 pairs, 3 seeds": ("compact, 2,000 pairs", "A lower"),
            "InceptionV3, 2,000 pairs, 3 seeds": ("InceptionV3, 2,000 pairs", "B lower"),
            "InceptionV3, 8,000 pairs, seed 0, 12 epochs":
                ("InceptionV3, 8,000 pairs, seed 0, 12 epochs", "A lower"),
            "fair fight: one recipe, 50 epochs": ("fair fight, compact", "A lower")}
    text = (Path(REPO) / "README.md").read_text()
    seen = 0
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip("|").split("|")]
        if line.startswith("|") and cells[0] in rows:
            setting, side = rows[cells[0]]
            n, k = map(int, re.search(r"lower on (\d+)[^(]*\((\d+) beyond", cells[1]).groups())
            assert (k, n) == (counts[setting][side]["beyond"], counts[setting][side]["decided"]), line
            seen += 1
    assert seen == len(rows)
