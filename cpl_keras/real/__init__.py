"""Real stereo data for the paper's Table 2, in the project's HDF5 schema.

* ``cpl_keras.real.middlebury``: crops and rescales of the Middlebury 2014
  "Motorcycle" pair that scikit-image ships (true right image, ground-truth
  disparity, exact intrinsics per crop).
* ``cpl_keras.real.tsinghua_cityscapes``: the Tsinghua-Daimler Cyclist
  Benchmark and Cityscapes, one layout (camera JSON, left image, 16-bit
  disparity PNG).
* ``cpl_keras.real.chessboard``: OpenCV's 13 sample chessboard pairs from one
  real, unrectified rig, every label derived from the images
  (``cv2.stereoCalibrate``, triangulated corners).
* ``cpl_keras.real.oakd``: twelve rectified pairs of an OAK-D Lite rig with
  its calibration (shipped; disparity measured by semi-global matching).
* ``cpl_keras.real.kitti``: the KITTI stereo 2015 / scene-flow and KITTI raw
  layouts (rectified projection matrices, ``disp_occ_0`` disparity).
* ``cpl_keras.real.build``: the command line that writes any of them as HDF5.

The helpers below are shared by the builders: a rectified pair's crop and
its labels, writing the samples (and, from ``cpl_keras.data.generate``, the
release's StereoBM disparity label). A rig's camera, with the exact
intrinsics of a crop + resize and the OpenCV-to-project axis change, is a
``cpl_keras.stereo_camera.StereoCamera``.
"""

from __future__ import annotations

import numpy as np

from cpl_keras import cli
from cpl_keras.frames import crop_resize_coordinate
from cpl_keras.data.pair import released_disparity  # noqa: F401  (the builders' label)
from cpl_keras.data.storage import min_bytes_per_pair
from cpl_keras.data.writer import StereoWriter
from cpl_keras.errors import Error
from cpl_keras.images import resize_image
from cpl_keras.stereo_camera import StereoCamera

#: Label conventions a real-data builder can write (see docs/real-data.md).
LABEL_MODES = ("rig", "vehicle")


class RealDataError(Error):
    """A real-data file or directory is missing or malformed (one-line message)."""


def rectified_camera(fx, fy, u0, v0, width, height, baseline):
    """The ``StereoCamera`` of a rectified rig in the "rig" convention: the
    right camera's intrinsics, no rotation, the right camera ``baseline``
    metres to the right (``ty = -baseline``)."""
    return StereoCamera(fx=fx, fy=fy, u0=u0, v0=v0, width=width, height=height,
                        baseline=baseline, pitch=0.0, tx=0.0, ty=-baseline, tz=0.0)


def rectified_crop(left, right, window, pixel, match, disparity, camera, image_size):
    """One sample of a rectified pair: both images cropped at ``window``
    ``(x0, y0, w, h)`` and resized to ``image_size`` squared, with the labels
    of the "rig" convention (the module doc of ``real.middlebury``).

    ``pixel`` = ``(u_left, v)``, a left pixel whose right match is ``match``
    pixels to its left; ``disparity`` is Eq. 4a's disparity there at full
    resolution (``match`` plus any offset of the principal points);
    ``camera`` the rig's ``StereoCamera`` at full resolution
    (``rectified_camera``). Returns ``(left crop, right crop, labels)``,
    labels as Python floats/ints."""
    x0, y0, cw, ch = window
    u_left, v_full = pixel
    crop = camera.crop(x0, y0, cw, ch)
    sx, sy = crop.resize_scales(image_size, image_size)
    small = crop.resize(image_size, image_size)
    u = float(crop_resize_coordinate(u_left - match, x0, sx))
    v = float(crop_resize_coordinate(v_full, y0, sy))
    d = sx * disparity
    X, Y, Z = small.to_world(u, v, d)
    crop_l = resize_image(left[y0:y0 + ch, x0:x0 + cw], image_size, image_size)
    crop_r = resize_image(right[y0:y0 + ch, x0:x0 + cw], image_size, image_size)
    return crop_l, crop_r, {
        **small.to_labels(disparity=d),
        "X": float(X), "Y": float(Y), "Z": float(Z), "u": u, "v": v,
        "disparity_released": released_disparity(crop_l, crop_r),
        "u_left": float(crop_resize_coordinate(u_left, x0, sx)),
        "crop_x0": x0, "crop_y0": y0, "crop_width": cw, "crop_height": ch,
    }


#: Labels of a rectified rig in the "rig" convention, shared by its builders.
RECTIFIED_LABEL_DESCRIPTIONS = {
    "disparity_released": "mean raw StereoBM(16, 15) output, as the release computed it",
    "tx": "right camera position in the left camera frame (0)",
    "ty": "right camera position in the left camera frame (-baseline: to the right)",
    "tz": "right camera position in the left camera frame (0)",
    "pitch": "relative pitch of the rectified pair (0)",
    "u": "projection pixel u in the RIGHT image (resized pixels)",
    "v": "projection pixel v (resized pixels)",
    "X": "image_to_world of the labels: the point in the left camera frame",
}


def check_crop_settings(crops, image_size, what="crops per pair"):
    """``(crops, image_size)`` as ints; ValueError (one line) when they cannot
    make a real set (StereoBM's block of 15 and 16 disparities need 32 px)."""
    crops, image_size = int(crops), int(image_size)
    if crops <= 0:
        raise ValueError(f"{what} must be positive, got {crops}")
    if image_size < 32:
        raise ValueError(f"image size must be at least 32 (StereoBM block 15 + 16 disparities), "
                         f"got {image_size}")
    return crops, image_size


#: Memory a sample holds beside its images until the file is written (its
#: labels as a dict of Python numbers): ``check_sample_room``.
SAMPLE_LABEL_BYTES = 4096


def check_sample_room(out, samples, image_size, what="samples"):
    """Raise ValueError (one line) before any work when ``samples`` samples
    of ``image_size`` px cannot be built into ``out``: ``write_samples``
    holds them all in memory (two raw images and the labels each), and the
    file needs at least ``storage.min_bytes_per_pair`` a sample on disk."""
    raw = 2 * image_size * image_size * 3
    cli.check_room(f"{samples} {what} at {image_size} px", out,
                   disk=samples * min_bytes_per_pair(image_size, 32),  # (about 30 labels)
                   memory=samples * (raw + SAMPLE_LABEL_BYTES))


def write_samples(out, samples, image_size, metadata, label_descriptions, block=64):
    """Write ``(left, right, labels)`` samples to the HDF5 file ``out``
    (atomically, ``block`` at a time); returns the path."""
    samples = list(samples)
    with StereoWriter(out, len(samples), image_size, metadata=metadata,
                      label_descriptions=label_descriptions) as writer:
        for start in range(0, len(samples), block):
            part = samples[start:start + block]
            labels = {name: np.array([s[2][name] for s in part]) for name in part[0][2]}
            writer.write(start, np.stack([s[0] for s in part]), np.stack([s[1] for s in part]),
                         labels)
    return str(out)
