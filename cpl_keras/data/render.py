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

import functools
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

    def reshape(self, shape):
        for name in ("t", "surface", "ident", "face", "xshift"):
            setattr(self, name, getattr(self, name).reshape(shape))
        return self


def _cell(town, x):
    """Per-cell table index of world x (the towns are periodic, ncell a power of 2)."""
    return ((x + 8 * town.period) * (1.0 / town.cell)).astype(np.intp) & (town.ncell - 1)


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
            fidx = side_offset + _cell(town, x)
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
    lo = o["lo"][idx].copy()
    hi = o["hi"][idx].copy()
    lo[:, 0] += shift
    hi[:, 0] += shift
    flat_t = hits.t
    n_rays = flat_t.size
    if view is not None:
        W, H = view.width, view.height
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
        grid = hits.t.reshape(H, W)
        big = keep & ((c1 - c0) * (r1 - r0) > 64)
        for n in np.flatnonzero(big):
            if grid[r0[n]:r1[n], c0[n]:c1[n]].max() < nearest[n]:
                keep[n] = False
        obj = np.flatnonzero(keep)
        widths = c1[obj] - c0[obj]
        areas = widths * (r1[obj] - r0[obj])
        pair_obj = np.repeat(obj, areas)
        offsets = np.repeat(np.cumsum(areas) - areas, areas)
        local = np.arange(pair_obj.size) - offsets
        w = np.repeat(widths, areas)
        pix = (r0[pair_obj] + local // w) * W + c0[pair_obj] + local % w
    else:
        pair_obj = np.repeat(np.arange(len(idx)), n_rays)
        pix = np.tile(np.arange(n_rays), len(idx))
    if pix.size == 0:
        return
    d = rays[:, pix]
    kind = o["kind"][idx[pair_obj]]
    t = np.full(pix.size, np.inf)
    face = np.zeros(pix.size, np.int8)
    m = kind == BOX
    if np.any(m):
        t[m], face[m] = _box(origin, d[:, m], lo[pair_obj[m]], hi[pair_obj[m]])
    m = kind == CYLINDER
    if np.any(m):
        centre = o["centre"][idx[pair_obj[m]]]
        t[m] = _cylinder(origin, d[:, m], centre[:, 0] + shift[pair_obj[m]], centre[:, 1],
                         o["radius"][idx[pair_obj[m]]], lo[pair_obj[m], 2], hi[pair_obj[m], 2])
    m = kind == SPHERE
    if np.any(m):
        centre = o["centre"][idx[pair_obj[m]]].copy()
        centre[:, 0] += shift[pair_obj[m]]
        t[m] = _sphere(origin, d[:, m], centre, o["radius"][idx[pair_obj[m]]])
    valid = t < flat_t[pix]
    if not np.any(valid):
        return
    t, pix, face, pair_obj = t[valid], pix[valid], face[valid], pair_obj[valid]
    order = np.lexsort((t, pix))
    first = np.ones(order.size, bool)
    first[1:] = pix[order][1:] != pix[order][:-1]
    sel = order[first]
    p = pix[sel]
    flat_t[p] = t[sel]
    hits.surface[p] = OBJECT
    hits.ident[p] = idx[pair_obj[sel]]
    hits.face[p] = face[sel]
    hits.xshift[p] = shift[pair_obj[sel]]


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


# ---------------------------------------------------------------------------
# Shading
# ---------------------------------------------------------------------------
_TEXELS_PER_M = 64.0


def _hash(*ints):
    h = np.zeros_like(ints[0], dtype=np.int64)
    for k, i in zip((73856093, 19349663, 83492791), ints):
        h ^= (i.astype(np.int64) * k) & 0xFFFFFF
    return h


def _facade_albedo(town, bank, bid, along, local, z, footprint):
    """Wall texture with windows. ``along`` (texture) and ``local`` (window grid)
    run along the wall in metres, ``z`` up it."""
    b = town.buildings
    rgb = bank.lookup(b["material"][bid], along * _TEXELS_PER_M, z * _TEXELS_PER_M,
                      footprint * _TEXELS_PER_M) * b["tint"][bid]
    pitch, floor, win_w = b["pitch"][bid], b["floor"][bid], b["win_w"][bid]
    col = np.floor(local / pitch)
    fc = np.abs(local / pitch - col - 0.5)
    level = np.floor(z / floor)
    fz = z / floor - level
    window = (fc < win_w / 2) & (fz > 0.3) & (fz < 0.3 + b["win_h"][bid])
    window &= (level >= 1) & (z < b["height"][bid] - 0.8)
    shop = b["shop"][bid] & (level == 0) & (z > 0.5) & (z < 2.6) & (fc < 0.42)
    glass = window | shop
    if np.any(glass):
        g = np.flatnonzero(glass)
        lit = (_hash(col[g].astype(np.int64), level[g].astype(np.int64), bid[g]) % 9) == 0
        sky = 0.12 + 0.25 * np.clip(fz[g], 0, 1)[:, None] * np.array([0.8, 0.9, 1.0], np.float32)
        rgb[g] = np.where(lit[:, None], np.array([0.85, 0.75, 0.45], np.float32), sky)
        frame = window[g] & (fc[g] > win_w[g] / 2 - 0.05)
        rgb[g[frame]] = 0.8
    cornice = z > b["height"][bid] - 0.35
    rgb[cornice] *= 0.7
    return rgb


def _ground_albedo(town, bank, x, y, footprint):
    ay = np.abs(y)
    inter = town.intersection[_cell(town, x)]
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
    scale = np.where(road, 2.0 * _TEXELS_PER_M, _TEXELS_PER_M)   # fine-grained asphalt
    rgb = bank.lookup(material, x * scale, y * scale, footprint * scale)
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
    ahead = town.intersection[_cell(town, x - 4.5)] & ~inter
    zebra = ahead & (ay < rh - 0.6) & (np.mod(y, 1.2) < 0.6)
    mark = lane & (centre | lanes | edge | zebra)
    if np.any(mark):
        g = np.flatnonzero(mark)
        # fade markings out when one pixel covers much more than a stripe
        strength = np.clip(0.3 / np.maximum(footprint[g], 1e-6), 0.0, 1.0)[:, None]
        colour = np.where(centre[g][:, None], paint, np.float32(0.88))
        rgb[g] += (colour * (0.8 + 0.2 * rgb[g]) - rgb[g]) * strength
    return rgb


def _sun_shadow(town, x, y, z):
    """True where the sun (direction ``town.sun``) is hidden by a building row.

    Points between the facade lines are tested against the front and back
    rows on the sun's side: one plane intersection each.
    """
    sun = town.sun
    side = 0 if sun[1] > 0 else 1
    shadow = np.zeros(x.shape, bool)
    heights = np.append(town.buildings["height"], -np.inf)
    for distance, table in ((town.facade, town.front_id), (town.back, town.back_id)):
        t = (np.sign(sun[1]) * distance - y) / sun[1]
        bid = table[side][_cell(town, x + t * sun[0])]
        shadow |= (t > 0) & (z + t * sun[2] < heights[bid])
    return shadow


def _car_shadow(town, x, y):
    """True for ground points whose sun ray passes through a parked car
    (tested where the ray is 0.2 m and 0.8 m above the ground)."""
    sun = town.sun
    y_in, y_out = town.car_band
    cells = town.car_cells.reshape(-1)
    shadow = np.zeros(x.shape, bool)
    for height in (0.2, 0.8):
        t = height / sun[2]
        xs, ys = x + t * sun[0], y + t * sun[1]
        ay = np.abs(ys)
        band = (ay > y_in) & (ay < y_out)
        shadow |= band & cells[(ys < 0) * town.ncell + _cell(town, xs)]
    return shadow


_LOOK_MATERIAL = np.array([MATERIAL_ID[m] for m in (
    "paint", "paint", "metal", "metal", "paint", "bark", "foliage")])
_LOOK_GAIN = np.array([1 / 0.8, 1 / 0.8, 1 / 0.45, 1 / 0.45, 1 / 0.8, 1 / 0.3, 1 / 0.25],
                      np.float32)
_LOOK_SCALE = np.array([1.0, 1.0, 1.0, 1.0, 1.0, 2.0, 1.5])


def _object_albedo(town, bank, ident, face, P, footprint):
    o = town.objects
    look = o["look"][ident]
    colour = o["colour"][ident].astype(np.float32)
    x, y, z = P
    scale = _LOOK_SCALE[look] * _TEXELS_PER_M
    tex = bank.lookup(_LOOK_MATERIAL[look], (x + y) * scale, z * scale,
                      footprint * _TEXELS_PER_M)
    rgb = colour * tex * _LOOK_GAIN[look][:, None]
    trunk = look == scenes.TRUNK
    rgb[trunk] = tex[trunk]
    rgb[(look == scenes.CAR_BODY) & (z < 0.42)] = 0.07
    cabin = look == scenes.CAR_CABIN
    if np.any(cabin):
        lo, hi = o["lo"][ident, 2], o["hi"][ident, 2]
        glass = cabin & (face != 2) & (z > lo + 0.06) & (z < hi - 0.08)
        rgb[glass] = np.array([0.1, 0.12, 0.16], np.float32)
    return rgb


def _object_normal(town, ident, face, P, D):
    o = town.objects
    kind = o["kind"][ident]
    n = np.zeros((len(ident), 3))
    rows = np.arange(len(ident))
    # box: the face axis, facing the ray
    n[rows, face] = -np.sign(D[face, rows])
    radial = P.T - o["centre"][ident]
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
    d = np.asarray(rays).reshape(3, -1)
    t = hits.t.reshape(-1)
    surface = hits.surface.reshape(-1)
    out = np.empty((t.size, 3), np.float32)
    norm = np.sqrt((d * d).sum(axis=0))
    dist = t * norm
    # size of one pixel on a fronto-parallel surface at this distance (metres)
    pixel = dist / max(view.fx, view.fy)
    sun = town.sun
    ambient, diffuse = np.float32(0.5), np.float32(0.6)
    order = np.argsort(surface, kind="stable")
    bounds = np.searchsorted(surface[order], np.arange(OBJECT + 2))

    def select(kind):
        return order[bounds[kind]:bounds[kind + 1]]

    P_all = origin[:, None] + t * d

    def point(g):
        return P_all[:, g]

    def footprint(g, axis):
        cos_inc = np.abs(d[axis, g]) / norm[g]
        return pixel[g] / np.sqrt(np.maximum(cos_inc, 1e-3))

    g = select(SKY)
    if g.size:
        dn = d[:, g] / norm[g]
        w = (np.clip(dn[2] * 2.5, 0.0, 1.0) ** 0.7)[:, None]
        rgb = (1 - w) * np.array([0.78, 0.84, 0.9], np.float32) + w * np.array(
            [0.32, 0.52, 0.85], np.float32)
        up = np.maximum(dn[2], 0.02)
        cloud = bank.lookup(MATERIAL_ID["clouds"], dn[0] / up * 40.0 + 4096.0,
                            dn[1] / up * 40.0 + 4096.0, 2.0 / up)[:, :1]
        cloud *= np.clip(dn[2] * 6.0, 0.0, 1.0)[:, None]
        out[g] = rgb * (1 - cloud) + np.float32(0.95) * cloud

    g = select(GROUND)
    if g.size:
        x, y, z = point(g)
        lit = np.where(_sun_shadow(town, x, y, z) | _car_shadow(town, x, y), 0.0, diffuse * sun[2])
        out[g] = _ground_albedo(town, bank, x, y, footprint(g, 2)) * (ambient + lit)[:, None]
    b = town.buildings
    for kind in (FACADE, BACK):
        g = select(kind)
        if g.size:
            x, y, z = point(g)
            bid = hits.ident.reshape(-1)[g]
            rgb = _facade_albedo(town, bank, bid, x, x - b["x0"][bid], z, footprint(g, 1))
            lit = np.maximum(0.0, np.where(y > 0, -sun[1], sun[1]))
            if kind == FACADE:
                lit[lit > 0] *= ~_sun_shadow(town, x[lit > 0], y[lit > 0], z[lit > 0])
            out[g] = rgb * (ambient + diffuse * lit)[:, None]
    g = select(SIDEWALL)
    if g.size:
        x, y, z = point(g)
        bid = hits.ident.reshape(-1)[g]
        ay = np.abs(y)
        rgb = _facade_albedo(town, bank, bid, ay, ay - town.facade, z, footprint(g, 0))
        front = hits.face.reshape(-1)[g] == 0
        light = ambient + diffuse * np.maximum(0.0, np.where(front, -sun[0], sun[0]))
        out[g] = rgb * light[:, None]
    g = select(OBJECT)
    if g.size:
        P = point(g)
        P[0] -= hits.xshift.reshape(-1)[g]
        ident = hits.ident.reshape(-1)[g]
        face = hits.face.reshape(-1)[g].astype(np.intp)
        rgb = _object_albedo(town, bank, ident, face, P, pixel[g])
        n = _object_normal(town, ident, face, P, d[:, g])
        out[g] = rgb * (ambient + diffuse * np.maximum(0.0, n @ sun))[:, None].astype(np.float32)

    # Aerial perspective: fade to the haze colour with distance (not the sky).
    fog = np.exp(np.where(surface == SKY, 0.0, dist) * (-1.0 / town.haze)).astype(np.float32)
    out *= fog[:, None]
    out += (1 - fog)[:, None] * town.haze_colour
    return out.reshape(shape + (3,))


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
