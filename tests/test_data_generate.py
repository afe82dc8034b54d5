"""generate_dataset: determinism, HDF5 round trip, atomic writes."""

import os
import signal
import subprocess
import sys

import h5py
import numpy as np
import pytest

from cpl_keras import camera, frames
from cpl_keras.data import blocks, generate
from cpl_keras.data.generate import generate_dataset, generate_file
from cpl_keras.data.pair import released_disparity
from cpl_keras.data.protocols import PROTOCOLS
from cpl_keras.data.storage import REQUIRED_LABELS, StereoFile
from helpers import REPO, wait_for_output


def _read(path):
    with h5py.File(path, "r") as f:
        return (f["left"][()], f["right"][()],
                {k: f["labels"][k][()] for k in f["labels"]})


def test_public_names():
    assert PROTOCOLS == ("cvgl", "random", "cameras", "wild", "zoom")


def test_cameras_protocol_squashes_real_aspect_ratios_into_fy():
    """cameras: fy / fx is the source image's aspect ratio (one of
    CAMERA_ASPECTS, +-5 %), so portrait and KITTI-wide rigs are both drawn;
    everything else as random, whose configurations are unchanged by it."""
    from cpl_keras.data import protocols

    configs = protocols.configurations("cameras", 0, 400, 64)
    assert len(configs) == 50
    ratios = np.array([c["fy"] / c["fx"] for c in configs])
    aspects = np.array([c["source_aspect"] for c in configs])
    assert set(aspects) <= set(protocols.CAMERA_ASPECTS) and len(set(aspects)) >= 6
    np.testing.assert_array_less(np.abs(ratios / aspects - 1), 0.05 + 1e-12)
    assert ratios.min() < 0.6 and ratios.max() > 3.0
    # the horizontal field of view is drawn as in random: fx from it
    fov = np.array([c["fov_deg"] for c in configs])
    np.testing.assert_allclose([c["fx"] for c in configs],
                               32 / np.tan(np.radians(fov) / 2), rtol=1e-9)
    random = protocols.configurations("random", 0, 400, 64)
    assert all(abs(c["fy"] / c["fx"] - 1) <= 0.05 + 1e-12 for c in random)
    assert "source_aspect" not in random[0]
    assert protocols.ranges("cameras")["source_aspects"] == list(protocols.CAMERA_ASPECTS)


def test_same_seed_same_bytes_with_any_worker_count(tmp_path):
    a = generate_dataset(tmp_path / "a.h5", protocol="random", pairs=6, seed=3, image_size=32,
                         workers=1, progress=False)
    b = generate_dataset(tmp_path / "b.h5", protocol="random", pairs=6, seed=3, image_size=32,
                         workers=2, progress=False)
    assert a == str(tmp_path / "a.h5")
    left_a, right_a, labels_a = _read(a)
    left_b, right_b, labels_b = _read(b)
    assert left_a.tobytes() == left_b.tobytes()
    assert right_a.tobytes() == right_b.tobytes()
    assert labels_a.keys() == labels_b.keys()
    for name in labels_a:
        assert labels_a[name].tobytes() == labels_b[name].tobytes(), name
    assert not np.array_equal(left_a, right_a)


def test_cached_dataset_is_made_once_under_its_versioned_name(tmp_path, monkeypatch):
    made, lines = [], []
    real = generate.generate_dataset
    monkeypatch.setattr(generate, "generate_dataset",
                        lambda out, **kw: made.append(out) or real(out, **kw))
    kwargs = dict(protocol="cvgl", pairs=4, seed=2, image_size=32, workers=1, progress=False)
    first = generate.cached_dataset(tmp_path / "cache", prefix="demo-", log=lines.append, **kwargs)
    version = generate.GENERATOR_VERSION
    assert os.path.basename(first) == f"demo-cvgl_4_32px_s2_v{version}.h5"
    assert len(made) == 1 and len(lines) == 1 and first in lines[0]
    with StereoFile(first) as data:
        assert data.num_pairs == 4 and data.metadata["seed"] == 2
    # the second call reuses the file; another seed is another file
    assert generate.cached_dataset(tmp_path / "cache", prefix="demo-", **kwargs) == first
    assert len(made) == 1
    other = generate.cached_dataset(tmp_path / "cache", **dict(kwargs, seed=3))
    assert os.path.basename(other) == f"cvgl_4_32px_s3_v{version}.h5" and len(made) == 2


