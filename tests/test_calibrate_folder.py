"""calibrate --folder on many pairs: one warning line for each kind of
warning (with the pairs it concerns, abbreviated), not one a pair; and a
progress bar on a terminal."""

import os
import re

import cv2
import numpy as np
import pytest

from cpl_keras.calibrate import Calibrator
from cpl_keras.calibration_warnings import WarningGroups, abbreviate, warning_kind
from cpl_keras.commands import calibrate as calibrate_command

PAIRS = 6


@pytest.fixture(scope="module")
def folder(tiny_run, tmp_path_factory):
    """``PAIRS`` pairs of random images (64x40), each right image shifted
    by its own disparity, and the tiny run."""
    root = tmp_path_factory.mktemp("rig")
    rng = np.random.default_rng(3)
    for k in range(PAIRS):
        left = (rng.random((40, 64, 3)) * 255).astype(np.uint8)
        cv2.imwrite(str(root / f"{k}_left.png"), left)
        cv2.imwrite(str(root / f"{k}_right.png"), np.roll(left, -2 - k, axis=1))
    return {"folder": str(root), "run": str(tiny_run["run"])}


def test_a_folders_warnings_are_one_line_for_each_kind(folder, capsys):
    """500 pairs gave 2,840 warning lines, one for each warning of each
    pair: now each kind of warning is one line naming how many pairs it
    concerns and which (the first three, then how many others), quoting its
    first pair's warning."""
    calibrator = Calibrator.from_run(folder["run"])
    kinds = {}
    for k in range(PAIRS):   # what each pair says on its own
        left, right = (os.path.join(folder["folder"], f"{k}_{side}.png")
                       for side in ("left", "right"))
        said = []
        calibrator.calibrate(left, right, warn=said.append)
        for line in said:
            if "demonstration model" not in line:
                kinds.setdefault(warning_kind(line, (left, right)), []).append(line)
    repeated = [kind for kind, lines in kinds.items() if len(set(lines)) > 1]
    assert repeated, kinds   # (a kind whose pairs' lines differ: per pair, several lines)

    assert calibrate_command.main(["--folder", folder["folder"], "--run", folder["run"]]) == 0
    err = capsys.readouterr().err.splitlines()
    grouped = {}
    for line in err:
        found = re.fullmatch(rf"{calibrate_command.PROG}: warning: (\d+) of {PAIRS} pairs "
                             r"\(([^)]*)\)(, as on [\w.]+)?: (.*)", line)
        if found:
            count, names, as_on, text = found.groups()
            first = names.split(", ")[0]
            paths = [os.path.join(folder["folder"], first.replace("left", side))
                     for side in ("left", "right")]
            kind = warning_kind(text, paths)
            assert kind not in grouped, line          # (one line a kind)
            grouped[kind] = int(count)
            assert (as_on == f", as on {first}") == (int(count) > 1), line
            if int(count) > 4:
                assert names.endswith(f" and {int(count) - 3} others"), line
    assert grouped == {kind: len(lines) for kind, lines in kinds.items()}, "\n".join(err)
    per_pair = [line for line in err if re.search(r"\d_left\.png: warning", line)]
    assert not per_pair, per_pair
    # the Python API gives the same lines
    lines = []
    calibrator.calibrate_folder(folder["folder"], warn=lines.append)
    assert [line for line in lines if re.match(r"warning: \d+ of", line)] == \
        [line.split(": ", 1)[1] for line in err if re.match(r".*?: warning: \d+ of", line)]


def test_warning_groups_name_a_few_pairs_and_count_the_others():
    groups = WarningGroups()
    for k in range(6):
        groups.add(f"{k}.png", f"warning: fx changes by {k + 1.5} px (std) between crops")
        if k % 2:
            groups.add(f"{k}.png", f"warning: the left image /d/{k}.png is grey",
                       (f"/d/{k}.png", f"/d/{k}r.png"))
    groups.add(None, "warning: this run is the demonstration model")
    groups.add(None, "warning: this run is the demonstration model")
    assert groups.lines(6) == [
        "warning: 6 of 6 pairs (0.png, 1.png, 2.png and 3 others), as on 0.png: fx changes by "
        "1.5 px (std) between crops",
        "warning: 3 of 6 pairs (1.png, 3.png, 5.png), as on 1.png: the left image /d/1.png is "
        "grey",
        "warning: this run is the demonstration model"]
    assert abbreviate(["a", "b", "c", "d"]) == "a, b, c, d"
    assert warning_kind("warning: predictions outside the training labels' range, in the "
                        "model's input units: fx 3 (trained on 1..2)") == \
        warning_kind("warning: predictions outside the training labels' range, in the "
                     "model's input units: b -4e+03 (trained on 0.1..2), pitch 7 (trained on "
                     "-1..1)")


@pytest.mark.parametrize("terminal, flags, shown", [
    (True, [], True), (True, ["--no-progress"], False), (False, [], False)])
def test_a_folder_shows_a_progress_bar_on_a_terminal(folder, capsys, monkeypatch, terminal,
                                                      flags, shown):
    """--folder on 500 pairs printed no progress for 33 s: on a terminal a
    bar of pairs done, their rate and the time left, as the generator's;
    none with --no-progress or when stderr is a file or a pipe."""
    import sys

    monkeypatch.setattr(sys.stderr, "isatty", lambda: terminal, raising=False)
    assert calibrate_command.main(["--folder", folder["folder"], "--run", folder["run"],
                                   *flags]) == 0
    err = capsys.readouterr().err
    bars = re.findall(r"\rcalibrating \[[#.]+\] (\d+)/(\d+) pairs +[\d.]+ pairs/s ETA +\d+s",
                      err)
    assert bars == ([(str(k), str(PAIRS)) for k in range(1, PAIRS + 1)] if shown else []), err
    assert ("\r" in err) == shown
    if shown:   # (the bar's line ended before the warnings)
        assert re.search(rf"{PAIRS}/{PAIRS} pairs .*\n{calibrate_command.PROG}: ", err), err
