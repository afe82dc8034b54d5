"""KITTI loaders on fixtures in KITTI's own file formats (tests/fixtures/kitti)."""

import os
import shutil

import cv2
import numpy as np
import pytest

from cpl_keras.camera import image_to_world
from cpl_keras.data.storage import StereoFile
from cpl_keras.commands import real_build
from cpl_keras.real import kitti
from helpers import (
    KITTI_CAM_TO_CAM as CAM_TO_CAM, KITTI_HEIGHT as HEIGHT, KITTI_OBJECT as OBJECT,
    KITTI_WIDTH as WIDTH, kitti_image, kitti_stereo_root,
)

SIZE = 32
FX, B = 721.5377, (44.85728 + 339.5242) / 721.5377


def test_calibration_files_parse_in_both_formats():
    raw = kitti.read_calib_file(CAM_TO_CAM)
    assert raw["calib_time"] == "09-Jan-2012 13:57:47"
    assert raw["P_rect_02"].shape == (12,) and raw["S_rect_02"].tolist() == [1242.0, 375.0]
    obj = kitti.read_calib_file(OBJECT)
    for calib, path in ((raw, CAM_TO_CAM), (obj, OBJECT)):
        P2, P3 = kitti.projection_matrices(calib, path)
        rig = kitti.rig_from_projections(P2, P3)
        assert rig["fx"] == pytest.approx(FX) and rig["u0"] == pytest.approx(609.5593)
        assert rig["baseline"] == pytest.approx(B, rel=1e-9)          # 0.5327 m
        # the exact camera offset (K^-1 P[:, 3]) agrees with KITTI's formula
        assert rig["ty"] == pytest.approx(-B, rel=1e-3)
        assert abs(rig["tx"]) < 1e-3 and abs(rig["tz"]) < 5e-3
    # the unrectified cameras' distance agrees with the rectified baseline
    assert kitti.raw_baseline(raw, CAM_TO_CAM) == pytest.approx(B, rel=2e-3)


@pytest.mark.parametrize("calib", ["cam_to_cam", "object"])
def test_stereo_2015_layout(tmp_path, calib):
    root = kitti_stereo_root(tmp_path, calib)
    out = kitti.build_kitti(root, tmp_path / "k.h5", image_size=SIZE)
    with StereoFile(out) as data:
        labels = data.labels
        assert data.num_pairs == 2
        assert data.metadata["rectified"] is True
    sx, sy = SIZE / WIDTH, SIZE / HEIGHT
    np.testing.assert_allclose(labels["fx"], FX * sx, rtol=1e-6)
    np.testing.assert_allclose(labels["fy"], FX * sy, rtol=1e-6)
    np.testing.assert_allclose(labels["baseline"], B, rtol=1e-6)
    assert np.all(labels["pitch"] == 0)
    # frame _10 has disp_occ_0: the valid pixel nearest the centre (399, 200)
    assert labels["disparity_valid"].tolist() == [1, 0]
    assert labels["disparity"][0] == pytest.approx(12.5 * sx, rel=1e-5)
    assert labels["u_left"][0] == pytest.approx((399 + 0.5) * sx - 0.5, abs=1e-4)
    assert labels["u"][0] == pytest.approx((399 - 12.5 + 0.5) * sx - 0.5, abs=1e-4)
    assert labels["v"][0] == pytest.approx((200 + 0.5) * sy - 0.5, abs=1e-4)
    # the point: depth fx b / d at full resolution
    assert labels["X"][0] == pytest.approx(FX * B / 12.5, rel=1e-4)
    eq = image_to_world(*(float(labels[k][0]) for k in (
        "fx", "fy", "u0", "v0", "baseline", "disparity", "pitch", "tx", "ty", "tz", "u", "v")))
    np.testing.assert_allclose(eq, [labels[k][0] for k in "XYZ"], rtol=1e-4, atol=1e-4)
    # frame _11 has no ground truth: undefined, never invented
    assert labels["disparity"][1] == 0 and labels["X"][1] == 0


