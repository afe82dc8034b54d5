"""Mixing dataset files (cpl_keras.data.mix): every pair and label carried
over, rig configurations kept apart, the real rigs recorded, and a model
never scored on a rig it was trained on."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from cpl_keras.data import mix
from cpl_keras.data.storage import DatasetError, StereoFile
from cpl_keras.data.writer import StereoWriter

from helpers import REPO, fixture_labels, writable_copy, write_stereo_fixture


def write_rig(path, n=6, image_size=16, rig="bench"):
    """A real-set-like file: one rig named in the metadata, config_id 0 and
    town_id -1 for every pair (as the real builders write them)."""
    rng = np.random.default_rng(5)
    labels = dict(fixture_labels(n, image_size, 1, 3))
    labels["config_id"] = np.zeros(n, np.int32)
    labels["town_id"] = np.full(n, -1, np.int32)
    labels["crop_x0"] = np.arange(n, dtype=np.float32)  # a label only this file has
    with StereoWriter(path, n, image_size, metadata={"rig": rig, "source": "test rig"}) as w:
        w.write(0, rng.integers(0, 256, (n, image_size, image_size, 3), dtype=np.uint8),
                rng.integers(0, 256, (n, image_size, image_size, 3), dtype=np.uint8), labels)
    return str(path)


@pytest.fixture
def sources(tmp_path):
    rendered = write_stereo_fixture(tmp_path / "rendered.h5", n=12, image_size=16, configs=4)
    other = write_stereo_fixture(tmp_path / "other.h5", n=8, image_size=16, configs=2, seed=4)
    return [rendered, write_rig(tmp_path / "bench.h5"), other]


def test_every_pair_and_label_is_carried_over_and_configurations_kept_apart(sources, tmp_path):
    out = mix.mix_datasets(tmp_path / "mix.h5", sources, command="a command")
    files = [StereoFile(p) for p in sources]
    with StereoFile(out) as mixed:
        assert mixed.num_pairs == 12 + 6 + 8
        common = set.intersection(*(set(f.labels) for f in files))
        assert set(mixed.labels) == common | {"source_index"}
        assert "crop_x0" not in mixed.labels  # only one source has it
        start = 0
        seen_configs = set()
        for k, f in enumerate(files):
            block = np.arange(start, start + f.num_pairs)
            for a, b in zip(mixed.read_pairs(block), f.read_pairs(np.arange(f.num_pairs))):
                np.testing.assert_array_equal(a, b)
            np.testing.assert_array_equal(mixed.labels["source_index"][block], k)
            for name in common - {"config_id", "town_id"}:
                np.testing.assert_array_equal(mixed.labels[name][block], f.labels[name])
            for name in ("config_id", "town_id"):
                # the same partition of the source's pairs, under new numbers
                new, old = mixed.labels[name][block], f.labels[name]
                assert np.array_equal(new[:, None] == new[None, :], old[:, None] == old[None, :])
            configs = set(mixed.labels["config_id"][block].tolist())
            assert not configs & seen_configs  # no configuration shared between sources
            seen_configs |= configs
            start += f.num_pairs
        meta = mixed.metadata
    for f in files:
        f.close()
    assert meta["protocol"] == mix.PROTOCOL and meta["rigs"] == ["bench"]
    assert [s["file"] for s in meta["sources"]] == ["rendered.h5", "bench.h5", "other.h5"]
    assert [s["pairs"] for s in meta["sources"]] == [12, 6, 8] and meta["command"] == "a command"
    assert mix.training_rigs(meta) == ["bench"]
    assert mix.training_rigs({"rig": "oakd"}) == ["oakd"] and mix.training_rigs({}) == []


def test_training_records_the_rigs_and_table2_refuses_them(sources, tmp_path, tiny_run):
    from cpl_keras.evaluation import EvaluationError, table2
    from cpl_keras.training.planning import plan_run

    out = mix.mix_datasets(tmp_path / "mix.h5", sources)
    plan = plan_run(out, variant="baseline", run_dir=str(tmp_path / "run"), backbone="small",
                    batch_size=4)
    assert plan.config.data.training_rigs == ["bench"]
    rendered = write_stereo_fixture(tmp_path / "rendered30.h5", n=30, image_size=16)
    assert plan_run(rendered, variant="baseline", run_dir=str(tmp_path / "r2"),
                    backbone="small", batch_size=4).config.data.training_rigs == []
    # a run trained on the bench rig (the shared run, its record rewritten)
    run_dir = tmp_path / "trained_on_bench"
    writable_copy(tiny_run["run"], run_dir)
    config = json.loads((run_dir / "config.json").read_text())
    (run_dir / "config.json").write_text(json.dumps(dict(config, training_rigs=["bench"])))
    with pytest.raises(EvaluationError, match="trained on pairs of the rig 'bench'"):
        table2.table2_rigs([str(run_dir)], [sources[1]], geometric=False)


def test_sources_that_do_not_fit_together_are_one_line_exit_2_and_no_file(sources, tmp_path):
    big = write_stereo_fixture(tmp_path / "big.h5", n=6, image_size=24)
    cases = {
        "sizes": ([sources[0], big], "differ in size (rendered.h5 16x16, big.h5 24x24)"),
        "one file": ([sources[0]], "at least two dataset files"),
        "missing": ([sources[0], str(tmp_path / "none.h5")], "dataset not found"),
        "no config_id": ([sources[0], write_stereo_fixture(tmp_path / "nc.h5", n=6, image_size=16,
                                                           drop=("config_id",))],
                         "needs the label(s) config_id"),
    }
    for name, (args, message) in cases.items():
        out = tmp_path / f"{name}.h5"
        process = subprocess.run([sys.executable, "-m", "cpl_keras.data.mix", *args, "--out",
                                  str(out)], capture_output=True, text=True, cwd=REPO, timeout=120)
        lines = process.stderr.strip().splitlines()
        assert process.returncode == 2 and len(lines) == 1, (name, process.stderr)
        assert message in lines[0] and lines[0].startswith("python -m cpl_keras.data.mix: error:")
        assert not os.path.exists(out) and not os.path.exists(f"{out}.partial"), name
    with pytest.raises(DatasetError, match="is also a source"):
        mix.mix_datasets(sources[0], sources)


def test_a_file_mixed_with_itself_is_refused_by_any_path_to_it(sources, tmp_path, monkeypatch):
    """The same file twice, by the same path, another spelling of it, or a
    link to it: one line, no file (every pair was copied twice, and a split
    put copies of one pair on both sides); the output as a source by a link."""
    rendered = sources[0]
    os.symlink(rendered, tmp_path / "link.h5")
    monkeypatch.chdir(tmp_path)
    said = " given twice: its pairs would be in the mix twice, and copies of one pair on both " \
           "sides of a split"
    cases = {"same path": ([rendered, sources[1], rendered], f"{rendered} is" + said),
             "spelled otherwise": ([rendered, "./rendered.h5"],
                                   f"{rendered} and ./rendered.h5 are one file," + said),
             "a link": ([rendered, "link.h5"], f"{rendered} and link.h5 are one file," + said)}
    for name, (args, message) in cases.items():
        out = tmp_path / "mix.h5"
        with pytest.raises(DatasetError) as error:
            mix.mix_datasets(out, args)
        assert str(error.value) == message, name
        assert not os.path.exists(out) and not os.path.exists(f"{out}.partial"), name
    with pytest.raises(DatasetError, match="the output link.h5 is also a source"):
        mix.mix_datasets("link.h5", sources)


def test_the_command_prints_the_file_and_a_summary(sources, tmp_path):
    out = tmp_path / "new" / "mix.h5"
    process = subprocess.run([sys.executable, "-m", "cpl_keras.data.mix", *sources, "--out",
                              str(out)], capture_output=True, text=True, cwd=REPO, timeout=120)
    assert process.returncode == 0, process.stderr
    assert process.stdout.strip() == str(out)
    assert "summary: 26 pairs from 3 files (12, 6, 8); real rigs: bench" in process.stderr
    with StereoFile(out) as f:
        assert f.metadata["command"].startswith("python -m cpl_keras.data.mix ")
