"""A numpy ray caster for the procedural towns (``cpl_keras.data.scenes``).

Every pixel's viewing ray is the paper's Eq. 6: pixel (u, v) at depth
``xCam = 1`` gives the camera point ``(1, yCam, zCam)`` of Eqs. 4b-4c
(``camera.camera_point``), turned into the world by the camera-to-world
rotation ``camera.rotation_matrix(pitch, yaw, roll)``. Because the ray's
camera-frame x component is 1, the ray parameter ``t`` of a hit IS the
point's depth ``xCam`` along the optical axis: the depth map the renderer
returns is exactly the ``xCam`` of Eq. 4a.

Pixel centres sit at integer (u, v): column i is u = i, row j is v = j.

Geometry is intersected analytically and vectorised over all pixels: the
ground plane z = 0, the facade planes |y| = facade and |y| = back with
per-cell building tables, the side walls of the front buildings, and objects
(boxes, vertical cylinders, spheres) tested only inside their projected
screen rectangle. The sky is a dome ``SKY_DISTANCE`` metres away.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cpl_keras import camera
from cpl_keras.data import scenes
from cpl_keras.data.scenes import BOX, CYLINDER, SPHERE
from cpl_keras.data.textures import MATERIAL_ID, texture_bank

SKY, GROUND, FACADE, SIDEWALL, BACK, OBJECT = range(6)
_TINY = 1e-12


@dataclass
class View:
    """One camera: pinhole intrinsics and its pose in the world.

    ``rotation`` is camera-to-world (``camera.rotation_matrix``), ``position``
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
            v, u = np.mgrid[0:self.height, 0:self.width].astype(np.float64)
        u = np.asarray(u, np.float64)
        v = np.asarray(v, np.float64)
        yCam, zCam = camera.camera_point(1.0, self.fx, self.fy, self.u0, self.v0, u, v)
        cam = np.stack(np.broadcast_arrays(np.ones_like(yCam), yCam, zCam))
        return np.tensordot(self.rotation, cam, axes=1)

    def project(self, points):
        """Pixel (u, v) and depth xCam of world points (..., 3) (Eqs. 4b-4c inverted)."""
        cam = (np.asarray(points) - self.position) @ self.rotation   # R^T (P - o)
        x = cam[..., 0]
        safe = np.where(np.abs(x) < 1e-9, 1e-9, x)
        u = self.u0 - self.fx * cam[..., 1] / safe
        v = self.v0 - self.fy * cam[..., 2] / safe
        return u, v, x


# ---------------------------------------------------------------------------
# Ray casting
# ---------------------------------------------------------------------------
class Hits:
    """Per-ray nearest hit: depth t (= xCam), surface kind, id and face."""

    def __init__(self, shape, norm):
        self.t = scenes.SKY_DISTANCE / norm
        self.surface = np.full(shape, SKY, np.int8)
        self.ident = np.zeros(shape, np.int32)
        self.face = np.zeros(shape, np.int8)

    def update(self, t, valid, surface, ident=0, face=0, where=None):
        """Keep ``t`` where valid and nearer; ``where`` is a slice for views."""
        sl = where if where is not None else slice(None)
        tb = self.t[sl]
        closer = valid & (t < tb)
        tb[closer] = t[closer]
        self.surface[sl][closer] = surface
        if np.ndim(ident):
            self.ident[sl][closer] = ident[closer]
        else:
            self.ident[sl][closer] = ident
        if np.ndim(face):
            self.face[sl][closer] = face[closer]
        else:
            self.face[sl][closer] = face


