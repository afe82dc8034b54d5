"""A real test set from an OAK-D Lite rig: 12 rectified indoor pairs.

The pairs and their calibration ship in ``cpl_keras/real/oakd_stereo/``
(from the ``stereodemo`` package, MIT): 640 x 480 grey images, fx = fy =
451.03 px, one principal point (cx, cy) for both cameras, a 7.5 cm baseline.
A short-baseline, wide-angle (71 deg) rig, unlike the synthetic ones.

Labels follow the project's "rig" convention (as ``real.middlebury``): the
right camera's pose in the left camera frame (``pitch = tx = tz = 0``,
``ty = -baseline``); ``(u, v)`` in the RIGHT image; ``u0`` the right
camera's principal point; ``X, Y, Z = camera.image_to_world(...)``.

These pairs have no ground-truth disparity. The disparity at the projection
pixel is *measured*: OpenCV's semi-global matcher on the full-resolution
pair, kept only where a right-to-left match agrees within one pixel
(``measure_disparity``), and inside the valid region of the rectification.
Labels that rest on it (disparity, X, Y, Z) carry that measurement's error;
intrinsics, baseline and pose are the calibration's. ``build_oakd`` draws
crops of each pair (random size, aspect, position; some the whole image),
resizes them to ``image_size`` squared and transforms the intrinsics
exactly (``StereoCamera.crop`` and ``resize``).
"""

from __future__ import annotations

import json
import os

import numpy as np

from cpl_keras.images import read_rgb
from cpl_keras.real import (
    RECTIFIED_LABEL_DESCRIPTIONS, RealDataError, check_crop_settings, check_sample_room,
    rectified_camera, rectified_crop, write_samples,
)

DATA_DIR = os.path.join(os.path.dirname(os.path.abspath(__file__)), "oakd_stereo")
CALIBRATION_FILE = "stereodemo_calibration.json"
#: Largest disparity searched (px, full resolution): 451 px * 7.5 cm / 0.25 m.
MAX_DISPARITY = 144
#: Smallest disparity kept (px, full resolution): 451 px * 7.5 cm / 3 px = 11 m,
#: beyond any of these rooms; a smaller match is a mismatch on a blank wall.
MIN_DISPARITY = 3.0
#: Smallest crop side, as a fraction of the image side; share of whole images.
MIN_CROP_FRACTION = 0.35
FULL_IMAGE_SHARE = 0.1

LABEL_DESCRIPTIONS = {
    "fx": "focal length along u after crop + resize (451.03 px at 640 x 480)",
    "fy": "focal length along v after crop + resize",
    "u0": "principal point u after crop + resize (both cameras share it)",
    "v0": "principal point v after crop + resize",
    "baseline": "75 mm (the rig's calibration)",
    "disparity": "sx * d, d MEASURED at the pixel (StereoSGBM, left-right checked): "
                 "Eq. 4a in resized pixels",
    **RECTIFIED_LABEL_DESCRIPTIONS,
}


def load_calibration(root=DATA_DIR):
    """The rig's calibration: ``fx``, ``fy``, ``cx``, ``cy``, ``baseline``,
    ``width``, ``height`` and the valid window ``(x0, y0, x1, y1)`` in pixels."""
    path = os.path.join(root, CALIBRATION_FILE)
    try:
        with open(path) as f:
            raw = json.load(f)
        if abs(raw["cx0"] - raw["cx1"]) > 1e-6:
            raise RealDataError(f"{path}: the two principal points differ; this loader "
                                "expects one (a rectified pair)")
        width, height = int(raw["width"]), int(raw["height"])
        x0, y0, x1, y1 = raw.get("left_image_rect_normalized", (0, 0, 1, 1))
        return {"fx": float(raw["fx"]), "fy": float(raw["fy"]), "cx": float(raw["cx0"]),
                "cy": float(raw["cy"]), "baseline": float(raw["baseline_meters"]),
                "width": width, "height": height,
                "valid": (int(np.ceil(x0 * width)), int(np.ceil(y0 * height)),
                          int(np.floor(x1 * width)), int(np.floor(y1 * height)))}
    except FileNotFoundError:
        raise RealDataError(f"calibration not found: {path}") from None
    except (KeyError, TypeError, ValueError) as error:
        raise RealDataError(f"{path}: unreadable calibration ({error})") from None


def find_pairs(root=DATA_DIR):
    """``[(scene, left path, right path)]``, sorted by scene name."""
    if not os.path.isdir(root):
        raise RealDataError(f"OAK-D folder not found: {root}")
    scenes = sorted(name[: -len("_left.png")] for name in os.listdir(root)
                    if name.endswith("_left.png"))
    pairs = [(s, os.path.join(root, f"{s}_left.png"), os.path.join(root, f"{s}_right.png"))
             for s in scenes if os.path.isfile(os.path.join(root, f"{s}_right.png"))]
    if not pairs:
        raise RealDataError(f"no *_left.png / *_right.png pairs in {root}")
    return pairs


