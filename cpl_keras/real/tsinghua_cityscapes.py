"""Tsinghua-Daimler Cyclist Benchmark and Cityscapes as project datasets.

Both datasets share one layout (the paper's Table 2 used the first)::

    ROOT/leftImg8bit/<split>/<city>/<name>_leftImg8bit.png    left image
    ROOT/disparity/<split>/<city>/<name>_disparity.png        16-bit disparity
    ROOT/camera/<split>/<city>/<name>_camera.json             calibration

The camera JSON is ``{"extrinsic": {"baseline", "pitch", "roll", "x", "y",
"yaw", "z"}, "intrinsic": {"fx", "fy", "u0", "v0"}}`` (metres, radians,
pixels; the extrinsic is the left camera's mounting in the vehicle frame,
x forward, y left, z up: the datasets' own camera model is exactly paper
Eqs. 4a-5c). A disparity PNG value ``p`` decodes to ``(p - 1) / 256``
pixels of the left image; ``p = 0`` is invalid.

The right image is not part of these layouts; it is made from the left one:

* ``right="warp"`` (default): the left image forward-warped with its
  disparity, ``right(u - d, v) = left(u, v)``, nearer points winning where
  several land on one pixel and holes filled from the left neighbour on the
  row. This is a true right view of the visible surfaces.
* ``right="released"``: what the authors' release did: the left image minus
  the resized disparity image read as 8-bit RGB (OpenCV's default imread of a
  16-bit PNG keeps the high byte), with uint8 wrap-around. Not a view of the
  scene; kept to reproduce Table 2's inputs.

Images are resized whole to ``image_size`` x ``image_size`` (like the
release), and the intrinsics are transformed exactly (per axis). Labels:

* ``labels="rig"`` (default, the project's convention): the right camera's
  pose in the left camera frame (``pitch = tx = tz = 0``,
  ``ty = -baseline``), projection pixel ``(u, v)`` in the (warped) right
  image at a left pixel with valid disparity that is visible in the right
  view, ``disparity = sx * d`` (Eq. 4a in resized pixels), ``X, Y, Z`` the
  point in the left camera frame.
* ``labels="vehicle"``: the dataset's own meaning, close to the release's
  labels: ``pitch``, ``tx, ty, tz`` = the JSON's pitch, x, y, z (the left
  camera in the vehicle frame), ``(u, v)`` in the LEFT image, ``X, Y, Z``
  the point in the vehicle frame. (The release also kept full-resolution
  intrinsics for 112-pixel images and read the disparity label at pixel
  (5, 5) plus 1; those quirks are not reproduced.)

In both modes ``X, Y, Z = camera.image_to_world(...)`` of the stored labels.
"""

from __future__ import annotations

import json
import os

import numpy as np

from cpl_keras.frames import crop_resize_coordinate
from cpl_keras.data.writer import StereoWriter
from cpl_keras.images import read_rgb, resize_image
from cpl_keras.real import (  # noqa: F401  (RealDataError is re-exported)
    LABEL_MODES, RealDataError, rectified_camera, released_disparity,
)
from cpl_keras.stereo_camera import StereoCamera

DATASETS = ("tsinghua", "cityscapes")
RIGHT_MODES = ("warp", "released")
INTRINSIC_KEYS = ("fx", "fy", "u0", "v0")
EXTRINSIC_KEYS = ("baseline", "pitch", "roll", "x", "y", "yaw", "z")
LEFT_SUFFIX = "_leftImg8bit.png"


def find_samples(root, split=None):
    """Sorted ``(name, left_png, disparity_png, camera_json)`` under ``root``.

    ``split`` (e.g. "test") restricts the search to that split folder. Every
    left image must have its disparity and camera file.
    """
    root = os.fspath(root)
    left_root = os.path.join(root, "leftImg8bit")
    if not os.path.isdir(left_root):
        raise RealDataError(f"no leftImg8bit directory under {root}")
    if split is not None:
        left_root = os.path.join(left_root, split)
        if not os.path.isdir(left_root):
            raise RealDataError(f"no split '{split}' under {os.path.join(root, 'leftImg8bit')}")
    samples = []
    for directory, _, files in os.walk(left_root):
        for file in files:
            if not file.endswith(LEFT_SUFFIX):
                continue
            name = file[: -len(LEFT_SUFFIX)]
            rel = os.path.relpath(directory, os.path.join(root, "leftImg8bit"))
            disparity = os.path.join(root, "disparity", rel, name + "_disparity.png")
            camera = os.path.join(root, "camera", rel, name + "_camera.json")
            for path in (disparity, camera):
                if not os.path.isfile(path):
                    raise RealDataError(f"missing {path} for {os.path.join(directory, file)}")
            samples.append((name, os.path.join(directory, file), disparity, camera))
    if not samples:
        raise RealDataError(f"no *{LEFT_SUFFIX} images under {left_root}")
    return sorted(samples)


