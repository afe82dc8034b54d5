"""Targets, splits and the streaming PyDataset (cpl_keras.datasets)."""

import os
import sys
import tracemalloc

import numpy as np
import pytest

from cpl_keras import camera
from cpl_keras.baselines import average_predictions, training_statistics
from cpl_keras.baselines.average import load_statistics, save_statistics
from cpl_keras.camera import TARGETS
from cpl_keras.data.storage import DatasetError
from cpl_keras.datasets import (
    adjacent_fraction, load_split, make_split, save_split, targets_from_labels,
)
from helpers import fixture_labels, write_stereo_fixture


# ---------------------------------------------------------------------------
# Targets
# ---------------------------------------------------------------------------
def test_paper_targets_are_the_stored_labels():
    labels = fixture_labels(20, 32)
    targets = targets_from_labels(labels)
    assert tuple(targets) == TARGETS
    for name in TARGETS:
        assert targets[name].dtype == np.float32
        np.testing.assert_array_equal(targets[name], labels[name])


def test_released_targets_use_degrees_and_stereobm_disparity():
    labels = fixture_labels(20, 32)
    targets = targets_from_labels(labels, as_released=True)
    np.testing.assert_allclose(targets["pitch"], np.degrees(labels["pitch"]), rtol=1e-6)
    np.testing.assert_array_equal(targets["disparity"], labels["disparity_released"])
    # X, Y, Z are the camera equations at the released values, not the stored ones.
    params = {name: targets[name].astype(np.float64) for name in camera.PARAMETERS}
    X, Y, Z = camera.image_to_world(**params, u=labels["u"], v=labels["v"])
    np.testing.assert_allclose(targets["X"], X, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(targets["Z"], Z, rtol=1e-5, atol=1e-5)
    assert not np.allclose(targets["X"], labels["X"])
    for name in ("fx", "u0", "tx", "ty", "tz", "baseline"):
        np.testing.assert_array_equal(targets[name], labels[name])


def released_frame_labels(labels, seed=1):
    """``labels`` plus release-frame extrinsics and pixel (as the generator stores)."""
    rng = np.random.default_rng(seed)
    n, size = len(labels["fx"]), float(labels["u0"][0] * 2)
    out = dict(labels)
    out["tx_released"] = rng.uniform(0.5, 168, n).astype(np.float32)
    out["baseline_released"] = out["tx_released"].copy()
    out["ty_released"] = rng.uniform(-5, 5, n).astype(np.float32)
    out["tz_released"] = rng.uniform(-0.4, 1.6, n).astype(np.float32)
    out["pitch_released"] = rng.uniform(-15, 45, n).astype(np.float32)
    out["u_released"] = np.full(n, size / 2, np.float32)
    out["v_released"] = np.full(n, size / 2, np.float32)
    return out


def test_released_targets_use_the_release_frame_and_pixel():
    labels = released_frame_labels(fixture_labels(20, 32))
    targets = targets_from_labels(labels, as_released=True)
    for name in ("baseline", "tx", "ty", "tz", "pitch"):
        np.testing.assert_array_equal(targets[name], labels[f"{name}_released"])
    np.testing.assert_array_equal(targets["disparity"], labels["disparity_released"])
    params = {name: targets[name].astype(np.float64) for name in camera.PARAMETERS}
    X, Y, Z = camera.image_to_world(**params, u=16.0, v=16.0)      # the release's pixel
    np.testing.assert_allclose(targets["X"], X, rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(targets["Y"], Y, rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(targets["Z"], Z, rtol=1e-5, atol=1e-4)
    # not the label pixel (u, v)
    X_uv, _, _ = camera.image_to_world(**params, u=labels["u"], v=labels["v"])
    assert not np.allclose(targets["X"], X_uv, rtol=1e-3)
    # the paper's targets ignore them
    np.testing.assert_array_equal(targets_from_labels(labels)["tx"], labels["tx"])
    # half a release frame is an error, not a silent mix
    del labels["tz_released"]
    with pytest.raises(DatasetError, match="tz_released"):
        targets_from_labels(labels, as_released=True)


def test_targets_name_missing_label():
    labels = fixture_labels(10, 32)
    del labels["disparity_released"]
    targets_from_labels(labels)  # the paper's targets do not need it
    with pytest.raises(DatasetError, match="disparity_released"):
        targets_from_labels(labels, as_released=True)


# ---------------------------------------------------------------------------
# Splits
# ---------------------------------------------------------------------------
def test_paper_split_is_seeded_70_30_with_separate_validation():
    labels = fixture_labels(200, 32)
    split = make_split(labels, "paper", seed=3)
    train, val, test = split["train"], split["val"], split["test"]
    assert len(test) == 60 and len(train) + len(val) == 140 and len(val) == 14
    assert len(np.intersect1d(train, test)) == 0
    assert len(np.intersect1d(val, test)) == 0
    assert len(np.intersect1d(train, val)) == 0
    assert len(np.union1d(np.union1d(train, val), test)) == 200
    again = make_split(labels, "paper", seed=3)
    other = make_split(labels, "paper", seed=4)
    assert all(np.array_equal(split[k], again[k]) for k in split)
    assert not np.array_equal(split["test"], other["test"])
    # Every configuration is in both train and test (the release's protocol).
    assert set(labels["config_id"][train]) == set(labels["config_id"][test])


def test_as_released_split_validates_on_the_test_set():
    labels = fixture_labels(100, 32)
    split = make_split(labels, "paper", seed=0, as_released=True)
    np.testing.assert_array_equal(split["val"], split["test"])
    assert len(split["train"]) == 70


def test_held_out_config_split_keeps_whole_configurations_out():
    labels = fixture_labels(300, 32, configs=10)
    split = make_split(labels, "held-out-config", seed=1)
    config = labels["config_id"]
    train_c, val_c, test_c = (set(config[split[k]]) for k in ("train", "val", "test"))
    assert not train_c & test_c and not val_c & test_c and not train_c & val_c
    assert train_c | val_c | test_c == set(range(10))
    assert 0.2 <= len(split["test"]) / 300 <= 0.45


def test_drive_split_holds_out_the_end_of_every_rigs_drive():
    labels = fixture_labels(200, 32, configs=5)
    labels["frame_index"] = (np.arange(200) // 5).astype(np.int32)   # 40 frames per rig
    split = make_split(labels, "drive", seed=0)
    config, frame = labels["config_id"], labels["frame_index"]
    for c in range(5):
        # by hand: 40 frames, the last 12 (30 %) test, 3 (10 % of 28) before them val
        assert sorted(frame[split["test"]][config[split["test"]] == c]) == list(range(28, 40))
        assert sorted(frame[split["val"]][config[split["val"]] == c]) == list(range(25, 28))
        assert sorted(frame[split["train"]][config[split["train"]] == c]) == list(range(25))
    # every rig seen in training, no test frame next to a training frame
    assert set(config[split["train"]]) == set(config[split["test"]]) == set(range(5))
    assert adjacent_fraction(labels, split) == 0.0
    assert adjacent_fraction(labels, split, near="val") == pytest.approx(5 / 60)
    # the paper's frame-level split: most test frames have a training neighbour
    paper = make_split(labels, "paper", seed=0)
    assert adjacent_fraction(labels, paper) > 0.7
    # as released, validation is the test set
    released = make_split(labels, "drive", as_released=True)
    np.testing.assert_array_equal(released["val"], released["test"])
    assert len(released["train"]) == 5 * 28


def test_drive_split_needs_the_frame_index():
    labels = fixture_labels(40, 32)
    del labels["frame_index"]
    with pytest.raises(DatasetError, match="frame_index"):
        make_split(labels, "drive")


def test_held_out_config_needs_configurations():
    labels = fixture_labels(30, 32, configs=2)
    with pytest.raises(DatasetError, match="at least 3 configurations"):
        make_split(labels, "held-out-config")
    with pytest.raises(ValueError, match="unknown split"):
        make_split(labels, "random")


def test_split_roundtrip(tmp_path):
    split = make_split(fixture_labels(50, 32), "paper")
    save_split(tmp_path / "split.npz", split)
    loaded = load_split(tmp_path / "split.npz")
    for key in ("train", "val", "test"):
        assert loaded[key].dtype == np.int64
        np.testing.assert_array_equal(loaded[key], split[key])


# ---------------------------------------------------------------------------
# Average baseline statistics
# ---------------------------------------------------------------------------
def test_training_statistics_and_the_release_bug(tmp_path):
    labels = fixture_labels(60, 32)
    targets = targets_from_labels(labels)
    train = np.arange(10, 50)
    stats = training_statistics(targets, train)
    assert stats["targets"] == list(TARGETS) and stats["num_train"] == 40
    np.testing.assert_allclose(stats["mean"]["fx"], targets["fx"][train].mean(), rtol=1e-6)
    np.testing.assert_allclose(stats["std"]["X"], targets["X"][train].std(), rtol=1e-5)
    # Release bug: parameter i <- mean of the 13 labels of training sample i.
    sample_3 = np.mean([targets[name][train[3]] for name in TARGETS])
    np.testing.assert_allclose(stats["release_average"][TARGETS[3]], sample_3, rtol=1e-5)
    save_statistics(tmp_path / "s.json", stats)
    assert load_statistics(tmp_path / "s.json") == stats
    mean = average_predictions(stats, 7)
    assert mean["tz"].shape == (7,) and np.all(mean["tz"] == np.float32(stats["mean"]["tz"]))
    release = average_predictions(stats, 2, kind="release")
    assert release["pitch"][0] == np.float32(stats["release_average"]["pitch"])
    with pytest.raises(ValueError, match="unknown Average kind"):
        average_predictions(stats, 2, kind="median")


def test_release_average_comes_from_the_release_labels():
    labels = released_frame_labels(fixture_labels(60, 32))
    paper = targets_from_labels(labels)
    released = targets_from_labels(labels, as_released=True)
    order = np.random.default_rng(5).permutation(np.arange(10, 50))
    stats = training_statistics(paper, order, release_targets=released)
    # the means are the paper targets' ...
    np.testing.assert_allclose(stats["mean"]["tz"], paper["tz"][order].mean(), rtol=1e-5)
    # ... the release's bug averages the release's 13 labels of sample i
    for i, name in enumerate(TARGETS):
        expected = np.mean([released[t][order[i]] for t in TARGETS])
        np.testing.assert_allclose(stats["release_average"][name], expected, rtol=1e-5)
    assert stats["release_average"] != training_statistics(paper, order)["release_average"]


def test_training_writes_the_release_average_of_the_release_labels(tmp_path):
    """train_stats.json's release_average: as-released targets, shuffled training order."""
    import json

    from cpl_keras.datasets import load_split
    from cpl_keras.training import train

    labels = released_frame_labels(fixture_labels(30, 16))
    path = write_stereo_fixture(tmp_path / "d.h5", n=30, image_size=16, labels=labels)
    run_dir = tmp_path / "run"
    train(path, variant="baseline", run_dir=str(run_dir), backbone="small", epochs=1,
          batch_size=19, seed=2, verbose=0)          # one batch: the 19 training pairs
    with open(run_dir / "train_stats.json") as f:
        stats = json.load(f)
    split = load_split(run_dir / "split.npz")
    order = np.random.default_rng(2).permutation(split["train"])
    released = targets_from_labels(labels, as_released=True)
    paper = targets_from_labels(labels)
    for i, name in enumerate(TARGETS):
        # parameter i <- the mean of the release's 13 labels of training sample i
        expected = np.mean([np.float64(released[t][order[i]]) for t in TARGETS])
        assert stats["release_average"][name] == pytest.approx(expected, rel=1e-6)
        assert stats["mean"][name] == pytest.approx(
            np.mean(paper[name][split["train"]].astype(np.float64)), rel=1e-5)
    # the evaluation scores the buggy row against the release's truth, the
    # plain Average (of a paper-mode run) against the paper's
    from cpl_keras.evaluation import make_table

    rows = make_table(1, [str(run_dir)], geometric=False).rows
    test = split["test"]
    bug, plain = rows["Average (release bug)"], rows["Average"]
    assert bug["as_released"] is True and plain["as_released"] is False
    for name in ("tx", "pitch", "X"):
        truth = released[name][test].astype(np.float64)
        assert bug["targets"][name]["mae"] == pytest.approx(
            np.mean(np.abs(truth - np.float32(stats["release_average"][name]))), rel=1e-5)
        assert bug["targets"][name]["mean"] == pytest.approx(truth.mean(), rel=1e-5)
        assert plain["targets"][name]["mean"] == pytest.approx(
            paper[name][test].astype(np.float64).mean(), rel=1e-5)


# ---------------------------------------------------------------------------
# StereoSequence
# ---------------------------------------------------------------------------
def test_sequence_batches_shuffles_and_pads(tmp_path):
    from cpl_keras.training.sequence import StereoSequence

    path = write_stereo_fixture(tmp_path / "d.h5", n=30, image_size=(16, 24))
    targets = targets_from_labels(fixture_labels(30, 24))
    indices = np.arange(3, 26)  # 23 pairs
    seq = StereoSequence(path, indices, targets, batch_size=5, shuffle=True, seed=7)
    assert len(seq) == 5
    x, y = seq[0]
    assert x["left_image"].shape == (5, 16, 24, 3) and x["left_image"].dtype == np.float32
    assert set(y) == set(TARGETS) and y["X"].shape == (5, 1)
    # Targets line up with the images read for the same pairs.
    from cpl_keras.data.storage import StereoFile

    with StereoFile(path) as f:
        left, _ = f.read_pairs(seq.batch_indices(0))
    np.testing.assert_array_equal(x["left_image"], left.astype(np.float32))
    np.testing.assert_array_equal(y["fx"][:, 0], targets["fx"][seq.batch_indices(0)])
    epoch0 = np.concatenate([seq.batch_indices(i) for i in range(len(seq))])
    assert sorted(epoch0) == list(indices)
    seq.on_epoch_end()
    epoch1 = np.concatenate([seq.batch_indices(i) for i in range(len(seq))])
    assert sorted(epoch1) == list(indices) and not np.array_equal(epoch0, epoch1)
    # The order of an epoch depends only on (seed, epoch): resuming replays it.
    seq.set_epoch(0)
    np.testing.assert_array_equal(seq.order(), epoch0)
    # Under 2 devices every batch divides: batch 5 -> 6, the last batch padded.
    padded = StereoSequence(path, indices, targets, batch_size=5, multiple_of=2)
    assert padded.batch_size == 6 and len(padded) == 4
    assert len(padded.batch_indices(3)) == 6  # 5 real pairs + 1 repeated
    with pytest.raises(IndexError):
        padded[4]
    seq.close()
    padded.close()


def test_sequence_with_threads_matches_single_reader(tmp_path):
    import keras

    from cpl_keras.training.sequence import StereoSequence

    path = write_stereo_fixture(tmp_path / "d.h5", n=24, image_size=16)
    targets = targets_from_labels(fixture_labels(24, 16))
    one = StereoSequence(path, np.arange(24), targets, batch_size=4)
    many = StereoSequence(path, np.arange(24), targets, batch_size=4, workers=3)
    from keras.src.trainers.data_adapters.py_dataset_adapter import PyDatasetAdapter

    adapter = PyDatasetAdapter(many)
    adapter.on_epoch_begin()
    batches = list(adapter.get_numpy_iterator())
    adapter.on_epoch_end()
    assert len(batches) == 6
    for i, (x, y) in enumerate(batches):
        np.testing.assert_array_equal(x["right_image"], one[i][0]["right_image"])
        np.testing.assert_array_equal(y["Y"], one[i][1]["Y"])
    assert isinstance(many, keras.utils.PyDataset)


def test_closing_a_sequence_stops_its_readers(tmp_path, monkeypatch):
    """``close()`` while a thread loads the images into memory stops the load
    at its next block (a Ctrl-C of train.py --workers 2 waited for the whole
    load, then the process was ended without the resume line); a closed
    streaming sequence does not open its file again for a reading thread
    that Keras left running."""
    import threading
    import time

    from cpl_keras.data.storage import StereoFile
    from cpl_keras.training import sequence

    path = write_stereo_fixture(tmp_path / "d.h5", n=40, image_size=16)
    targets = targets_from_labels(fixture_labels(40, 16))
    read, reading = StereoFile.read_pairs, threading.Event()

    def slow_read(self, indices):
        reading.set()
        time.sleep(0.2)
        return read(self, indices)

    monkeypatch.setattr(StereoFile, "read_pairs", slow_read)
    monkeypatch.setattr(sequence, "LOAD_BLOCK", 4)  # 10 blocks: 2 s
    seq = sequence.StereoSequence(path, np.arange(40), targets, batch_size=8, in_memory=True)
    errors = []

    def load():
        try:
            seq[0]
        except ValueError as error:
            errors.append(str(error))

    loader = threading.Thread(target=load)
    loader.start()
    assert reading.wait(timeout=10)
    start = time.monotonic()
    seq.close()
    waited = time.monotonic() - start
    loader.join(timeout=10)
    assert waited < 1.0, waited
    assert errors == [f"the sequence of {seq.path} is closed"]
    monkeypatch.undo()
    streaming = sequence.StereoSequence(path, np.arange(40), targets, batch_size=8,
                                        in_memory=False)
    assert streaming[0][0]["left_image"].shape == (8, 16, 16, 3)
    streaming.close()
    with pytest.raises(ValueError, match="closed"):
        streaming[1]
    assert streaming._file is None


def test_sequence_memory_does_not_grow_with_the_dataset(tmp_path):
    from cpl_keras.training.sequence import StereoSequence

    peaks = []
    for n in (40, 400):
        path = write_stereo_fixture(tmp_path / f"d{n}.h5", n=n, image_size=32)
        targets = targets_from_labels(fixture_labels(n, 32))
        seq = StereoSequence(path, np.arange(n), targets, batch_size=8, shuffle=True,
                             in_memory=False)
        seq[0]
        tracemalloc.start()
        for i in range(len(seq)):
            seq[i]
        peaks.append(tracemalloc.get_traced_memory()[1])
        tracemalloc.stop()
        seq.close()
    image_bytes = 400 * 32 * 32 * 3 * 2
    assert peaks[1] < 2 * peaks[0] + 100_000, peaks
    assert peaks[1] < image_bytes / 4, peaks


def test_numpy_modules_do_not_import_keras():
    import subprocess

    code = ("import sys, cpl_keras.datasets, cpl_keras.baselines; "
            "sys.exit(1 if 'keras' in sys.modules else 0)")
    result = subprocess.run([sys.executable, "-c", code], cwd=os.path.dirname(os.path.dirname(
        os.path.abspath(__file__))), timeout=600)
    assert result.returncode == 0


def test_malformed_hdf5_objects_are_named_in_one_line(tmp_path):
    import h5py

    from cpl_keras.data.storage import DatasetError, StereoFile

    path = tmp_path / "odd.h5"
    with h5py.File(path, "w") as f:
        f.create_group("left")
        f.create_dataset("right", data=np.zeros((2, 8, 8, 3), np.uint8))
    with pytest.raises(DatasetError, match="'/left' is not an array"):
        StereoFile(path)
    with h5py.File(path, "w") as f:
        for side in ("left", "right"):
            f.create_dataset(side, data=np.zeros((2, 8, 8, 3), np.uint8))
        f.create_group("labels").create_dataset("fx", data=np.array([b"a", b"b"]))
    with pytest.raises(DatasetError, match="label 'fx' is not a numeric array"):
        StereoFile(path)


def test_sequence_in_memory_serves_the_same_batches(tmp_path, monkeypatch):
    from cpl_keras.training import sequence
    from cpl_keras.training.sequence import StereoSequence

    n = 60
    path = write_stereo_fixture(tmp_path / "d.h5", n=n, image_size=32)
    targets = targets_from_labels(fixture_labels(n, 32))
    indices = np.random.default_rng(3).permutation(n)[:37]
    streamed = StereoSequence(path, indices, targets, batch_size=8, shuffle=True, seed=5,
                              multiple_of=3, in_memory=False)
    cached = StereoSequence(path, indices, targets, batch_size=8, shuffle=True, seed=5,
                            multiple_of=3, in_memory=True)
    assert not streamed.in_memory and cached.in_memory
    for epoch in (0, 1):
        streamed.set_epoch(epoch)
        cached.set_epoch(epoch)
        for i in range(len(streamed)):
            (xs, ys), (xc, yc) = streamed[i], cached[i]
            for key in xs:
                np.testing.assert_array_equal(xs[key], xc[key])
                assert xc[key].dtype == np.float32
            for key in ys:
                np.testing.assert_array_equal(ys[key], yc[key])
    # "auto" keeps the images when they fit under the limit, streams otherwise
    pair_bytes = 2 * 32 * 32 * 3
    monkeypatch.setattr(sequence, "IN_MEMORY_LIMIT", 37 * pair_bytes)
    assert StereoSequence(path, indices, targets).in_memory
    monkeypatch.setattr(sequence, "IN_MEMORY_LIMIT", 37 * pair_bytes - 1)
    assert not StereoSequence(path, indices, targets).in_memory
    with pytest.raises(ValueError, match="in_memory"):
        StereoSequence(path, indices, targets, in_memory="yes")


def test_labels_no_camera_has_are_refused_naming_the_label_and_count(tmp_path):
    from cpl_keras.data.storage import DatasetError
    from cpl_keras.datasets import targets_from_labels
    from cpl_keras.training import plan_run
    from helpers import fixture_labels, write_stereo_fixture

    labels = fixture_labels(40, 32)
    for name, value in (("fx", -100.0), ("disparity", 0.0), ("fy", 0.0), ("baseline", -1.0)):
        bad = dict(labels, **{name: labels[name].copy()})
        bad[name][[3, 7]] = value
        with pytest.raises(DatasetError, match=f"label '{name}' is not positive on 2 of 40 "
                           "pairs, which no camera has"):
            targets_from_labels(bad)
    nan = dict(labels, tz=labels["tz"].copy())
    nan["tz"][0] = np.nan
    with pytest.raises(DatasetError, match="target 'tz' has non-finite values on 1 of 40"):
        targets_from_labels(nan)
    # as released, the disparity is StereoBM's mean: negative is what it is;
    # and the baseline is tx, a signed difference
    assert (targets_from_labels(labels, as_released=True)["disparity"] < 0).any()
    backwards = dict(labels, baseline=-labels["baseline"])
    assert (targets_from_labels(backwards, as_released=True)["baseline"] < 0).all()
    # a real set's pair without a measured disparity says so (disparity_valid 0)
    unmeasured = dict(labels, disparity=labels["disparity"].copy(),
                      disparity_valid=np.ones(40, np.int32))
    unmeasured["disparity"][5] = 0.0
    unmeasured["disparity_valid"][5] = 0
    assert targets_from_labels(unmeasured)["disparity"][5] == 0.0
    # training refuses such a file before anything is written
    bad = dict(labels, fx=labels["fx"].copy())
    bad["fx"][0] = -100.0
    data = write_stereo_fixture(tmp_path / "bad.h5", labels=bad)
    with pytest.raises(DatasetError, match="bad.h5: label 'fx' is not positive on 1 of 40"):
        plan_run(data, variant="baseline", run_dir=str(tmp_path / "run"), backbone="small")
    assert not (tmp_path / "run").exists()
