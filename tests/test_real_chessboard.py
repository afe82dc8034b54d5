"""The chessboard rig: labels derived from OpenCV's sample pairs, checked
against OpenCV's own calibration files and against the camera equations."""

import os
import re
import shutil

import numpy as np
import pytest

from cpl_keras.camera import image_to_world
from cpl_keras.frames import rotation_matrix
from cpl_keras.data.storage import StereoFile
from cpl_keras.frames import CV_TO_PROJECT, opencv_pose_to_rig
from cpl_keras.commands import chessboard as chessboard_command
from cpl_keras.commands import real_build
from cpl_keras.real import chessboard

SIZE = 32


def _yaml_matrix(path, key):
    text = open(path).read()
    block = re.search(rf"{key}: !!opencv-matrix.*?data: \[(.*?)\]", text, re.S).group(1)
    return np.array([float(v) for v in block.replace("\n", " ").split(",")])


@pytest.fixture(scope="module")
def cal():
    return chessboard.calibrate()


def test_copied_images_and_licence():
    names = sorted(os.listdir(chessboard.DATA_DIR))
    assert "LICENSE.opencv" in names and "README.md" in names
    assert len([n for n in names if n.endswith(".jpg")]) == 26
    size = sum(os.path.getsize(os.path.join(chessboard.DATA_DIR, n)) for n in names)
    assert size < 1_000_000
    # the pairs are the ones OpenCV's stereo_calib sample lists
    listed = re.findall(r'"(\w+\.jpg)"', open(os.path.join(chessboard.DATA_DIR, "stereo_calib.xml")).read())
    pairs = chessboard.find_pairs()
    assert [os.path.basename(p) for _, l, r in pairs for p in (l, r)] == listed


def test_calibration_matches_opencv_files(cal):
    """Tolerances measured: our left camera is within 0.2 px / 0.04 % of
    OpenCV's left_intrinsics.yml (the same single-camera model with the aspect
    ratio fixed); OpenCV's stereo sample (intrinsics.yml) forces one focal
    length on both cameras and a rational distortion model, so its fx lies
    between ours (536.1 left, 542.3 right) and its principal points differ
    by up to 7 px (left) and 14 px (right)."""
    assert cal["rms_px"] == pytest.approx(0.447, abs=0.01)
    assert len(cal["pairs"]) == 13 and not cal["skipped"]
    left = _yaml_matrix(os.path.join(chessboard.DATA_DIR, "left_intrinsics.yml"), "camera_matrix")
    K1, K2 = cal["K_left"], cal["K_right"]
    assert K1[0, 0] == pytest.approx(left[0], rel=1e-3)         # 536.07 vs 535.92
    assert K1[0, 2] == pytest.approx(left[2], abs=0.5)          # 342.37 vs 342.28
    assert K1[1, 2] == pytest.approx(left[5], abs=0.5)          # 235.53 vs 235.57
    stereo_m1 = _yaml_matrix(os.path.join(chessboard.DATA_DIR, "intrinsics.yml"), "M1")
    stereo_m2 = _yaml_matrix(os.path.join(chessboard.DATA_DIR, "intrinsics.yml"), "M2")
    for K, M in ((K1, stereo_m1), (K2, stereo_m2)):
        assert K[0, 0] == pytest.approx(M[0], rel=0.015)        # 534.8 vs 536.1 / 542.3
        assert K[1, 1] == pytest.approx(M[4], rel=0.015)
    assert K1[0, 2] == pytest.approx(stereo_m1[2], abs=8)       # 342.4 vs 335.7
    assert K2[1, 2] == pytest.approx(stereo_m2[5], abs=8)       # 247.0 vs 242.1
    rig = cal["rig"]
    assert rig["fx_left"] == pytest.approx(536.1, abs=0.5)
    assert rig["fx"] == pytest.approx(542.3, abs=0.5)
    # 3.344 squares of 25 mm to the right (y left, so negative), small rotation
    assert rig["baseline"] == pytest.approx(0.0836, abs=0.0005)
    assert rig["ty"] == pytest.approx(-rig["baseline"], rel=1e-3)
    assert abs(rig["tx"]) < 0.003 and abs(rig["tz"]) < 0.003
    assert rig["rotation_deg"] == pytest.approx(0.31, abs=0.05)
    assert abs(rig["pitch"]) < np.radians(0.1)


