"""A real, unrectified stereo rig with measured ground truth: OpenCV's sample
chessboard pairs.

``cpl_keras/real/opencv_chessboard/`` holds OpenCV's 13 sample pairs
(``left01..14.jpg``, ``right01..14.jpg``, no 10; 640 x 480 grey; Apache-2.0,
see the README and LICENSE.opencv there) from one real stereo rig, each
showing a chessboard with 9 x 6 inner corners and 25 mm squares. Every label
is derived from the images themselves:

1. ``cv2.findChessboardCorners`` (+ ``cornerSubPix``) on both images of every
   pair; a pair where either image has no corners is skipped and counted.
2. ``cv2.calibrateCamera`` per camera (pinhole + 5 distortion coefficients),
   then ``cv2.stereoCalibrate`` with those intrinsics fixed: the rotation R
   and translation T with ``X_right = R X_left + T`` (OpenCV axes, metres).
   The RMS reprojection error of the stereo calibration is recorded.
3. R, T are converted to the project's convention
   (``StereoCamera.from_opencv_pose``, through ``opencv_pose_to_rig``):
   the right camera's pose in the left camera frame, x forward, y left, z up,
   ``P_left = R_lr P_right + t``; ``tx, ty, tz = t``, ``baseline = |t|``,
   ``pitch, yaw, roll = frames.euler_from_rotation(R_lr)`` (Eq. 5's pitch,
   positive tilts the right camera down relative to the left one).
4. Each corner is triangulated (``cv2.triangulatePoints`` on the undistorted
   corners of both images): ``X, Y, Z`` is that point in the left camera
   frame (project axes), and the disparity is Eq. 4a's, ``fx * b / xCam`` with
   xCam the point's depth in the right camera (``camera.disparity_from_depth``).

Labels follow the "rig" convention of the other real sets: the projection
pixel ``(u, v)`` is in the RIGHT image (the detected corner), so ``fx, fy,
u0, v0`` are the right camera's intrinsics (the left camera's are kept as
``fx_left, fy_left, u0_left, v0_left``; the cameras differ by about 1 %).

Samples: per pair, the whole image and ``crops - 1`` random windows (the
Middlebury set's crop rule), each resized to ``image_size`` squared with the
intrinsics transformed exactly (``StereoCamera.crop`` and ``resize``). The projection
pixel is the corner nearest the window's centre among those seen inside the
window in both images (for the whole image: the corner nearest the image
centre).

What Eqs. 4a-5c cannot express, and is therefore a model error rather than a
label error: the lens distortion (the images are as captured; the
coefficients are in the metadata and are unchanged by crop and resize, which
act on pixels, not on normalised coordinates) and the relative yaw and roll
(stored as ``yaw``, ``roll``). ``camera.image_to_world`` of the labels
therefore differs from the triangulated X, Y, Z by a few millimetres
(bounded in tests/test_real_chessboard.py).

``python -m cpl_keras.real.chessboard [--root DIR] [--pair 01]`` prints the
derived calibration, full resolution, in the keys and units of
``python -m cpl_keras.calibrate``.
"""

from __future__ import annotations

import glob
import math
import os

import numpy as np

from cpl_keras.camera import PARAMETERS, UNITS, disparity_from_depth
from cpl_keras.frames import CV_TO_PROJECT, crop_resize_coordinate, opencv_pose_to_rig
from cpl_keras.images import read_gray, resize_image
from cpl_keras.real import (
    RealDataError, check_crop_settings, check_sample_room, released_disparity, write_samples,
)
from cpl_keras.real.middlebury import draw_window
from cpl_keras.stereo_camera import INTRINSICS, StereoCamera

#: The project's copy of OpenCV's sample pairs.
DATA_DIR = os.path.join(os.path.dirname(os.path.abspath(__file__)), "opencv_chessboard")
#: Inner corners (columns, rows) and square size (metres) of OpenCV's board.
BOARD = (9, 6)
SQUARE = 0.025
#: Fewest usable pairs a stereo calibration is run on.
MIN_PAIRS = 3
#: Image file suffixes searched for pairs.
SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp")

