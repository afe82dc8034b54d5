"""Shading for the ray caster (``cpl_keras.data.render``): the colour of every hit.

Each kind of surface a ray can hit (``scenes.SKY`` .. ``scenes.OBJECT``) takes
its material from the photographic textures (``textures.texture_bank``,
mip-mapped by the pixel's footprint on the surface) with procedural detail:
window grids and shop fronts on the facades; road, curb, verge, sidewalk,
lane markings and zebra crossings on the ground; car windows. Surfaces are
lit by the town's sun (ambient plus Lambert, with the shadows of the building
rows and of the parked cars on the ground) and faded into the town's haze
with distance; the sky has a gradient and clouds.
"""

from __future__ import annotations

import functools

import numpy as np

from cpl_keras.data import scenes
from cpl_keras.data.scenes import BACK, FACADE, GROUND, OBJECT, SIDEWALL, SKY
from cpl_keras.data.scenes import CYLINDER, SPHERE
from cpl_keras.data.textures import MATERIAL_ID, texture_bank

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
    ahead = town.intersection[town.cell_index(x - 4.5)] & ~inter
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
        bid = table[side][town.cell_index(x + t * sun[0])]
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
        shadow |= band & cells[(ys < 0) * town.ncell + town.cell_index(xs)]
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
    pixels = _Pixels(view, origin, rays, hits)
    out = np.empty((pixels.t.size, 3), np.float32)
    for kind, colour in _SHADERS:
        g = pixels.select(kind)
        if g.size:
            out[g] = colour(town, bank, pixels, g)
    _aerial_perspective(town, pixels, out)
    return out.reshape(hits.t.shape + (3,))


class _Pixels:
    """The hits of a view, flattened and grouped by surface kind, and what
    the shading of every kind reads from them."""

    def __init__(self, view, origin, rays, hits):
        self.d = np.asarray(rays).reshape(3, -1)
        self.t = hits.t.reshape(-1)
        self.surface = hits.surface.reshape(-1)
        self.ident = hits.ident.reshape(-1)
        self.face = hits.face.reshape(-1)
        self.xshift = hits.xshift.reshape(-1)
        self.norm = np.sqrt((self.d * self.d).sum(axis=0))
        self.dist = self.t * self.norm
        # size of one pixel on a fronto-parallel surface at this distance (metres)
        self.pixel = self.dist / max(view.fx, view.fy)
        self._order = np.argsort(self.surface, kind="stable")
        self._bounds = np.searchsorted(self.surface[self._order], np.arange(OBJECT + 2))
        self._points = origin[:, None] + self.t * self.d

    def select(self, kind):
        """Indices of the pixels whose ray hit a surface of ``kind``."""
        return self._order[self._bounds[kind]:self._bounds[kind + 1]]

    def point(self, g):
        """The world points (3, n) hit by pixels ``g``."""
        return self._points[:, g]

    def footprint(self, g, axis):
        """Size (metres) of pixels ``g`` on their surface, whose normal is along ``axis``."""
        cos_inc = np.abs(self.d[axis, g]) / self.norm[g]
        return self.pixel[g] / np.sqrt(np.maximum(cos_inc, 1e-3))


_AMBIENT, _DIFFUSE = np.float32(0.5), np.float32(0.6)


def _sky(town, bank, pixels, g):
    """A gradient from the horizon up, with clouds."""
    dn = pixels.d[:, g] / pixels.norm[g]
    w = (np.clip(dn[2] * 2.5, 0.0, 1.0) ** 0.7)[:, None]
    rgb = (1 - w) * np.array([0.78, 0.84, 0.9], np.float32) + w * np.array(
        [0.32, 0.52, 0.85], np.float32)
    up = np.maximum(dn[2], 0.02)
    cloud = bank.lookup(MATERIAL_ID["clouds"], dn[0] / up * 40.0 + 4096.0,
                        dn[1] / up * 40.0 + 4096.0, 2.0 / up)[:, :1]
    cloud *= np.clip(dn[2] * 6.0, 0.0, 1.0)[:, None]
    return rgb * (1 - cloud) + np.float32(0.95) * cloud


def _ground(town, bank, pixels, g):
    """The ground, in the shadows of the building rows and the parked cars."""
    x, y, z = pixels.point(g)
    shadow = _sun_shadow(town, x, y, z) | _car_shadow(town, x, y)
    lit = np.where(shadow, 0.0, _DIFFUSE * town.sun[2])
    return _ground_albedo(town, bank, x, y, pixels.footprint(g, 2)) * (_AMBIENT + lit)[:, None]


def _facade(town, bank, pixels, g, front):
    """Facades along the street; the ``front`` row's in the shadows of the
    building rows on the sun's side."""
    x, y, z = pixels.point(g)
    bid = pixels.ident[g]
    rgb = _facade_albedo(town, bank, bid, x, x - town.buildings["x0"][bid], z,
                         pixels.footprint(g, 1))
    lit = np.maximum(0.0, np.where(y > 0, -town.sun[1], town.sun[1]))
    if front:
        lit[lit > 0] *= ~_sun_shadow(town, x[lit > 0], y[lit > 0], z[lit > 0])
    return rgb * (_AMBIENT + _DIFFUSE * lit)[:, None]


def _side_wall(town, bank, pixels, g):
    """Side walls of the front-row buildings (facing along x)."""
    x, y, z = pixels.point(g)
    bid = pixels.ident[g]
    ay = np.abs(y)
    rgb = _facade_albedo(town, bank, bid, ay, ay - town.facade, z, pixels.footprint(g, 0))
    front = pixels.face[g] == 0
    light = _AMBIENT + _DIFFUSE * np.maximum(0.0, np.where(front, -town.sun[0], town.sun[0]))
    return rgb * light[:, None]


def _object(town, bank, pixels, g):
    """Cars, lamps, signs and trees (no shadows)."""
    P = pixels.point(g)
    P[0] -= pixels.xshift[g]
    ident = pixels.ident[g]
    face = pixels.face[g].astype(np.intp)
    rgb = _object_albedo(town, bank, ident, face, P, pixels.pixel[g])
    n = _object_normal(town, ident, face, P, pixels.d[:, g])
    lit = _AMBIENT + _DIFFUSE * np.maximum(0.0, n @ town.sun)
    return rgb * lit[:, None].astype(np.float32)


#: The colour of each kind of surface, in the order they are shaded.
_SHADERS = ((SKY, _sky), (GROUND, _ground),
            (FACADE, functools.partial(_facade, front=True)),
            (BACK, functools.partial(_facade, front=False)),
            (SIDEWALL, _side_wall), (OBJECT, _object))


def _aerial_perspective(town, pixels, out):
    """Fade ``out`` (in place) to the haze colour with distance (not the sky)."""
    fog = np.exp(np.where(pixels.surface == SKY, 0.0, pixels.dist) * (-1.0 / town.haze))
    fog = fog.astype(np.float32)
    out *= fog[:, None]
    out += (1 - fog)[:, None] * town.haze_colour
