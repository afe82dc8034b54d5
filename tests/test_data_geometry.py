"""Geometry of the synthetic stereo data: renderer, rig labels and camera model agree."""

import math

import numpy as np
import pytest

from cpl_keras import camera
from cpl_keras.data import protocols, render, scenes
from cpl_keras.data.generate import render_pair

SIZE = 48


def _rectified_rig(baseline=0.6, fov_deg=80.0, x=230.0, town_id=0):
    """Left and right views of a rectified lateral rig (right camera to the right)."""
    fx = float(camera.focal_from_fov(math.radians(fov_deg), SIZE))
    rot = camera.rotation_matrix(0.0)
    left_pos = np.array([x, 1.0, 1.5])
    right_pos = left_pos + np.array([0.0, -baseline, 0.0])    # ty = -baseline
    left = render.View(fx, fx, SIZE / 2, SIZE / 2, SIZE, SIZE, left_pos, rot)
    right = render.View(fx, fx, SIZE / 2, SIZE / 2, SIZE, SIZE, right_pos, rot)
    return scenes.make_town(town_id), left, right


def test_focal_from_fov_matches_cvgl_configurations():
    assert float(camera.focal_from_fov(math.radians(90.0), 112)) == pytest.approx(56.0)
    for cfg in protocols.configurations("cvgl", 0, 100, 112):
        expected = 112 / (2 * math.tan(math.radians(cfg["fov_deg"]) / 2))
        assert cfg["fx"] == pytest.approx(expected)
        assert cfg["fy"] == cfg["fx"]
        assert (cfg["u0"], cfg["v0"]) == (56.0, 56.0)
        assert 50.0 <= cfg["fov_deg"] <= 150.0


def test_point_seen_by_right_camera_appears_at_u_plus_d_in_left_camera():
    town, left, right = _rectified_rig()
    _, depth_right = render.render(town, right)
    fx, b = right.fx, 0.6
    rng = np.random.default_rng(0)
    checked = 0
    for u, v in rng.integers(4, SIZE - 4, size=(40, 2)):
        xCam = depth_right[v, u]
        d = fx * b / xCam                                   # Eq. 4a inverted
        point = right.position + xCam * right.rays(u, v)    # the 3D point
        # the left camera's ray through (u + d, v) must reach the same point
        xCam_left = render.depth_at(town, left, u + d, v)[0]
        if abs(xCam_left - xCam) > 1e-6 * xCam:
            continue                    # occluded from the left camera
        point_left = left.position + xCam_left * left.rays(u + d, v)
        np.testing.assert_allclose(point_left, point, rtol=0, atol=1e-6 * xCam)
        pu, pv, pd = camera.world_to_image(*(point - left.position), fx, fx, SIZE / 2, SIZE / 2,
                                           b, 0.0, 0.0, 0.0, 0.0)
        assert pu == pytest.approx(u + d) and pv == pytest.approx(v) and pd == pytest.approx(d)
        checked += 1
    assert checked >= 30


def test_left_image_is_right_image_shifted_by_disparity():
    """Sampling the left image at (u + d, v) reproduces the right image."""
    town, left, right = _rectified_rig(baseline=0.8, fov_deg=70.0)
    img_left, _ = render.render(town, left)
    img_right, depth_right = render.render(town, right)
    v, u = np.mgrid[0:SIZE, 0:SIZE]
    d = right.fx * 0.8 / depth_right
    assert d.max() > 3.0                       # near things shift by several pixels
    assert d.min() < 0.1                       # far things (sky) hardly move
    src = u + d
    i0 = np.floor(src).astype(int)
    moving = (i0 + 1 < SIZE) & (d > 1.0)
    frac = (src - i0)[moving][:, None]
    warped = (1 - frac) * img_left[v[moving], i0[moving]] + frac * img_left[v[moving], i0[moving] + 1]
    target = img_right[moving].astype(float)
    err_warped = np.median(np.abs(warped - target).mean(axis=-1))
    err_plain = np.median(np.abs(img_left[moving].astype(float) - target).mean(axis=-1))
    assert moving.sum() > 500
    assert err_warped < 1.0
    assert err_warped < 0.5 * err_plain


