"""Stereo-rig protocols: how camera configurations and frames are drawn.

Frames and labels
-----------------
The label extrinsics (pitch, tx, ty, tz, and the nuisance yaw, roll) are the
RIGHT camera's pose relative to the LEFT camera, in the left camera's frame
(x forward, y left, z up): ``P_left = R(pitch, yaw, roll) P_right + t`` with
``t = (tx, ty, tz)`` the right camera centre seen from the left camera. In
both protocols the relative rotation is a pitch only, ``R_rel = Ry(pitch)``
(yaw = roll = 0), so paper Eq. 5 maps the right camera's points into the left
camera's frame exactly (positive pitch tilts the axis down). Both cameras
share the intrinsics fx, fy, u0, v0.

Release frame
-------------
The release stored its extrinsics in another frame: right-minus-left
differences of the two cameras' mounting poses in the VEHICLE frame, in
CARLA's conventions (x forward, y RIGHT, z up; pitch in DEGREES, positive
up), and baseline = tx. ``released_extrinsics`` gives those values for a
configuration (``tx/ty/tz/pitch/baseline_released`` labels). Against ours,
pitch and ty flip sign and tx, tz are not rotated into the left camera's
frame (cvgl: tz_released is -0.4..1.6 m, our tz 1..44 m).

Projection pixel
----------------
Every protocol labels the point seen at a pixel chosen on scene geometry
by one rule that depends on the image only: ``cpl_keras.data.pixels``.

``cvgl`` (the paper's protocol, CARLA conventions converted)
    Left camera on the vehicle at (x=2, y=0, z=1.4) m, looking down 15 deg
    (CARLA pitch -15 = our pitch +15). 50 right-camera configurations, 25 per
    town, drawn once from the seed: fov 50-150 deg (shared by both cameras),
    x 2-170 m, y -5..5 m, z 1-3 m, pitch -30..30 deg in CARLA's convention
    (y right, pitch up), converted with y = -y_carla, pitch = -pitch_carla.
    fx = fy = W / (2 tan(fov/2)), u0 = v0 = W/2, baseline = tx (as released).
    Configurations with |tx| < 0.5 m are redrawn so that the disparity never
    underflows the camera model's division floor (a deviation from the
    release, which had no such rule). Release frame: the CARLA values minus
    the left camera's (x=2, y=0, z=1.4, pitch=-15 deg).

``random`` (realistic stereo rigs, continuous ranges)
    Every configuration is drawn independently: lateral baseline 0.05-1.0 m
    with the right camera to the right (ty = -baseline), small tx and tz,
    relative pitch of a few degrees and NO relative yaw or roll (Eq. 5 models
    pitch only), horizontal fov 40-120 deg, fy = fx * (1 +- 5 %), principal
    point off centre by up to 10 % of the image (as a crop would do), left
    camera mounted 1.2-2.0 m high looking -5..15 deg down with a small
    absolute yaw and roll (shared by the right camera). baseline = |t| (the
    distance between the centres). One configuration per
    ``RANDOM_FRAMES_PER_CONFIG`` frames, so whole configurations can be held
    out. Release frame (an analogue): the vehicle-frame differences of the
    two camera poses in CARLA's conventions, as for cvgl, with
    baseline_released = |t| (the release's ``baseline = tx`` fitted the
    forward-offset CVGL rigs, not lateral ones).

``cameras`` (random rigs seen as real cameras' images are)
    As ``random``, but each configuration's source image has one of the
    aspect ratios of ``CAMERA_ASPECTS`` (4:3 to KITTI's 3.3:1, and portrait)
    and is squashed to the square model input, as calibrate maps a user's
    image: the horizontal fov keeps fx, and fy = fx * aspect (+- 5 %), so
    fy is a label to learn, not fx again (``source_aspect`` in the
    configuration). Rendering the square image with those intrinsics is
    exactly the squashed source image, without its resampling.

``wild`` (the ``cameras`` rigs under randomised light and colour)
    The configurations, poses, drives, projection pixels and labels of
    ``cameras`` for the same (seed, pairs, image size), and per
    configuration an appearance (``WILD_APPEARANCE``, the ``appearance``
    entry of the configuration): the sun's direction (15-75 deg above the
    horizon, any azimuth), the haze distance (150-1500 m, log-uniform), the
    haze colour (a blend of a cool grey-blue and a warm grey) and a gain per
    colour channel that both images share (white balance: red 1 + t and blue
    1 - t with t in -0.15..0.15, green 1 + g with g in -0.04..0.04). The
    appearance is drawn from its own generator, seeded from (seed,
    configuration), so the geometry draws are those of ``cameras`` and
    ``cameras`` itself is unchanged. Only the images, and the StereoBM
    disparity computed from them, differ from ``cameras``.

``zoom`` (the ``wild`` rigs with the fields of view of zoom and long lenses)
    As ``wild``, but the horizontal fov is drawn from ``ZOOM_FOV_DEG``
    (10-120 deg) instead of 40-120: real cameras, and crops of their images,
    go down to 10-30 deg, which ``cameras`` never renders. Every other draw
    is that of ``cameras`` and ``wild`` for the same (seed, pairs, image
    size) (the same generator, the fov drawn from a wider interval at the
    same step), so fx, fy and the disparity are the only labels that differ
    from ``wild``, and the appearance per configuration is ``wild``'s.

Frames: configuration c owns a contiguous run of pair indices (a drive); frame
k of it puts the vehicle at x = start + k * step along the main street, with a
slow lateral sway. Everything about pair i is a function of (seed, i) only.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np

from cpl_keras import camera, frames
from cpl_keras.data import pixels, scenes

PROTOCOLS = ("cvgl", "random", "cameras", "wild", "zoom")
#: Protocols whose rigs are those of ``cameras`` (and whose appearance is
#: drawn per configuration): the protocol -> its horizontal fov range (deg).
CAMERA_RIG_FOV_DEG = {"cameras": (40.0, 120.0), "wild": (40.0, 120.0), "zoom": (10.0, 120.0)}
ZOOM_FOV_DEG = CAMERA_RIG_FOV_DEG["zoom"]

CVGL_CONFIGS = 50
CVGL_LEFT = {"x": 2.0, "y": 0.0, "z": 1.4, "pitch_deg": 15.0}
CVGL_RANGES = {
    "fov_deg": (50.0, 150.0), "x_m": (2.0, 170.0), "y_carla_m": (-5.0, 5.0),
    "z_m": (1.0, 3.0), "pitch_carla_deg": (-30.0, 30.0),
}
CVGL_MIN_BASELINE = 0.5

RANDOM_FRAMES_PER_CONFIG = 8
RANDOM_RANGES = {
    "fov_deg": (40.0, 120.0), "aspect_jitter": (-0.05, 0.05),
    "principal_offset_fraction": (-0.1, 0.1), "baseline_m": (0.05, 1.0),
    "tx_m": (-0.05, 0.05), "tz_m": (-0.03, 0.03), "pitch_deg": (-3.0, 3.0),
    "left_x_m": (0.5, 2.5), "left_y_m": (-0.8, 0.8), "left_z_m": (1.2, 2.0),
    "left_pitch_deg": (-5.0, 15.0), "left_yaw_deg": (-3.0, 3.0), "left_roll_deg": (-2.0, 2.0),
}
#: The ``cameras`` protocol's source images, width / height: 4:3, 3:2, 16:10,
#: 16:9, KITTI's 1242x375, square, and portrait 3:4 and 9:16. Each is
#: squashed to the square model input as inference does.
CAMERA_ASPECTS = (4 / 3, 3 / 2, 16 / 10, 16 / 9, 1242 / 375, 1.0, 3 / 4, 9 / 16)
#: The ``wild`` protocol's appearance per configuration: the sun's elevation
#: above the horizon and azimuth (degrees from the street's x axis towards
#: its left, y), the haze distance (metres, drawn log-uniform), the haze
#: colour ``(1 - b) cool + b warm`` with b in ``haze_blend``, and the white
#: balance, a gain per colour channel shared by the left and right image.
WILD_APPEARANCE = {
    "sun_elevation_deg": (15.0, 75.0), "sun_azimuth_deg": (-180.0, 180.0),
    "haze_m": (150.0, 1500.0), "haze_colour_cool": (0.66, 0.72, 0.80),
    "haze_colour_warm": (0.80, 0.77, 0.70), "haze_blend": (0.0, 1.0),
    # white balance as cameras get it wrong: along the blue-amber axis (red
    # gain 1 + t, blue 1 - t), with a small green-magenta tint (green 1 + g)
    "white_balance_temperature": (-0.15, 0.15), "white_balance_tint": (-0.04, 0.04),
}
DRIVE = {"step_m": (1.5, 4.0), "sway_m": 0.35}


def ranges(protocol):
    """The parameter ranges of ``protocol`` (for metadata)."""
    check_protocol(protocol)
    base = CVGL_RANGES if protocol == "cvgl" else RANDOM_RANGES
    out = {k: list(v) if isinstance(v, tuple) else v for k, v in base.items()}
    if protocol in CAMERA_RIG_FOV_DEG:
        out["source_aspects"] = list(CAMERA_ASPECTS)
        out["fov_deg"] = list(CAMERA_RIG_FOV_DEG[protocol])
    if protocol in ("wild", "zoom"):
        out["appearance"] = {k: list(v) for k, v in WILD_APPEARANCE.items()}
        out["appearance"]["haze_m_drawn"] = "log-uniform"
    out.update({f"drive_{k}": list(v) if isinstance(v, tuple) else v for k, v in DRIVE.items()})
    out.update(pixels.rule())
    if protocol == "cvgl":
        out["left_camera"] = dict(CVGL_LEFT)
        out["min_abs_tx_m"] = CVGL_MIN_BASELINE
    else:
        out["frames_per_config"] = RANDOM_FRAMES_PER_CONFIG
    return out


def check_protocol(protocol):
    if protocol not in PROTOCOLS:
        raise ValueError(f"unknown protocol {protocol!r}; choose one of {', '.join(PROTOCOLS)}")


def num_configs(protocol, pairs):
    check_protocol(protocol)
    if protocol == "cvgl":
        return CVGL_CONFIGS
    return max(1, math.ceil(pairs / RANDOM_FRAMES_PER_CONFIG))


def _relative(rot_left, pos_left, rot_right, pos_right):
    """Right pose in the left camera's frame: R_rel = R_L^T R_R, t = R_L^T (c_R - c_L)."""
    rel = rot_left.T @ rot_right
    t = rot_left.T @ (np.asarray(pos_right) - np.asarray(pos_left))
    pitch, yaw, roll = frames.euler_from_rotation(rel)
    return pitch, yaw, roll, t


