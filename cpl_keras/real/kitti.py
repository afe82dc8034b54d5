"""KITTI as a real test set (for users who have it; nothing is downloaded).

Two layouts are read:

* **stereo 2015 / scene flow** (also 2012)::

      ROOT[/training]/image_2/000000_10.png          left (camera 2, rectified)
      ROOT[/training]/image_3/000000_10.png          right (camera 3, rectified)
      ROOT[/training]/disp_occ_0/000000_10.png       left disparity (16 bit, p / 256 px, 0 = none)
      ROOT[/training]/calib_cam_to_cam/000000.txt    P_rect_02, P_rect_03 (data_scene_flow_calib)
      ROOT[/training]/calib/000000.txt               or P2, P3 (object / stereo 2012 format)

* **raw**::

      ROOT/2011_09_26/calib_cam_to_cam.txt                          P_rect_02, P_rect_03, R_rect_*, T_02, T_03
      ROOT/2011_09_26/2011_09_26_drive_0001_sync/image_02/data/0000000000.png
      ROOT/2011_09_26/2011_09_26_drive_0001_sync/image_03/data/0000000000.png

A calibration file is plain text, one ``key: values`` line per entry
(``calib_time:`` holds a date; every other value is a row of numbers in
scientific notation). Labels come from the rectified projection matrices
``P2 = P_rect_02`` (left) and ``P3 = P_rect_03`` (right), ``P = K [I | t]``
with ``t`` the camera's offset from rectified camera 0:

* ``fx, fy, u0, v0`` = ``P3[0, 0], P3[1, 1], P3[0, 2], P3[1, 2]`` (the right
  camera: the projection pixel is in the right image), resized exactly;
* ``baseline = (P2[0, 3] - P3[0, 3]) / fx`` (KITTI's own formula);
* ``tx, ty, tz``: the right camera centre in the left camera frame, project
  axes (x forward, y left, z up): ``K^-1 P[:, 3]`` of both cameras,
  differenced and rotated from OpenCV axes (``ty ~ -baseline``; tx, tz are
  the millimetre offsets KITTI's rectification leaves);
* ``pitch = yaw = roll = 0`` (rectified).

Disparity comes from ``disp_occ_0`` where the frame has it: the projection
pixel is the left pixel with valid disparity nearest the image centre, moved
to the right image (``u_right = u_left - d``), ``disparity = sx * d``, and
``X, Y, Z = camera.image_to_world`` of the labels. Where there is no
ground-truth disparity (raw data, ``_11`` frames, the testing split) the
disparity and X, Y, Z are **undefined**: the label ``disparity_valid`` is 0,
the stored values are 0 placeholders, the pixel is the right image's centre,
and Table 2 reports ``n/a`` for them; nothing is estimated.

Images are resized whole to ``image_size`` squared, like the Tsinghua-Daimler
and Cityscapes sets.
"""

from __future__ import annotations

import os
import re

import numpy as np

from cpl_keras.frames import CV_TO_PROJECT, crop_resize_coordinate
from cpl_keras.data.writer import StereoWriter
from cpl_keras.images import read_rgb, resize_image
from cpl_keras.real import RealDataError, released_disparity
from cpl_keras.stereo_camera import StereoCamera

LAYOUTS = ("stereo", "raw")
#: Keys of the left / right rectified projection matrices, in lookup order.
LEFT_KEYS, RIGHT_KEYS = ("P_rect_02", "P2"), ("P_rect_03", "P3")
#: Keys whose value is text, not numbers.
TEXT_KEYS = ("calib_time",)
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")

LABEL_DESCRIPTIONS = {
    "fx": "P3[0,0] (right camera, rectified) after resize",
    "fy": "P3[1,1] after resize",
    "u0": "P3[0,2] after resize (right camera)",
    "v0": "P3[1,2] after resize",
    "baseline": "(P2[0,3] - P3[0,3]) / fx",
    "disparity": "sx * disp_occ_0 at the left pixel (Eq. 4a in resized px); 0 where disparity_valid = 0",
    "disparity_valid": "1: disparity, X, Y, Z from disp_occ_0; 0: undefined (no ground truth)",
    "tx": "right camera centre in the left camera frame from K^-1 P[:,3] (x forward)",
    "ty": "right camera centre in the left camera frame (y left)",
    "tz": "right camera centre in the left camera frame (z up)",
    "pitch": "0 (rectified)",
    "u": "projection pixel u in the RIGHT image (resized)",
    "v": "projection pixel v (resized)",
    "X": "image_to_world of the labels (left camera frame); 0 where disparity_valid = 0",
}


