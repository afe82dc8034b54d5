"""A numpy ray caster for the procedural towns (``cpl_keras.data.scenes``).

Every pixel's viewing ray is the paper's Eq. 6: pixel (u, v) at depth
``xCam = 1`` gives the camera point ``(1, yCam, zCam)`` of Eqs. 4b-4c
(``camera.camera_point``), turned into the world by the camera-to-world
rotation ``frames.rotation_matrix(pitch, yaw, roll)``. Because the ray's
camera-frame x component is 1, the ray parameter ``t`` of a hit IS the
point's depth ``xCam`` along the optical axis: the depth map the renderer
returns is exactly the ``xCam`` of Eq. 4a.

Pixel centres sit at integer (u, v): column i is u = i, row j is v = j.

Geometry is intersected analytically and vectorised over all pixels: the
ground plane z = 0, the facade planes |y| = facade and |y| = back with
per-cell building tables, the side walls of the front buildings, and objects
(boxes, vertical cylinders, spheres) tested only inside their projected
screen rectangle. The sky is a dome ``SKY_DISTANCE`` metres away.

``render`` colours the hits with ``cpl_keras.data.shading`` and returns the
image with its depth map; ``depth_at`` casts single pixels.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from cpl_keras import camera, frames
from cpl_keras.data import scenes
from cpl_keras.data.scenes import BACK, FACADE, GROUND, OBJECT, SIDEWALL, SKY
from cpl_keras.data.scenes import BOX, CYLINDER, SPHERE
from cpl_keras.data.shading import shade

_TINY = 1e-12


@dataclass
class View:
    """One camera: pinhole intrinsics and its pose in the world.

    ``rotation`` is camera-to-world (``frames.rotation_matrix``), ``position``
    the camera centre in world coordinates (x fwd, y left, z up).
    """

    fx: float
    fy: float
    u0: float
    v0: float
    width: int
    height: int
    position: np.ndarray
    rotation: np.ndarray

    def rays(self, u=None, v=None):
        """World directions (3, ...) of pixels (u, v) (default: all pixel centres).

        The camera-frame ray is (1, yCam, zCam) at xCam = 1 (Eq. 6).
        """
        if u is None:
            cam = _camera_rays(float(self.fx), float(self.fy), float(self.u0), float(self.v0),
                               int(self.width), int(self.height))
            return np.tensordot(self.rotation, cam, axes=1)
        u = np.asarray(u, np.float64)
        v = np.asarray(v, np.float64)
        yCam, zCam = camera.camera_point(1.0, self.fx, self.fy, self.u0, self.v0, u, v)
        cam = np.stack(np.broadcast_arrays(np.ones_like(yCam), yCam, zCam))
        return np.tensordot(self.rotation, cam, axes=1)


@functools.lru_cache(maxsize=64)
def _camera_rays(fx, fy, u0, v0, width, height):
    """Camera-frame rays (1, yCam, zCam) of every pixel centre (Eq. 6), cached."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    yCam, zCam = camera.camera_point(1.0, fx, fy, u0, v0, u, v)
    rays = np.stack([np.ones_like(yCam), yCam, zCam])
    rays.flags.writeable = False
    return rays


