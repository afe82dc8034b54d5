"""A user's stereo pairs as image files: reading one pair (``read_pair``),
finding every pair of a folder (``find_pairs``) and what its matched
features say against it (``pair_doubts``: one image turned against the
other, or left and right swapped), for calibrate. Bad input is a
``CalibrationError`` with a one-line message."""

from __future__ import annotations

import math
import os

import numpy as np

from cpl_keras.baselines.geometric import match_points
from cpl_keras.errors import Error
from cpl_keras.images import ORIENTATIONS, exif_orientation, read_rgb, resize_image


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


#: The longest side (px) a pair's features are matched at for ``pair_doubts``
#: (SIFT there: about 0.1 s a pair).
DOUBT_SIDE = 320
#: The fewest matches (or, for a turn, RANSAC inliers) that say anything.
DOUBT_MATCHES = 20
#: Matches whose right-image feature lies left of its left-image one: a
#: share at most this says swapped (measured at ``DOUBT_SIDE`` on the
#: shipped chessboard and OAK-D pairs: 0.93 or more as given, 0.26 or less
#: swapped).
SWAPPED_SHARE = 0.3


def _matches(left, right):
    """SIFT matches of the pair at ``DOUBT_SIDE``: (left points, right points)."""
    scale = min(1.0, DOUBT_SIDE / max(left.shape[:2]))
    if scale < 1.0:
        width, height = round(left.shape[1] * scale), round(left.shape[0] * scale)
        left, right = resize_image(left, width, height), resize_image(right, width, height)
    return match_points(left, right, detector="sift", upscale=1.0, ratio=0.7)


def _turn_deg(points_left, points_right):
    """The rotation (degrees) of the similarity that takes the left image's
    matched points onto the right's, or None when RANSAC finds no
    ``DOUBT_MATCHES`` inliers."""
    import cv2

    if len(points_left) < DOUBT_MATCHES:
        return None
    fit, inliers = cv2.estimateAffinePartial2D(points_left, points_right, method=cv2.RANSAC,
                                               ransacReprojThreshold=3.0)
    if fit is None or int(inliers.sum()) < DOUBT_MATCHES:
        return None
    return math.degrees(math.atan2(fit[1, 0], fit[0, 0]))


def pair_doubts(left, right, left_path, right_path):
    """What the pair's matched features say against it (lines, empty: none):
    the left image turned by 90 degrees or more against the right (a stereo
    rig's two images are taken alike: an EXIF orientation that one file has
    and the other not, say), or left and right swapped (a lateral rig's right
    image sees a point left of where the left image sees it; here most
    matches, mostly horizontal, lie the other way). Too few matches say
    nothing."""
    points_left, points_right = _matches(left, right)
    turn = _turn_deg(points_left, points_right)
    if turn is not None and abs(turn) > 45:
        said = [exif_orientation(path) for path in (left_path, right_path)]
        exif = "" if said[0] == said[1] else (
            f" (their EXIF orientations applied: the left file's {said[0]}, "
            f"{ORIENTATIONS[said[0]]}, the right file's {said[1]}, {ORIENTATIONS[said[1]]})")
        return [f"the left image is turned by about {abs(turn):.0f} degrees against the right "
                f"one{exif}: a rig's two images are taken alike; turn one to match the other"]
    if len(points_left) < DOUBT_MATCHES:
        return []
    shift = points_left - points_right          # (x_left - x_right: the disparity's sign)
    ahead = int(np.sum(shift[:, 0] > 0))
    lateral = np.median(np.abs(shift[:, 0])) >= np.median(np.abs(shift[:, 1]))
    if lateral and ahead <= SWAPPED_SHARE * len(shift):
        return [f"the pair looks swapped: in {len(shift) - ahead} of {len(shift)} matched "
                "features the right image's lies to the right of the left image's (a rig's "
                "right image sees a point further left); give the left camera's image first"]
    return []


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