def read_camera(path):
    """The camera JSON as ``{"intrinsic": {...}, "extrinsic": {...}}`` of floats."""
    try:
        with open(path) as f:
            data = json.load(f)
    except (OSError, json.JSONDecodeError) as error:
        raise RealDataError(f"cannot read camera file {path}: {error}") from None
    out = {}
    for group, keys in (("intrinsic", INTRINSIC_KEYS), ("extrinsic", EXTRINSIC_KEYS)):
        values = data.get(group) if isinstance(data, dict) else None
        if not isinstance(values, dict):
            raise RealDataError(f"camera file {path} has no '{group}' object")
        out[group] = {}
        for key in keys:
            try:
                value = float(values[key])
            except (KeyError, TypeError, ValueError):
                raise RealDataError(f"camera file {path}: missing or non-numeric {group}.{key}") from None
            if not np.isfinite(value):
                raise RealDataError(f"camera file {path}: {group}.{key} is not finite")
            out[group][key] = value
    for key in ("fx", "fy"):
        if out["intrinsic"][key] <= 0:
            raise RealDataError(f"camera file {path}: intrinsic.{key} must be positive")
    if out["extrinsic"]["baseline"] <= 0:
        raise RealDataError(f"camera file {path}: extrinsic.baseline must be positive")
    return out


