"""Procedural towns: the streets the stereo rig drives along.

World frame: x forward along the main street, y left, z up (metres), ground
plane z = 0. The main street's centre line is y = 0. Each town is periodic in
x with period ``Town.period``, so a drive never reaches an end.

A town is made of

* the ground: asphalt road (|y| < road_half) with lane markings, a curb, an
  optional grass verge, a sidewalk up to the facade line ``|y| = facade``;
  cross streets cut through every block;
* a front row of buildings on each side (facade plane |y| = facade; the
  renderer intersects that plane and looks the building up in a per-cell
  table), with their side walls visible in gaps and at cross streets;
* a back row of taller buildings (plane |y| = back) seen above and between
  the front row;
* objects: parked cars (two boxes each), street lamps, signs and trees
  (vertical cylinders, boxes and spheres);
* a sky dome at ``SKY_DISTANCE`` metres, so every pixel has a finite depth.

Two towns mirror CARLA's Town 1 and Town 2: ``Town01`` is a brick town with
wide blocks and street lamps, ``Town02`` a leafy plaster suburb with grass
verges, trees and short blocks. Their layouts are fixed (independent of the
dataset seed), like CARLA's maps.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np

from cpl_keras.data.textures import MATERIAL_ID

#: Distance of the sky dome from the camera (metres).
SKY_DISTANCE = 1000.0
#: Names of the towns, indexed by town id.
TOWNS = ("Town01", "Town02")

#: Parked cars stand between road_half - 1.95 and road_half - 0.2 m from the centre line.
CAR_BAND = (1.95, 0.2)

#: What a ray can hit: the sky dome, the ground, a front-row facade, a front
#: building's side wall, a back-row facade, an object.
SKY, GROUND, FACADE, SIDEWALL, BACK, OBJECT = range(6)

# Object kinds and looks.
BOX, CYLINDER, SPHERE = 0, 1, 2
CAR_BODY, CAR_CABIN, POLE, LAMP, SIGN, TRUNK, CROWN = range(7)

STYLES = {
    "Town01": dict(
        seed=101, road_half=7.5, verge=0.0, facade=11.0, back=40.0,
        block=(70.0, 130.0), cross=16.0, width=(8.0, 22.0), height=(7.0, 16.0),
        back_height=(14.0, 40.0), alley=0.25,
        walls=("brick_red", "brick_yellow", "brick_red", "stone"),
        back_walls=("concrete", "stone", "brick_yellow"),
        sidewalk="sidewalk", lamp_every=30.0, tree_every=0.0, sign_prob=0.3,
        car_prob=0.65, centre="white_dashed",
        sun=(0.45, 0.55, 0.7), haze=600.0, haze_colour=(0.72, 0.76, 0.80),
    ),
    "Town02": dict(
        seed=202, road_half=7.5, verge=1.6, facade=12.5, back=45.0,
        block=(45.0, 85.0), cross=14.0, width=(9.0, 16.0), height=(5.0, 10.0),
        back_height=(9.0, 24.0), alley=0.45,
        walls=("plaster", "plaster", "concrete", "brick_yellow"),
        back_walls=("plaster", "concrete", "stone"),
        sidewalk="paving", lamp_every=45.0, tree_every=11.0, sign_prob=0.15,
        car_prob=0.5, centre="yellow_double",
        sun=(-0.35, 0.6, 0.72), haze=450.0, haze_colour=(0.78, 0.80, 0.82),
    ),
}


@dataclass
class Town:
    """One town's layout (all lengths in metres)."""

    town_id: int
    name: str
    period: float
    cell: float
    road_half: float
    verge: float
    facade: float
    back: float
    centre: str
    sidewalk_material: int
    sun: np.ndarray
    haze: float
    haze_colour: np.ndarray
    # per-cell tables along x, shape (ncell,) or (2, ncell) for [left, right]
    intersection: np.ndarray = field(repr=False)
    front_id: np.ndarray = field(repr=False)
    next_start: np.ndarray = field(repr=False)
    next_id: np.ndarray = field(repr=False)
    prev_end: np.ndarray = field(repr=False)
    prev_id: np.ndarray = field(repr=False)
    back_id: np.ndarray = field(repr=False)
    # buildings (front then back), one row per building
    buildings: dict = field(repr=False)
    # objects, one row per primitive, sorted by x centre
    objects: dict = field(repr=False)
    # cells covered by a parked car, (2, ncell), and the cars' |y| band
    car_cells: np.ndarray = field(repr=False)
    car_band: tuple = (0.0, 0.0)

    @property
    def ncell(self):
        return len(self.intersection)

    def cell_index(self, x):
        """Per-cell table index of world x (the towns are periodic, ncell a power of 2)."""
        return ((x + 8 * self.period) * (1.0 / self.cell)).astype(np.intp) & (self.ncell - 1)

    def describe(self):
        """A JSON-able summary, stored in dataset metadata."""
        return {
            "name": self.name, "town_id": self.town_id, "period_m": self.period,
            "road_half_width_m": self.road_half, "facade_distance_m": self.facade,
            "back_row_distance_m": self.back,
            "front_buildings": int((self.buildings["row"] == 0).sum()),
            "objects": int(len(self.objects["kind"])),
        }