def released_extrinsics(rot_left, pos_left, rot_right, pos_right, baseline=None):
    """The release's extrinsic labels of a rig: right-minus-left differences
    of the two mounting poses in the vehicle frame, in CARLA's conventions.

    Positions are vehicle-frame (x forward, y left, z up, ours); CARLA's y
    points right and its pitch (degrees) is positive up, i.e. ``-`` our pitch
    of the camera's absolute rotation. Returns a dict ``tx, ty, tz`` (m),
    ``pitch`` (degrees) and ``baseline`` (m): ``tx`` as released unless
    ``baseline`` is given.
    """
    d = np.asarray(pos_right, np.float64) - np.asarray(pos_left, np.float64)
    pitch_left = frames.euler_from_rotation(rot_left)[0]
    pitch_right = frames.euler_from_rotation(rot_right)[0]
    out = {"tx": float(d[0]), "ty": float(-d[1]), "tz": float(d[2]),
           "pitch": math.degrees(pitch_left - pitch_right)}
    out["baseline"] = out["tx"] if baseline is None else float(baseline)
    return out


def _u(rng, lo_hi):
    return float(rng.uniform(*lo_hi))


@functools.lru_cache(maxsize=8)
def _configurations(protocol, seed, pairs, image_size):
    """The configuration table of a dataset, drawn from (seed, protocol):
    configuration after configuration, its rig, then its drive. ``wild``:
    the ``cameras`` table, each configuration with its ``appearance``;
    ``zoom``: the same with the fov drawn from its own range."""
    rigs = "cameras" if protocol in CAMERA_RIG_FOV_DEG else protocol
    rng = np.random.default_rng([seed, PROTOCOLS.index(rigs)])
    configs = []
    for c in range(num_configs(protocol, pairs)):
        if protocol == "cvgl":
            cfg = _cvgl_rig(rng, c, image_size)
        else:
            cfg = _random_rig(rng, c, protocol, image_size)
        cfg.update(_drive(rng, cfg["town_id"]))
        if protocol in ("wild", "zoom"):
            cfg["appearance"] = _appearance(seed, c)
        configs.append(cfg)
    return tuple(configs)


