"""The towns' objects (boxes, vertical cylinders, spheres) as the ray caster
(``cpl_keras.data.render``) meets them: which pixels each may cover, and
where a ray hits it.

``covered_pixels`` gives the (object, pixel) pairs worth testing in a view:
each object's screen rectangle (a bounding sphere's, then the exact outline
of its box clipped to the near plane), less the objects smaller than
``LOD_PIXELS`` and the large ones hidden behind what is already hit.
``intersect`` gives the ray parameter t of each ray against its object
(``inf`` on a miss), analytically and vectorised: a slab test for boxes, the
side surface of vertical cylinders, spheres.
"""

from __future__ import annotations

import numpy as np

from cpl_keras import camera
from cpl_keras.data.scenes import BOX, CYLINDER, SPHERE

#: A ray direction component below this is taken as this (the slab test).
_TINY = 1e-12
_CORNERS = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], bool)
_EDGES = np.array([(a, b) for a in range(8) for b in range(a + 1, 8)
                   if (_CORNERS[a] != _CORNERS[b]).sum() == 1])
#: The near plane (xCam, metres) a box near the camera is clipped to.
_NEAR = 1e-3
#: Objects are at most this large (metres): the level of detail's reach.
MAX_OBJECT_SIZE = 8.0
#: Objects smaller than this on screen (pixels) are skipped in full views.
LOD_PIXELS = 0.75


def covered_pixels(view, focal, lo, hi, depth):
    """The (object, pixel) pairs to test: the pixels of each object's screen
    rectangle (its box: ``lo``, ``hi`` (n, 3)), less the objects smaller than
    ``LOD_PIXELS`` and the large ones hidden behind what ``depth`` (the ray
    parameters of the hits so far, flat) already holds."""
    c0, c1, r0, r1, nearest = _screen_rects(view, lo, hi)
    size = np.max(hi - lo, axis=1)
    keep = (c1 > c0) & (r1 > r0) & (size * focal / np.maximum(nearest, 1e-3) > LOD_PIXELS)
    # tighten the bounding-sphere rectangles of the survivors: exact box outlines
    k = np.flatnonzero(keep)
    if k.size:
        e0, e1, f0, f1, _ = _clipped_rects(view, lo[k], hi[k])
        c0[k], c1[k] = np.maximum(c0[k], e0), np.minimum(c1[k], e1)
        r0[k], r1[k] = np.maximum(r0[k], f0), np.minimum(r1[k], f1)
        keep[k] = (c1[k] > c0[k]) & (r1[k] > r0[k])
    # skip large objects hidden behind what is already there (walls, ground)
    grid = depth.reshape(view.height, view.width)
    big = keep & ((c1 - c0) * (r1 - r0) > 64)
    for n in np.flatnonzero(big):
        if grid[r0[n]:r1[n], c0[n]:c1[n]].max() < nearest[n]:
            keep[n] = False
    obj = np.flatnonzero(keep)
    return _rect_pixels(obj, c0[obj], c1[obj], r0[obj], r1[obj], view.width)