def _fill(rng, x0, x1, width, gap_prob, gap):
    """Split [x0, x1] into segments of random width with occasional gaps."""
    segments = []
    x = x0
    while x1 - x > 3.0:
        w = rng.uniform(*width)
        end = min(x + w, x1)
        if x1 - end < 3.0:
            end = x1
        segments.append((x, end))
        x = end
        if rng.random() < gap_prob:
            x += rng.uniform(*gap)
    return segments


@functools.lru_cache(maxsize=None)
def make_town(town_id):
    """The town with id ``town_id`` (0 = Town01, 1 = Town02), built once per process.

    Drawn from the town's own seed, in this order: the blocks, the buildings,
    the objects.
    """
    if town_id not in range(len(TOWNS)):
        raise ValueError(f"unknown town id {town_id}; known: 0..{len(TOWNS) - 1}")
    name = TOWNS[town_id]
    st = STYLES[name]
    rng = np.random.default_rng(st["seed"])
    period, cell = 1024.0, 0.25
    ncell = int(period / cell)
    xs = (np.arange(ncell) + 0.5) * cell

    blocks = _blocks(rng, st, period)
    intersection = np.ones(ncell, bool)
    for b0, b1 in blocks:
        intersection[(xs >= b0) & (xs < b1)] = False
    buildings, front_id, back_id = _buildings(rng, st, blocks, xs)
    neighbours = _front_neighbours(buildings, period, cell, ncell)
    objects = _make_objects(rng, st, blocks)
    return Town(
        town_id=town_id, name=name, period=period, cell=cell,
        road_half=st["road_half"], verge=st["verge"], facade=st["facade"], back=st["back"],
        centre=st["centre"], sidewalk_material=MATERIAL_ID[st["sidewalk"]],
        sun=np.asarray(st["sun"]) / np.linalg.norm(st["sun"]), haze=st["haze"],
        haze_colour=np.asarray(st["haze_colour"], np.float32),
        intersection=intersection, front_id=front_id, back_id=back_id, **neighbours,
        buildings=buildings, objects=objects, car_cells=_car_cells(objects, xs),
        car_band=(st["road_half"] - CAR_BAND[0], st["road_half"] - CAR_BAND[1]),
    )


def _blocks(rng, st, period):
    """The blocks ``(x0, x1)`` along the main street, separated by cross streets."""
    lengths = []
    while sum(lengths) + len(lengths) * st["cross"] < period - st["block"][1]:
        lengths.append(rng.uniform(*st["block"]))
    lengths.append(period - sum(lengths) - (len(lengths) + 1) * st["cross"])
    blocks = []
    x = st["cross"]
    for length in lengths:
        blocks.append((x, x + length))
        x += length + st["cross"]
    return blocks


