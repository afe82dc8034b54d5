"""The dataset CLI: bad arguments fail cleanly, good ones write a dataset and a preview."""

import os
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from cpl_keras.data.generate import generate_dataset
from cpl_keras.data.storage import StereoFile
from helpers import REPO


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "cpl_keras.data.generate", *args], cwd=REPO,
                          capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize("args, needle", [
    (["--pairs", "0"], "pairs"),
    (["--pairs", "-3"], "pairs"),
    (["--pairs", "4", "--protocol", "carla"], "protocol"),
    (["--pairs", "4", "--image-size", "8"], "image_size"),
    (["--pairs", "four"], "pairs"),
    (["--pairs", "4", "--workers", "0"], "workers"),
    # refused before any work: the file cannot fit on any disk
    (["--pairs", "10000000000000"], "10000000000000 cvgl pairs at 112 px (at least 19.0 KB a "
     "pair on disk) need at least 190 PB of disk;"),
])
def test_bad_arguments_one_line_exit_2_no_file(tmp_path, args, needle):
    out = tmp_path / "d.h5"
    result = _cli(*args, "--out", str(out))
    assert result.returncode == 2
    assert "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0]
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("make_out", [
    lambda tmp: tmp / "file.txt" / "d.h5",               # parent is a file
    lambda tmp: tmp / "file.txt" / "sub" / "d.h5",       # an ancestor is a file
    lambda tmp: tmp,                                     # a directory, not a file
])
def test_unwritable_output_path(tmp_path, make_out):
    (tmp_path / "file.txt").write_text("x")
    before = sorted(os.listdir(tmp_path))
    result = _cli("--pairs", "4", "--out", str(make_out(tmp_path)))
    assert result.returncode == 2
    assert "Traceback" not in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1
    assert sorted(os.listdir(tmp_path)) == before


def test_missing_output_folders_are_created(tmp_path):
    out, sheet = tmp_path / "data" / "sub" / "d.h5", tmp_path / "previews" / "p.png"
    result = _cli("--pairs", "2", "--image-size", "16", "--workers", "1", "--no-progress",
                  "--out", str(out), "--preview", str(sheet))
    assert result.returncode == 0, result.stderr
    assert out.is_file() and sheet.is_file()


def test_missing_out_and_preview(tmp_path):
    result = _cli("--pairs", "4")
    assert result.returncode == 2 and len(result.stderr.strip().splitlines()) == 1


def test_library_rejects_bad_arguments_with_one_line(tmp_path):
    for kwargs in ({"pairs": 0}, {"pairs": 2, "protocol": "x"}, {"pairs": 2, "image_size": 4},
                   {"pairs": True}, {"pairs": 2, "seed": -1}):
        with pytest.raises(ValueError) as err:
            generate_dataset(tmp_path / "d.h5", progress=False, **kwargs)
        assert "\n" not in str(err.value)
    assert os.listdir(tmp_path) == []


def test_dataset_and_preview(tmp_path):
    out, sheet = tmp_path / "d.h5", tmp_path / "p.png"
    result = _cli("--protocol", "random", "--pairs", "4", "--image-size", "32", "--workers", "1",
                  "--out", str(out), "--preview", str(sheet), "--seed", "9")
    assert result.returncode == 0, result.stderr
    assert "4/4 pairs" in result.stderr                 # the progress bar
    with StereoFile(out) as data:
        assert len(data) == 4
        assert data.metadata["command_line"].endswith("--seed 9")
    with Image.open(sheet) as image:
        assert image.width > 2 * 32 and image.height > 32
    assert sorted(os.listdir(tmp_path)) == ["d.h5", "p.png"]


@pytest.mark.parametrize("protocol, seed", [("cvgl", 0), ("random", 1)])
def test_the_committed_contact_sheets_are_the_current_generators(tmp_path, protocol, seed):
    """docs/preview_<protocol>.png is what docs/data.md's command draws now,
    byte for byte, so that the documented ``cp`` into docs/ leaves `git
    status` empty (a sheet drawn by an older generator moves its labels and
    the projection pixel: 1-2 % of the pixels differ)."""
    from cpl_keras.data.preview import write_preview

    sheet = write_preview(tmp_path / "p.png", protocol, 10000, seed)
    with open(sheet, "rb") as now, \
            open(os.path.join(REPO, "docs", f"preview_{protocol}.png"), "rb") as committed:
        assert now.read() == committed.read()


def test_summary_reports_sky_at_the_release_pixel(tmp_path):
    import re

    import numpy as np

    from cpl_keras.data.generate import label_summary

    out = tmp_path / "d.h5"
    result = _cli("--protocol", "cvgl", "--pairs", "6", "--image-size", "32", "--workers", "1",
                  "--out", str(out), "--no-progress")
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == str(out)
    line = [x for x in result.stderr.splitlines() if x.startswith("summary:")]
    assert len(line) == 1, result.stderr
    with StereoFile(out) as data:
        sky = int(np.sum(data.labels["sky_at_release_pixel"]))
        fallback = int(np.sum(data.labels["projection_fallback"]))
        summary = label_summary(data.labels)
    assert summary["pairs"] == 6 and summary["sky_at_release_pixel"] == sky
    assert re.search(rf"sees the sky in {sky} of 6 pairs", line[0]), line[0]
    assert re.search(rf"{fallback} from the fallback", line[0]), line[0]
    assert summary["beyond_max_distance"] == 0