def _cvgl_rig(rng, c, image_size):
    """Configuration ``c`` of the cvgl protocol: the right camera drawn in
    CARLA's conventions (again while |tx| < ``CVGL_MIN_BASELINE``), the left
    one fixed."""
    W = H = image_size
    town_id = 0 if c < CVGL_CONFIGS // 2 else 1
    while True:
        fov = _u(rng, CVGL_RANGES["fov_deg"])
        x = _u(rng, CVGL_RANGES["x_m"])
        y_carla = _u(rng, CVGL_RANGES["y_carla_m"])
        z = _u(rng, CVGL_RANGES["z_m"])
        pitch_carla = _u(rng, CVGL_RANGES["pitch_carla_deg"])
        pitch, yaw, roll, t = cvgl_relative_pose(x, y_carla, z, pitch_carla)
        if abs(t[0]) >= CVGL_MIN_BASELINE:
            break
    fx = fy = float(camera.focal_from_fov(math.radians(fov), W))
    cfg = {
        "carla": {"fov_deg": fov, "x": x, "y": y_carla, "z": z, "pitch_deg": pitch_carla},
        "left_pose": {"position": [CVGL_LEFT["x"], CVGL_LEFT["y"], CVGL_LEFT["z"]],
                      "pitch": math.radians(CVGL_LEFT["pitch_deg"]), "yaw": 0.0, "roll": 0.0},
        "right_pose": {"position": [x, -y_carla, z], "pitch": -math.radians(pitch_carla),
                       "yaw": 0.0, "roll": 0.0},
        "released": cvgl_released(x, y_carla, z, pitch_carla),
    }
    cfg.update(_rig_entries(c, town_id, fov, (fx, fy, W / 2, H / 2), float(t[0]), t,
                            (pitch, yaw, roll)))
    return cfg


