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
screen rectangle (``cpl_keras.data.objects``). The sky is a dome ``SKY_DISTANCE`` metres away.

``render`` colours the hits with ``cpl_keras.data.shading`` and returns the
image with its depth map; ``depth_at`` casts single pixels.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from cpl_keras import camera, frames
from cpl_keras.data import objects, scenes
from cpl_keras.data.scenes import BACK, FACADE, GROUND, OBJECT, SIDEWALL, SKY
from cpl_keras.data.shading import shade

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
    # level of detail: objects (at most MAX_OBJECT_SIZE m) further than this are
    # smaller than LOD_PIXELS; they are skipped in full views
    reach = min(960.0, objects.MAX_OBJECT_SIZE * focal / objects.LOD_PIXELS) \
        if view is not None else 960.0
    idx, shift = _candidate_objects(town, origin, reach)
    if len(idx) == 0:
        return
    if view is not None:
        lo = o["lo"][idx].copy()
        hi = o["hi"][idx].copy()
        lo[:, 0] += shift
        hi[:, 0] += shift
        pair_obj, pix = objects.covered_pixels(view, focal, lo, hi, hits.t)
    else:
        n_rays = hits.t.size
        pair_obj = np.repeat(np.arange(len(idx)), n_rays)
        pix = np.tile(np.arange(n_rays), len(idx))
    if pix.size == 0:
        return
    ident, xshift = idx[pair_obj], shift[pair_obj]
    t, face = objects.intersect(o, origin, rays[:, pix], ident, xshift)
    hits.update_objects(pix, t, ident, face, xshift)


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
