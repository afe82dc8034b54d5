"""``analyses/aggregate_seeds.py``: one table over several seeds from the
committed per-seed tables, as the committed aggregated folders hold it."""

import json
import os

import pytest

from helpers import REPO, load_script

CPU = "paper_results/cpu-8000"


def test_it_writes_the_committed_aggregate_from_the_committed_seeds(tmp_path, monkeypatch):
    """Two drive-split seeds: the page (its command aside), the CSV and the
    JSON's numbers are the committed interim-drive-2seeds', the page ends
    with the differences beyond the spread, and regenerate gives the page
    main wrote."""
    script = load_script("analyses/aggregate_seeds.py")
    monkeypatch.chdir(REPO)
    out = tmp_path / "interim-drive-2seeds"
    tables = [f"{CPU}/interim-drive-s{s}/table1.json" for s in (0, 1)]
    assert script.main(tables + ["--seeds", "0", "1", "--out", str(out)]) == 0
    committed = os.path.join(REPO, CPU, "interim-drive-2seeds")
    with open(os.path.join(committed, "table1.md")) as f:
        page = f.read()
    written = (out / "table1.md").read_text()
    assert written.replace(str(out), f"{CPU}/interim-drive-2seeds") == page
    assert "\n## Beyond the spread\n\n| rows compared |" in written
    with open(os.path.join(committed, "table1.csv")) as f:
        assert (out / "table1.csv").read_text() == f.read()
    with open(os.path.join(committed, "table1.json")) as f:
        stored = json.load(f)
    mine = json.loads((out / "table1.json").read_text())
    assert mine.pop("command").endswith(f"--out {out}")
    assert mine == {k: v for k, v in stored.items() if k != "command"}
    assert script.regenerate(str(out / "table1.md")) == written


@pytest.mark.parametrize("argv, message", [
    (["a.json", "--seeds", "0", "--out", "x"], "two or more tables"),
    (["a.json", "b.json", "--seeds", "0", "--out", "x"], "2 tables but 1 seeds"),
])
def test_it_refuses_too_few_tables_or_seeds_in_one_line(argv, message, capsys):
    script = load_script("analyses/aggregate_seeds.py")
    with pytest.raises(SystemExit) as exit_:
        script.main(argv)
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1