def test_extrinsics_match_an_epipolar_estimate(cal):
    """The rig's extrinsics against a second derivation that shares only the
    intrinsics (checked against OpenCV's files above): this test's own
    corner detection, the essential matrix of all 13 pairs' corners
    (findEssentialMat, recoverPose), and the metric scale from the board's
    25 mm squares triangulated with that unit-baseline pose. Measured: 84.8
    mm against 83.6, rotation 0.43 deg against 0.31 (0.19 deg apart),
    translation directions 0.2 deg apart."""
    import cv2

    board = (9, 6)
    left, right = [], []
    for _, path_l, path_r in chessboard.find_pairs():
        for path, found in ((path_l, left), (path_r, right)):
            grey = cv2.imread(path, cv2.IMREAD_GRAYSCALE)
            ok, corners = cv2.findChessboardCorners(grey, board)
            assert ok, path
            criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.01)
            corners = cv2.cornerSubPix(grey, corners, (11, 11), (-1, -1), criteria)
            found.append(corners.reshape(-1, 2))
    norm_l = cv2.undistortPoints(np.concatenate(left)[:, None], cal["K_left"], cal["D_left"])
    norm_r = cv2.undistortPoints(np.concatenate(right)[:, None], cal["K_right"], cal["D_right"])
    norm_l, norm_r = norm_l.reshape(-1, 2), norm_r.reshape(-1, 2)
    E, _ = cv2.findEssentialMat(norm_l, norm_r, np.eye(3), method=cv2.RANSAC, prob=0.999,
                                threshold=1e-3)
    _, R_e, t_e, _ = cv2.recoverPose(E, norm_l, norm_r, np.eye(3))
    P_left = np.hstack([np.eye(3), np.zeros((3, 1))])
    points = cv2.triangulatePoints(P_left, np.hstack([R_e, t_e]), norm_l.T, norm_r.T)
    grid = (points[:3] / points[3]).T.reshape(-1, board[1], board[0], 3)
    unit_spacing = np.median(np.linalg.norm(np.diff(grid, axis=2), axis=3))
    baseline = 0.025 / unit_spacing                     # |t_e| = 1 in the triangulation
    rig = cal["rig"]
    assert rig["baseline"] == pytest.approx(baseline, rel=0.03)
    angle = np.degrees(np.linalg.norm(cv2.Rodrigues(R_e)[0]))
    assert rig["rotation_deg"] == pytest.approx(angle, abs=0.2)
    between = np.degrees(np.linalg.norm(cv2.Rodrigues(R_e @ cal["R"].T)[0]))
    assert between < 0.3
    direction = cal["T"] / np.linalg.norm(cal["T"])
    assert np.degrees(np.arccos(np.clip(direction @ t_e.ravel(), -1, 1))) < 0.5


def test_pose_conversion_matches_rotation_convention():
    # a right camera pitched down by 0.2 rad and 0.1 m to the right of the left one
    R_lr = rotation_matrix(0.2, 0.05, -0.03)
    t = np.array([0.01, -0.1, 0.02])
    # OpenCV's extrinsics of that rig: X_right = R X_left + T (OpenCV axes)
    R_cv = CV_TO_PROJECT.T @ R_lr.T @ CV_TO_PROJECT
    T_cv = -R_cv @ (CV_TO_PROJECT.T @ t)
    R_back, t_back = opencv_pose_to_rig(R_cv, T_cv)
    np.testing.assert_allclose(R_back, R_lr, atol=1e-12)
    np.testing.assert_allclose(t_back, t, atol=1e-12)


def test_triangulated_points_lie_on_the_board(cal):
    """Triangulated corners keep the board's 25 mm spacing and reproject
    through the right camera to the detected corners (undistorted)."""
    for pair in cal["pairs"]:
        grid = pair["points"].reshape(6, 9, 3)
        spacing = np.linalg.norm(np.diff(grid, axis=1), axis=2)
        assert np.median(spacing) == pytest.approx(0.025, rel=0.01)
        assert np.all(pair["points"][:, 0] > 0.2) and np.all(pair["depth_right"] > 0.2)