def read_calib_file(path):
    """A KITTI calibration file as ``{key: float64 array or str}``.

    Raises ``RealDataError`` (naming the file and line) for a missing file, a
    line without ``key:`` or a non-numeric value."""
    path = os.fspath(path)
    try:
        with open(path) as f:
            lines = f.read().splitlines()
    except OSError as error:
        raise RealDataError(f"cannot read calibration file {path}: {error.strerror or error}") from None
    out = {}
    for number, line in enumerate(lines, 1):
        if not line.strip():
            continue
        key, sep, value = line.partition(":")
        key = key.strip()
        if not sep or not key or " " in key:
            raise RealDataError(f"{path}: line {number} is not 'key: values'")
        if key in TEXT_KEYS:
            out[key] = value.strip()
            continue
        try:
            numbers = np.array([float(v) for v in value.split()], dtype=np.float64)
        except ValueError:
            raise RealDataError(f"{path}: line {number} ({key}) has a non-numeric value") from None
        if not numbers.size or not np.all(np.isfinite(numbers)):
            raise RealDataError(f"{path}: line {number} ({key}) has no finite numbers")
        out[key] = numbers
    return out


def projection_matrices(calib, path):
    """``(P2, P3)`` (3x4 each) from a parsed calibration file."""
    matrices = []
    for keys in (LEFT_KEYS, RIGHT_KEYS):
        key = next((k for k in keys if k in calib), None)
        if key is None:
            raise RealDataError(f"{path}: no {' or '.join(keys)} line")
        values = calib[key]
        if isinstance(values, str) or values.size != 12:
            raise RealDataError(f"{path}: {key} must hold 12 numbers, got "
                                f"{0 if isinstance(values, str) else values.size}")
        P = values.reshape(3, 4)
        if not (P[0, 0] > 0 and P[1, 1] > 0 and P[2, 2] != 0):
            raise RealDataError(f"{path}: {key} is not a projection matrix (fx, fy > 0)")
        matrices.append(P)
    return matrices[0], matrices[1]


def rig_from_projections(P2, P3):
    """Full-resolution rig labels from the rectified projection matrices
    (see the module doc)."""
    P2, P3 = np.asarray(P2, np.float64), np.asarray(P3, np.float64)
    fx = float(P3[0, 0])
    offset = [np.linalg.solve(P[:, :3], P[:, 3]) for P in (P2, P3)]   # t of P = K [I | t]
    # camera centre = -t (rectified camera 0 frame, OpenCV axes): right minus left
    t = CV_TO_PROJECT @ (offset[0] - offset[1])
    return {"fx": fx, "fy": float(P3[1, 1]), "u0": float(P3[0, 2]), "v0": float(P3[1, 2]),
            "u0_left": float(P2[0, 2]), "baseline": float((P2[0, 3] - P3[0, 3]) / fx),
            "tx": float(t[0]), "ty": float(t[1]), "tz": float(t[2]),
            "pitch": 0.0, "yaw": 0.0, "roll": 0.0}