# ---------------------------------------------------------------------------
# Ray casting
# ---------------------------------------------------------------------------
class Hits:
    """Per-ray nearest hit: depth t (= xCam), surface kind, id, face, period shift.

    Arrays are flat (one entry per ray); ``cast`` reshapes them to the rays'
    shape before returning.
    """

    def __init__(self, n, norm):
        self.t = scenes.SKY_DISTANCE / norm
        self.surface = np.full(n, SKY, np.int8)
        self.ident = np.zeros(n, np.int32)
        self.face = np.zeros(n, np.int8)
        self.xshift = np.zeros(n)               # period shift of the object hit

    def update(self, t, surface, ident=0, face=0):
        """Keep ``t`` (inf = no hit) where it is nearer than the current hit."""
        closer = t < self.t
        np.copyto(self.t, t, where=closer)
        np.copyto(self.surface, surface, where=closer, casting="unsafe")
        np.copyto(self.ident, ident, where=closer, casting="unsafe")
        np.copyto(self.face, face, where=closer, casting="unsafe")

    def update_objects(self, pix, t, ident, face, xshift):
        """Object hits at rays ``pix`` (several may share a ray): the nearest
        of those at a ray becomes its hit where it is nearer than the current one."""
        valid = t < self.t[pix]
        if not np.any(valid):
            return
        t, pix, ident, face, xshift = (a[valid] for a in (t, pix, ident, face, xshift))
        order = np.lexsort((t, pix))
        first = np.ones(order.size, bool)
        first[1:] = pix[order][1:] != pix[order][:-1]
        sel = order[first]
        p = pix[sel]
        self.t[p] = t[sel]
        self.surface[p] = OBJECT
        self.ident[p] = ident[sel]
        self.face[p] = face[sel]
        self.xshift[p] = xshift[sel]

    def reshape(self, shape):
        for name in ("t", "surface", "ident", "face", "xshift"):
            setattr(self, name, getattr(self, name).reshape(shape))
        return self


def cast(town, origin, rays, view=None):
    """Nearest hits of rays ``origin + t * rays`` (rays: (3, ...)) in ``town``.

    ``view`` (optional) enables screen-rectangle culling of objects for a
    full pixel grid; without it every nearby object is tested on every ray.
    """
    rays = np.asarray(rays, np.float64)
    shape = rays.shape[1:]
    d = rays.reshape(3, -1)
    ox, oy, oz = (float(c) for c in origin)
    dx, dy, dz = d
    hits = Hits(dx.size, np.sqrt(dx * dx + dy * dy + dz * dz))
    b = town.buildings
    heights = np.append(b["height"], -np.inf)     # id -1 (no building) never hits
    ncell = town.ncell

    with np.errstate(divide="ignore", invalid="ignore"):
        # Ground plane z = 0.
        hits.update(np.where(dz < 0, -oz / dz, np.inf), GROUND)

        # Facade planes: y = +distance (left side, table row 0) or -distance.
        side = dy < 0
        side_offset = side * ncell
        for row, distance, table, surface in ((0, town.facade, town.front_id, FACADE),
                                              (1, town.back, town.back_id, BACK)):
            t = (np.where(side, -distance, distance) - oy) / dy
            t = np.where(t > 1e-9, t, np.inf)
            tc = np.minimum(t, 1e6)
            x = ox + tc * dx
            z = oz + tc * dz
            fidx = side_offset + town.cell_index(x)
            bid = table.reshape(-1)[fidx]
            hit = (z >= 0) & (z < heights[bid])
            hits.update(np.where(hit, t, np.inf), surface, bid)
            if row == 0:
                # Side walls of the next (previous) building seen through a gap.
                g = np.flatnonzero((bid < 0) & (z >= 0) & (t < hits.t))
                if g.size:
                    forward = dx[g] > 0
                    fg = fidx[g]
                    base = np.floor(x[g] / town.cell) * town.cell
                    xs = base + np.where(forward, town.next_start.reshape(-1)[fg],
                                         town.prev_end.reshape(-1)[fg])
                    k = np.where(forward, town.next_id.reshape(-1)[fg],
                                 town.prev_id.reshape(-1)[fg])
                    ts = (xs - ox) / dx[g]
                    ys = np.abs(oy + ts * dy[g])
                    zs = oz + ts * dz[g]
                    wall = ((ts > 1e-9) & (ys >= town.facade) & (ys <= town.back)
                            & (zs >= 0) & (zs < heights[k]) & (ts < hits.t[g]))
                    w = g[wall]
                    hits.t[w] = ts[wall]
                    hits.surface[w] = SIDEWALL
                    hits.ident[w] = k[wall]
                    hits.face[w] = np.where(forward[wall], 0, 1)

    _cast_objects(town, np.array([ox, oy, oz]), d, hits, view)
    return hits.reshape(shape)