LABEL_DESCRIPTIONS = {
    "fx": "right camera focal length along u after crop + resize (cv2.calibrateCamera)",
    "fy": "right camera focal length along v after crop + resize",
    "u0": "right camera principal point u after crop + resize",
    "v0": "right camera principal point v after crop + resize",
    "baseline": "|t|, distance between the camera centres (cv2.stereoCalibrate, 25 mm squares)",
    "disparity": "Eq. 4a disparity fx * b / xCam, xCam the triangulated corner's depth in the right camera",
    "disparity_released": "mean raw StereoBM(16, 15) output, as the release computed it",
    "tx": "right camera centre in the left camera frame (x forward)",
    "ty": "right camera centre in the left camera frame (y left)",
    "tz": "right camera centre in the left camera frame (z up)",
    "pitch": "relative pitch (Eq. 5; right camera pose in the left frame)",
    "yaw": "relative yaw (not modelled by Eq. 5)",
    "roll": "relative roll (not modelled by Eq. 5)",
    "u": "projection pixel u in the RIGHT image: the detected chessboard corner",
    "v": "projection pixel v in the RIGHT image",
    "X": "triangulated corner in the left camera frame (x forward)",
    "Y": "triangulated corner in the left camera frame (y left)",
    "Z": "triangulated corner in the left camera frame (z up)",
}


def find_pairs(root=DATA_DIR):
    """Sorted ``(name, left_path, right_path)``: every ``left<name>.<ext>``
    under ``root`` with its ``right<name>.<ext>``. A left image without its
    right image is an error (``RealDataError`` naming the file)."""
    root = os.fspath(root)
    if not os.path.isdir(root):
        raise RealDataError(f"chessboard folder not found: {root}")
    pairs = []
    for path in sorted(glob.glob(os.path.join(root, "left*"))):
        base = os.path.basename(path)
        stem, ext = os.path.splitext(base)
        if ext.lower() not in SUFFIXES:
            continue
        right = os.path.join(root, "right" + stem[len("left"):] + ext)
        if not os.path.isfile(right):
            raise RealDataError(f"missing right image {right} for {path}")
        pairs.append((stem[len("left"):], path, right))
    if not pairs:
        raise RealDataError(f"no left*.jpg / left*.png images under {root}")
    return pairs


def _read_gray(path):
    return read_gray(path, error=RealDataError)


def detect_corners(gray, board=BOARD):
    """Sub-pixel inner corners ``(n, 2)`` float64 of a grey image, or None."""
    import cv2

    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCorners(gray, tuple(board), flags=flags)
    if not found:
        return None
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.01)
    corners = cv2.cornerSubPix(gray, corners, (11, 11), (-1, -1), criteria)
    return corners.reshape(-1, 2).astype(np.float64)