_CACHED = """
import sys
from cpl_keras.data.generate import cached_dataset
path = cached_dataset(sys.argv[1], protocol="random", pairs=8, seed=0, image_size=16,
                      workers=1, progress=False,
                      log=lambda line: print(line, file=sys.stderr, flush=True))
print(path)
"""


def test_two_processes_wanting_one_cached_dataset_make_it_once(tmp_path):
    """Two processes that want the same cached dataset while a third holds
    its lock (making it): each says once that it waits, then one makes the
    file and the other takes it (two demonstration runs on an empty cache:
    the second failed on HDF5's lock of the first's temporary file)."""
    from filelock import FileLock

    cache = tmp_path / "cache"
    cache.mkdir()
    path = os.path.join(cache, generate.dataset_name("random", 8, 0, 16))
    lock = FileLock(path + ".lock")
    lock.acquire()
    try:
        processes = [subprocess.Popen([sys.executable, "-c", _CACHED, str(cache)], cwd=REPO,
                                      text=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                      env=dict(os.environ, KERAS_BACKEND="jax"))
                     for _ in range(2)]
        for process in processes:
            assert process.stderr.readline() == f"waiting for another process making {path}\n"
    finally:
        lock.release()
    outcomes = [process.communicate(timeout=120) for process in processes]
    assert [process.returncode for process in processes] == [0, 0], outcomes
    assert [out for out, _ in outcomes] == [path + "\n"] * 2
    made = [err for _, err in outcomes if err.startswith("generating 8 random pairs")]
    assert len(made) == 1 and sorted(err for _, err in outcomes)[0] == "", outcomes
    with StereoFile(path) as data:
        assert data.num_pairs == 8
    assert os.listdir(cache) == [os.path.basename(path)]  # (the lock removed)


def test_different_seeds_give_different_images(tmp_path):
    a = generate_dataset(tmp_path / "a.h5", pairs=3, seed=0, image_size=24, workers=1,
                         progress=False)
    b = generate_dataset(tmp_path / "b.h5", pairs=3, seed=1, image_size=24, workers=1,
                         progress=False)
    left_a, _, labels_a = _read(a)
    left_b, _, labels_b = _read(b)
    assert not np.array_equal(left_a, left_b)
    assert not np.array_equal(labels_a["fx"], labels_b["fx"])


