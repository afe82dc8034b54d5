"""Real data: Middlebury crops, Tsinghua-Daimler / Cityscapes layout, the CLI."""

import os

import cv2
import numpy as np
import pytest

from cpl_keras.camera import image_to_camera, image_to_world
from cpl_keras.data.storage import StereoFile
from cpl_keras.frames import crop_resize_coordinate
from cpl_keras.commands import real_build
from cpl_keras.real import build
from cpl_keras.real import middlebury, tsinghua_cityscapes
from cpl_keras.stereo_camera import StereoCamera
from helpers import tsinghua_root

SIZE = 32


@pytest.fixture(scope="module")
def middlebury_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("mb") / "middlebury.h5"
    return middlebury.build_middlebury(path, crops=12, image_size=SIZE, seed=3)


def test_crop_resize_intrinsics_by_hand():
    # crop at (10, 20), 200 x 100 px, resized to 50 x 50: sx = 0.25, sy = 0.5
    full = StereoCamera(fx=400.0, fy=400.0, u0=110.0, v0=70.0, width=640, height=480,
                        baseline=0.1, pitch=0.0, tx=0.0, ty=-0.1, tz=0.0)
    crop = full.crop(10, 20, 200, 100)
    assert crop.resize_scales(50, 50) == (0.25, 0.5)
    small = crop.resize(50, 50)
    assert (small.fx, small.fy, small.width, small.height) == (100.0, 200.0, 50, 50)
    assert small.u0 == pytest.approx((110.0 - 10 + 0.5) * 0.25 - 0.5)
    assert small.v0 == pytest.approx((70.0 - 20 + 0.5) * 0.5 - 0.5)


def test_middlebury_point_reprojects_to_same_3d_point(middlebury_file):
    left, right, disparity, cal = middlebury.load_motorcycle()
    f, cx0, cy, doffs, b = (cal[k] for k in ("focal", "cx0", "cy", "doffs", "baseline"))
    with StereoFile(middlebury_file) as data:
        labels = data.labels
        assert data.image_shape == (SIZE, SIZE, 3)
        n = data.num_pairs
    for i in range(n):
        x0, y0 = labels["crop_x0"][i], labels["crop_y0"][i]
        sx = SIZE / labels["crop_width"][i]
        sy = SIZE / labels["crop_height"][i]
        # the ground-truth pixel of the original left image, from the stored labels
        u_left_full = (labels["u_left"][i] + 0.5) / sx - 0.5 + x0
        v_full = (labels["v"][i] + 0.5) / sy - 0.5 + y0
        iu, iv = int(round(u_left_full)), int(round(v_full))
        assert abs(u_left_full - iu) < 1e-2 and abs(v_full - iv) < 1e-2
        d = disparity[iv, iu]
        assert np.isfinite(d)
        # before the transform: left camera, Middlebury depth Z = b f / (d + doffs)
        before = np.array(image_to_camera(f, f, cx0, cy, b, d + doffs, iu, iv))
        assert before[0] == pytest.approx(b * f / (d + doffs))
        # after the transform: the stored labels through Eqs. 4a-5c
        after = np.array(image_to_world(*(labels[k][i] for k in (
            "fx", "fy", "u0", "v0", "baseline", "disparity", "pitch", "tx", "ty", "tz",
            "u", "v"))))
        np.testing.assert_allclose(after, before, rtol=2e-4, atol=2e-4)
        np.testing.assert_allclose(after, [labels[k][i] for k in "XYZ"], rtol=1e-5, atol=1e-5)
        # the right-image pixel is the left one shifted by the Middlebury disparity
        assert labels["u"][i] == pytest.approx(labels["u_left"][i] - d * sx, abs=1e-3)
    assert np.all(labels["ty"] == np.float32(-b)) and np.all(labels["pitch"] == 0)


def test_middlebury_uses_true_right_image(middlebury_file):
    left, right, _, _ = middlebury.load_motorcycle()
    with StereoFile(middlebury_file) as data:
        labels = data.labels
        full = np.flatnonzero((labels["crop_width"] == left.shape[1])
                              & (labels["crop_height"] == left.shape[0]))
        i = int(full[0]) if full.size else 0
        l_img, r_img = data.read_pairs([i])
    x0, y0 = int(labels["crop_x0"][i]), int(labels["crop_y0"][i])
    w, h = int(labels["crop_width"][i]), int(labels["crop_height"][i])
    expected = cv2.resize(right[y0:y0 + h, x0:x0 + w], (SIZE, SIZE), interpolation=cv2.INTER_AREA)
    np.testing.assert_array_equal(r_img[0], expected)
    assert not np.array_equal(l_img[0], r_img[0])