def calibrate(root=DATA_DIR, board=BOARD, square=SQUARE):
    """Detect, calibrate and triangulate a folder of chessboard pairs.

    Returns a dict: ``K_left``, ``D_left``, ``K_right``, ``D_right``, ``R``, ``T``
    (OpenCV; ``X_right = R X_left + T``, metres), ``rms_px`` (stereo reprojection
    RMS), ``rms_left_px``, ``rms_right_px``, the rig's ``camera`` and ``left_camera``
    (``rig_cameras``) and labels ``rig`` (``rig_parameters``; full resolution),
    ``image_size`` (width, height), ``pairs`` (per used pair: name, paths, corners,
    triangulated points, right depths), ``skipped`` (pairs without corners).
    """
    import cv2

    pairs = find_pairs(root)
    board = tuple(int(b) for b in board)
    grid = np.zeros((board[0] * board[1], 3), np.float32)
    grid[:, :2] = np.mgrid[0:board[0], 0:board[1]].T.reshape(-1, 2) * float(square)
    used, skipped, size = [], [], None
    for name, left_path, right_path in pairs:
        left, right = _read_gray(left_path), _read_gray(right_path)
        if left.shape != right.shape:
            raise RealDataError(f"{right_path} is {right.shape[1]}x{right.shape[0]}, "
                                f"{left_path} is {left.shape[1]}x{left.shape[0]}")
        if size is None:
            size = (left.shape[1], left.shape[0])
        elif size != (left.shape[1], left.shape[0]):
            raise RealDataError(f"{left_path} is {left.shape[1]}x{left.shape[0]}, "
                                f"earlier images are {size[0]}x{size[1]}")
        corners_l, corners_r = detect_corners(left, board), detect_corners(right, board)
        missing = [p for p, c in ((left_path, corners_l), (right_path, corners_r)) if c is None]
        if missing:
            skipped.append((name, "chessboard corners not found in " + ", ".join(
                os.path.basename(p) for p in missing)))
            continue
        used.append({"name": name, "left": left_path, "right": right_path,
                     "corners_left": corners_l, "corners_right": corners_r})
    if len(used) < MIN_PAIRS:
        detail = f"; {skipped[0][1]}" if skipped else ""
        raise RealDataError(f"chessboard corners ({board[0]}x{board[1]}) found in {len(used)} "
                            f"of {len(pairs)} pairs under {root}, need {MIN_PAIRS}{detail}")
    objects = [grid] * len(used)
    img_l = [p["corners_left"].astype(np.float32).reshape(-1, 1, 2) for p in used]
    img_r = [p["corners_right"].astype(np.float32).reshape(-1, 1, 2) for p in used]
    rms_l, K1, D1, _, _ = cv2.calibrateCamera(objects, img_l, size, None, None)
    rms_r, K2, D2, _, _ = cv2.calibrateCamera(objects, img_r, size, None, None)
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-6)
    rms, K1, D1, K2, D2, R, T, _, _ = cv2.stereoCalibrate(
        objects, img_l, img_r, K1, D1, K2, D2, size, flags=cv2.CALIB_FIX_INTRINSIC,
        criteria=criteria)
    cal = {"K_left": K1, "D_left": D1.reshape(-1), "K_right": K2, "D_right": D2.reshape(-1),
           "R": R, "T": T.reshape(3), "rms_px": float(rms), "rms_left_px": float(rms_l),
           "rms_right_px": float(rms_r), "image_size": size, "board": board,
           "square": float(square), "skipped": skipped, "num_found": len(pairs)}
    cal["camera"], cal["left_camera"] = rig_cameras(cal)
    cal["rig"] = rig_parameters(cal)
    for pair in used:
        pair["points"], pair["depth_right"] = triangulate(cal, pair["corners_left"],
                                                          pair["corners_right"])
    cal["pairs"] = used
    return cal


def rig_cameras(cal):
    """``(right, left)``: the rig's ``StereoCamera`` at full resolution from
    OpenCV's calibration, with the right camera's intrinsics (the labels'
    camera) and with the left camera's (the same pose)."""
    width, height = cal["image_size"]
    return tuple(StereoCamera.from_opencv_pose(cal["R"], cal["T"], cal[key], width, height)
                 for key in ("K_right", "K_left"))


def rig_parameters(cal):
    """The rig in the project's conventions, full resolution, from its
    cameras (``rig_cameras``): ``fx, fy, u0, v0`` (right camera), ``*_left``
    (left camera), ``baseline``, ``tx, ty, tz`` (metres), ``pitch, yaw,
    roll`` (radians), and the angle of the relative rotation."""
    right, left = cal["camera"], cal["left_camera"]
    R_lr, _ = opencv_pose_to_rig(cal["R"], cal["T"])
    return {
        **{name: getattr(right, name) for name in INTRINSICS},
        **{f"{name}_left": getattr(left, name) for name in INTRINSICS},
        **{name: getattr(right, name) for name in ("baseline", "tx", "ty", "tz", "pitch", "yaw",
                                                   "roll")},
        "rotation_deg": float(np.degrees(np.arccos(np.clip((np.trace(R_lr) - 1) / 2, -1, 1)))),
    }


def triangulate(cal, corners_left, corners_right):
    """``(points, depth_right)``: the corners triangulated from the undistorted
    pixels of both images, as (n, 3) points in the left camera frame (project
    axes, metres), and each point's depth (x) in the right camera frame."""
    import cv2

    K1, K2, R, T = cal["K_left"], cal["K_right"], cal["R"], cal["T"].reshape(3, 1)
    ideal_l = cv2.undistortPoints(corners_left.reshape(-1, 1, 2), K1, cal["D_left"], P=K1)
    ideal_r = cv2.undistortPoints(corners_right.reshape(-1, 1, 2), K2, cal["D_right"], P=K2)
    P1 = K1 @ np.hstack([np.eye(3), np.zeros((3, 1))])
    P2 = K2 @ np.hstack([R, T])
    homog = cv2.triangulatePoints(P1, P2, ideal_l.reshape(-1, 2).T, ideal_r.reshape(-1, 2).T)
    points_cv = (homog[:3] / homog[3]).T                     # left camera, OpenCV axes
    depth_right = (points_cv @ R.T + T.reshape(1, 3))[:, 2]  # OpenCV z = project x
    return points_cv @ CV_TO_PROJECT.T, depth_right