def cvgl_relative_pose(x, y_carla, z, pitch_carla):
    """``(pitch, yaw, roll, t)`` of the cvgl right camera mounted at CARLA's
    ``x, y_carla, z`` (m), ``pitch_carla`` (deg, up) as the labels see it: its
    pose in the fixed left camera's frame (``CVGL_LEFT``). The generator and
    ``cpl_keras.data.import_cvgl`` (the release's labels read back) use it."""
    left = (CVGL_LEFT["x"], CVGL_LEFT["y"], CVGL_LEFT["z"])
    rot_left = frames.rotation_matrix(math.radians(CVGL_LEFT["pitch_deg"]))
    rot_right = frames.rotation_matrix(math.radians(-pitch_carla))
    return _relative(rot_left, left, rot_right, (x, -y_carla, z))


def cvgl_released(x, y_carla, z, pitch_carla):
    """The release's labels of it: CARLA's values minus the left camera's, b = tx."""
    released = {"tx": x - CVGL_LEFT["x"], "ty": y_carla - CVGL_LEFT["y"],
                "tz": z - CVGL_LEFT["z"], "pitch": pitch_carla - (-CVGL_LEFT["pitch_deg"])}
    released["baseline"] = released["tx"]
    return released


def cvgl_carla_from_released(tx, ty, tz, pitch):
    """CARLA's ``(x, y_carla, z, pitch_carla)``: ``cvgl_released`` inverted."""
    return (tx + CVGL_LEFT["x"], ty + CVGL_LEFT["y"], tz + CVGL_LEFT["z"],
            pitch - CVGL_LEFT["pitch_deg"])


def _random_rig(rng, c, protocol, image_size):
    """Configuration ``c`` of the random and cameras protocols: intrinsics,
    the left camera's mounting, and the right camera relative to it (a pitch
    only, so Eq. 5 is exact)."""
    W = H = image_size
    R = RANDOM_RANGES
    town_id = c % len(scenes.TOWNS)
    fov = _u(rng, CAMERA_RIG_FOV_DEG.get(protocol, R["fov_deg"]))
    fx = float(camera.focal_from_fov(math.radians(fov), W))
    # cameras: a source image of width / height ``aspect`` squashed
    # to the square input keeps fx and multiplies fy by the aspect
    aspect = float(rng.choice(CAMERA_ASPECTS)) if protocol in CAMERA_RIG_FOV_DEG else 1.0
    fy = fx * aspect * (1.0 + _u(rng, R["aspect_jitter"]))
    u0 = W / 2 + _u(rng, R["principal_offset_fraction"]) * W
    v0 = H / 2 + _u(rng, R["principal_offset_fraction"]) * H
    left = (_u(rng, R["left_x_m"]), _u(rng, R["left_y_m"]), _u(rng, R["left_z_m"]))
    lp, ly, lr = (math.radians(_u(rng, R[k])) for k in
                  ("left_pitch_deg", "left_yaw_deg", "left_roll_deg"))
    rot_left = frames.rotation_matrix(lp, ly, lr)
    lateral = _u(rng, R["baseline_m"])
    t = np.array([_u(rng, R["tx_m"]), -lateral, _u(rng, R["tz_m"])])
    # relative rotation: pitch only (R_rel = Ry(pitch)), so Eq. 5 is exact
    rp = math.radians(_u(rng, R["pitch_deg"]))
    rot_right = rot_left @ frames.rotation_matrix(rp)
    right = tuple(np.asarray(left) + rot_left @ t)
    _, _, _, t = _relative(rot_left, left, rot_right, right)
    baseline = float(np.linalg.norm(t))
    cfg = {
        "left_pose": {"position": list(left), "pitch": lp, "yaw": ly, "roll": lr},
        "right_rotation": rot_right.tolist(),
        "right_pose": {"position": [float(p) for p in right]},
    }
    if protocol in CAMERA_RIG_FOV_DEG:
        cfg["source_aspect"] = aspect
    cfg["released"] = released_extrinsics(rot_left, left, rot_right, right, baseline=baseline)
    cfg.update(_rig_entries(c, town_id, fov, (fx, fy, u0, v0), baseline, t, (rp, 0.0, 0.0)))
    return cfg


