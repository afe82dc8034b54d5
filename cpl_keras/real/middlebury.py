"""A real test set from the Middlebury 2014 "Motorcycle" pair.

``skimage.data.stereo_motorcycle()`` ships offline: a rectified left and
right image (500 x 741, a 4x down-sampled Middlebury 2014 pair), the left
image's ground-truth disparity (nan = unknown) and, in its docstring, the
calibration ``CALIBRATION``. Middlebury disparities are measured between two
cameras whose principal points differ by ``doffs`` in x (``cx1 - cx0 =
doffs``), so depth is ``Z = baseline * f / (d + doffs)``: the disparity of
paper Eq. 4a (``d = fx * b / xCam``, one shared principal point) is
``d + doffs``.

``build_middlebury`` draws many crops (random size, aspect and position; some
cover the whole image) of both images at the same window, resizes each to
``image_size`` x ``image_size`` and transforms the intrinsics exactly
(``StereoCamera.crop`` and ``resize``). Labels follow the project's
conventions ("rig" mode): extrinsics are the right camera's pose in the left
camera frame (x forward, y left, z up), so ``pitch = tx = tz = 0`` and
``ty = -baseline`` (the right camera is to the right); the projection pixel
``(u, v)`` is in the RIGHT image, at a point whose ground-truth disparity is
known and whose left match lies inside the crop; ``u0`` is the right
camera's principal point; ``disparity = sx * (d + doffs)`` (Eq. 4a in the
resized pixels), and ``X, Y, Z = camera.image_to_world(...)`` is the point in
the left camera frame. Extra labels keep the crop window, the left camera's
principal point (``u0_left``) and the pixel in the left image (``u_left``).
"""

from __future__ import annotations

import numpy as np

from cpl_keras.frames import crop_resize_coordinate
from cpl_keras.real import (
    RECTIFIED_LABEL_DESCRIPTIONS, check_crop_settings, check_sample_room, rectified_camera,
    rectified_crop, write_samples,
)

#: Calibration of the pair as scikit-image documents it (pixels, metres).
CALIBRATION = {
    "focal": 994.978, "cx0": 311.193, "cy": 254.877, "doffs": 31.086, "baseline": 0.193001,
}
#: Smallest crop side, as a fraction of the image side.
MIN_CROP_FRACTION = 0.25
#: Share of samples that use the whole image (a pure rescale).
FULL_IMAGE_SHARE = 0.1

LABEL_DESCRIPTIONS = {
    "fx": "right (and left) camera focal length along u after crop + resize",
    "fy": "focal length along v after crop + resize",
    "u0": "RIGHT camera principal point u after crop + resize (left: u0_left)",
    "v0": "principal point v after crop + resize",
    "baseline": "193.001 mm (Middlebury calibration)",
    "disparity": "sx * (d + doffs): Eq. 4a disparity fx * b / xCam in resized pixels",
    **RECTIFIED_LABEL_DESCRIPTIONS,
}


def load_motorcycle():
    """``(left, right, disparity, calibration)``: uint8 RGB images, the left
    image's ground-truth disparity (float64, nan where unknown)."""
    from skimage import data

    left, right, disparity = data.stereo_motorcycle()
    disparity = np.asarray(disparity, dtype=np.float64)
    disparity[~np.isfinite(disparity)] = np.nan
    return left, right, disparity, dict(CALIBRATION)


def draw_window(rng, width, height):
    if rng.random() < FULL_IMAGE_SHARE:
        return 0, 0, width, height
    crop_w = int(rng.uniform(MIN_CROP_FRACTION, 1.0) * width)
    aspect = rng.uniform(0.6, 1.6)                       # crop height / crop width
    crop_h = int(np.clip(crop_w * aspect, MIN_CROP_FRACTION * height, height))
    x0 = int(rng.integers(0, width - crop_w + 1))
    y0 = int(rng.integers(0, height - crop_h + 1))
    return x0, y0, crop_w, crop_h


def _draw_pixel(rng, disparity, window):
    """An integer left pixel inside ``window`` with known disparity whose right
    match ``u_left - d`` is inside the window too (None if there is none)."""
    x0, y0, w, h = window
    block = disparity[y0:y0 + h, x0:x0 + w]
    rows, cols = np.nonzero(np.isfinite(block))
    u_left = cols + x0
    u_right = u_left - block[rows, cols]
    ok = (u_right >= x0) & (u_right <= x0 + w - 1)
    if not ok.any():
        return None
    k = int(rng.choice(np.flatnonzero(ok)))
    return int(u_left[k]), int(rows[k] + y0)


def middlebury_samples(crops, image_size=112, seed=0):
    """Yield ``(left, right, labels)`` for ``crops`` random crops (one sample
    each; labels are Python floats/ints, see the module doc)."""
    left, right, disparity, cal = load_motorcycle()
    height, width = disparity.shape
    f, cx0, cy, doffs, b = (cal[k] for k in ("focal", "cx0", "cy", "doffs", "baseline"))
    rig = rectified_camera(f, f, cx0 + doffs, cy, width, height, b)
    rng = np.random.default_rng(seed)
    index = 0
    while index < crops:
        window = draw_window(rng, width, height)
        pixel = _draw_pixel(rng, disparity, window)
        if pixel is None:
            continue
        x0, y0, cw, ch = window
        d_full = float(disparity[pixel[1], pixel[0]])
        crop_l, crop_r, labels = rectified_crop(left, right, window, pixel, d_full,
                                                d_full + doffs, rig, image_size)
        labels.update(u0_left=float(crop_resize_coordinate(cx0, x0, image_size / cw)),
                      config_id=index, town_id=-1, frame_index=index)
        yield crop_l, crop_r, labels
        index += 1


def build_middlebury(out, *, crops=500, image_size=112, seed=0, block=64, command=None):
    """Write the Middlebury test set to ``out`` (HDF5, atomic); returns the path."""
    crops, image_size = check_crop_settings(crops, image_size, what="number of crops")
    check_sample_room(out, crops, image_size, "crops")
    metadata = {
        "source": "Middlebury 2014 Motorcycle (skimage.data.stereo_motorcycle, 4x down-sampled)",
        "rig": "middlebury", "rectified": True,
        "calibration": CALIBRATION, "crops": crops, "image_size": image_size, "seed": int(seed),
        "labels": "rig: right camera pose in the left camera frame; (u, v) in the right image",
        "min_crop_fraction": MIN_CROP_FRACTION, "full_image_share": FULL_IMAGE_SHARE,
        "command": command,
    }
    return write_samples(out, middlebury_samples(crops, image_size, seed), image_size, metadata,
                         LABEL_DESCRIPTIONS, block=block)
