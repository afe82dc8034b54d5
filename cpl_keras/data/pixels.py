"""The projection pixel: which point of the right image a pair's disparity
and X, Y, Z labels describe.

Every protocol chooses the projection pixel (u, v) on scene geometry, by a
rule that depends on the image only, so that a network can tell from the
pair which point its disparity and X, Y, Z labels describe: the pixel
(W/2 + W/8, H/2 + H/16) when its point is nearer than ``MAX_LABEL_DISTANCE``
along the ray, otherwise the first pixel below it in the same column that is
(never the sky dome, whose 1000 m depth gave X, Y, Z labels of hundreds of
metres), down to 1/8 of the image from the bottom. The start is off the image
centre because the centre is the principal point of every cvgl rig, where
yCam = zCam = 0 (``projection_candidates``); pixels on the principal row or
column are skipped. If no candidate is near enough, the nearest pixel at
least 1/8 of the image from the border (and off the principal row and
column) is taken and the pair is flagged (``projection_fallback``). (A
pixel drawn at random per pair, as an earlier version did, makes those
labels unpredictable from the images: the network is not told the pixel.)
The release's fixed pixel is kept as such only for the as-released labels.

``rule`` is the rule as the dataset's metadata records it;
``choose_projection_pixel`` applies it to a rendered depth map.
"""

from __future__ import annotations

import numpy as np

from cpl_keras import camera

#: Projection pixels lie at least this fraction of the image from the border.
PROJECTION_MARGIN_FRACTION = 0.125
#: How the projection pixel is chosen, in words (see the module docstring).
PROJECTION_RULE = ("the pixel (W/2 + W/8, H/2 + H/16) when its point is nearer than "
                   "max_label_distance_m, else the first pixel below it in its column that "
                   "is; pixels within principal_clearance_px of the principal row or column "
                   "are skipped")
#: The projection column and first row, as offsets from the image centre in
#: fractions of the image side (see ``projection_candidates``).
PROJECTION_OFFSET = (1 / 8, 1 / 16)
#: A candidate is at least this far (pixels) from the principal row v0 and
#: column u0: on them zCam = 0 (v = v0) or yCam = 0 (u = u0), and the
#: disentangled term of fy (or fx's Y part) gets no gradient from the point.
PRINCIPAL_CLEARANCE = 1.0
#: A candidate is taken only if its point is nearer than this along the ray
#: (metres; the sky dome is at ``scenes.SKY_DISTANCE`` = 1000 m).
MAX_LABEL_DISTANCE = 200.0


def rule():
    """The projection-pixel rule as a dataset's metadata records it."""
    return {"projection_margin_fraction": PROJECTION_MARGIN_FRACTION,
            "projection_rule": PROJECTION_RULE,
            "projection_offset": list(PROJECTION_OFFSET),
            "principal_clearance_px": PRINCIPAL_CLEARANCE,
            "max_label_distance_m": MAX_LABEL_DISTANCE}


def projection_candidates(width, height, u0, v0):
    """The candidate projection pixels (u, v) of an image, in the order they
    are tried: the column ``W/2 + W/8`` from row ``H/2 + H/16`` down to the
    margin, less any pixel on the principal row or column (``off_principal``).

    The release projected the image centre, which is the principal point of
    every cvgl rig: there yCam = zCam = 0 and the point says nothing of fx,
    fy or pitch. This generator's former rule (the centre, then down its
    column) still left v = v0 in 45 % of the cvgl labels and u = u0 in 92 %,
    so the disentangled term of fy had no gradient from the point in half of
    every batch. The rule depends on the image size only, so a network can
    tell from the pair which point its disparity and X, Y, Z labels describe
    (a pixel drawn at random per pair would make those labels unpredictable:
    the network is not told the pixel).
    """
    margin = projection_margin(width)
    u = int(round(width / 2 + PROJECTION_OFFSET[0] * width))
    u = min(max(u, margin), width - margin - 1)
    first = int(round(height / 2 + PROJECTION_OFFSET[1] * height))
    rows = np.arange(min(first, height - margin - 1), height - margin)
    keep = off_principal(u, rows, u0, v0)
    return np.stack([np.full(int(keep.sum()), u), rows[keep]], axis=1).astype(float)


def off_principal(u, v, u0, v0):
    """True where pixel (u, v) is at least ``PRINCIPAL_CLEARANCE`` from the
    principal row v0 and column u0."""
    return (np.abs(np.asarray(u) - u0) >= PRINCIPAL_CLEARANCE) & \
        (np.abs(np.asarray(v) - v0) >= PRINCIPAL_CLEARANCE)


def projection_margin(size):
    """Smallest distance (pixels) of a projection pixel from the border."""
    return int(PROJECTION_MARGIN_FRACTION * size)


def release_pixel(width, height):
    """The release's fixed projection pixel (W/2, H/2) (56, 56 at 112 px)."""
    return width / 2, height / 2


def ray_distance(cfg, xCam, u, v):
    """Distance from the camera centre of the point at depth xCam seen at (u, v):
    xCam * |(1, yCam, zCam)| with the pixel's Eq. 6 ray."""
    ray_y, ray_z = camera.camera_point(1.0, cfg["fx"], cfg["fy"], cfg["u0"], cfg["v0"], u, v)
    return np.asarray(xCam) * np.sqrt(1.0 + np.square(ray_y) + np.square(ray_z))


def choose_projection_pixel(cfg, depth, candidates, margin, principal_point=None):
    """The projection pixel of a pair: ``((u, v), fallback)``.

    The first candidate (integer pixels) whose point is nearer than
    ``MAX_LABEL_DISTANCE`` along the ray (so never the sky) is taken,
    ``fallback = 0``. If none is, the nearest pixel at least ``margin`` from
    the border (and, given ``principal_point``, off its row and column,
    ``off_principal``) is taken (first in row-major order among
    equals), ``fallback = 1``.
    """
    cu = np.asarray(candidates)[:, 0].astype(np.intp)
    cv = np.asarray(candidates)[:, 1].astype(np.intp)
    distance = ray_distance(cfg, depth[cv, cu], cu, cv)
    near = np.flatnonzero(distance < MAX_LABEL_DISTANCE)
    if len(near):
        return (float(cu[near[0]]), float(cv[near[0]])), 0
    H, W = depth.shape
    v, u = np.mgrid[margin:H - margin, margin:W - margin]
    inner = ray_distance(cfg, depth[v, u], u, v)
    if principal_point is not None:
        inner = np.where(off_principal(u, v, *principal_point), inner, np.inf)
    k = int(np.argmin(inner))
    return (float(u.flat[k]), float(v.flat[k])), 1