def _window_pixel(pair, window, width, height):
    """Index of the corner nearest the window's centre among those inside the
    window in both images (None if there is none)."""
    x0, y0, w, h = window
    inside = np.ones(len(pair["corners_right"]), bool)
    for corners in (pair["corners_right"], pair["corners_left"]):
        inside &= ((corners[:, 0] >= x0) & (corners[:, 0] <= x0 + w - 1)
                   & (corners[:, 1] >= y0) & (corners[:, 1] <= y0 + h - 1))
    if not inside.any():
        return None
    centre = np.array([x0 + (w - 1) / 2.0, y0 + (h - 1) / 2.0])
    distance = np.linalg.norm(pair["corners_right"] - centre, axis=1)
    distance[~inside] = np.inf
    return int(np.argmin(distance))


def chessboard_samples(cal, crops=20, image_size=112, seed=0):
    """Yield ``(left, right, labels)``: per used pair the whole image and
    ``crops - 1`` random windows (see the module doc)."""
    import cv2

    rng = np.random.default_rng(seed)
    rig = cal["camera"]
    width, height = cal["image_size"]
    for index, pair in enumerate(cal["pairs"]):
        left_full = cv2.cvtColor(_read_gray(pair["left"]), cv2.COLOR_GRAY2RGB)
        right_full = cv2.cvtColor(_read_gray(pair["right"]), cv2.COLOR_GRAY2RGB)
        made = attempts = 0
        while made < crops:
            attempts += 1
            full = made == 0 or attempts > 100 * crops    # whole image: every corner inside
            window = (0, 0, width, height) if full else draw_window(rng, width, height)
            k = _window_pixel(pair, window, width, height)
            if k is None:
                continue
            x0, y0, cw, ch = window
            crop = cal["camera"].crop(x0, y0, cw, ch)
            sx, sy = crop.resize_scales(image_size, image_size)
            small = crop.resize(image_size, image_size)
            small_left = cal["left_camera"].crop(x0, y0, cw, ch).resize(image_size, image_size)
            d_full = float(disparity_from_depth(rig.fx, rig.baseline, pair["depth_right"][k]))
            u_r, v_r = pair["corners_right"][k]
            u_l, v_l = pair["corners_left"][k]
            crop_l = resize_image(left_full[y0:y0 + ch, x0:x0 + cw], image_size, image_size)
            crop_r = resize_image(right_full[y0:y0 + ch, x0:x0 + cw], image_size, image_size)
            X, Y, Z = pair["points"][k]
            labels = {
                **small.to_labels(disparity=sx * d_full),
                "X": float(X), "Y": float(Y), "Z": float(Z),
                "u": float(crop_resize_coordinate(u_r, x0, sx)),
                "v": float(crop_resize_coordinate(v_r, y0, sy)),
                "disparity_released": released_disparity(crop_l, crop_r),
                **{f"{name}_left": getattr(small_left, name) for name in INTRINSICS},
                "u_left": float(crop_resize_coordinate(u_l, x0, sx)),
                "v_left": float(crop_resize_coordinate(v_l, y0, sy)),
                "corner_index": k, "crop_x0": x0, "crop_y0": y0, "crop_width": cw,
                "crop_height": ch, "config_id": 0, "town_id": -1, "frame_index": index,
            }
            yield crop_l, crop_r, labels
            made += 1


