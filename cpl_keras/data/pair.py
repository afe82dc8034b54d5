"""One pair of the synthetic stereo dataset: its two images and its labels.

Each pair is rendered by ``cpl_keras.data.render`` in a town of
``cpl_keras.data.scenes`` with a rig from ``cpl_keras.data.protocols`` (in
the ``wild`` protocol under its configuration's sun, haze and white
balance, which change the images only), and labelled with the paper's 13
targets:

* the intrinsics fx, fy, u0, v0 and the extrinsics pitch, tx, ty, tz of the
  right camera relative to the left one (see ``protocols``),
* the true disparity at the projection pixel (u, v) of the right image,
  ``d = fx * baseline / xCam`` (Eq. 4a inverted), xCam being the rendered
  depth of that pixel; (u, v) is chosen on scene geometry, never the sky
  (``pixels.choose_projection_pixel``),
* X, Y, Z = ``camera.image_to_world`` of those labels (Eqs. 4a-5c), so the
  labels obey the camera equations exactly and name the rendered point in
  the left camera's frame.

What the release's labels need is stored beside them: its disparity (mean
of the raw ``cv2.StereoBM`` map, ``released_disparity``) as
``disparity_released``, its extrinsics (vehicle-frame differences, CARLA
conventions, pitch in degrees) as ``<name>_released`` and its fixed pixel
(W/2, H/2) as ``u_released``, ``v_released``; ``sky_at_release_pixel`` says
whether that pixel sees the sky. ``datasets.targets_from_labels(...,
as_released=True)`` turns them into the release's targets.
``LABEL_DESCRIPTIONS`` says what each stored label is;
``cpl_keras.data.generate`` writes the pairs to a dataset.
"""

from __future__ import annotations

import numpy as np

from cpl_keras import camera, frames
from cpl_keras.data import pixels, protocols, render, scenes
from cpl_keras.data.scenes import SKY_DISTANCE

LABEL_DESCRIPTIONS = {
    "fx": "focal length along u, pixels (shared by both cameras)",
    "fy": "focal length along v, pixels (shared by both cameras)",
    "u0": "principal point u, pixels",
    "v0": "principal point v, pixels",
    "baseline": "cvgl: tx as released; random: distance between the camera centres",
    "disparity": "true disparity at (u, v) of the right image: fx * baseline / xCam (Eq. 4a)",
    "disparity_released": "mean of the raw cv2.StereoBM_create(16, 15) map of the grey pair "
                          "(16x fixed point, invalid -16 included), as in the release",
    "tx": "right camera centre in the left camera frame, x (forward)",
    "ty": "right camera centre in the left camera frame, y (left)",
    "tz": "right camera centre in the left camera frame, z (up)",
    "pitch": "relative pitch right-to-left (Eq. 5), radians, positive tilts down; the release "
             "stored degrees and fed them to sin/cos as radians",
    "yaw": "relative yaw right-to-left, radians: always 0 (the relative rotation is a pitch "
           "only); kept for format stability",
    "roll": "relative roll right-to-left, radians: always 0 (the relative rotation is a pitch "
            "only); kept for format stability",
    "X": "Eq. 5a at (u, v): image_to_world of the stored labels (left camera frame)",
    "Y": "Eq. 5b at (u, v): image_to_world of the stored labels (left camera frame)",
    "Z": "Eq. 5c at (u, v): image_to_world of the stored labels (left camera frame)",
    "u": "projection pixel u (column) in the right image, on scene geometry (not the sky)",
    "v": "projection pixel v (row) in the right image, on scene geometry (not the sky)",
    "baseline_released": "baseline as released (release frame): cvgl tx_released; random: "
                         "distance between the camera centres",
    "tx_released": "as released: right-minus-left camera x in the vehicle frame (CARLA, "
                   "forward), metres",
    "ty_released": "as released: right-minus-left camera y in the vehicle frame (CARLA, "
                   "RIGHT), metres",
    "tz_released": "as released: right-minus-left camera z in the vehicle frame (CARLA, up), "
                   "metres",
    "pitch_released": "as released: right-minus-left camera pitch, DEGREES, CARLA convention "
                      "(positive up); the release fed it to sin/cos as radians",
    "u_released": "the release's fixed projection pixel u = W/2 (as-released X, Y, Z)",
    "v_released": "the release's fixed projection pixel v = H/2 (as-released X, Y, Z)",
    "sky_at_release_pixel": "1 if the release's pixel (W/2, H/2) of the right image sees the "
                            "sky dome, else 0",
    "projection_fallback": "1 if no drawn candidate pixel was nearer than MAX_LABEL_DISTANCE "
                           "and the nearest pixel inside the margin was taken, else 0",
    "config_id": "rig configuration",
    "town_id": "town (0 = Town01, 1 = Town02)",
    "frame_index": "frame along the configuration's drive",
}
#: The extrinsics stored a second time in the release's frame (``<name>_released``).
RELEASE_FRAME = ("baseline", "tx", "ty", "tz", "pitch")
FLOAT_LABELS = camera.TARGETS + ("u", "v", "disparity_released", "yaw", "roll") + tuple(
    f"{k}_released" for k in RELEASE_FRAME) + ("u_released", "v_released")
INT_LABELS = ("config_id", "town_id", "frame_index", "sky_at_release_pixel",
              "projection_fallback")
#: Units of the labels that ``camera.UNITS`` does not name.
EXTRA_UNITS = {"baseline_released": "m", "tx_released": "m", "ty_released": "m",
               "tz_released": "m", "pitch_released": "deg", "u_released": "px",
               "v_released": "px"}