def test_near_objects_shift_more_than_far_ones():
    town, left, right = _rectified_rig()
    _, depth = render.render(town, right)
    d = right.fx * 0.6 / depth
    bottom, top = d[-2].mean(), d[SIZE // 2 - 2].mean()    # road near vs horizon
    assert bottom > 3 * top


@pytest.mark.parametrize("protocol", ["cvgl", "random"])
def test_labels_obey_camera_equations_and_describe_the_rendered_point(protocol):
    pairs = 60
    for index in (0, 29, 59):
        _, _, lab = render_pair(protocol, 5, pairs, SIZE, index)
        X, Y, Z = camera.image_to_world(
            lab["fx"], lab["fy"], lab["u0"], lab["v0"], lab["baseline"], lab["disparity"],
            lab["pitch"], lab["tx"], lab["ty"], lab["tz"], lab["u"], lab["v"])
        np.testing.assert_allclose([X, Y, Z], [lab["X"], lab["Y"], lab["Z"]], rtol=1e-9)
        # the rendered point, in the left camera's frame
        s = protocols.pair_setup(protocol, 5, pairs, SIZE, index)
        right, left = s["right"], s["left"]
        xCam = render.depth_at(s["town"], right, lab["u"], lab["v"])[0]
        assert lab["disparity"] == pytest.approx(lab["fx"] * lab["baseline"] / xCam)
        world = right.position + xCam * right.rays(lab["u"], lab["v"])
        in_left = left.rotation.T @ (world - left.position)
        if protocol == "cvgl":       # yaw = roll = 0: X, Y, Z is exactly that point
            np.testing.assert_allclose([X, Y, Z], in_left, rtol=1e-9, atol=1e-9)
        # relative pose labels: P_left = R(pitch, yaw, roll) P_right + t
        R = camera.rotation_matrix(lab["pitch"], lab["yaw"], lab["roll"])
        in_right = right.rotation.T @ (world - right.position)
        np.testing.assert_allclose(R @ in_right + [lab["tx"], lab["ty"], lab["tz"]], in_left,
                                   atol=1e-9 * max(1.0, abs(xCam)))


def test_cvgl_labels_convert_carla_conventions():
    for cfg in protocols.configurations("cvgl", 1, 50, 112)[:10]:
        carla = cfg["carla"]
        assert cfg["pitch"] == pytest.approx(math.radians(-carla["pitch_deg"] - 15.0))
        # right camera centre relative to the left camera, rotated into its frame
        dx, dy, dz = carla["x"] - 2.0, -carla["y"], carla["z"] - 1.4
        p = math.radians(15.0)
        assert cfg["tx"] == pytest.approx(math.cos(p) * dx - math.sin(p) * dz)
        assert cfg["ty"] == pytest.approx(dy)
        assert cfg["tz"] == pytest.approx(math.sin(p) * dx + math.cos(p) * dz)
        assert cfg["baseline"] == cfg["tx"] and abs(cfg["tx"]) >= 0.5


def test_random_protocol_ranges():
    configs = protocols.configurations("random", 3, 400, 64)
    assert len(configs) == 50
    for cfg in configs:
        lateral = -cfg["ty"]
        assert 0.04 < lateral < 1.01
        assert cfg["baseline"] == pytest.approx(math.sqrt(cfg["tx"]**2 + cfg["ty"]**2 + cfg["tz"]**2))
        for angle in ("pitch", "yaw", "roll"):
            assert abs(cfg[angle]) < math.radians(3.5)
        assert 40.0 <= cfg["fov_deg"] <= 120.0
        assert abs(cfg["fy"] / cfg["fx"] - 1) <= 0.05 + 1e-9
    assert len({round(c["u0"], 3) for c in configs}) > 40        # off-centre, varied
    assert {c["town_id"] for c in configs} == {0, 1}


def test_every_pixel_has_finite_positive_depth():
    town = scenes.make_town(1)
    fx = float(camera.focal_from_fov(math.radians(150.0), SIZE))
    view = render.View(fx, fx, SIZE / 2, SIZE / 2, SIZE, SIZE, np.array([50.0, 0.0, 2.0]),
                       camera.rotation_matrix(math.radians(-30.0)))
    image, depth = render.render(town, view)
    assert np.all(np.isfinite(depth)) and depth.min() > 0
    assert depth.max() <= scenes.SKY_DISTANCE
    assert image.dtype == np.uint8 and image.shape == (SIZE, SIZE, 3)
    assert image.std() > 10                   # a textured scene, not a flat colour