def test_dataset_labels(tmp_path):
    out = chessboard.build_chessboard(tmp_path / "cb.h5", crops=3, image_size=SIZE, seed=1)
    with StereoFile(out) as data:
        labels, meta = data.labels, data.metadata
        assert data.num_pairs == 13 * 3 and data.image_shape == (SIZE, SIZE, 3)
        left, right = data.read_pairs([0])
    assert meta["rectified"] is False and meta["rig"] == "chessboard"
    assert meta["calibration"]["rms_px"] == pytest.approx(0.447, abs=0.01)
    full = np.arange(13 * 3) % 3 == 0                   # each pair's first sample
    assert np.all(labels["crop_width"][full] == 640)
    # whole image: fx scales by 32 / 640, u0 with the pixel-centre mapping
    rig = meta["calibration"]["rig_full_resolution"]
    np.testing.assert_allclose(labels["fx"][full], rig["fx"] * SIZE / 640, rtol=1e-5)
    np.testing.assert_allclose(labels["u0"][full], (rig["u0"] + 0.5) * SIZE / 640 - 0.5, rtol=1e-5)
    np.testing.assert_allclose(labels["ty"], rig["ty"], rtol=1e-5)
    # the whole-image pixel is the corner nearest the image centre, on the board
    assert np.all(np.abs(labels["u"][full] - (SIZE - 1) / 2) < SIZE / 4)
    # Eq. 4a: disparity = fx * b / xCam (right camera depth) ~ fx * b / X
    np.testing.assert_allclose(labels["disparity"], labels["fx"] * labels["baseline"] / labels["X"],
                               rtol=0.02)
    # Eqs. 4-5 on the labels land on the triangulated point up to what they
    # cannot model (lens distortion and yaw/roll of ~0.3 deg): measured max
    # 14 mm over all crops, 3 mm on the whole images.
    eq = np.array(image_to_world(*(labels[k].astype(np.float64) for k in (
        "fx", "fy", "u0", "v0", "baseline", "disparity", "pitch", "tx", "ty", "tz", "u", "v"))))
    truth = np.array([labels[k] for k in "XYZ"])
    error = np.abs(eq - truth)
    assert error.max() < 0.02 and error[:, full].max() < 0.004
    assert left.shape == (1, SIZE, SIZE, 3) and np.all(left[0, ..., 0] == left[0, ..., 1])


def _copy_pairs(tmp_path, names=("01", "02", "03", "04")):
    for n in names:
        for side in ("left", "right"):
            shutil.copy(os.path.join(chessboard.DATA_DIR, f"{side}{n}.jpg"), tmp_path)
    return tmp_path


def test_pair_without_corners_is_skipped_and_counted(tmp_path, capsys):
    root = _copy_pairs(tmp_path / "rig" if (tmp_path / "rig").mkdir() is None else None)
    blank = np.full((480, 640), 128, np.uint8)
    import cv2
    cv2.imwrite(str(root / "right03.jpg"), blank)
    out = tmp_path / "cb.h5"
    assert real_build.main(["chessboard", "--root", str(root), "--crops", "1", "--image-size",
                       str(SIZE), "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "skipped 1 of 4 pairs" in err and "right03.jpg" in err
    with StereoFile(out) as data:
        assert data.num_pairs == 3
        assert data.metadata["calibration"]["pairs_skipped"][0]["pair"] == "03"


def test_bad_chessboard_inputs(tmp_path, capsys):
    root = _copy_pairs(tmp_path / "rig" if (tmp_path / "rig").mkdir() is None else None,
                       names=("01", "02"))
    out = tmp_path / "cb.h5"
    # corners found in too few pairs
    assert real_build.main(["chessboard", "--root", str(root), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("python -m cpl_keras.real.build: error: chessboard corners") and "\n" not in err
    # a left image without its right image
    os.remove(root / "right02.jpg")
    assert real_build.main(["chessboard", "--root", str(root), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert "missing right image" in err and "right02.jpg" in err and "\n" not in err
    assert not out.exists() and not os.path.exists(str(out) + ".partial")
    assert chessboard_command.main(["--root", str(tmp_path / "none")]) == 2
    assert "not found" in capsys.readouterr().err