def test_raw_layout(tmp_path):
    drive = tmp_path / "2011_09_26" / "2011_09_26_drive_0001_sync"
    for cam in ("image_02", "image_03"):
        (drive / cam / "data").mkdir(parents=True)
        cv2.imwrite(str(drive / cam / "data" / "0000000000.png"), kitti_image(cam == "image_03"))
    shutil.copy(CAM_TO_CAM, tmp_path / "2011_09_26" / "calib_cam_to_cam.txt")
    out = tmp_path / "raw.h5"
    assert real_build.main(["kitti", "--layout", "raw", "--root", str(tmp_path), "--image-size",
                       str(SIZE), "--out", str(out)]) == 0
    with StereoFile(out) as data:
        labels, meta = data.labels, data.metadata
    assert labels["disparity_valid"].tolist() == [0]
    assert labels["baseline"][0] == pytest.approx(B, rel=1e-6)
    check = next(iter(meta["calibration_checks"].values()))
    assert check["T_02_T_03_distance_m"] == pytest.approx(B, rel=2e-3)
    assert meta["names"] == ["2011_09_26_drive_0001_sync/0000000000"]


def _fails(argv, capsys, *needles):
    assert real_build.main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("python -m cpl_keras.real.build: error: ") and "\n" not in err, err
    for needle in needles:
        assert needle in err, err


def test_bad_kitti_inputs(tmp_path, capsys):
    root = kitti_stereo_root(tmp_path / "k")
    out = tmp_path / "bad.h5"
    args = ["kitti", "--root", str(root), "--image-size", str(SIZE), "--out", str(out)]
    calib = root / "training" / "calib_cam_to_cam" / "000000.txt"
    # malformed calibration: a value that is not a number, a short matrix, no P_rect_03
    text = open(CAM_TO_CAM).read()
    calib.write_text(text.replace("P_rect_03: 7.215377e+02", "P_rect_03: 7.2x5377e+02"))
    _fails(args, capsys, str(calib), "P_rect_03", "non-numeric")
    calib.write_text(text.replace(" 2.729905e-03\n", "\n"))
    _fails(args, capsys, "P_rect_03 must hold 12 numbers")
    calib.write_text("\n".join(l for l in text.splitlines() if not l.startswith("P_rect_03")))
    _fails(args, capsys, "no P_rect_03 or P3")
    calib.write_text("calib_time 09-Jan-2012\n")
    _fails(args, capsys, "line 1 is not 'key: values'")
    # missing calibration file, missing right image
    os.remove(calib)
    _fails(args, capsys, "missing calibration file", "000000.txt")
    shutil.copy(CAM_TO_CAM, calib)
    os.remove(root / "training" / "image_3" / "000000_11.png")
    _fails(args, capsys, "missing right image", "000000_11.png")
    assert not out.exists() and not os.path.exists(str(out) + ".partial")
    _fails(["kitti", "--out", str(out)], capsys, "--root is required")


def test_calibration_in_a_separate_root(tmp_path, capsys):
    """KITTI ships the calibration as an archive of its own: --kitti-calib
    finds it unpacked elsewhere, and without it the missing file is named."""
    root = kitti_stereo_root(tmp_path / "images", "cam_to_cam")
    separate = tmp_path / "calib_archive" / "training" / "calib_cam_to_cam"
    separate.mkdir(parents=True)
    shutil.move(str(root / "training" / "calib_cam_to_cam" / "000000.txt"), separate)
    out = tmp_path / "k.h5"
    assert real_build.main(["kitti", "--root", str(root), "--out", str(out), "--image-size",
                       str(SIZE)]) == 2
    assert "missing calibration file" in capsys.readouterr().err and not out.exists()
    assert real_build.main(["kitti", "--root", str(root), "--out", str(out), "--image-size",
                       str(SIZE), "--kitti-calib", str(tmp_path / "calib_archive")]) == 0
    with StereoFile(out) as data:
        np.testing.assert_allclose(data.labels["fx"], FX * SIZE / WIDTH, rtol=1e-6)


def test_raw_calibration_in_a_separate_root(tmp_path):
    """KITTI raw: the date's calib_cam_to_cam.txt found under --kitti-calib."""
    drive = tmp_path / "raw" / "2011_09_26" / "2011_09_26_drive_0001_sync"
    for cam in ("image_02", "image_03"):
        (drive / cam / "data").mkdir(parents=True)
        cv2.imwrite(str(drive / cam / "data" / "0000000000.png"), kitti_image(cam == "image_03"))
    (tmp_path / "calib" / "2011_09_26").mkdir(parents=True)
    shutil.copy(CAM_TO_CAM, tmp_path / "calib" / "2011_09_26" / "calib_cam_to_cam.txt")
    out = tmp_path / "raw.h5"
    assert real_build.main(["kitti", "--layout", "raw", "--root", str(tmp_path / "raw"),
                       "--image-size", str(SIZE), "--out", str(out), "--kitti-calib",
                       str(tmp_path / "calib")]) == 0
    with StereoFile(out) as data:
        assert data.labels["baseline"][0] == pytest.approx(B, rel=1e-6)
