"""A user's stereo pairs as image files: reading one pair (``read_pair``)
and finding every pair of a folder (``find_pairs``), for calibrate. Bad
input is a ``CalibrationError`` with a one-line message."""

from __future__ import annotations

import os

import numpy as np

from cpl_keras.errors import Error
from cpl_keras.images import read_rgb


class CalibrationError(Error):
    """Bad input to calibrate (one-line message)."""


def read_pair(left_path, right_path):
    """The two images of a pair, checked to be a pair (CalibrationError)."""
    left, right = read_rgb(left_path, CalibrationError), read_rgb(right_path, CalibrationError)
    if left.shape != right.shape:
        raise CalibrationError(
            f"left and right images differ in size: {left.shape[1]}x{left.shape[0]} "
            f"and {right.shape[1]}x{right.shape[0]}")
    if np.array_equal(left, right):
        raise CalibrationError("left and right images are identical: a stereo pair needs two "
                               "views")
    return left, right


def is_grey(image):
    """Whether the RGB ``image`` has no colour (its three channels equal)."""
    return bool(np.array_equal(image[..., 0], image[..., 1])
                and np.array_equal(image[..., 1], image[..., 2]))


IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm", ".pgm")


def find_pairs(folder):
    """The stereo pairs of ``folder``, sorted: image files whose names differ
    only by ``left`` -> ``right`` (any case: ``left01.jpg``/``right01.jpg``,
    ``desk_left.png``/``desk_right.png``), or files of the same name in
    ``folder/left`` and ``folder/right``. CalibrationError when there is
    none, or when a left image has no right one."""
    if not os.path.isdir(folder):
        raise CalibrationError(f"not a directory: {folder}")
    pairs, unmatched = [], []
    sides = [os.path.join(folder, side) for side in ("left", "right")]
    if all(os.path.isdir(side) for side in sides):
        names = sorted(n for n in os.listdir(sides[0]) if n.lower().endswith(IMAGE_SUFFIXES))
        for name in names:
            right = os.path.join(sides[1], name)
            (pairs if os.path.isfile(right) else unmatched).append(
                (os.path.join(sides[0], name), right))
    else:
        names = set(os.listdir(folder))
        for name in sorted(names):
            lower = name.lower()
            if "left" not in lower or not lower.endswith(IMAGE_SUFFIXES):
                continue
            at = lower.index("left")
            match = [n for n in names if n.lower() == lower[:at] + "right" + lower[at + 4:]]
            pair = (os.path.join(folder, name),
                    os.path.join(folder, match[0]) if match else None)
            (pairs if match else unmatched).append(pair)
    if unmatched:
        raise CalibrationError(f"{unmatched[0][0]} has no right image in {folder}")
    if not pairs:
        raise CalibrationError(f"no stereo pairs in {folder} (names with left/right, or "
                               "left/ and right/ folders of the same names)")
    return pairs