def _rect_pixels(obj, c0, c1, r0, r1, width):
    """Every pixel of the rectangles [r0, r1) x [c0, c1) of objects ``obj``,
    object after object, row by row: (object of each pixel, flat pixel index
    in an image ``width`` wide)."""
    widths = c1 - c0
    areas = widths * (r1 - r0)
    pair = np.repeat(np.arange(obj.size), areas)
    offsets = np.repeat(np.cumsum(areas) - areas, areas)
    local = np.arange(pair.size) - offsets
    w = np.repeat(widths, areas)
    return obj[pair], (r0[pair] + local // w) * width + c0[pair] + local % w


def intersect(objects, origin, d, ident, xshift):
    """Ray parameters t (inf on a miss) and box face axes of rays ``d`` (3, n)
    from ``origin``: ray i against object ``ident[i]`` moved by ``xshift[i]``
    along x (the town's period)."""
    kind = objects["kind"][ident]
    lo = objects["lo"][ident]
    hi = objects["hi"][ident]
    lo[:, 0] += xshift
    hi[:, 0] += xshift
    t = np.full(ident.size, np.inf)
    face = np.zeros(ident.size, np.int8)
    m = kind == BOX
    if np.any(m):
        t[m], face[m] = _box(origin, d[:, m], lo[m], hi[m])
    m = kind == CYLINDER
    if np.any(m):
        centre = objects["centre"][ident[m]]
        t[m] = _cylinder(origin, d[:, m], centre[:, 0] + xshift[m], centre[:, 1],
                         objects["radius"][ident[m]], lo[m, 2], hi[m, 2])
    m = kind == SPHERE
    if np.any(m):
        centre = objects["centre"][ident[m]].copy()
        centre[:, 0] += xshift[m]
        t[m] = _sphere(origin, d[:, m], centre, objects["radius"][ident[m]])
    return t, face


def _screen_rects(view, lo, hi):
    """Pixel rectangles [r0, r1) x [c0, c1) covering boxes (lo, hi) (n, 3), and a
    lower bound of the depth of each box.

    Boxes well in front of the camera use their bounding sphere (cheap);
    boxes near or across the camera plane are clipped to the near plane
    xCam = _NEAR exactly (``_clipped_rects``).
    """
    centre = 0.5 * (lo + hi)
    radius = 0.5 * np.sqrt(((hi - lo) ** 2).sum(axis=1))
    cam = (centre - view.position) @ view.rotation
    x = cam[:, 0]
    nearest = x - radius
    W, H = view.width, view.height
    ahead = nearest > 0.05 * np.maximum(radius, 1.0)
    # a sphere seen from distance x: its image lies within fx * r / (x - r) of the centre
    safe = np.where(ahead, nearest, 1.0)
    u, v = camera.camera_to_pixel(np.where(ahead, x, 1.0), cam[:, 1], cam[:, 2],
                                  view.fx, view.fy, view.u0, view.v0)
    # |u(p) - u(centre)| <= fx r / (x - r) * (1 + |yCam| / x) for every point p
    # of the sphere (and likewise for v)
    ru = view.fx * radius / safe * (1.0 + np.abs(cam[:, 1]) / np.where(ahead, x, 1.0))
    rv = view.fy * radius / safe * (1.0 + np.abs(cam[:, 2]) / np.where(ahead, x, 1.0))
    c0 = np.floor(np.clip(u - ru, -1, W + 1)).astype(np.intp).clip(0, W)
    c1 = (np.ceil(np.clip(u + ru, -1, W + 1)) + 1).astype(np.intp).clip(0, W)
    r0 = np.floor(np.clip(v - rv, -1, H + 1)).astype(np.intp).clip(0, H)
    r1 = (np.ceil(np.clip(v + rv, -1, H + 1)) + 1).astype(np.intp).clip(0, H)
    near = np.flatnonzero(~ahead & (x + radius > _NEAR))
    c0[~ahead] = c1[~ahead] = 0
    if near.size:
        c0[near], c1[near], r0[near], r1[near], nearest[near] = _clipped_rects(
            view, lo[near], hi[near])
    return c0, c1, r0, r1, nearest


def _clipped_rects(view, lo, hi):
    """Exact screen rectangles of boxes clipped to the near plane xCam = _NEAR."""
    corners = np.where(_CORNERS[None], hi[:, None], lo[:, None])          # (n, 8, 3)
    cam = (corners - view.position) @ view.rotation                       # (n, 8, 3)
    ca, cb = cam[:, _EDGES[:, 0]], cam[:, _EDGES[:, 1]]                   # (n, 12, 3)
    da, db = ca[..., 0], cb[..., 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (_NEAR - da) / (db - da)
    crossing = (da - _NEAR) * (db - _NEAR) < 0
    clipped = ca + np.where(crossing, s, 0.0)[..., None] * (cb - ca)
    points = np.concatenate([cam, clipped], axis=1)                       # (n, 20, 3)
    ok = np.concatenate([cam[..., 0] >= _NEAR, crossing], axis=1)
    x = np.where(ok, points[..., 0], 1.0)
    u, v = camera.camera_to_pixel(x, points[..., 1], points[..., 2],
                                  view.fx, view.fy, view.u0, view.v0)
    big = 1e9
    umin = np.where(ok, u, big).min(axis=1)
    umax = np.where(ok, u, -big).max(axis=1)
    vmin = np.where(ok, v, big).min(axis=1)
    vmax = np.where(ok, v, -big).max(axis=1)
    W, H = view.width, view.height
    c0 = np.floor(np.clip(umin, -1, W + 1)).astype(np.intp).clip(0, W)
    c1 = (np.ceil(np.clip(umax, -1, W + 1)) + 1).astype(np.intp).clip(0, W)
    r0 = np.floor(np.clip(vmin, -1, H + 1)).astype(np.intp).clip(0, H)
    r1 = (np.ceil(np.clip(vmax, -1, H + 1)) + 1).astype(np.intp).clip(0, H)
    nearest = np.where(ok, points[..., 0], np.inf).min(axis=1)
    return c0, c1, r0, r1, nearest


def _box(o, d, lo, hi):
    """Slab test; returns (t, face axis) with t = inf on a miss."""
    tn = np.full(d.shape[1], -np.inf)
    tf = np.full(d.shape[1], np.inf)
    face = np.zeros(d.shape[1], np.int8)
    for axis in range(3):
        da = d[axis]
        da = np.where(np.abs(da) < _TINY, _TINY, da)
        a = (lo[:, axis] - o[axis]) / da
        c = (hi[:, axis] - o[axis]) / da
        near = np.minimum(a, c)
        face = np.where(near > tn, axis, face)
        tn = np.maximum(tn, near)
        tf = np.minimum(tf, np.maximum(a, c))
    return np.where((tn <= tf) & (tn > 1e-9), tn, np.inf), face


def _cylinder(o, d, xc, yc, r, z0, z1):
    """Vertical cylinder (side surface only); t = inf on a miss."""
    px, py = o[0] - xc, o[1] - yc
    a = np.maximum(d[0] * d[0] + d[1] * d[1], _TINY)
    bb = d[0] * px + d[1] * py
    cc = px * px + py * py - r * r
    disc = bb * bb - a * cc
    t = (-bb - np.sqrt(np.maximum(disc, 0.0))) / a
    z = o[2] + t * d[2]
    return np.where((disc > 0) & (t > 1e-9) & (z >= z0) & (z <= z1), t, np.inf)


def _sphere(o, d, c, r):
    p = o - c
    a = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
    bb = d[0] * p[:, 0] + d[1] * p[:, 1] + d[2] * p[:, 2]
    cc = (p * p).sum(axis=1) - r * r
    disc = bb * bb - a * cc
    t = (-bb - np.sqrt(np.maximum(disc, 0.0))) / a
    return np.where((disc > 0) & (t > 1e-9), t, np.inf)