def _candidate_objects(town, origin, reach=960.0):
    """Indices and x shifts of objects within ``reach`` metres ahead (periodic town)."""
    o = town.objects
    xc = 0.5 * (o["lo"][:, 0] + o["hi"][:, 0])
    base = np.floor(origin[0] / town.period) * town.period
    idx, shift = [], []
    for k in (-1, 0, 1):
        s = base + k * town.period
        lo = np.searchsorted(xc, origin[0] - s - 40.0)
        hi = np.searchsorted(xc, origin[0] - s + reach)
        idx.append(np.arange(lo, hi))
        shift.append(np.full(hi - lo, s))
    return np.concatenate(idx), np.concatenate(shift)


def _cast_objects(town, origin, rays, hits, view):
    """Objects (boxes, cylinders, spheres), all tested in one vectorised batch.

    With a ``view`` each object is tested only on the pixels of its projected
    screen rectangle; without one, on every ray.
    """
    o = town.objects
    focal = max(view.fx, view.fy) if view is not None else 0.0
    # level of detail: objects (at most _MAX_OBJECT_SIZE m) further than this are
    # smaller than _LOD_PIXELS; they are skipped in full views
    reach = min(960.0, _MAX_OBJECT_SIZE * focal / _LOD_PIXELS) if view is not None else 960.0
    idx, shift = _candidate_objects(town, origin, reach)
    if len(idx) == 0:
        return
    if view is not None:
        lo = o["lo"][idx].copy()
        hi = o["hi"][idx].copy()
        lo[:, 0] += shift
        hi[:, 0] += shift
        pair_obj, pix = _covered_pixels(view, focal, lo, hi, hits.t)
    else:
        n_rays = hits.t.size
        pair_obj = np.repeat(np.arange(len(idx)), n_rays)
        pix = np.tile(np.arange(n_rays), len(idx))
    if pix.size == 0:
        return
    ident, xshift = idx[pair_obj], shift[pair_obj]
    t, face = _intersect_objects(o, origin, rays[:, pix], ident, xshift)
    hits.update_objects(pix, t, ident, face, xshift)


def _covered_pixels(view, focal, lo, hi, depth):
    """The (object, pixel) pairs to test: the pixels of each object's screen
    rectangle (its box: ``lo``, ``hi`` (n, 3)), less the objects smaller than
    ``_LOD_PIXELS`` and the large ones hidden behind what ``depth`` (the ray
    parameters of the hits so far, flat) already holds."""
    c0, c1, r0, r1, nearest = _screen_rects(view, lo, hi)
    size = np.max(hi - lo, axis=1)
    keep = (c1 > c0) & (r1 > r0) & (size * focal / np.maximum(nearest, 1e-3) > _LOD_PIXELS)
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


def _intersect_objects(objects, origin, d, ident, xshift):
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


_CORNERS = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], bool)
_EDGES = np.array([(a, b) for a in range(8) for b in range(a + 1, 8)
                   if (_CORNERS[a] != _CORNERS[b]).sum() == 1])
_NEAR = 1e-3
_MAX_OBJECT_SIZE = 8.0
_LOD_PIXELS = 0.75


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


def render(town, view):
    """Render ``view`` in ``town``: (uint8 RGB (H, W, 3), depth xCam float64 (H, W))."""
    rays = view.rays()
    hits = cast(town, view.position, rays, view)
    rgb = shade(town, view, np.asarray(view.position, np.float64), rays, hits)
    image = np.clip(rgb * 255.0 + 0.5, 0, 255).astype(np.uint8)
    return image, hits.t


def depth_at(town, view, u, v):
    """Depth xCam of the single pixel (u, v) of ``view`` (no culling, exact)."""
    rays = view.rays(np.atleast_1d(u), np.atleast_1d(v))
    return cast(town, view.position, rays).t
