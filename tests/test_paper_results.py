"""The committed results: every reproduction folder under paper_results/ has
tables that are what its published predictions give (rebuilt here, without
weights or datasets), and every decimal figure a report quotes is a cell of
the tables (or of the run table) it speaks about."""

import json
import os
import math
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from helpers import REPO

RESULTS = Path(REPO) / "paper_results"
#: Every committed reproduction: a folder with its reproduce.json.
REPRODUCTIONS = sorted(p.parent for p in RESULTS.glob("**/reproduce.json"))
#: A decimal figure as the reports write it: 0.012, -1.849, 4.6 (not 2 or 1,000).
DECIMAL = re.compile(r"(?<![\w.])-?\d+\.\d+(?![\w.])")


def _files(folder):
    return {str(p.relative_to(folder)): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


@pytest.mark.parametrize("folder", REPRODUCTIONS, ids=lambda p: str(p.relative_to(RESULTS)))
def test_committed_tables_are_what_their_predictions_give(folder, tmp_path):
    copy = tmp_path / "results"
    shutil.copytree(folder, copy)
    result = subprocess.run([sys.executable, "-m", "cpl_keras.reproduce", "--from-predictions",
                             str(copy)], capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    committed, rebuilt = _files(folder), _files(copy)
    assert set(rebuilt) == set(committed)
    for name, data in committed.items():
        if name.endswith(".json"):
            # the same numbers to the last few bits: numpy's vectorised arctan
            # differs by an ulp between CPUs (AVX-512 on AMD EPYC against
            # Intel), which moves the 16th digit of a FoV AUC
            assert _same_numbers(json.loads(rebuilt[name]), json.loads(data)), name
        elif name != "REPORT.md":
            assert rebuilt[name] == data, name
    # REPORT.md: the same, but for the note saying how it was rebuilt
    note = re.compile(r"The tables and this page were rebuilt from the published predictions "
                      r"[^\n]*\n\n```\n[^\n]*\n```\n\n")
    assert note.sub("", rebuilt["REPORT.md"].decode()) == \
        note.sub("", committed["REPORT.md"].decode())


@pytest.mark.parametrize("folder", REPRODUCTIONS, ids=lambda p: str(p.relative_to(RESULTS)))
def test_committed_predictions_are_those_their_records_were_made_from(folder):
    """Each committed predictions file holds the arrays whose checksum its
    reproduce.json recorded (a file edited by hand is named here, as a rerun
    of the preset names it), and the record lists every one of them."""
    from cpl_keras.reproduce.record import CHECKSUMS, checksums

    summary = json.loads((folder / "reproduce.json").read_text())
    recorded = summary[CHECKSUMS]
    assert list(recorded) == summary["predictions"]
    now = checksums([folder / name for name in recorded], folder)
    assert [name for name in recorded if now[name] != recorded[name]] == []


def _same_numbers(a, b, rel=1e-12):
    """Whether two parsed JSON values are equal, floats within ``rel``, keys
    in the same order (a rebuild in place changes no byte but the last bits
    of a float)."""
    if isinstance(a, dict):
        return isinstance(b, dict) and list(a) == list(b) and all(
            _same_numbers(a[k], b[k], rel) for k in a)
    if isinstance(a, list):
        return isinstance(b, list) and len(a) == len(b) and all(
            _same_numbers(x, y, rel) for x, y in zip(a, b))
    if isinstance(a, float) and isinstance(b, (int, float)) and not isinstance(b, bool):
        return a == b or (math.isnan(a) and math.isnan(b)) or \
            abs(a - b) <= rel * max(abs(a), abs(b))
    return a == b


def test_same_numbers_tells_an_ulp_from_a_change():
    assert _same_numbers({"x": [0.009523920589337891, "a"]}, {"x": [0.009523920589337903, "a"]})
    assert not _same_numbers({"x": [0.0095239205893]}, {"x": [0.0095239205894]})
    assert not _same_numbers({"x": 1, "y": 2}, {"y": 2, "x": 1})  # (the file's key order)
    assert not _same_numbers({"x": 1.0}, {"y": 1.0}) and not _same_numbers([1.0], [1.0, 2.0])
    assert not _same_numbers({"x": "a"}, {"x": "b"})


def _quoted(text):
    """The decimal figures of ``text`` outside code (blocks and inline) and
    link targets."""
    text = re.sub(r"```.*?```", "", text, flags=re.S)
    text = re.sub(r"`[^`\n]*`", "", text)
    text = re.sub(r"\]\([^)]*\)", "]", text)
    return DECIMAL.findall(text)


def _cells(folder, document=None):
    """Every decimal figure of the tables and the run tables under ``folder``
    (Markdown files; not the comparisons with the paper, nor ``document``)."""
    found = set()
    for path in folder.rglob("*.md"):
        if path.name == "discussion.md" or path == document:
            continue
        text = path.read_text()
        if path.name == "REPORT.md":
            text = text.split("## Comparison with the paper")[0]
        found.update(DECIMAL.findall(text))
    return found


def _discussions():
    """(document, its text, the folder whose tables back it): each
    reproduction's comparison with the paper, and paper_results/README.md."""
    import json

    found = []
    for folder in REPRODUCTIONS:
        text = json.loads((folder / "reproduce.json").read_text()).get("discussion") or ""
        if text:
            found.append((str(folder.relative_to(RESULTS)) + "/reproduce.json", text, folder))
    found.append(("README.md", (RESULTS / "README.md").read_text(), RESULTS))
    return found


@pytest.mark.parametrize("name, text, folder", _discussions(), ids=lambda v: v
                         if isinstance(v, str) and v.endswith(("json", "md")) else "")
def test_every_quoted_figure_is_in_a_table(name, text, folder):
    cells = _cells(folder, document=RESULTS / name)
    missing = [figure for figure in _quoted(text) if figure not in cells]
    assert not missing, f"{name} quotes figures found in no table: {missing}"


def test_the_figure_check_catches_a_figure_not_in_the_tables(tmp_path):
    (tmp_path / "table1_cvgl.md").write_text("| MTL-CPL-A | 0.012 ± 0.003 | -1.849 |\n")
    cells = _cells(tmp_path)
    assert {"0.012", "0.003", "-1.849"} <= cells
    quoted = _quoted("CPL-A gets 0.012 (spread 0.003) against 0.013; `x 9.99` [a](v1.5.md)")
    assert quoted == ["0.012", "0.003", "0.013"]
    assert [f for f in quoted if f not in cells] == ["0.013"]


#: An absolute path of a machine: a POSIX root folder of user or temporary
#: data, a Windows drive, or a home folder's shorthand.
MACHINE_PATH = re.compile(
    r"(?:^|[\s\"'`=(\[,:])(/(?:tmp|root|home|work|Users|var|private|mnt|opt|srv|scratch|data)/"
    r"|[A-Za-z]:\\\\|~/\.cache/\S*pytest)")


def _tracked(*folders):
    done = subprocess.run(["git", "ls-files", *folders], cwd=REPO, text=True,
                          capture_output=True, timeout=60)
    if done.returncode != 0:
        pytest.skip("not a git checkout")
    return [name for name in done.stdout.splitlines() if name]


def test_no_tracked_result_or_doc_names_a_machine_path():
    """paper_results/ and docs/ are read on other machines: no file of them
    (text files, and the strings of the stored .npz predictions) holds an
    absolute path of the machine that wrote it."""
    import numpy as np

    found = []
    for name in _tracked("paper_results", "docs"):
        path = os.path.join(REPO, name)
        if name.endswith(".png"):
            continue
        if name.endswith(".npz"):
            with np.load(path, allow_pickle=False) as stored:
                texts = [str(v) for key in stored.files if stored[key].dtype.kind in "US"
                         for v in stored[key].ravel()]
        else:
            with open(path, encoding="utf-8", errors="replace") as f:
                texts = f.read().splitlines()
        found += [f"{name}: {text.strip()[:120]}" for text in texts if MACHINE_PATH.search(text)]
    assert not found, "\n".join(found)


def test_the_machine_path_scan_catches_one():
    for text in ("--data /tmp/d/cvgl_1000.h5", '"data": "/home/me/cvgl.h5"',
                 "CPL_KERAS_CACHE=/root/.cache/x", r"C:\\Users\\me"):
        assert MACHINE_PATH.search(text), text
    for text in ("--data data/cvgl.h5", "runs/dry", "paper_results/cpu/runs", "km/h"):
        assert not MACHINE_PATH.search(text), text


#: Every published run directory (``published.publish_run_dir``) under paper_results/.
PUBLISHED_RUNS = sorted(p.parent for p in RESULTS.glob("**/runs/*/config.json"))


def test_every_published_run_restores_and_publishes_again(tmp_path):
    """Each committed run record, of whichever config.json layout, reads as a
    ``RunConfig``, restores (``published.restore_run_dir``: its config pointing at
    the dataset and the run directory given) and loads as a run; published
    again from there, its config is the record's but for the run directory's
    name and the note of where it was restored from."""
    import dataclasses

    from cpl_keras import published, runs

    assert len(PUBLISHED_RUNS) >= 50
    for number, record in enumerate(PUBLISHED_RUNS):
        config = runs.read_run_config(record)
        assert published.is_published(record) and config.status == "finished", record
        data = tmp_path / "data" / config.data.path
        run_dir = tmp_path / "runs" / str(number)
        published.restore_run_dir(str(record), str(run_dir), str(data))
        run = runs.load_run(run_dir)
        assert run.config == dataclasses.replace(
            config, data=dataclasses.replace(config.data, path=str(data)), run_dir=str(run_dir),
            other=dict(config.other, restored_from=str(record))), record
        again = tmp_path / "records" / str(number)
        published.publish_run_dir(str(run_dir), str(again))
        assert runs.read_run_config(again) == dataclasses.replace(
            run.config, data=config.data, run_dir=str(number)), record
        assert (again / "log.csv").read_bytes() == (record / "log.csv").read_bytes()


def _words(text):
    """Words as a reader counts them: link targets and table rules left out."""
    text = re.sub(r"\]\([^)]*\)", "]", text)
    return re.findall(r"[A-Za-z0-9][\w.,'=-]*", text.replace("|", " "))


def test_the_readme_answer_fits_one_screen():
    """README's answer: at most 300 words with its table, at most 6 rows, no
    cell over 40 words, each row linking its evidence."""
    text = (Path(REPO) / "README.md").read_text()
    start = text.index("## The answer")
    section = text[start:text.index("\n## ", start + 1)]
    assert len(_words(section)) <= 300, len(_words(section))
    rows = [line for line in section.splitlines()
            if line.startswith("|") and not line.startswith("|---")][1:]
    assert 1 <= len(rows) <= 6, rows
    for row in rows:
        cells = [cell.strip() for cell in row.strip("|").split("|")]
        assert max(len(_words(cell)) for cell in cells) <= 40, row
        assert re.search(r"\]\((paper_results|docs)/", cells[-1]), row
    assert len(_words("a b [c](d/e.md) | f")) == 4  # (the count can tell)


def test_the_index_lists_every_folder_of_paper_results():
    """paper_results/README.md has a line for every folder, each with its status."""
    text = (RESULTS / "README.md").read_text()
    folders = sorted(p.name for p in RESULTS.iterdir() if p.is_dir())
    listed = re.findall(r"^\| \[([\w.-]+)/\]\([^)]*\) \|", text, re.M)
    assert sorted(listed) == folders, set(folders) ^ set(listed)
    for line in text.splitlines():
        if re.match(r"^\| \[[\w.-]+/\]", line):
            assert line.rstrip(" |").split("|")[-1].strip(), line  # (a status)


def _sentences(text):
    """Prose sentences of a Markdown page: tables, headings, images and
    link targets left out."""
    prose = "\n".join(line for line in text.splitlines()
                      if not line.startswith(("|", "#", "!", "<!--")))
    prose = re.sub(r"\]\([^)]*\)", "]", prose).replace("**", "")
    blocks = re.split(r"\n\s*\n|\n- ", prose)
    return [s for block in blocks
            for s in re.split(r"(?<=[.!?])\s+(?=[A-Z(])", re.sub(r"\s+", " ", block))
            if s.strip()]


def test_the_explanation_page_is_short_and_in_order():
    """why.md: its title starts with "Why", at most 1,500 words, no sentence
    over 40 words, and its parts in order: the question, the answer in three
    sentences, the findings, what is not decided."""
    text = (RESULTS / "inception-2000-ablations" / "why.md").read_text()
    assert text.startswith("# Why ")
    assert len(_words(text)) <= 1500, len(_words(text))
    long = [s for s in _sentences(text) if len(_words(s)) > 40]
    assert not long, long
    headings = re.findall(r"^## (.+)$", text, re.M)
    assert headings == ["The question", "The answer in three sentences", "The findings",
                        "What is not decided"], headings
    answer = text.split("## The answer in three sentences", 1)[1].split("\n## ", 1)[0]
    assert len(_sentences(answer)) == 3, _sentences(answer)
    # every finding links its evidence
    findings = text.split("## The findings", 1)[1].split("\n## ", 1)[0]
    for finding in re.split(r"\n(?=\*\*\d+\.)", findings.strip()):
        assert re.search(r"\]\([^)]+\.md\)", finding), finding[:80]
    assert len(_sentences("One. Two (three). Four")) == 3  # (the count can tell)


FOLDER_HEADINGS = ["Question", "Answer", "Status", "Command", "Evidence", "Not decided"]
STATUSES = ("finished", "in progress", "stopped", "superseded", "kept up to date")


def test_every_folder_readme_has_the_fixed_headings_and_its_status_agrees_with_the_index():
    """Each folder of paper_results/ has a README.md written by hand whose
    first sections are Question, Answer (at most 150 words), Status, Command,
    Evidence and Not decided; its status is the one the index gives; a
    superseded folder says so before its first section."""
    index = (RESULTS / "README.md").read_text()
    for folder in sorted(p for p in RESULTS.iterdir() if p.is_dir()):
        page = folder / "README.md"
        assert page.exists(), f"{folder.name} has no README.md"
        text = page.read_text()
        assert text.startswith("# ") and "Written by hand" in text.split("\n## ", 1)[0], \
            folder.name
        headings = re.findall(r"^## (.+)$", text, re.M)
        assert headings[:6] == FOLDER_HEADINGS, (folder.name, headings[:6])
        sections = dict(re.findall(r"^## (.+?)\n(.*?)(?=^## |\Z)", text, re.M | re.S))
        assert len(_words(sections["Answer"])) <= 150, (folder.name,
                                                        len(_words(sections["Answer"])))
        status = sections["Status"].strip().split("\n")[0].lower()
        assert status.startswith(STATUSES), (folder.name, status)
        row = re.search(rf"^\| \[{re.escape(folder.name)}/\]\([^)]*\) \|.*\| ([^|]+) \|$", index,
                        re.M)
        assert row, folder.name
        assert row.group(1).strip().lower().split(",")[0].split(" (")[0] in status, \
            (folder.name, row.group(1), status)
        if "superseded" in status or "superseded" in row.group(1):
            assert "superseded" in status, (folder.name, status)
            assert "superseded" in text.split("\n## ", 1)[0].lower(), folder.name


def _log_rows(path):
    import csv

    with open(path, newline="") as f:
        return {int(row["epoch"]): row for row in csv.DictReader(f)}


def test_the_corrected_statements_hold_against_the_committed_files():
    """Figures that a review found wrong, as now written, recomputed from the
    committed logs and configs."""
    ablations = RESULTS / "inception-2000-ablations" / "runs"
    # inception-8000: each run's training time, and the epochs' pace (epochs 1 and 4 aside)
    page = (RESULTS / "inception-8000" / "README.md").read_text()
    for variant, row in (("cpl-a", "InceptionV3 MTL-CPL-A, seed 0, 12 epochs"),
                         ("baseline", "InceptionV3 MTL-Baseline, seed 0, 12 epochs")):
        config = json.loads((RESULTS / "inception-8000" / "runs" / f"cvgl_{variant}-12ep-s0"
                             / "config.json").read_text())
        line = next(line for line in page.splitlines() if line.startswith(f"| {row} |"))
        assert f"{config['wall_time_s']:,.3f} s" in line, (variant, config["wall_time_s"])
        log = _log_rows(RESULTS / "inception-8000" / "runs" / f"cvgl_{variant}-12ep-s0_log.csv")
        walls = [float(log[e]["wall_time_s"]) for e in sorted(log)]
        epochs = [b - a for a, b in zip([0.0] + walls, walls)]
        paced = [t for e, t in enumerate(epochs, 1) if e not in (1, 4)]
        assert 620 <= round(min(paced)) and round(max(paced)) <= 678, (variant, paced)
    # the published InceptionV3 MTL-CPL-A seed 0: Eq. 9's weights at the end of its log
    log = _log_rows(RESULTS / "inception-2000-ema" / "runs" / "cvgl_cpl-a-s0_log.csv")
    last = log[max(log)]
    assert [round(float(last[f"alpha_{p}"]), 2) for p in ("u0", "v0")] == [12.03, 9.93]
    assert [round(float(last[f"alpha_{p}"]), 3) for p in ("baseline", "tx")] == [1.136, 0.826]
    # (d): with patience 5 it would have stopped at epoch 35, not 22
    d = _log_rows(ablations / "cvgl_cpl-a-patience20-s0_log.csv")
    best, since = float("inf"), 0
    for epoch in sorted(d):
        value = float(d[epoch]["val_nmae"])
        best, since = (value, 0) if value < best else (best, since + 1)
        if since == 5:
            break
    assert epoch == 35
    # (d) against the patience-20 MTL-Baseline on validation, at equal epochs
    b = _log_rows(ablations / "cvgl_baseline-patience20-s0_log.csv")
    names = ("fx", "fy", "u0", "v0", "baseline", "disparity", "tx", "ty", "tz", "pitch")
    lower = {e: sum(float(d[e][f"val_nmae_{n}"]) < float(b[e][f"val_nmae_{n}"]) for n in names)
             for e in (83, 103)}
    assert lower == {83: 8, 103: 7}, lower