def measure_disparity(left, right, max_disparity=MAX_DISPARITY, min_disparity=MIN_DISPARITY):
    """The left image's disparity (float, NaN where unknown): StereoSGBM, kept
    where the right image's own match (the mirrored pair) agrees within 1 px
    and it is at least ``min_disparity``."""
    import cv2

    grey_l = cv2.cvtColor(left, cv2.COLOR_RGB2GRAY)
    grey_r = cv2.cvtColor(right, cv2.COLOR_RGB2GRAY)
    block = 5
    matcher = cv2.StereoSGBM_create(
        minDisparity=0, numDisparities=max_disparity, blockSize=block,
        P1=8 * block * block, P2=32 * block * block, uniquenessRatio=10,
        speckleWindowSize=100, speckleRange=2, disp12MaxDiff=1,
        mode=cv2.STEREO_SGBM_MODE_HH)
    d_left = matcher.compute(grey_l, grey_r).astype(np.float64) / 16.0
    # the right image's disparity: the same matcher on the mirrored pair
    d_right = matcher.compute(grey_r[:, ::-1].copy(), grey_l[:, ::-1].copy())
    d_right = d_right[:, ::-1].astype(np.float64) / 16.0
    height, width = d_left.shape
    cols = np.arange(width)[None, :].repeat(height, 0)
    target = np.rint(cols - d_left).astype(int)
    inside = (d_left > 0) & (target >= 0) & (target < width)
    back = np.full_like(d_left, np.nan)
    rows = np.arange(height)[:, None].repeat(width, 1)
    back[inside] = d_right[rows[inside], target[inside]]
    ok = inside & (d_left >= min_disparity) & (np.abs(back - d_left) <= 1.0)
    return np.where(ok, d_left, np.nan)


def draw_window(rng, valid):
    x0, y0, x1, y1 = valid
    width, height = x1 - x0, y1 - y0
    if rng.random() < FULL_IMAGE_SHARE:
        return x0, y0, width, height
    crop_w = int(rng.uniform(MIN_CROP_FRACTION, 1.0) * width)
    crop_h = int(np.clip(crop_w * rng.uniform(0.6, 1.6), MIN_CROP_FRACTION * height, height))
    return (int(rng.integers(x0, x1 - crop_w + 1)), int(rng.integers(y0, y1 - crop_h + 1)),
            crop_w, crop_h)


def _draw_pixel(rng, disparity, window):
    """A left pixel in ``window`` with a measured disparity whose right match
    is inside the window too (None if there is none)."""
    x0, y0, w, h = window
    block = disparity[y0:y0 + h, x0:x0 + w]
    rows, cols = np.nonzero(np.isfinite(block))
    u_left = cols + x0
    ok = (u_left - block[rows, cols]) >= x0
    if not ok.any():
        return None
    k = int(rng.choice(np.flatnonzero(ok)))
    return int(u_left[k]), int(rows[k] + y0)


def oakd_samples(crops_per_pair=20, image_size=112, seed=0, root=DATA_DIR):
    """Yield ``(left, right, labels)``: ``crops_per_pair`` crops of every pair."""
    cal = load_calibration(root)
    rig = rectified_camera(*(cal[k] for k in ("fx", "fy", "cx", "cy", "width", "height",
                                              "baseline")))
    rng = np.random.default_rng(seed)
    index = 0
    for pair_index, (scene, left_path, right_path) in enumerate(find_pairs(root)):
        left, right = read_rgb(left_path, RealDataError), read_rgb(right_path, RealDataError)
        if left.shape[:2] != (cal["height"], cal["width"]) or right.shape != left.shape:
            raise RealDataError(f"{scene}: images are not {cal['width']}x{cal['height']}")
        disparity = measure_disparity(left, right)
        drawn = tries = 0
        while drawn < crops_per_pair:
            tries += 1
            if tries > 100 * crops_per_pair:
                raise RealDataError(f"{scene}: no pixel with a measured disparity in "
                                    f"{tries} crops")
            window = draw_window(rng, cal["valid"])
            pixel = _draw_pixel(rng, disparity, window)
            if pixel is None:
                continue
            d_full = float(disparity[pixel[1], pixel[0]])
            crop_l, crop_r, labels = rectified_crop(
                left, right, window, pixel, d_full, d_full, rig, image_size)
            yield crop_l, crop_r, dict(labels, config_id=0, town_id=-1, frame_index=index,
                                       pair_index=pair_index)
            drawn += 1
            index += 1


def build_oakd(out, *, root=DATA_DIR, crops=20, image_size=112, seed=0, command=None):
    """Write the OAK-D test set to ``out`` (HDF5, atomic; ``crops`` per pair);
    returns the path."""
    crops, image_size = check_crop_settings(crops, image_size)
    check_sample_room(out, crops * len(find_pairs(root)), image_size, "crops")
    cal = load_calibration(root)
    shipped = os.path.abspath(os.fspath(root)) == DATA_DIR
    metadata = {
        "source": "OAK-D Lite pairs of the stereodemo package (" + (
            "cpl_keras/real/oakd_stereo" if shipped else os.path.abspath(os.fspath(root))) + ")",
        "rig": "oakd", "rectified": True, "crops_per_pair": crops,
        "image_size": image_size, "seed": int(seed),
        "calibration": {k: v for k, v in cal.items() if k != "valid"},
        "valid_window": list(cal["valid"]),
        "disparity": "measured: StereoSGBM with a left-right check (no ground truth)",
        "labels": "rig: right camera pose in the left camera frame; (u, v) in the right image",
        "command": command,
    }
    return write_samples(out, oakd_samples(crops, image_size, seed, root), image_size,
                         metadata, LABEL_DESCRIPTIONS)
