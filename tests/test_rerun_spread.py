"""``analyses/rerun_spread.py``: the spread between two trainings of one seed,
and the "lower on N" counts beyond twice it, from the committed files."""

import json

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
    # a spread that was not measured is not used: every setting borrows a measured one
    assert {c["towers"] for c in result["comparisons"]} <= set(result["spread"])
    # a tampered JSON fails the check
    tampered = json.loads(json.dumps(result))
    tampered["spread"]["compact"]["fx"] += 0.001
    (tmp_path / "spread.json").write_text(json.dumps(tampered))
    (tmp_path / "spread.md").write_text(script.markdown(result))
    monkeypatch.setattr(script, "OUT", str(tmp_path / "spread"))
    assert script.main(["--check"]) == 1