def _buildings(rng, st, blocks, xs):
    """The buildings of both sides, one row per building (``row`` 0: the front
    row, 1: the back row), and the per-cell building ids of the front and back
    rows, shape (2, ncell) for [left, right], -1 where there is none."""
    rows = {k: [] for k in ("row", "side", "x0", "x1", "height", "material", "tint",
                            "floor", "pitch", "win_w", "win_h", "shop")}

    def add_building(row, side, x0, x1, height, material):
        rows["row"].append(row)
        rows["side"].append(side)
        rows["x0"].append(x0)
        rows["x1"].append(x1)
        rows["height"].append(height)
        rows["material"].append(MATERIAL_ID[material])
        rows["tint"].append(rng.uniform(0.75, 1.15, 3) * rng.uniform(0.85, 1.1))
        rows["floor"].append(rng.uniform(2.9, 3.6))
        rows["pitch"].append(rng.uniform(2.2, 3.6))
        rows["win_w"].append(rng.uniform(0.35, 0.6))
        rows["win_h"].append(rng.uniform(0.4, 0.6))
        rows["shop"].append(rng.random() < 0.5)

    front_id = -np.ones((2, len(xs)), np.int32)
    back_id = -np.ones((2, len(xs)), np.int32)
    for side in (0, 1):
        for b0, b1 in blocks:
            for x0, x1 in _fill(rng, b0, b1, st["width"], st["alley"], (1.5, 5.0)):
                front_id[side, (xs >= x0) & (xs < x1)] = len(rows["row"])
                add_building(0, side, x0, x1, rng.uniform(*st["height"]),
                             st["walls"][rng.integers(len(st["walls"]))])
            for x0, x1 in _fill(rng, b0 - 2.0, b1 + 2.0, (15.0, 40.0), 0.0, (0, 0)):
                back_id[side, (xs >= x0) & (xs < x1)] = len(rows["row"])
                add_building(1, side, x0, x1, rng.uniform(*st["back_height"]),
                             st["back_walls"][rng.integers(len(st["back_walls"]))])
    buildings = {k: np.asarray(v) for k, v in rows.items()}
    buildings["tint"] = buildings["tint"].astype(np.float32)
    return buildings, front_id, back_id


def _front_neighbours(buildings, period, cell, ncell):
    """Next building start / previous building end for each cell (front row),
    as offsets from the cell's left edge so they survive the wrap, and those
    buildings' ids: the ``Town`` fields ``next_start``, ``next_id``,
    ``prev_end``, ``prev_id``."""
    next_start = np.zeros((2, ncell))
    next_id = np.zeros((2, ncell), np.int32)
    prev_end = np.zeros((2, ncell))
    prev_id = np.zeros((2, ncell), np.int32)
    edges = np.arange(ncell) * cell
    for side in (0, 1):
        ids = np.flatnonzero((buildings["row"] == 0) & (buildings["side"] == side))
        x0 = buildings["x0"][ids]
        x1 = buildings["x1"][ids]
        order = np.argsort(x0)
        ids, x0, x1 = ids[order], x0[order], x1[order]
        ext_x0 = np.concatenate([x0, x0 + period])
        ext_ids = np.concatenate([ids, ids])
        k = np.searchsorted(ext_x0, edges + cell, side="left")
        next_start[side] = ext_x0[k] - edges
        next_id[side] = ext_ids[k]
        ext_x1 = np.concatenate([x1 - period, x1])
        order1 = np.argsort(ext_x1)
        ext_x1, ext_ids1 = ext_x1[order1], np.concatenate([ids, ids])[order1]
        k = np.searchsorted(ext_x1, edges, side="right") - 1
        prev_end[side] = ext_x1[k] - edges
        prev_id[side] = ext_ids1[k]
    return {"next_start": next_start, "next_id": next_id, "prev_end": prev_end,
            "prev_id": prev_id}


def _car_cells(objects, xs):
    """The cells where a parked car stands, (2, ncell) for [left, right] (for
    their shadows on the ground)."""
    car_cells = np.zeros((2, len(xs)), bool)
    body = objects["look"] == CAR_BODY
    for lo, hi in zip(objects["lo"][body], objects["hi"][body]):
        car_cells[0 if lo[1] > 0 else 1, (xs >= lo[0]) & (xs < hi[0])] = True
    return car_cells