def _rig_entries(c, town_id, fov, intrinsics, baseline, t, rotation):
    """The entries every protocol's configuration has: its id and town, the
    intrinsics (fx, fy, u0, v0), baseline, and the right camera's pose in the
    left camera's frame (``t``, ``rotation``: pitch, yaw, roll)."""
    fx, fy, u0, v0 = intrinsics
    pitch, yaw, roll = rotation
    return {
        "config_id": c, "town_id": town_id, "town": scenes.TOWNS[town_id],
        "fov_deg": fov, "fx": fx, "fy": fy, "u0": u0, "v0": v0, "baseline": baseline,
        "tx": float(t[0]), "ty": float(t[1]), "tz": float(t[2]),
        "pitch": pitch, "yaw": yaw, "roll": roll,
    }


def _drive(rng, town_id):
    """A configuration's drive: where it starts along the town, its step per
    frame and the phase of its sway (see ``vehicle_position``)."""
    return {"start_x": _u(rng, (0.0, scenes.make_town(town_id).period)),
            "step": _u(rng, DRIVE["step_m"]), "sway_phase": _u(rng, (0.0, 2 * math.pi))}


def _appearance(seed, c):
    """Configuration ``c``'s appearance in the ``wild`` protocol, drawn from
    its own generator (seed, ``wild``, c): the sun (unit vector, world frame),
    the haze distance and colour, and the white balance (JSON-able)."""
    A = WILD_APPEARANCE
    rng = np.random.default_rng([seed, PROTOCOLS.index("wild"), c])
    elevation = _u(rng, A["sun_elevation_deg"])
    azimuth = _u(rng, A["sun_azimuth_deg"])
    haze = math.exp(_u(rng, tuple(math.log(h) for h in A["haze_m"])))
    blend = _u(rng, A["haze_blend"])
    temperature = _u(rng, A["white_balance_temperature"])
    tint = _u(rng, A["white_balance_tint"])
    gains = [1.0 + temperature, 1.0 + tint, 1.0 - temperature]
    el, az = math.radians(elevation), math.radians(azimuth)
    sun = [math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)]
    colour = [(1 - blend) * cool + blend * warm
              for cool, warm in zip(A["haze_colour_cool"], A["haze_colour_warm"])]
    return {"sun": sun, "sun_elevation_deg": elevation, "sun_azimuth_deg": azimuth,
            "haze_m": haze, "haze_blend": blend, "haze_colour": colour,
            "white_balance": gains}


def appearance_town(town, appearance):
    """``town`` lit as ``appearance`` says: its sun, haze and haze colour
    replaced (``dataclasses.replace``: the layout's arrays are shared, the
    cached town is left as it is)."""
    return dataclasses.replace(town, sun=np.asarray(appearance["sun"], np.float64),
                               haze=float(appearance["haze_m"]),
                               haze_colour=np.asarray(appearance["haze_colour"], np.float32))


def configurations(protocol, seed, pairs, image_size):
    """The configuration table (list of JSON-able dicts) of a dataset."""
    return [dict(c) for c in _configurations(protocol, int(seed), int(pairs), int(image_size))]


def config_of_pair(protocol, pairs, index):
    """(config_id, frame_index) of pair ``index``: contiguous runs per configuration."""
    n = num_configs(protocol, pairs)
    c = index * n // pairs
    first = -(-c * pairs // n)
    return c, index - first


def pair_config(protocol, seed, pairs, image_size, index):
    """``(configuration, frame_index)`` of pair ``index`` (the configuration
    is the cached record: read it, do not change it)."""
    c, frame = config_of_pair(protocol, pairs, index)
    return _configurations(protocol, int(seed), int(pairs), int(image_size))[c], frame


def vehicle_position(cfg, frame, period):
    """The vehicle's position (x, y, z) at ``frame`` of its drive along a town
    of ``period`` metres: ``step`` on per frame, a slow lateral sway."""
    return np.array([math.fmod(cfg["start_x"] + frame * cfg["step"], period),
                     DRIVE["sway_m"] * math.sin(0.07 * frame + cfg["sway_phase"]), 0.0])
