"""Geometry of the synthetic stereo data: renderer, rig labels and camera model agree."""

import math

import numpy as np
import pytest

from cpl_keras import camera, frames
from cpl_keras.data import pixels, protocols, render, scenes
from cpl_keras.data.pair import pair_setup, render_pair

SIZE = 48


def _rectified_rig(baseline=0.6, fov_deg=80.0, x=230.0, town_id=0):
    """Left and right views of a rectified lateral rig (right camera to the right)."""
    fx = float(camera.focal_from_fov(math.radians(fov_deg), SIZE))
    rot = frames.rotation_matrix(0.0)
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
        s = pair_setup(protocol, 5, pairs, SIZE, index)
        right, left = s["right"], s["left"]
        xCam = render.depth_at(s["town"], right, lab["u"], lab["v"])[0]
        assert lab["disparity"] == pytest.approx(lab["fx"] * lab["baseline"] / xCam)
        world = right.position + xCam * right.rays(lab["u"], lab["v"])
        in_left = left.rotation.T @ (world - left.position)
        # no relative yaw or roll in either protocol: X, Y, Z is exactly that point
        assert lab["yaw"] == 0.0 and lab["roll"] == 0.0
        np.testing.assert_allclose([X, Y, Z], in_left, rtol=1e-9, atol=1e-9)
        # relative pose labels: P_left = R(pitch, yaw, roll) P_right + t
        R = frames.rotation_matrix(lab["pitch"], lab["yaw"], lab["roll"])
        in_right = right.rotation.T @ (world - right.position)
        np.testing.assert_allclose(R @ in_right + [lab["tx"], lab["ty"], lab["tz"]], in_left,
                                   atol=1e-9 * max(1.0, abs(xCam)))


@pytest.mark.parametrize("protocol", ["cvgl", "random"])
def test_label_point_is_the_rendered_point_in_both_cameras(protocol):
    """(X, Y, Z) projected into the LEFT camera lands on a surface at depth X,
    and the right camera's depth at (u, v) is fx * b / d."""
    pairs, seen, matched = 40, 0, 0
    for index in range(0, pairs, 2):
        _, _, lab = render_pair(protocol, 2, pairs, SIZE, index)
        s = pair_setup(protocol, 2, pairs, SIZE, index)
        fx, fy, u0, v0 = lab["fx"], lab["fy"], lab["u0"], lab["v0"]
        xCam = render.depth_at(s["town"], s["right"], lab["u"], lab["v"])[0]
        assert xCam == pytest.approx(fx * lab["baseline"] / lab["disparity"], rel=1e-9)
        # never the sky dome: the point is a surface point near the right camera
        ray = camera.camera_point(1.0, fx, fy, u0, v0, lab["u"], lab["v"])
        assert xCam * math.hypot(1.0, *ray) < pixels.MAX_LABEL_DISTANCE
        X, Y, Z = lab["X"], lab["Y"], lab["Z"]
        u_left, v_left = camera.camera_to_pixel(X, Y, Z, fx, fy, u0, v0)
        if not (X > 0 and 0 <= u_left <= SIZE - 1 and 0 <= v_left <= SIZE - 1):
            continue                       # outside the left image
        seen += 1
        depth_left = render.depth_at(s["town"], s["left"], u_left, v_left)[0]
        # the left ray ends on a surface at or before the point (occlusion) ...
        assert depth_left <= X * (1 + 1e-9)
        # ... and most label points are visible there, at depth X (measured:
        # relative error below 1.2e-14 at the visible ones; 1e-9 allowed)
        if abs(depth_left - X) <= 1e-9 * X:
            matched += 1
    assert seen >= 8, seen
    assert matched >= 0.75 * seen, (matched, seen)


def test_random_rigs_have_no_relative_yaw_or_roll():
    """The right camera's rotation relative to the left is Ry(pitch) (Eq. 5)."""
    configs = protocols.configurations("random", 4, 80, 64)
    for index in range(0, 80, 8):
        s = pair_setup("random", 4, 80, 64, index)
        cfg = s["config"]
        relative = s["left"].rotation.T @ s["right"].rotation
        np.testing.assert_allclose(relative, frames.rotation_matrix(cfg["pitch"]), atol=1e-12)
        assert cfg["yaw"] == 0.0 and cfg["roll"] == 0.0
    assert len({round(c["pitch"], 6) for c in configs}) > 5          # pitch still varies
    # the left camera's own mounting yaw and roll stay
    assert any(abs(c["left_pose"]["yaw"]) > 1e-3 for c in configs)


