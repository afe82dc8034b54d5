"""``analyses/rerun_spread.py``: the spread between two trainings of one seed,
and the "lower on N" counts beyond twice it, from the committed files."""

import json
import os

from helpers import load_script


def test_the_committed_spread_page_is_what_the_committed_files_give(capsys):
    script = load_script("analyses/rerun_spread.py")
    assert script.main(["--check"]) == 0, capsys.readouterr().err


def test_the_counts_follow_the_rule_and_the_check_can_fail(tmp_path, monkeypatch):
    script = load_script("analyses/rerun_spread.py")
    result = script.compute()
    for comparison in result["comparisons"]:
        spread = result["spread"][comparison["towers"]]
        for column, entry in comparison["columns"].items():
            assert entry["beyond_twice_spread"] == (entry["gap"] > 2 * spread[column]) or \
                abs(entry["gap"] - 2 * spread[column]) < 1e-4, (comparison["setting"], column)
    # a fair fight's row says "so far" exactly while its page lacks some of the
    # protocol's seeds (the page names them: ``protocol_seeds``)
    for comparison in result["comparisons"]:
        with open(os.path.join(script.RESULTS, comparison["verdicts"])) as f:
            page = json.load(f)
        if "protocol_seeds" in page:
            seeds = page["pairs"][script.PAIR]["seeds"]
            assert ("so far" in comparison["setting"]) == (seeds != page["protocol_seeds"])
    # a spread that was not measured is not used: every setting borrows a measured one
    assert {c["towers"] for c in result["comparisons"]} <= set(result["spread"])
    # a tampered JSON fails the check
    tampered = json.loads(json.dumps(result))
    tampered["spread"]["compact"]["fx"] += 0.001
    (tmp_path / "spread.json").write_text(json.dumps(tampered))
    (tmp_path / "spread.md").write_text(script.markdown(result))
    monkeypatch.setattr(script, "OUT", str(tmp_path / "spread"))
    assert script.main(["--check"]) == 1


def test_the_readme_counts_beyond_twice_the_spread_are_the_pages():
    """README's answer: each "(K beyond)" is spread.json's count for its row."""
    import re
    from pathlib import Path

    from helpers import REPO

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