def read_disparity_png(path):
    """``(disparity, raw)``: float64 pixels ``(p - 1) / 256`` (nan where
    ``p = 0``) and the raw uint16 values."""
    import cv2

    raw = cv2.imread(os.fspath(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise RealDataError(f"cannot read disparity image {path}")
    if raw.ndim != 2 or raw.dtype != np.uint16:
        raise RealDataError(f"disparity image {path} must be 16-bit single-channel, got {raw.dtype} {raw.shape}")
    disparity = (raw.astype(np.float64) - 1.0) / 256.0
    disparity[raw == 0] = np.nan
    return disparity, raw


def warp_to_right(left, disparity):
    """Forward-warp ``left`` with its disparity: ``right(u - d, v) = left(u, v)``.

    Returns ``(right, visible)``: the image and a mask of the left pixels
    that won their target pixel (not occluded, landed inside the image).
    """
    height, width = disparity.shape
    right = np.zeros_like(left)
    filled = np.zeros((height, width), bool)
    visible = np.zeros((height, width), bool)
    rows, cols = np.nonzero(np.isfinite(disparity))
    d = disparity[rows, cols]
    target = np.rint(cols - d).astype(np.int64)
    inside = (target >= 0) & (target < width)
    rows, cols, d, target = rows[inside], cols[inside], d[inside], target[inside]
    order = np.argsort(d, kind="stable")              # far first, near last (wins)
    rows, cols, target = rows[order], cols[order], target[order]
    flat = rows * width + target
    winner = np.full(height * width, -1, np.int64)
    winner[flat] = np.arange(len(flat))                # the last write wins
    won = winner[flat] == np.arange(len(flat))
    right.reshape(-1, left.shape[-1])[flat[won]] = left[rows[won], cols[won]]
    filled.reshape(-1)[flat[won]] = True
    visible[rows[won], cols[won]] = True
    # holes (occlusions, invalid disparity): copy the nearest filled pixel on the left
    index = np.where(filled, np.arange(width)[None, :], 0)
    np.maximum.accumulate(index, axis=1, out=index)
    right = np.take_along_axis(right, index[..., None].repeat(left.shape[-1], -1), axis=1)
    return right, visible


def released_right(left_small, raw_disparity, size):
    """The release's "right" image: left minus the resized 8-bit disparity
    image (high byte of the 16-bit PNG, as RGB), uint8 wrap-around."""
    high_byte = (raw_disparity >> 8).astype(np.uint8)
    small = resize_image(high_byte, size, size)
    return np.subtract(left_small, np.repeat(small[..., None], 3, axis=-1), dtype=np.uint8)


def sample_from_files(left_path, disparity_path, camera_path, image_size=112, right="warp",
                      labels="rig", rng=None):
    """One ``(left, right, labels)`` sample (see the module doc)."""
    if right not in RIGHT_MODES:
        raise ValueError(f"unknown right-image mode '{right}' (use {', '.join(RIGHT_MODES)})")
    if labels not in LABEL_MODES:
        raise ValueError(f"unknown label mode '{labels}' (use {', '.join(LABEL_MODES)})")
    rng = np.random.default_rng(0) if rng is None else rng
    camera = read_camera(camera_path)
    left_full = read_rgb(left_path, RealDataError)
    disparity, raw = read_disparity_png(disparity_path)
    if disparity.shape != left_full.shape[:2]:
        raise RealDataError(
            f"disparity {disparity_path} is {disparity.shape}, image is {left_full.shape[:2]}")
    height, width = disparity.shape
    intr, extr = camera["intrinsic"], camera["extrinsic"]
    full = _camera(intr, extr, width, height, labels)
    sx, sy = full.resize_scales(image_size, image_size)
    small = full.resize(image_size, image_size)
    left_small = resize_image(left_full, image_size, image_size)
    right_full, visible = warp_to_right(left_full, disparity)
    if right == "warp":
        right_small = resize_image(right_full, image_size, image_size)
    else:
        right_small = released_right(left_small, raw, image_size)

    valid = visible & (disparity > 0)
    if not valid.any():
        raise RealDataError(f"{disparity_path} has no valid positive disparity")
    rows, cols = np.nonzero(valid)
    k = int(rng.integers(len(rows)))
    v_full, u_left = int(rows[k]), int(cols[k])
    d_full = float(disparity[v_full, u_left])
    d = sx * d_full
    v = float(crop_resize_coordinate(v_full, 0, sy))
    # rig: the pixel in the right image; vehicle: in the left (the dataset's camera)
    u = float(crop_resize_coordinate(u_left - d_full if labels == "rig" else u_left, 0, sx))
    X, Y, Z = small.to_world(u, v, d)
    out = {
        **small.to_labels(disparity=d),
        "X": float(X), "Y": float(Y), "Z": float(Z), "u": u, "v": v,
        "disparity_released": released_disparity(left_small, right_small),
        "u_left": float(crop_resize_coordinate(u_left, 0, sx)),
        "mount_x": extr["x"], "mount_y": extr["y"], "mount_z": extr["z"],
        "mount_pitch": extr["pitch"], "mount_yaw": extr["yaw"], "mount_roll": extr["roll"],
        "full_width": width, "full_height": height,
    }
    return left_small, right_small, out


def _camera(intr, extr, width, height, labels):
    """The dataset's camera at full resolution: in the "rig" convention the
    right camera of a rectified pair (``rectified_camera``), in the
    "vehicle" one the left camera mounted on the vehicle (its extrinsics)."""
    if labels == "rig":
        return rectified_camera(intr["fx"], intr["fy"], intr["u0"], intr["v0"], width, height,
                                extr["baseline"])
    return StereoCamera(fx=intr["fx"], fy=intr["fy"], u0=intr["u0"], v0=intr["v0"],
                        width=width, height=height, baseline=extr["baseline"],
                        pitch=extr["pitch"], tx=extr["x"], ty=extr["y"], tz=extr["z"],
                        yaw=extr["yaw"], roll=extr["roll"])


def build_stereo_dataset(root, out, *, dataset="tsinghua", split=None, image_size=112,
                         right="warp", labels="rig", seed=0, limit=None, command=None):
    """Write ``root`` (Tsinghua-Daimler or Cityscapes layout) as a project
    HDF5 file at ``out`` (atomic); returns the path."""
    if dataset not in DATASETS:
        raise ValueError(f"unknown dataset '{dataset}' (use {', '.join(DATASETS)})")
    image_size = int(image_size)
    if image_size < 32:
        raise ValueError(f"image size must be at least 32, got {image_size}")
    samples = find_samples(root, split)
    if limit is not None:
        if int(limit) <= 0:
            raise ValueError(f"limit must be positive, got {limit}")
        samples = samples[: int(limit)]
    rng = np.random.default_rng(seed)
    metadata = {
        "source": dataset, "rig": dataset, "rectified": labels == "rig",
        "root": os.path.abspath(os.fspath(root)), "split": split,
        "image_size": image_size, "right": right, "labels": labels, "seed": int(seed),
        "names": [s[0] for s in samples], "command": command,
    }
    with StereoWriter(out, len(samples), image_size, metadata=metadata) as writer:
        for index, (_, left_path, disparity_path, camera_path) in enumerate(samples):
            left, right_img, lab = sample_from_files(
                left_path, disparity_path, camera_path, image_size, right, labels, rng)
            lab.update(config_id=index, town_id=-1, frame_index=index)
            writer.write(index, left[None], right_img[None],
                         {k: np.array([val]) for k, val in lab.items()})
    return str(out)