def _make_objects(rng, st, blocks):
    rows = {k: [] for k in ("kind", "look", "lo", "hi", "centre", "radius", "colour")}

    def add(kind, look, lo, hi, colour, centre=(0, 0, 0), radius=0.0):
        rows["kind"].append(kind)
        rows["look"].append(look)
        rows["lo"].append(lo)
        rows["hi"].append(hi)
        rows["centre"].append(centre)
        rows["radius"].append(radius)
        rows["colour"].append(colour)

    def cylinder(look, x, y, r, z0, z1, colour):
        add(CYLINDER, look, (x - r, y - r, z0), (x + r, y + r, z1), colour, (x, y, 0.0), r)

    road, verge = st["road_half"], st["verge"]
    car_colours = np.array([
        (0.75, 0.1, 0.1), (0.1, 0.2, 0.6), (0.85, 0.85, 0.85), (0.1, 0.1, 0.1),
        (0.5, 0.5, 0.55), (0.9, 0.75, 0.2), (0.2, 0.45, 0.25), (0.6, 0.6, 0.65),
    ])
    for b0, b1 in blocks:
        for sign in (1.0, -1.0):
            # Parked cars along the curb (the rig's corridor |y| <= 5.5 stays free).
            x = b0 + rng.uniform(2.0, 6.0)
            while x < b1 - 6.0:
                length = rng.uniform(3.8, 5.0)
                if rng.random() < st["car_prob"]:
                    y_in, y_out = road - CAR_BAND[0], road - CAR_BAND[1]
                    ylo, yhi = sorted((sign * y_in, sign * y_out))
                    colour = car_colours[rng.integers(len(car_colours))] * rng.uniform(0.8, 1.1)
                    top = rng.uniform(1.35, 1.7)
                    add(BOX, CAR_BODY, (x, ylo, 0.15), (x + length, yhi, 0.9), colour)
                    add(BOX, CAR_CABIN, (x + 0.22 * length, ylo + 0.12, 0.9),
                        (x + 0.8 * length, yhi - 0.12, top), colour)
                x += length + rng.uniform(0.8, 6.0)
            # Street lamps at the curb side of the sidewalk.
            y_pole = sign * (road + verge + 0.6)
            if st["lamp_every"]:
                for xl in np.arange(b0 + 4.0, b1 - 2.0, st["lamp_every"]):
                    xl += rng.uniform(-2, 2)
                    grey = (0.35, 0.36, 0.38)
                    cylinder(POLE, xl, y_pole, 0.11, 0.0, 7.5, grey)
                    y_arm = y_pole - sign * 1.6
                    ylo, yhi = sorted((y_pole, y_arm))
                    add(BOX, LAMP, (xl - 0.15, ylo, 7.3), (xl + 0.15, yhi, 7.55), grey)
            # Traffic signs near the block ends.
            if rng.random() < st["sign_prob"]:
                xs = b1 - rng.uniform(3.0, 8.0) if sign > 0 else b0 + rng.uniform(3.0, 8.0)
                cylinder(POLE, xs, y_pole, 0.05, 0.0, 2.6, (0.6, 0.6, 0.62))
                colour = ((0.8, 0.1, 0.1), (0.1, 0.25, 0.75), (0.95, 0.8, 0.1))[rng.integers(3)]
                add(BOX, SIGN, (xs - 0.04, y_pole - 0.35, 2.0), (xs + 0.04, y_pole + 0.35, 2.7),
                    colour)
            # Trees in the verge (Town02) or sparse on the sidewalk.
            every = st["tree_every"]
            y_tree = sign * (road + (verge / 2 + 0.25 if verge else 2.2))
            if every:
                for xt in np.arange(b0 + 3.0, b1 - 3.0, every):
                    xt += rng.uniform(-1.5, 1.5)
                    r = rng.uniform(1.6, 2.6)
                    cylinder(TRUNK, xt, y_tree, 0.18, 0.0, 3.0, (0.3, 0.22, 0.15))
                    zc = 2.6 + r
                    add(SPHERE, CROWN, (xt - r, y_tree - r, zc - r), (xt + r, y_tree + r, zc + r),
                        rng.uniform(0.8, 1.15, 3) * (0.22, 0.38, 0.15), (xt, y_tree, zc), r)
    objects = {k: np.asarray(v, np.float64) for k, v in rows.items()}
    objects["kind"] = objects["kind"].astype(np.int32)
    objects["look"] = objects["look"].astype(np.int32)
    order = np.argsort(0.5 * (objects["lo"][:, 0] + objects["hi"][:, 0]), kind="stable")
    return {k: v[order] for k, v in objects.items()}