def metadata_of(cal):
    """JSON-ready calibration record stored in the HDF5 metadata."""
    return {
        "rms_px": cal["rms_px"], "rms_left_px": cal["rms_left_px"],
        "rms_right_px": cal["rms_right_px"],
        "K_left": np.asarray(cal["K_left"]).tolist(), "D_left": np.asarray(cal["D_left"]).tolist(),
        "K_right": np.asarray(cal["K_right"]).tolist(),
        "D_right": np.asarray(cal["D_right"]).tolist(),
        "R_opencv": np.asarray(cal["R"]).tolist(), "T_opencv_m": np.asarray(cal["T"]).tolist(),
        "rig_full_resolution": cal["rig"], "image_size": list(cal["image_size"]),
        "board_inner_corners": list(cal["board"]), "square_m": cal["square"],
        "pairs_used": [p["name"] for p in cal["pairs"]],
        "pairs_skipped": [{"pair": n, "reason": r} for n, r in cal["skipped"]],
    }


def build_chessboard(out, *, root=DATA_DIR, crops=20, image_size=112, seed=0, command=None,
                     report=None):
    """Calibrate the rig in ``root`` and write its test set to ``out`` (HDF5,
    atomic); returns the path. ``report`` (a callable) receives one line on
    the skipped pairs, if any."""
    crops, image_size = check_crop_settings(crops, image_size)
    check_sample_room(out, crops * len(find_pairs(root)), image_size, "crops")
    cal = calibrate(root)
    if cal["skipped"] and report is not None:
        report(f"skipped {len(cal['skipped'])} of {cal['num_found']} pairs: "
               + "; ".join(f"{n}: {r}" for n, r in cal["skipped"]))
    metadata = {
        # the shipped pairs by their place in the package: no machine's folder in the file
        "source": "OpenCV sample stereo chessboard pairs (" + (
            "cpl_keras/real/opencv_chessboard" if os.path.abspath(os.fspath(root)) == DATA_DIR
            else os.path.abspath(os.fspath(root))) + ")",
        "rig": "chessboard", "rectified": False, "crops_per_pair": crops,
        "image_size": image_size, "seed": int(seed), "calibration": metadata_of(cal),
        "labels": "rig: right camera pose in the left camera frame; (u, v) in the right image",
        "command": command,
    }
    return write_samples(out, chessboard_samples(cal, crops, image_size, seed), image_size,
                         metadata, LABEL_DESCRIPTIONS)


def calibration_report(cal, pair=None):
    """The derived calibration in the keys and units of ``python -m
    cpl_keras.calibrate``: full-resolution pixels, metres, radians (and
    pitch in degrees, fields of view), plus the point of one pair."""
    rig = cal["rig"]
    width, height = cal["image_size"]
    out = {
        "image_width": width, "image_height": height,
        "rms_reprojection_px": cal["rms_px"],
        "parameters": {name: rig[name] for name in PARAMETERS if name != "disparity"},
        "pitch_deg": math.degrees(rig["pitch"]), "yaw_deg": math.degrees(rig["yaw"]),
        "roll_deg": math.degrees(rig["roll"]), "rotation_deg": rig["rotation_deg"],
        "fov_horizontal_deg": cal["camera"].fov_deg[0],
        "fov_vertical_deg": cal["camera"].fov_deg[1],
        "left_camera": {k: rig[k + "_left"] for k in ("fx", "fy", "u0", "v0")},
        "units": {name: UNITS[name] for name in PARAMETERS},
        "pairs_used": len(cal["pairs"]), "pairs_skipped": len(cal["skipped"]),
    }
    if pair is not None:
        match = [p for p in cal["pairs"] if p["name"] == pair]
        if not match:
            raise RealDataError(f"pair {pair} not among the calibrated pairs")
        p = match[0]
        width_c = np.array([(width - 1) / 2.0, (height - 1) / 2.0])
        k = int(np.argmin(np.linalg.norm(p["corners_right"] - width_c, axis=1)))
        out["pair"] = {"left": p["left"], "right": p["right"],
                       "u": float(p["corners_right"][k, 0]), "v": float(p["corners_right"][k, 1]),
                       "disparity": float(disparity_from_depth(rig["fx"], rig["baseline"],
                                                               p["depth_right"][k])),
                       "point": dict(zip("XYZ", (float(x) for x in p["points"][k])))}
        out["parameters"]["disparity"] = out["pair"]["disparity"]
    return out


if __name__ == "__main__":  # the command line: cpl_keras/commands/chessboard.py
    import runpy

    runpy.run_module("cpl_keras.commands.chessboard", run_name="__main__")