#: A ray sees the sky when its hit is at least this fraction of SKY_DISTANCE away.
SKY_FRACTION = 0.99


# ---------------------------------------------------------------------------
# The release's disparity
# ---------------------------------------------------------------------------
def _stereo_bm():
    import cv2

    cv2.setNumThreads(1)
    return cv2.StereoBM_create(numDisparities=BM_DISPARITIES, blockSize=BM_BLOCK)


BM_DISPARITIES, BM_BLOCK = 16, 15


def released_disparity(left, right):
    """Mean of the raw StereoBM map of an RGB pair, as the release computed it.

    Images narrower than ``numDisparities + blockSize - 1`` = 30 pixels have no
    valid match window (OpenCV then leaves its output uninitialised): the map
    is all invalid and the mean is -16.
    """
    import cv2

    if left.shape[1] < BM_DISPARITIES + BM_BLOCK - 1 or left.shape[0] < BM_BLOCK:
        return -16.0
    grey_l = cv2.cvtColor(np.ascontiguousarray(left, dtype=np.uint8), cv2.COLOR_RGB2GRAY)
    grey_r = cv2.cvtColor(np.ascontiguousarray(right, dtype=np.uint8), cv2.COLOR_RGB2GRAY)
    return float(_stereo_bm().compute(grey_l, grey_r).mean())


# ---------------------------------------------------------------------------
# A pair and its labels
# ---------------------------------------------------------------------------
def pair_setup(protocol, seed, pairs, image_size, index):
    """Everything needed to render pair ``index``: its configuration, town,
    the two cameras' views and the candidate projection pixels."""
    cfg, frame = protocols.pair_config(protocol, seed, pairs, image_size, index)
    town = scenes.make_town(cfg["town_id"])
    appearance = cfg.get("appearance")
    if appearance is not None:
        town = protocols.appearance_town(town, appearance)
    vehicle = protocols.vehicle_position(cfg, frame, town.period)
    W = H = int(image_size)
    left_rot = _rotation(cfg["left_pose"])
    if "right_rotation" in cfg:
        right_rot = np.asarray(cfg["right_rotation"])
    else:
        right_rot = _rotation(cfg["right_pose"])
    intr = (cfg["fx"], cfg["fy"], cfg["u0"], cfg["v0"], W, H)
    left = render.View(*intr, vehicle + np.asarray(cfg["left_pose"]["position"]), left_rot)
    right = render.View(*intr, vehicle + np.asarray(cfg["right_pose"]["position"]), right_rot)
    return {"config": cfg, "frame_index": frame, "town": town, "left": left, "right": right,
            "uv_candidates": pixels.projection_candidates(W, H, cfg["u0"], cfg["v0"]),
            "margin": pixels.projection_margin(W), "release_uv": pixels.release_pixel(W, H),
            "principal_point": (cfg["u0"], cfg["v0"]),
            "white_balance": None if appearance is None else appearance["white_balance"]}


def _rotation(pose):
    return frames.rotation_matrix(pose["pitch"], pose["yaw"], pose["roll"])


def render_pair(protocol, seed, pairs, image_size, index):
    """Left image, right image (uint8 (H, W, 3)) and the labels of pair ``index``."""
    s = pair_setup(protocol, seed, pairs, image_size, index)
    town, cfg, right = s["town"], s["config"], s["right"]
    left_img, _ = render.render(town, s["left"])
    right_img, right_depth = render.render(town, right)
    if s["white_balance"] is not None:         # wild: one gain per channel, both images
        left_img = white_balance(left_img, s["white_balance"])
        right_img = white_balance(right_img, s["white_balance"])
    (u, v), fallback = pixels.choose_projection_pixel(
        cfg, right_depth, s["uv_candidates"], s["margin"], s["principal_point"])
    # the depth of exactly (u, v), cast on its own (also for non-integer pixels)
    xCam = float(render.depth_at(town, right, u, v)[0])
    # the release's fixed pixel: does it see the sky dome?
    u_rel, v_rel = s["release_uv"]
    sky = pixels.ray_distance(cfg, render.depth_at(town, right, u_rel, v_rel)[0], u_rel, v_rel) \
        >= SKY_FRACTION * SKY_DISTANCE
    disparity = float(camera.disparity_from_depth(cfg["fx"], cfg["baseline"], xCam))
    X, Y, Z = camera.image_to_world(
        cfg["fx"], cfg["fy"], cfg["u0"], cfg["v0"], cfg["baseline"], disparity,
        cfg["pitch"], cfg["tx"], cfg["ty"], cfg["tz"], u, v,
    )
    labels = {k: cfg[k] for k in ("fx", "fy", "u0", "v0", "baseline", "tx", "ty", "tz",
                                  "pitch", "yaw", "roll")}
    labels.update(disparity=disparity, X=float(X), Y=float(Y), Z=float(Z), u=u, v=v,
                  disparity_released=released_disparity(left_img, right_img),
                  config_id=cfg["config_id"], town_id=cfg["town_id"],
                  frame_index=s["frame_index"])
    labels.update({f"{k}_released": float(cfg["released"][k]) for k in RELEASE_FRAME})
    labels.update(u_released=float(u_rel), v_released=float(v_rel),
                  sky_at_release_pixel=int(sky), projection_fallback=int(fallback))
    return left_img, right_img, labels


def white_balance(image, gains):
    """A uint8 RGB image with each channel multiplied by its gain (rounded, clipped)."""
    out = image.astype(np.float32) * np.asarray(gains, np.float32)
    return np.clip(out + 0.5, 0, 255).astype(np.uint8)