@pytest.mark.parametrize("protocol", ["cvgl", "random"])
def test_projection_pixel_on_geometry_and_release_pixel_sky_flag(protocol):
    pairs = 50
    sky_flags = []
    for index in range(0, pairs, 5):
        _, _, lab = render_pair(protocol, 0, pairs, SIZE, index)
        s = pair_setup(protocol, 0, pairs, SIZE, index)
        margin = pixels.projection_margin(SIZE)
        assert lab["u"] == int(lab["u"]) and lab["v"] == int(lab["v"])
        assert margin <= lab["u"] < SIZE - margin and margin <= lab["v"] < SIZE - margin
        assert lab["projection_fallback"] in (0, 1)
        # the release's fixed pixel, and whether it sees the sky dome
        assert (lab["u_released"], lab["v_released"]) == (SIZE / 2, SIZE / 2)
        d = render.depth_at(s["town"], s["right"], SIZE / 2, SIZE / 2)[0]
        ray = camera.camera_point(1.0, lab["fx"], lab["fy"], lab["u0"], lab["v0"],
                                  SIZE / 2, SIZE / 2)
        assert lab["sky_at_release_pixel"] == int(
            d * math.hypot(1.0, *ray) >= 0.99 * scenes.SKY_DISTANCE)
        sky_flags.append(lab["sky_at_release_pixel"])
    if protocol == "cvgl":
        assert 0 < sum(sky_flags) < len(sky_flags)    # the release's pixel often sees the sky


def test_projection_fallback_takes_the_nearest_pixel_inside_the_margin():
    from cpl_keras.data.pixels import choose_projection_pixel

    cfg = {"fx": 30.0, "fy": 30.0, "u0": 16.0, "v0": 16.0}
    depth = np.full((32, 32), scenes.SKY_DISTANCE)
    depth[30, 30] = 1.0                     # nearest, but inside the border margin
    depth[20, 9] = 50.0
    candidates = np.array([[5.0, 5.0], [16.0, 16.0]])       # both see the sky
    (u, v), fallback = choose_projection_pixel(cfg, depth, candidates, margin=4)
    assert (u, v, fallback) == (9.0, 20.0, 1)
    depth[16, 16] = 150.0                   # a candidate near enough: no fallback
    assert choose_projection_pixel(cfg, depth, candidates, margin=4) == ((16.0, 16.0), 0)
    depth[16, 16] = 250.0                   # beyond MAX_LABEL_DISTANCE: not taken
    assert choose_projection_pixel(cfg, depth, candidates, margin=4)[1] == 1


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
        # the release's frame: CARLA values minus the left camera's, pitch in degrees
        released = cfg["released"]
        assert released["tx"] == pytest.approx(carla["x"] - 2.0)
        assert released["ty"] == pytest.approx(carla["y"])
        assert released["tz"] == pytest.approx(carla["z"] - 1.4)
        assert -0.4 - 1e-9 <= released["tz"] <= 1.6 + 1e-9
        assert released["pitch"] == pytest.approx(carla["pitch_deg"] + 15.0)
        assert released["pitch"] == pytest.approx(-math.degrees(cfg["pitch"]))
        assert released["baseline"] == released["tx"]
        # the generic vehicle-frame difference (used by the random protocol) agrees
        generic = protocols.released_extrinsics(
            frames.rotation_matrix(p), (2.0, 0.0, 1.4),
            frames.rotation_matrix(math.radians(-carla["pitch_deg"])),
            (carla["x"], -carla["y"], carla["z"]))
        for key in released:
            assert generic[key] == pytest.approx(released[key], abs=1e-9)


def test_random_protocol_ranges():
    configs = protocols.configurations("random", 3, 400, 64)
    assert len(configs) == 50
    for cfg in configs:
        lateral = -cfg["ty"]
        assert 0.04 < lateral < 1.01
        assert cfg["baseline"] == pytest.approx(math.sqrt(cfg["tx"]**2 + cfg["ty"]**2 + cfg["tz"]**2))
        assert abs(cfg["pitch"]) < math.radians(3.5)
        # release-frame analogue: vehicle-frame difference of the camera centres,
        # CARLA's y (right) and pitch sign (up), degrees
        left = np.array(cfg["left_pose"]["position"])
        right = np.array(cfg["right_pose"]["position"])
        released = cfg["released"]
        assert released["tx"] == pytest.approx(right[0] - left[0])
        assert released["ty"] == pytest.approx(-(right[1] - left[1]))
        assert released["tz"] == pytest.approx(right[2] - left[2])
        right_pitch = frames.euler_from_rotation(np.array(cfg["right_rotation"]))[0]
        assert released["pitch"] == pytest.approx(
            math.degrees(cfg["left_pose"]["pitch"] - right_pitch))
        assert released["baseline"] == pytest.approx(cfg["baseline"])
        assert 0.0 < released["ty"] < 1.1            # the right camera is to the right
        assert 40.0 <= cfg["fov_deg"] <= 120.0
        assert abs(cfg["fy"] / cfg["fx"] - 1) <= 0.05 + 1e-9
    assert len({round(c["u0"], 3) for c in configs}) > 40        # off-centre, varied
    assert {c["town_id"] for c in configs} == {0, 1}