def _plane_t(origin, d, value):
    """Ray parameter where ``origin + t d`` reaches coordinate ``value`` (inf if parallel)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (value - origin) / d
    return np.where(np.isfinite(t) & (t > 1e-9), t, np.inf)


def cast(town, origin, rays, view=None):
    """Nearest hits of rays ``origin + t * rays`` (rays: (3, ...)) in ``town``.

    ``view`` (optional) enables screen-rectangle culling of objects for a
    full pixel grid; without it every nearby object is tested on every ray.
    """
    ox, oy, oz = (float(c) for c in origin)
    dx, dy, dz = rays
    norm = np.sqrt(dx * dx + dy * dy + dz * dz)
    hits = Hits(dx.shape, norm)
    b = town.buildings

    # Ground plane z = 0.
    hits.update(_plane_t(oz, dz, 0.0), dz < 0, GROUND)

    # Front facades: plane y = +facade (left side, side 0) or -facade (right).
    side = (dy < 0).astype(np.intp)
    for row, distance, table, surface in ((0, town.facade, town.front_id, FACADE),
                                          (1, town.back, town.back_id, BACK)):
        t = _plane_t(oy, dy, np.where(side == 0, distance, -distance))
        finite = np.isfinite(t)
        t_ok = np.where(finite, t, 0.0)
        x = ox + t_ok * dx
        z = oz + t_ok * dz
        cell = town.cell_index(x)
        bid = table[side, cell]
        height = b["height"][bid]
        hit = finite & (bid >= 0) & (z >= 0) & (z < height)
        hits.update(t, hit, surface, bid)
        if row == 0:
            # Side walls of the next (or previous) building seen through a gap.
            forward = dx > 0
            base = np.floor(x / town.cell) * town.cell
            xs = base + np.where(forward, town.next_start[side, cell], town.prev_end[side, cell])
            k = np.where(forward, town.next_id[side, cell], town.prev_id[side, cell])
            ts = _plane_t(ox, dx, xs)
            ts_ok = np.where(np.isfinite(ts), ts, 0.0)
            ys = np.abs(oy + ts_ok * dy)
            zs = oz + ts_ok * dz
            wall = (finite & (bid < 0) & np.isfinite(ts) & (ys >= town.facade)
                    & (ys <= town.back) & (zs >= 0) & (zs < b["height"][k]))
            hits.update(ts, wall, SIDEWALL, k, np.where(forward, 0, 1))

    _cast_objects(town, np.array([ox, oy, oz]), rays, hits, view)
    return hits


def _candidate_objects(town, origin):
    """Indices and x shifts of objects within reach of the camera (periodic town)."""
    o = town.objects
    xc = 0.5 * (o["lo"][:, 0] + o["hi"][:, 0])
    base = np.floor(origin[0] / town.period) * town.period
    idx, shift = [], []
    for k in (-1, 0, 1):
        s = base + k * town.period
        lo = np.searchsorted(xc, origin[0] - s - 40.0)
        hi = np.searchsorted(xc, origin[0] - s + 960.0)
        idx.append(np.arange(lo, hi))
        shift.append(np.full(hi - lo, s))
    return np.concatenate(idx), np.concatenate(shift)


def _cast_objects(town, origin, rays, hits, view):
    o = town.objects
    idx, shift = _candidate_objects(town, origin)
    if len(idx) == 0:
        return
    lo = o["lo"][idx].copy()
    hi = o["hi"][idx].copy()
    lo[:, 0] += shift
    hi[:, 0] += shift
    centre = o["centre"][idx].copy()
    centre[:, 0] += shift
    if view is not None:
        corners = np.stack([np.where(np.array([i, j, k], bool), hi, lo)
                            for i in (0, 1) for j in (0, 1) for k in (0, 1)], axis=1)
        u, v, depth = view.project(corners)
        near = depth.max(axis=1)
        keep = near > 1e-3
        size = np.max(hi - lo, axis=1)
        # level of detail: skip objects smaller than a third of a pixel
        keep &= size * max(view.fx, view.fy) / np.maximum(depth.min(axis=1), 1e-3) > 0.33
        behind = depth.min(axis=1) <= 1e-3
        c0 = np.where(behind, 0, np.floor(u.min(axis=1)) - 1).clip(0, view.width)
        c1 = np.where(behind, view.width, np.ceil(u.max(axis=1)) + 2).clip(0, view.width)
        r0 = np.where(behind, 0, np.floor(v.min(axis=1)) - 1).clip(0, view.height)
        r1 = np.where(behind, view.height, np.ceil(v.max(axis=1)) + 2).clip(0, view.height)
        keep &= (c1 > c0) & (r1 > r0)
        rects = np.stack([r0, r1, c0, c1], axis=1).astype(int)
    else:
        keep = np.ones(len(idx), bool)
        rects = None
    for n in np.flatnonzero(keep):
        if rects is not None:
            r0, r1, c0, c1 = rects[n]
            sl = (slice(r0, r1), slice(c0, c1))
            dx, dy, dz = rays[0][sl], rays[1][sl], rays[2][sl]
        else:
            sl = None
            dx, dy, dz = rays
        kind = o["kind"][idx[n]]
        if kind == BOX:
            t, valid, face = _box(origin, dx, dy, dz, lo[n], hi[n])
        elif kind == CYLINDER:
            t, valid = _cylinder(origin, dx, dy, dz, centre[n], o["radius"][idx[n]],
                                 lo[n, 2], hi[n, 2])
            face = 0
        else:
            t, valid = _sphere(origin, dx, dy, dz, centre[n], o["radius"][idx[n]])
            face = 0
        hits.update(t, valid, OBJECT, int(idx[n]), face, where=sl)
    hits.shift = dict(zip(idx.tolist(), shift.tolist()))


def _box(o, dx, dy, dz, lo, hi):
    tn = np.full(dx.shape, -np.inf)
    tf = np.full(dx.shape, np.inf)
    face = np.zeros(dx.shape, np.int8)
    for axis, d in enumerate((dx, dy, dz)):
        d = np.where(np.abs(d) < _TINY, _TINY, d)
        a = (lo[axis] - o[axis]) / d
        c = (hi[axis] - o[axis]) / d
        near = np.minimum(a, c)
        face = np.where(near > tn, axis, face)
        tn = np.maximum(tn, near)
        tf = np.minimum(tf, np.maximum(a, c))
    valid = (tn <= tf) & (tn > 1e-9)
    return tn, valid, face


def _cylinder(o, dx, dy, dz, c, r, z0, z1):
    px, py = o[0] - c[0], o[1] - c[1]
    a = np.maximum(dx * dx + dy * dy, _TINY)
    bb = dx * px + dy * py
    cc = px * px + py * py - r * r
    disc = bb * bb - a * cc
    t = (-bb - np.sqrt(np.maximum(disc, 0.0))) / a
    z = o[2] + t * dz
    return t, (disc > 0) & (t > 1e-9) & (z >= z0) & (z <= z1)


def _sphere(o, dx, dy, dz, c, r):
    p = o - c
    a = dx * dx + dy * dy + dz * dz
    bb = dx * p[0] + dy * p[1] + dz * p[2]
    cc = p @ p - r * r
    disc = bb * bb - a * cc
    t = (-bb - np.sqrt(np.maximum(disc, 0.0))) / a
    return t, (disc > 0) & (t > 1e-9)


# ---------------------------------------------------------------------------
# Shading
# ---------------------------------------------------------------------------
_TEXELS_PER_M = 64.0


def _hash(*ints):
    h = np.zeros_like(ints[0], dtype=np.int64)
    for k, i in zip((73856093, 19349663, 83492791), ints):
        h ^= (i.astype(np.int64) * k) & 0xFFFFFF
    return h


def _facade_albedo(town, bank, bid, along, z, footprint):
    """Wall texture with windows; ``along`` runs along the wall (metres)."""
    b = town.buildings
    rgb = bank.lookup(b["material"][bid], along * _TEXELS_PER_M, z * _TEXELS_PER_M,
                      footprint * _TEXELS_PER_M) * b["tint"][bid]
    local = along - np.where(b["row"][bid] == 0, 0.0, 0.0)
    pitch, floor = b["pitch"][bid], b["floor"][bid]
    col = np.floor(local / pitch)
    fc = local / pitch - col
    level = np.floor(z / floor)
    fz = z / floor - level
    window = (np.abs(fc - 0.5) < b["win_w"][bid] / 2) & (fz > 0.3) & (fz < 0.3 + b["win_h"][bid])
    window &= (level >= 1) & (z < b["height"][bid] - 0.8)
    shop = b["shop"][bid] & (level == 0) & (z > 0.5) & (z < 2.6) & (np.abs(fc - 0.5) < 0.42)
    glass = window | shop
    if np.any(glass):
        lit = (_hash(col.astype(np.int64), level.astype(np.int64), bid) % 9) == 0
        sky = 0.12 + 0.25 * np.clip(fz, 0, 1)[..., None] * np.array([0.8, 0.9, 1.0], np.float32)
        glass_rgb = np.where(lit[..., None], np.array([0.85, 0.75, 0.45], np.float32), sky)
        rgb = np.where(glass[..., None], glass_rgb, rgb)
        frame = (window & ((np.abs(fc - 0.5) > b["win_w"][bid] / 2 - 0.04)))
        rgb = np.where(frame[..., None], np.float32(0.85), rgb)
    cornice = z > b["height"][bid] - 0.35
    rgb = np.where(cornice[..., None], rgb * 0.7, rgb)
    return rgb


def _ground_albedo(town, bank, x, y, footprint):
    ay = np.abs(y)
    inter = town.intersection[town.cell_index(x)]
    rh = town.road_half
    road = (ay < rh) | inter
    curb = ~road & (ay < rh + 0.25)
    verge = ~road & ~curb & (ay < rh + 0.25 + town.verge)
    walk = ~road & ~curb & ~verge & (ay < town.facade)
    material = np.select(
        [road, curb, verge, walk],
        [MATERIAL_ID["asphalt"], MATERIAL_ID["curb"], MATERIAL_ID["grass"],
         town.sidewalk_material],
        MATERIAL_ID["asphalt_light"],
    )
    fp = footprint * _TEXELS_PER_M
    rgb = bank.lookup(material, x * _TEXELS_PER_M, y * _TEXELS_PER_M, fp)
    lane = ~inter & (ay < rh)
    if town.centre == "white_dashed":
        centre = (ay < 0.08) & (np.mod(x, 9.0) < 3.0)
        paint = np.float32(0.85)
    else:
        centre = (ay > 0.08) & (ay < 0.22)
        paint = np.array([0.85, 0.7, 0.15], np.float32)
    lanes = (np.abs(ay - rh / 2) < 0.07) & (np.mod(x, 12.0) < 4.0)
    edge = np.abs(ay - (rh - 0.35)) < 0.08
    # zebra crossings at the start of every block
    ahead = town.intersection[town.cell_index(x - 4.5)] & ~inter
    zebra = ahead & (ay < rh - 0.6) & (np.mod(y, 1.2) < 0.6)
    mark = lane & (centre | lanes | edge | zebra)
    # antialias markings: fade them out when a pixel covers much more than a stripe
    strength = np.clip(0.25 / np.maximum(footprint, 1e-6), 0.0, 1.0)[..., None]
    colour = np.where((lane & centre)[..., None], paint, np.float32(0.88))
    rgb = np.where(mark[..., None], rgb + (colour * (0.8 + 0.2 * rgb) - rgb) * strength, rgb)
    return rgb


def _object_albedo(town, bank, ident, face, P, footprint):
    o = town.objects
    look = o["look"][ident]
    colour = o["colour"][ident].astype(np.float32)
    lo, hi = o["lo"][ident], o["hi"][ident]
    x, y, z = P
    fp = footprint * _TEXELS_PER_M
    rgb = colour * bank.lookup(MATERIAL_ID["paint"], (x + y) * _TEXELS_PER_M,
                               z * _TEXELS_PER_M, fp) / 0.8
    body = look == scenes.CAR_BODY
    rgb = np.where((body & (z < 0.42))[..., None], np.float32(0.07), rgb)
    cabin = look == scenes.CAR_CABIN
    glass = cabin & (face != 2) & (z > lo[:, 2] + 0.06) & (z < hi[:, 2] - 0.08)
    rgb = np.where(glass[..., None], np.array([0.1, 0.12, 0.16], np.float32), rgb)
    metal = (look == scenes.POLE) | (look == scenes.LAMP)
    rgb = np.where(metal[..., None], colour * bank.lookup(
        MATERIAL_ID["metal"], x * _TEXELS_PER_M, z * _TEXELS_PER_M, fp) / 0.45, rgb)
    trunk = look == scenes.TRUNK
    rgb = np.where(trunk[..., None], bank.lookup(
        MATERIAL_ID["bark"], (x + y) * _TEXELS_PER_M * 2, z * _TEXELS_PER_M, fp), rgb)
    crown = look == scenes.CROWN
    rgb = np.where(crown[..., None], colour / 0.25 * bank.lookup(
        MATERIAL_ID["foliage"], (x + y) * _TEXELS_PER_M * 1.5, z * _TEXELS_PER_M * 1.5, fp),
        rgb)
    return rgb


def _object_normal(town, ident, face, P, D):
    o = town.objects
    kind = o["kind"][ident]
    n = np.zeros((len(ident), 3))
    rows = np.arange(len(ident))
    # box: the face axis, facing the ray
    n[rows, face] = -np.sign(D[face, rows])
    centre = o["centre"][ident]
    radial = P.T - centre
    cyl = kind == CYLINDER
    radial_c = radial.copy()
    radial_c[:, 2] = 0.0
    n = np.where(cyl[:, None], radial_c, n)
    n = np.where((kind == SPHERE)[:, None], radial, n)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-9)
    return n


def shade(town, view, origin, rays, hits):
    """RGB float32 image (H, W, 3) in [0, 1] for the hits of a full view."""
    bank = texture_bank()
    shape = hits.t.shape
    out = np.empty(shape + (3,), np.float32)
    dx, dy, dz = rays
    norm = np.sqrt(dx * dx + dy * dy + dz * dz)
    dist = hits.t * norm
    # size of one pixel on a fronto-parallel surface at this distance (metres)
    pixel = dist / max(view.fx, view.fy)
    surface = hits.surface
    P = np.stack([origin[k] + hits.t * rays[k] for k in range(3)])
    sun = town.sun

    # Sky: gradient and clouds projected on a plane above the town.
    m = surface == SKY
    if np.any(m):
        d = rays[:, m] / norm[m]
        elev = np.clip(d[2], 0.0, 1.0)
        w = np.clip(elev * 2.5, 0.0, 1.0)[:, None] ** 0.7
        rgb = (1 - w) * np.array([0.78, 0.84, 0.9], np.float32) + w * np.array(
            [0.32, 0.52, 0.85], np.float32)
        up = np.maximum(d[2], 0.02)
        cloud = texture_bank().lookup(MATERIAL_ID["clouds"], d[0] / up * 40.0, d[1] / up * 40.0,
                                      np.full(up.shape, 2.0) / up)[:, :1]
        cloud *= np.clip(d[2] * 6.0, 0.0, 1.0)[:, None]
        out[m] = rgb * (1 - cloud) + np.float32(0.95) * cloud

    ambient, diffuse = 0.5, 0.6
    m = surface == GROUND
    if np.any(m):
        cos_inc = np.abs(dz[m]) / norm[m]
        fp = pixel[m] / np.sqrt(np.maximum(cos_inc, 1e-3))
        rgb = _ground_albedo(town, bank, P[0, m], P[1, m], fp)
        out[m] = rgb * (ambient + diffuse * sun[2])
    for surface_kind in (FACADE, BACK):
        m = surface == surface_kind
        if np.any(m):
            bid = hits.ident[m]
            cos_inc = np.abs(dy[m]) / norm[m]
            fp = pixel[m] / np.sqrt(np.maximum(cos_inc, 1e-3))
            rgb = _facade_albedo(town, bank, bid, P[0, m], P[2, m], fp)
            normal_y = np.where(P[1, m] > 0, -1.0, 1.0)
            out[m] = rgb * (ambient + diffuse * np.maximum(0.0, normal_y * sun[1]))[:, None]
    m = surface == SIDEWALL
    if np.any(m):
        bid = hits.ident[m]
        cos_inc = np.abs(dx[m]) / norm[m]
        fp = pixel[m] / np.sqrt(np.maximum(cos_inc, 1e-3))
        rgb = _facade_albedo(town, bank, bid, np.abs(P[1, m]), P[2, m], fp)
        normal_x = np.where(hits.face[m] == 0, -1.0, 1.0)
        out[m] = rgb * (ambient + diffuse * np.maximum(0.0, normal_x * sun[0]))[:, None]
    m = surface == OBJECT
    if np.any(m):
        ident = hits.ident[m]
        face = hits.face[m].astype(np.intp)
        Pm = P[:, m].copy()
        shift = getattr(hits, "shift", {})
        if shift:
            Pm[0] -= np.array([shift.get(i, 0.0) for i in ident.tolist()])
        rgb = _object_albedo(town, bank, ident, face, Pm, pixel[m])
        n = _object_normal(town, ident, face, Pm, rays[:, m])
        out[m] = rgb * (ambient + diffuse * np.maximum(0.0, n @ sun))[:, None]

    # Aerial perspective: fade to the haze colour with distance (not the sky).
    fog = np.exp(-dist / town.haze)[..., None].astype(np.float32)
    solid = (surface != SKY)[..., None]
    out = np.where(solid, out * fog + town.haze_colour * (1 - fog), out)
    return out


def render(town, view):
    """Render ``view`` in ``town``: (uint8 RGB (H, W, 3), depth xCam float64 (H, W))."""
    rays = view.rays()
    hits = cast(town, view.position, rays, view)
    rgb = shade(town, view, view.position, rays, hits)
    image = np.clip(rgb * 255.0 + 0.5, 0, 255).astype(np.uint8)
    return image, hits.t


def depth_at(town, view, u, v):
    """Depth xCam of the single pixel (u, v) of ``view`` (no culling, exact)."""
    rays = view.rays(np.atleast_1d(u), np.atleast_1d(v))
    return cast(town, view.position, rays).t