def test_demonstration_next_step_states_disk_and_time(tmp_path, monkeypatch):
    """The full-scale command the demonstration proposes comes with its cost,
    measured on a generated file (bytes per pair) and by rendering a sample
    now with the generator's worker processes (time), and says that the
    time is an estimate from so many sampled pairs at the machine's load."""
    import functools
    import importlib.util
    import re

    from cpl_keras.commands import train
    from cpl_keras.data.estimate import estimate_cost

    sample = generate_dataset(tmp_path / "s.h5", pairs=8, image_size=32, workers=1,
                              progress=False)
    cost = estimate_cost(1000, sample, workers=2, seconds=0.5)
    assert cost["bytes_per_pair"] == pytest.approx(os.path.getsize(sample) / 8)
    assert cost["bytes"] == pytest.approx(1000 * cost["bytes_per_pair"])
    assert cost["seconds"] == pytest.approx(1000 / cost["pairs_per_second"])
    assert cost["workers"] == 2 and cost["sampled_pairs"] > 0
    assert cost["sample_seconds"] >= 0.5 or cost["sampled_pairs"] + 2 * 32 >= 1000
    monkeypatch.setattr(train, "estimate_cost",
                        functools.partial(estimate_cost, workers=1, seconds=0.3))
    spec = importlib.util.spec_from_file_location(
        "train_script", os.path.join(os.path.dirname(os.path.dirname(__file__)), "train.py"))
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    text = script.next_step("cpl-a", sample)
    assert "--pairs 123017" in text
    assert re.search(r"about [\d.]+ GB of disk \([\d.]+ KB a pair at 32 px, measured on the "
                     r"demonstration file\) and about [\d.]+ (s|min|h) to generate with \d+ "
                     r"worker process(es)?: an estimate from \d+ pairs sampled just now \(\d+ "
                     r"pairs/s over [\d.]+ s\) at this machine's present load", text), text


@pytest.mark.parametrize("flags, momentum", [
    ([], 0.9),                          # the demonstration's own average
    (["--weight-ema", "0.99"], 0.99),   # as given
    (["--weight-ema", "0"], 0.0),
    (["--as-released"], None),          # the release's (planning: 0)
    (["--data", "X.h5"], None),         # training's default (planning: 0.99)
])
def test_the_demonstration_validates_a_short_average_of_the_weights(
        flags, momentum, monkeypatch, tmp_path):
    from cpl_keras.commands import train as command

    seen = {}

    class Stop(Exception):
        pass

    def fake_train(data, **kwargs):
        seen.update(kwargs, data=data)
        raise Stop

    monkeypatch.setattr(command, "train", fake_train)
    monkeypatch.setattr(command, "demo_dataset", lambda: "demo.h5")
    with pytest.raises(Stop):
        command.main(["--variant", "cpl-a", "--run-dir", str(tmp_path / "run"), *flags])
    assert seen["training"].weight_ema == momentum
    assert seen["data"] == ("X.h5" if "--data" in flags else "demo.h5")


@pytest.mark.parametrize("workers, pace", [(2, 1.0), (2, 0.5), (1, 1.0)])
def test_the_generation_estimate_times_the_workers_at_once_long_enough(
        tmp_path, monkeypatch, workers, pace):
    """The demonstration's estimate rendered 16 pairs on one core (0.15 s)
    and divided by the cores: 9-11 minutes for a dataset that took about 18
    on a machine shared with other jobs. The sample is now rendered by the
    generator's workers all at once, at whatever pace the machine's load
    leaves them (``pace``: a share of a core), for at least
    ``SAMPLE_SECONDS``, and timed from the arrival of every worker's first
    block (its set-up, about ten pairs' time, left out)."""
    from cpl_keras.data import estimate

    sample = generate_dataset(str(tmp_path / "s.h5"), pairs=4, image_size=32, workers=1,
                              progress=False)
    clock, seen = {"now": 0.0}, {}
    pair_seconds, block = 0.01, 8   # (one pair on a whole core; pairs a block)

    def iter_blocks(protocol, seed, pairs, image_size, workers_given, first):
        seen.update(workers=workers_given, first=first, pairs=pairs)
        try:
            for number, start in enumerate(range(first, pairs, block)):
                if number < workers_given:   # every worker's first block: its set-up
                    clock["now"] = 1.0
                else:                        # the workers' blocks, side by side
                    clock["now"] += block * pair_seconds / pace / workers_given
                yield start, (np.zeros((block, 1)), None, None)
        finally:
            seen["closed"] = True

    monkeypatch.setattr(estimate, "iter_blocks", iter_blocks)
    monkeypatch.setattr(estimate.time, "perf_counter", lambda: clock["now"])
    cost = estimate.estimate_cost(123017, sample, workers=workers)
    assert seen == {"workers": workers, "first": 123017 - estimate.MAX_SAMPLE_PAIRS,
                    "pairs": 123017, "closed": True}
    rate = workers * pace / pair_seconds
    assert cost["pairs_per_second"] == pytest.approx(rate)
    assert cost["seconds"] == pytest.approx(123017 / rate)
    assert estimate.SAMPLE_SECONDS <= cost["sample_seconds"] < estimate.SAMPLE_SECONDS + 0.1
    assert cost["sampled_pairs"] == pytest.approx(rate * cost["sample_seconds"])