@pytest.mark.parametrize("protocol", PROTOCOLS)
def test_round_trip_with_metadata(tmp_path, protocol):
    path = generate_dataset(tmp_path / "d.h5", protocol=protocol, pairs=5, seed=2,
                            image_size=32, workers=1, progress=False)
    with StereoFile(path) as data:
        assert len(data) == 5 and data.image_shape == (32, 32, 3)
        for name in REQUIRED_LABELS + ("yaw", "roll", "config_id", "town_id", "frame_index"):
            assert name in data.labels, name
        # every stored label is described
        assert set(data.labels) == set(generate.LABEL_DESCRIPTIONS)
        meta = data.metadata
        assert meta["protocol"] == protocol and meta["seed"] == 2 and meta["image_size"] == 32
        assert [t["name"] for t in meta["towns"]] == ["Town01", "Town02"]
        assert meta["generator_version"] == generate.GENERATOR_VERSION
        assert len(meta["configurations"]) == (50 if protocol == "cvgl" else 1)
        assert "fov_deg" in meta["ranges"]
        left, right = data.read_pairs([4, 0])
        assert left.shape == (2, 32, 32, 3) and left.dtype == np.uint8
        lab = data.labels
        X, Y, Z = camera.image_to_world(*(lab[k].astype(np.float64) for k in (
            "fx", "fy", "u0", "v0", "baseline", "disparity", "pitch", "tx", "ty", "tz", "u", "v")))
        np.testing.assert_allclose(X, lab["X"], rtol=1e-4, atol=1e-3)
        np.testing.assert_allclose(Y, lab["Y"], rtol=1e-4, atol=1e-3)
        np.testing.assert_allclose(Z, lab["Z"], rtol=1e-4, atol=1e-3)
        assert lab["config_id"].dtype == np.int32
    with h5py.File(path, "r") as f:
        assert f["labels/pitch"].attrs["unit"] == "rad"
        assert "degrees" in f["labels/pitch"].attrs["description"]
        assert f["labels/pitch_released"].attrs["unit"] == "deg"
        assert f["labels/tz_released"].attrs["unit"] == "m"
        assert f["labels/sky_at_release_pixel"].dtype == np.int32
        for name in f["labels"]:
            assert f["labels"][name].attrs["description"], name
        assert f["left"].chunks == (1, 32, 32, 3) and f["left"].compression == "gzip"
    # the release's pixel is kept only for the as-released labels
    np.testing.assert_array_equal(lab["u_released"], 16.0)
    np.testing.assert_array_equal(lab["v_released"], 16.0)
    np.testing.assert_array_equal(lab["yaw"], 0.0)
    np.testing.assert_array_equal(lab["roll"], 0.0)
    if protocol == "cvgl":
        np.testing.assert_array_equal(lab["baseline"], lab["tx"])
        np.testing.assert_array_equal(lab["baseline_released"], lab["tx_released"])


def _released_by_hand(protocol, cfg):
    """The release's extrinsics of a configuration, from the metadata."""
    if protocol == "cvgl":
        c = cfg["carla"]         # right camera minus the fixed left (2, 0, 1.4, -15 deg)
        tx = c["x"] - 2.0
        return {"baseline": tx, "tx": tx, "ty": c["y"] - 0.0, "tz": c["z"] - 1.4,
                "pitch": c["pitch_deg"] - (-15.0)}
    left = np.array(cfg["left_pose"]["position"])
    right = np.array(cfg["right_pose"]["position"])
    right_pitch = frames.euler_from_rotation(np.array(cfg["right_rotation"]))[0]
    return {"baseline": cfg["baseline"], "tx": right[0] - left[0], "ty": left[1] - right[1],
            "tz": right[2] - left[2],
            "pitch": np.degrees(cfg["left_pose"]["pitch"] - right_pitch)}