def test_tsinghua_layout_rig_labels(tmp_path):
    camera = tsinghua_root(tmp_path)
    out = tsinghua_cityscapes.build_stereo_dataset(tmp_path, tmp_path / "t.h5", image_size=SIZE, seed=1)
    with StereoFile(out) as data:
        labels = data.labels
        assert data.num_pairs == 2
    b = camera["extrinsic"]["baseline"]
    sx, sy = SIZE / 96, SIZE / 48
    np.testing.assert_allclose(labels["fx"], 120.0 * sx, rtol=1e-6)
    np.testing.assert_allclose(labels["fy"], 125.0 * sy, rtol=1e-6)
    np.testing.assert_allclose(labels["u0"], crop_resize_coordinate(47.0, 0, sx), rtol=1e-6)
    np.testing.assert_allclose(labels["disparity"], 8.0 * sx, rtol=1e-6)   # (p - 1) / 256 = 8
    np.testing.assert_allclose(labels["ty"], -b, rtol=1e-6)
    assert np.all(labels["pitch"] == 0) and np.all(labels["tx"] == 0)
    np.testing.assert_allclose(labels["u"], labels["u_left"] - 8.0 * sx, atol=1e-4)
    # the point is the left camera's: depth fx * b / d at full resolution
    np.testing.assert_allclose(labels["X"], 120.0 * b / 8.0, rtol=1e-5)


def test_tsinghua_vehicle_labels_match_dataset_camera_model(tmp_path):
    camera = tsinghua_root(tmp_path)
    out = tsinghua_cityscapes.build_stereo_dataset(tmp_path, tmp_path / "v.h5", image_size=SIZE,
                                        labels="vehicle", right="released")
    with StereoFile(out) as data:
        labels = data.labels
        left, right = data.read_pairs([0])
    e, k = camera["extrinsic"], camera["intrinsic"]
    assert labels["pitch"][0] == pytest.approx(e["pitch"])
    assert labels["tz"][0] == pytest.approx(e["z"])
    # the 3D point at full resolution, from the JSON, equals the stored one
    sx, sy = SIZE / 96, SIZE / 48
    u_full = (labels["u"][0] + 0.5) / sx - 0.5
    v_full = (labels["v"][0] + 0.5) / sy - 0.5
    full = image_to_world(k["fx"], k["fy"], k["u0"], k["v0"], e["baseline"], 8.0,
                          e["pitch"], e["x"], e["y"], e["z"], u_full, v_full)
    np.testing.assert_allclose([labels[n][0] for n in "XYZ"], full, rtol=1e-4)
    # the release's right image: left minus the disparity image's high byte, wrapping
    high = np.uint8((8 * 256 + 1) >> 8)
    expected = (left[0, :, -1].astype(np.int64) - int(high)) % 256
    np.testing.assert_array_equal(right[0, :, -1], expected)
    assert tsinghua_cityscapes.released_right(np.zeros((4, 4, 3), np.uint8),
                                   np.full((4, 4), 2 * 256 + 1, np.uint16), 4).max() == 254


def test_warp_moves_pixels_by_disparity():
    rng = np.random.default_rng(0)
    left = (rng.random((10, 40, 3)) * 255).astype(np.uint8)
    disparity = np.full((10, 40), 5.0)
    disparity[:, 20:] = 9.0                                   # a nearer region
    right, visible = tsinghua_cityscapes.warp_to_right(left, disparity)
    np.testing.assert_array_equal(right[:, 0:11], left[:, 5:16])   # right(u - 5) = left(u)
    np.testing.assert_array_equal(right[:, 11:31], left[:, 20:40]) # nearer region wins
    assert visible[:, 5:16].all() and visible[:, 20:].all()
    assert not visible[:, 16:20].any()                        # occluded by the near region
    np.testing.assert_array_equal(right[:, 31:], right[:, 30:31].repeat(9, 1))  # hole fill