def test_every_pixel_has_finite_positive_depth():
    town = scenes.make_town(1)
    fx = float(camera.focal_from_fov(math.radians(150.0), SIZE))
    view = render.View(fx, fx, SIZE / 2, SIZE / 2, SIZE, SIZE, np.array([50.0, 0.0, 2.0]),
                       frames.rotation_matrix(math.radians(-30.0)))
    image, depth = render.render(town, view)
    assert np.all(np.isfinite(depth)) and depth.min() > 0
    assert depth.max() <= scenes.SKY_DISTANCE
    assert image.dtype == np.uint8 and image.shape == (SIZE, SIZE, 3)
    assert image.std() > 10                   # a textured scene, not a flat colour


@pytest.mark.parametrize("protocol", ["cvgl", "random"])
def test_projection_pixel_is_the_first_geometry_down_the_off_centre_column(protocol):
    """The pixel depends on the image only (a network can see which point the
    labels describe): (W/2 + W/8, H/2 + H/16) when it is on near geometry,
    else the first such pixel below it in the same column."""
    column, first = SIZE // 2 + SIZE // 8, SIZE // 2 + SIZE // 16   # 30, 27 at 48 px
    below = checked = 0
    for index in range(12):
        s = pair_setup(protocol, 3, 12, SIZE, index)
        _, _, lab = render_pair(protocol, 3, 12, SIZE, index)
        if lab["projection_fallback"]:
            continue
        checked += 1
        assert lab["u"] == column and lab["v"] >= first
        cfg = s["config"]
        for v in range(first, int(lab["v"]) + 1):
            if abs(v - cfg["v0"]) < pixels.PRINCIPAL_CLEARANCE:
                continue
            ray = camera.camera_point(1.0, cfg["fx"], cfg["fy"], cfg["u0"], cfg["v0"],
                                      column, v)
            depth = render.depth_at(s["town"], s["right"], column, v)[0]
            near = depth * math.hypot(1.0, *ray) < pixels.MAX_LABEL_DISTANCE
            assert near == (v == lab["v"]), (index, v)
        below += lab["v"] > first
    assert checked >= 9, checked  # (fallback pairs are a few %: most pairs are checked)
    if protocol == "cvgl":
        assert below > 0          # the first pixel can see the sky: the rule walks down


@pytest.mark.parametrize("protocol", ["cvgl", "random"])
def test_projection_pixels_avoid_the_principal_row_and_column(protocol):
    """On the principal row zCam = 0 (fy's term has no gradient from the
    point), on the principal column yCam = 0. The former rule put 45 % of
    the cvgl labels on v = v0 and 92 % on u = u0."""
    us, vs = [], []
    for index in range(0, 60, 3):
        _, _, lab = render_pair(protocol, 0, 60, SIZE, index)
        us.append(lab["u"] - lab["u0"])
        vs.append(lab["v"] - lab["v0"])
    assert min(np.abs(us)) >= pixels.PRINCIPAL_CLEARANCE
    assert min(np.abs(vs)) >= pixels.PRINCIPAL_CLEARANCE
    # the candidates themselves, for any principal point
    for u0, v0 in ((24.0, 24.0), (31.0, 27.0), (32.5, 33.0)):
        c = pixels.projection_candidates(SIZE, SIZE, u0, v0)
        assert len(c) > 0
        assert np.all(np.abs(c[:, 0] - u0) >= 1.0) and np.all(np.abs(c[:, 1] - v0) >= 1.0)
    # column 30 from row 27 down to row 41 (the margin is 6 at 48 px); row 27 skipped
    # when it is the principal row, every row when the column is the principal column
    assert pixels.projection_candidates(SIZE, SIZE, 24.0, 24.0)[:, 1].tolist() == \
        list(range(27, 42))
    assert pixels.projection_candidates(SIZE, SIZE, 24.0, 27.0)[:, 1].tolist() == \
        list(range(28, 42))
    assert len(pixels.projection_candidates(SIZE, SIZE, 30.0, 0.0)) == 0


def test_projection_fallback_avoids_the_principal_row_and_column():
    from cpl_keras.data.pixels import choose_projection_pixel

    cfg = {"fx": 30.0, "fy": 30.0, "u0": 16.0, "v0": 16.0}
    depth = np.full((32, 32), scenes.SKY_DISTANCE)
    depth[16, 9] = 10.0                     # nearest, but on the principal row
    depth[20, 16] = 20.0                    # next, on the principal column
    depth[21, 9] = 50.0
    candidates = np.zeros((0, 2))
    assert choose_projection_pixel(cfg, depth, candidates, 4) == ((9.0, 16.0), 1)
    assert choose_projection_pixel(cfg, depth, candidates, 4, (16.0, 16.0)) == ((9.0, 21.0), 1)