@pytest.mark.parametrize("protocol", PROTOCOLS)
def test_as_released_targets_reproduce_the_release_labels(tmp_path, protocol):
    """Release frame (vehicle-frame right-minus-left, CARLA conventions, degrees),
    StereoBM disparity and X, Y, Z at the release's pixel (W/2, H/2)."""
    from cpl_keras.datasets import targets_from_labels

    size = 32
    path = generate_dataset(tmp_path / "d.h5", protocol=protocol, pairs=6, seed=4,
                            image_size=size, workers=1, progress=False)
    with StereoFile(path) as data:
        lab = data.labels
        configs = data.metadata["configurations"]
    released = targets_from_labels(lab, as_released=True)
    paper = targets_from_labels(lab)
    for i in range(6):
        expected = _released_by_hand(protocol, configs[lab["config_id"][i]])
        for name, value in expected.items():
            assert released[name][i] == pytest.approx(value, rel=1e-5, abs=1e-5), (name, i)
    np.testing.assert_array_equal(released["disparity"], lab["disparity_released"])
    for name in ("fx", "fy", "u0", "v0"):
        np.testing.assert_array_equal(released[name], lab[name])
    params = {name: released[name].astype(np.float64) for name in camera.PARAMETERS}
    X, Y, Z = camera.image_to_world(**params, u=size / 2, v=size / 2)   # the release's pixel
    np.testing.assert_allclose(released["X"], X, rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(released["Y"], Y, rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(released["Z"], Z, rtol=1e-5, atol=1e-4)
    if protocol == "cvgl":
        # release tz is the height difference (-0.4..1.6 m); ours is far larger
        assert np.all((released["tz"] >= -0.4 - 1e-6) & (released["tz"] <= 1.6 + 1e-6))
        assert np.all(paper["tz"] > 1.0)
        np.testing.assert_allclose(released["pitch"], -np.degrees(paper["pitch"]), rtol=1e-4)
        np.testing.assert_allclose(released["ty"], -paper["ty"], rtol=1e-5)


def test_old_format_files_are_refused_with_a_one_line_hint(tmp_path):
    import json

    from cpl_keras.data.storage import DatasetError

    path = generate_dataset(tmp_path / "old.h5", protocol="cvgl", pairs=2, seed=0,
                            image_size=16, workers=1, progress=False)
    with StereoFile(path) as data:
        assert data.metadata["generator_version"] == generate.GENERATOR_VERSION
    with h5py.File(path, "r+") as f:
        meta = json.loads(f.attrs["metadata_json"])
        meta["generator_version"] = "1.0"
        f.attrs["metadata_json"] = json.dumps(meta)
    with pytest.raises(DatasetError) as error:
        StereoFile(path)
    message = str(error.value)
    assert "\n" not in message
    assert str(path) in message and "1.0" in message
    assert "python -m cpl_keras.data.generate --protocol cvgl --pairs 2" in message


def test_an_unknown_schema_version_is_refused_in_one_line_and_none_is_version_1(tmp_path):
    """A file whose ``schema_version`` is 99 (or not a number) is refused in
    one line that names it (it was read as if it were version 1); one
    without the attribute (older writers, files made by hand) still reads."""
    from cpl_keras.data.storage import SCHEMA_VERSION, DatasetError
    from helpers import write_stereo_fixture

    path = write_stereo_fixture(tmp_path / "data.h5", n=4, image_size=8)
    for version, said in ((99, "99 is not this reader's 1; a newer cpl-keras wrote it: "
                               "update cpl-keras to read it"),
                          ("two", "two is not this reader's 1 (not a layout it knows)")):
        with h5py.File(path, "r+") as f:
            f.attrs["schema_version"] = version
        with pytest.raises(DatasetError) as error:
            StereoFile(path)
        assert str(error.value) == f"{path}: dataset schema version {said}"
    with h5py.File(path, "r+") as f:
        del f.attrs["schema_version"]
    with StereoFile(path) as data:
        assert data.num_pairs == 4
    with h5py.File(path, "r+") as f:
        f.attrs["schema_version"] = SCHEMA_VERSION
    with StereoFile(path) as data:
        assert data.num_pairs == 4


def test_released_disparity_is_the_raw_stereobm_mean():
    import cv2

    rng = np.random.default_rng(0)
    left = rng.integers(0, 255, (48, 48, 3), dtype=np.uint8)
    right = np.roll(left, -4, axis=1)
    raw = cv2.StereoBM_create(numDisparities=16, blockSize=15).compute(
        cv2.cvtColor(left, cv2.COLOR_RGB2GRAY), cv2.cvtColor(right, cv2.COLOR_RGB2GRAY))
    value = released_disparity(left, right)
    assert value == pytest.approx(raw.mean())
    assert (raw == -16).any()                  # invalid pixels are part of the mean
    # too narrow for a match window: all invalid (OpenCV's output is undefined there)
    assert released_disparity(left[:20, :20], right[:20, :20]) == -16.0


def _crash_after_first_block(monkeypatch):
    """Blocks of 2 pairs, and a renderer that crashes at the second one;
    returns a callable that mends it (the blocks stay of 2 pairs)."""
    original = blocks.render_block
    calls = []

    def failing(*args):
        if calls:
            raise RuntimeError("renderer crashed")
        calls.append(1)
        return original(*args)

    monkeypatch.setattr(blocks, "BLOCK", 2)
    monkeypatch.setattr(blocks, "render_block", failing)
    return lambda: monkeypatch.setattr(blocks, "render_block", original)


def test_a_crash_keeps_the_partial_file_and_the_next_call_continues_it_byte_for_byte(
        tmp_path, monkeypatch):
    mend = _crash_after_first_block(monkeypatch)
    out = tmp_path / "d.h5"
    kwargs = dict(pairs=6, image_size=16, workers=1, progress=False)
    with pytest.raises(RuntimeError):
        generate_dataset(out, **kwargs)
    assert os.listdir(tmp_path) == ["d.h5.partial"]       # nothing under the final name
    with h5py.File(tmp_path / "d.h5.partial", "r") as f:
        assert f.attrs["pairs_complete"] == 2
    mend()
    lines = []
    assert generate_dataset(out, log=lines.append, **kwargs) == str(out)
    assert lines == [f"resuming {out}.partial at pair 2 of 6"]
    assert os.listdir(tmp_path) == ["d.h5"]
    (tmp_path / "whole").mkdir()
    whole = generate_dataset(tmp_path / "whole" / "d.h5", **kwargs)
    with open(out, "rb") as a, open(whole, "rb") as b:
        assert a.read() == b.read()                       # the very same file


def test_a_partial_file_of_other_arguments_is_refused_untouched_or_restarted(
        tmp_path, monkeypatch):
    mend = _crash_after_first_block(monkeypatch)
    out, partial = tmp_path / "d.h5", tmp_path / "d.h5.partial"
    kwargs = dict(pairs=6, image_size=16, workers=1, progress=False)
    with pytest.raises(RuntimeError):
        generate_dataset(out, seed=0, **kwargs)
    mend()
    before = partial.read_bytes()
    with pytest.raises(ValueError, match=r"d\.h5\.partial holds an interrupted run of other "
                       r"settings \(seed 0, not 1\); delete it, or start again with --restart$"):
        generate_dataset(out, seed=1, **kwargs)
    assert partial.read_bytes() == before and not out.exists()
    lines = []
    generate_dataset(out, seed=1, restart=True, log=lines.append, **kwargs)
    assert lines == [] and os.listdir(tmp_path) == ["d.h5"]
    with StereoFile(out) as data:
        assert data.metadata["seed"] == 1 and len(data) == 6


def test_an_unfinished_partial_file_is_refused_as_data_naming_the_command_that_finishes_it(
        tmp_path, monkeypatch, capsys):
    """Given to training or evaluation, an interrupted generation's
    ``.partial`` file (its other pairs zeros) is named as unfinished, with the
    command that made it; train.py says so in one line, exit 2 (it said that
    label 'fx' is not positive on the pairs never written)."""
    from cpl_keras.commands import train

    mend = _crash_after_first_block(monkeypatch)
    out = tmp_path / "d.h5"
    with pytest.raises(RuntimeError):
        generate_file(out, "cvgl", 6, 0, 16, 1, False,
                      "python -m cpl_keras.data.generate --pairs 6 --out d.h5")
    mend()
    line = (f"{out}.partial is an unfinished dataset (2 of 6 pairs written): finish it with the "
            "command that made it (python -m cpl_keras.data.generate --pairs 6 --out d.h5), "
            "then use the file without .partial")
    with pytest.raises(ValueError) as refused:
        StereoFile(f"{out}.partial")
    assert str(refused.value) == line
    capsys.readouterr()
    assert train.main(["--variant", "baseline", "--backbone", "small", "--data",
                       f"{out}.partial", "--run-dir", str(tmp_path / "run")]) == 2
    assert capsys.readouterr().err == f"cpl-train: error: {line}\n"
    assert os.listdir(tmp_path) == ["d.h5.partial"]


def test_an_unreadable_partial_file_is_started_again(tmp_path):
    out = tmp_path / "d.h5"
    (tmp_path / "d.h5.partial").write_bytes(b"\x89HDF\r\n\x1a\n" + b"x" * 100)
    lines = []
    generate_dataset(out, pairs=3, image_size=16, workers=1, progress=False, log=lines.append)
    assert lines == [f"{out}.partial cannot be read (an interrupted write); starting again "
                     "from the first pair"]
    assert os.listdir(tmp_path) == ["d.h5"]


def test_tables_beyond_the_free_memory_are_refused_before_any_work(tmp_path, monkeypatch):
    from cpl_keras import cli

    def never(*args):
        raise AssertionError("rendered a block")

    monkeypatch.setattr(blocks, "render_block", never)
    monkeypatch.setattr(cli, "available_memory", lambda: 10**6)
    # random: a rig every 8 pairs, its configuration held by the parent and each worker
    with pytest.raises(ValueError, match=r"^8000 random pairs at 16 px .* need about 24\.0 MB "
                       r"of memory; 1\.0 MB is available$"):
        generate_dataset(tmp_path / "d.h5", protocol="random", pairs=8000, image_size=16,
                         workers=2, progress=False)
    assert os.listdir(tmp_path) == []


def test_killed_write_leaves_no_file_at_final_path(tmp_path):
    out = tmp_path / "big.h5"
    proc = subprocess.Popen(
        [sys.executable, "-m", "cpl_keras.data.generate", "--pairs", "5000", "--image-size", "32",
         "--workers", "1", "--out", str(out)],
        cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    # killed while it writes: its progress bar shows the first block in big.h5.partial
    seen = wait_for_output(proc.stderr, "/5000 pairs")
    assert "/5000 pairs" in seen and (tmp_path / "big.h5.partial").exists(), seen
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=300)
    proc.stderr.close()
    assert not out.exists()


def test_generator_imports_no_deep_learning_backend():
    code = ("import sys\n"
            "import cpl_keras.data.generate, cpl_keras.data.preview\n"
            "from cpl_keras.data.pair import render_pair\n"
            "render_pair('cvgl', 0, 4, 32, 0)\n"
            "print(sorted({m.split('.')[0] for m in sys.modules} & "
            "{'keras', 'jax', 'tensorflow', 'torch'}))\n")
    result = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True,
                            text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "[]"


def test_configurations_own_contiguous_drives():
    from cpl_keras.data.protocols import config_of_pair, num_configs

    for protocol, pairs in (("cvgl", 120), ("random", 37)):
        ids = [config_of_pair(protocol, pairs, i) for i in range(pairs)]
        configs = [c for c, _ in ids]
        assert configs == sorted(configs)
        assert configs[-1] == num_configs(protocol, pairs) - 1
        for (c0, f0), (c1, f1) in zip(ids, ids[1:]):
            assert (f1 == f0 + 1) if c1 == c0 else (f1 == 0)


def test_a_dataset_of_other_settings_is_not_replaced_without_force(tmp_path):
    """The docs once made data/random.h5 twice with other settings, the
    second silently replacing the first: now another dataset at --out is
    refused in one line naming both, the same one is left as it is, and
    --force replaces it."""
    from cpl_keras.data.generate import generate_dataset
    from cpl_keras.data.storage import StereoFile

    out = str(tmp_path / "d.h5")
    generate_dataset(out, pairs=12, image_size=32, workers=1, progress=False)
    before = os.path.getmtime(out), open(out, "rb").read()
    lines = []
    assert generate_dataset(out, pairs=12, image_size=32, workers=1, progress=False,
                            log=lines.append) == out
    assert (os.path.getmtime(out), open(out, "rb").read()) == before
    assert lines and "already holds this dataset" in lines[-1]
    with pytest.raises(ValueError, match=r"d.h5 holds another dataset \(12 cvgl pairs at 32 px, "
                       r"seed 0, .*\), not 12 cvgl pairs at 32 px, seed 1, .*give --force"):
        generate_dataset(out, pairs=12, seed=1, image_size=32, workers=1, progress=False)
    assert open(out, "rb").read() == before[1]
    generate_dataset(out, pairs=12, seed=1, image_size=32, workers=1, progress=False,
                     force=True)
    with StereoFile(out) as f:
        assert f.metadata["seed"] == 1