def read_disparity(path):
    """KITTI disparity PNG: float64 ``p / 256`` px, nan where ``p = 0``."""
    import cv2

    raw = cv2.imread(os.fspath(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise RealDataError(f"cannot read disparity image {path}")
    if raw.ndim != 2 or raw.dtype != np.uint16:
        raise RealDataError(f"disparity image {path} must be 16-bit single-channel, "
                            f"got {raw.dtype} {raw.shape}")
    disparity = raw.astype(np.float64) / 256.0
    disparity[raw == 0] = np.nan
    return disparity



def _images(directory):
    return sorted(f for f in os.listdir(directory) if f.lower().endswith(IMAGE_SUFFIXES))


def _split_base(root, split, probe):
    """``root``, ``root/split``, or ``root/training`` when ``probe`` is only there."""
    base = os.path.join(os.fspath(root), split) if split else os.fspath(root)
    if split is None and not os.path.isdir(os.path.join(base, probe)) and \
            os.path.isdir(os.path.join(base, "training", probe)):
        base = os.path.join(base, "training")
    return base


def find_stereo_frames(root, split=None, calib_root=None):
    """``[(name, left, right, calib, disparity or None)]`` of a stereo 2015 /
    scene-flow folder (``root`` or ``root/split`` holds ``image_2``). The
    calibration files are looked for beside the images, then under
    ``calib_root`` (KITTI ships them as an archive of their own,
    ``data_scene_flow_calib``, whose ``training/calib_cam_to_cam`` may be
    unpacked elsewhere)."""
    base = _split_base(root, split, "image_2")
    calib_bases = [base] + ([b for b in (_split_base(calib_root, split, "calib_cam_to_cam"),
                                         _split_base(calib_root, split, "calib"))]
                            if calib_root else [])
    left_dir = os.path.join(base, "image_2")
    if not os.path.isdir(left_dir):
        raise RealDataError(f"no image_2 directory under {base}")
    frames = []
    for file in _images(left_dir):
        name = os.path.splitext(file)[0]
        right = os.path.join(base, "image_3", file)
        if not os.path.isfile(right):
            raise RealDataError(f"missing right image {right} for {os.path.join(left_dir, file)}")
        sequence = re.sub(r"_\d+$", "", name)
        candidates = [os.path.join(b, folder, sequence + ".txt") for b in calib_bases
                      for folder in ("calib_cam_to_cam", "calib")]
        calib = next((c for c in candidates if os.path.isfile(c)), None)
        if calib is None:
            raise RealDataError(f"missing calibration file {candidates[0]} (or {candidates[1]}) "
                                f"for {os.path.join(left_dir, file)}")
        disparity = os.path.join(base, "disp_occ_0", name + ".png")
        frames.append((name, os.path.join(left_dir, file), right, calib,
                       disparity if os.path.isfile(disparity) else None))
    if not frames:
        raise RealDataError(f"no images in {left_dir}")
    return frames


def find_raw_frames(root, calib_root=None):
    """``[(name, left, right, calib, None)]`` of a KITTI raw folder: every
    ``image_02/data`` under ``root``; the calibration is the nearest
    ``calib_cam_to_cam.txt`` in the drive folder or above it (up to ``root``),
    else ``calib_root/<date>/calib_cam_to_cam.txt`` (the date's own archive,
    ``<date>_calib.zip``, unpacked elsewhere)."""
    root = os.path.abspath(os.fspath(root))
    frames = []
    for directory, subdirs, _ in os.walk(root):
        subdirs.sort()
        if os.path.basename(directory) != "data" or os.path.basename(
                os.path.dirname(directory)) != "image_02":
            continue
        drive = os.path.dirname(os.path.dirname(directory))
        calib, probe = None, drive
        while calib is None:
            candidate = os.path.join(probe, "calib_cam_to_cam.txt")
            if os.path.isfile(candidate):
                calib = candidate
            elif probe == root or os.path.dirname(probe) == probe:
                date = os.path.basename(os.path.dirname(drive))
                separate = os.path.join(os.fspath(calib_root), date, "calib_cam_to_cam.txt") \
                    if calib_root else None
                if separate and os.path.isfile(separate):
                    calib = separate
                    break
                raise RealDataError(f"missing calibration file calib_cam_to_cam.txt for {drive}"
                                    + (f" (nor {separate})" if separate else ""))
            else:
                probe = os.path.dirname(probe)
        for file in _images(directory):
            right = os.path.join(drive, "image_03", "data", file)
            if not os.path.isfile(right):
                raise RealDataError(f"missing right image {right} for {os.path.join(directory, file)}")
            name = os.path.basename(drive) + "/" + os.path.splitext(file)[0]
            frames.append((name, os.path.join(directory, file), right, calib, None))
    if not frames:
        raise RealDataError(f"no image_02/data folders under {root}")
    return frames


def raw_baseline(calib, path):
    """``|T_02 - T_03|`` (metres) of a raw calib_cam_to_cam.txt: the unrectified
    cameras' distance, a check on the rectified baseline (None if absent)."""
    if "T_02" not in calib or "T_03" not in calib:
        return None
    if calib["T_02"].size != 3 or calib["T_03"].size != 3:
        raise RealDataError(f"{path}: T_02 and T_03 must hold 3 numbers")
    return float(np.linalg.norm(calib["T_02"] - calib["T_03"]))


def sample_from_frame(left_path, right_path, calib_path, disparity_path=None, image_size=112):
    """One ``(left, right, labels)`` sample (see the module doc)."""
    calib = read_calib_file(calib_path)
    P2, P3 = projection_matrices(calib, calib_path)
    rig = rig_from_projections(P2, P3)
    left_full, right_full = read_rgb(left_path, RealDataError), read_rgb(right_path, RealDataError)
    if left_full.shape != right_full.shape:
        raise RealDataError(f"{right_path} is {right_full.shape[1]}x{right_full.shape[0]}, "
                            f"{left_path} is {left_full.shape[1]}x{left_full.shape[0]}")
    height, width = left_full.shape[:2]
    full = StereoCamera.from_labels(rig, width, height)
    sx, sy = full.resize_scales(image_size, image_size)
    camera = full.resize(image_size, image_size)
    left = resize_image(left_full, image_size, image_size)
    right = resize_image(right_full, image_size, image_size)
    labels = {**camera.to_labels(),
              "u0_left": float(crop_resize_coordinate(rig["u0_left"], 0, sx)),
              "disparity_released": released_disparity(left, right),
              "full_width": width, "full_height": height}
    pixel = None
    if disparity_path is not None:
        disparity = read_disparity(disparity_path)
        if disparity.shape != (height, width):
            raise RealDataError(f"disparity {disparity_path} is {disparity.shape[1]}x"
                                f"{disparity.shape[0]}, image is {width}x{height}")
        rows, cols = np.nonzero(disparity > 0)
        if rows.size:
            k = int(np.argmin((cols - (width - 1) / 2.0) ** 2 + (rows - (height - 1) / 2.0) ** 2))
            pixel = int(cols[k]), int(rows[k]), float(disparity[rows[k], cols[k]])
    if pixel is not None:
        u_left, v_full, d_full = pixel
        u = float(crop_resize_coordinate(u_left - d_full, 0, sx))
        v = float(crop_resize_coordinate(v_full, 0, sy))
        d = sx * d_full
        X, Y, Z = camera.to_world(u, v, d)
        labels.update(u=u, v=v, disparity=d, X=float(X), Y=float(Y), Z=float(Z),
                      u_left=float(crop_resize_coordinate(u_left, 0, sx)), disparity_valid=1)
    else:
        centre_u = float(crop_resize_coordinate((width - 1) / 2.0, 0, sx))
        centre_v = float(crop_resize_coordinate((height - 1) / 2.0, 0, sy))
        labels.update(u=centre_u, v=centre_v, disparity=0.0, X=0.0, Y=0.0, Z=0.0,
                      u_left=centre_u, disparity_valid=0)
    return left, right, labels, calib


def build_kitti(root, out, *, layout="stereo", split=None, image_size=112, limit=None,
                calib_root=None, command=None):
    """Write a KITTI folder (``layout`` "stereo" or "raw") as a project HDF5
    file at ``out`` (atomic); returns the path. ``calib_root``: where the
    calibration files are when they are not beside the images."""
    if layout not in LAYOUTS:
        raise ValueError(f"unknown KITTI layout '{layout}' (use {', '.join(LAYOUTS)})")
    image_size = int(image_size)
    if image_size < 32:
        raise ValueError(f"image size must be at least 32, got {image_size}")
    if not os.path.isdir(os.fspath(root)):
        raise RealDataError(f"dataset root not found: {root}")
    if calib_root is not None and not os.path.isdir(os.fspath(calib_root)):
        raise RealDataError(f"calibration root not found: {calib_root}")
    frames = (find_stereo_frames(root, split, calib_root) if layout == "stereo"
              else find_raw_frames(root, calib_root))
    if limit is not None:
        if int(limit) <= 0:
            raise ValueError(f"limit must be positive, got {limit}")
        frames = frames[: int(limit)]
    checks = {}
    for calib_path in sorted({f[3] for f in frames}) if layout == "raw" else ():
        calib = read_calib_file(calib_path)
        P2, P3 = projection_matrices(calib, calib_path)
        checks[calib_path] = {"rectified_baseline_m": rig_from_projections(P2, P3)["baseline"],
                              "T_02_T_03_distance_m": raw_baseline(calib, calib_path),
                              "calib_time": calib.get("calib_time")}
    metadata = {
        "source": f"KITTI {layout}", "rig": "kitti", "rectified": True, "layout": layout,
        "root": os.path.abspath(os.fspath(root)), "split": split, "image_size": image_size,
        "names": [f[0] for f in frames],
        "frames_with_disparity": int(sum(f[4] is not None for f in frames)),
        "undefined_when_disparity_valid_is_0": ["disparity", "X", "Y", "Z"],
        "calibration_checks": checks, "command": command,
        "labels": "rig: right camera pose in the left camera frame; (u, v) in the right image",
    }
    with StereoWriter(out, len(frames), image_size, metadata=metadata,
                      label_descriptions=LABEL_DESCRIPTIONS) as writer:
        for index, (_, left_path, right_path, calib_path, disparity_path) in enumerate(frames):
            left, right, labels, _ = sample_from_frame(left_path, right_path, calib_path,
                                                       disparity_path, image_size)
            labels.update(config_id=index, town_id=-1, frame_index=index)
            writer.write(index, left[None], right[None],
                         {k: np.array([v]) for k, v in labels.items()})
    return str(out)