def test_bad_inputs_one_line_errors(tmp_path, capsys):
    tsinghua_root(tmp_path, names=("x_1",))
    os.remove(tmp_path / "camera" / "test" / "tsinghuaDaimlerDataset" / "x_1_camera.json")
    out = tmp_path / "bad.h5"
    assert real_build.main(["tsinghua", "--root", str(tmp_path), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("python -m cpl_keras.real.build: error: missing") and "\n" not in err
    assert not out.exists() and not os.path.exists(str(out) + ".partial")

    broken = tmp_path / "broken"
    tsinghua_root(broken, camera={"intrinsic": {"fx": 1.0}, "extrinsic": {}})
    assert real_build.main(["cityscapes", "--root", str(broken), "--out", str(out)]) == 2
    assert "intrinsic" in capsys.readouterr().err and not out.exists()

    assert real_build.main(["tsinghua", "--out", str(out)]) == 2
    assert "--root is required" in capsys.readouterr().err
    (tmp_path / "file.txt").write_text("x")
    assert real_build.main(["middlebury", "--out", str(tmp_path / "file.txt" / "x.h5")]) == 2
    assert "is a file" in capsys.readouterr().err
    assert real_build.main(["tsinghua", "--root", str(tmp_path / "none"),
                       "--out", str(tmp_path / "new" / "x.h5")]) == 2
    assert "root not found" in capsys.readouterr().err and not (tmp_path / "new").exists()
    with pytest.raises(SystemExit) as exit_info:
        real_build.main(["middlebury", "--crops", "0", "--out", str(out)])
    assert exit_info.value.code == 2
    assert "--crops" in capsys.readouterr().err and not out.exists()
    with pytest.raises(SystemExit) as exit_info:
        real_build.main(["carla", "--out", str(out)])
    assert exit_info.value.code == 2


@pytest.mark.parametrize("limit", ["0", "-3"])
def test_a_limit_below_one_is_refused(tmp_path, capsys, limit):
    out = tmp_path / "m.h5"
    with pytest.raises(SystemExit) as exit_info:
        real_build.main(["middlebury", "--limit", limit, "--out", str(out)])
    assert exit_info.value.code == 2
    assert capsys.readouterr().err == ("python -m cpl_keras.real.build: error: argument --limit: "
                                       f"must be a positive integer, got {limit}\n")
    assert os.listdir(tmp_path) == []


def test_crops_beyond_the_free_disk_or_memory_are_refused_before_any_work(
        tmp_path, capsys, monkeypatch):
    from cpl_keras import cli
    from cpl_keras.real import chessboard, oakd

    def never(*args, **kwargs):
        raise AssertionError("started the work")

    for module, name in ((middlebury, "middlebury_samples"), (oakd, "oakd_samples"),
                         (chessboard, "calibrate")):
        monkeypatch.setattr(module, name, never)
    out = tmp_path / "m.h5"
    for source, crops in (("middlebury", "1000000000000"), ("oakd", "1000000000000"),
                          ("chessboard", "1000000000000")):
        assert real_build.main([source, "--crops", crops, "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert err.startswith("python -m cpl_keras.real.build: error: ") and \
            " crops at 112 px need at least " in err and " PB of disk; " in err, err
        assert err.count("\n") == 1
    monkeypatch.setattr(cli, "available_memory", lambda: 10**9)
    assert real_build.main(["middlebury", "--crops", "20000", "--out", str(out)]) == 2
    assert capsys.readouterr().err == ("python -m cpl_keras.real.build: error: 20000 crops at "
                                       "112 px need about 1.6 GB of memory; 1.0 GB is "
                                       "available\n")
    assert os.listdir(tmp_path) == []


def test_cli_builds_middlebury(tmp_path, capsys):
    out = tmp_path / "new" / "folder" / "m.h5"  # missing folders are created
    assert real_build.main(["middlebury", "--crops", "3", "--image-size", "32", "--out", str(out)]) == 0
    assert capsys.readouterr().out.strip() == str(out)
    with StereoFile(out) as data:
        assert data.num_pairs == 3
        assert "cpl_keras.real.build middlebury" in data.metadata["command"]


def test_build_all_keyword_api(tmp_path):
    """``build.build_all``: the sets named, their crops per source, a file
    kept unless ``force``, a root given for a set that needs one checked."""
    lines = []
    out = tmp_path / "real"
    paths = build.build_all(str(out), stems=("middlebury",), crops_per_source={"middlebury": 3},
                            image_size=32, seed=1, report=lines.append)
    assert paths == [str(out / "middlebury.h5")] and os.listdir(out) == ["middlebury.h5"]
    with StereoFile(paths[0]) as f:
        assert len(f) == 3 and f.read_pairs(np.arange(1))[0].shape == (1, 32, 32, 3)
    stamp = os.stat(paths[0]).st_mtime_ns
    build.build_all(str(out), stems=("middlebury",), image_size=32, report=lines.append)
    assert os.stat(paths[0]).st_mtime_ns == stamp and "exists, kept" in lines[-1]
    build.build_all(str(out), stems=("middlebury",), crops_per_source={"middlebury": 2},
                    image_size=32, force=True, report=lines.append)
    with StereoFile(paths[0]) as f:
        assert len(f) == 2
    with pytest.raises(ValueError, match="dataset root not found"):
        build.build_all(str(out), stems=(), roots={"kitti": str(tmp_path / "nowhere")},
                        report=lines.append)
