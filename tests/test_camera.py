"""The camera equations (paper Eqs. 4a-5c) against hand-worked values."""

import math

import numpy as np
import pytest

from cpl_keras import camera, frames


def test_image_to_camera_by_hand():
    # fx = 100, b = 0.5 m, d = 10 px -> xCam = 100 * 0.5 / 10 = 5 m      (4a)
    # u - u0 = 60 - 50 = 10 -> yCam = -(5 / 100) * 10 = -0.5 m          (4b)
    # v0 - v = 50 - 40 = 10, fy = 200 -> zCam = (5 / 200) * 10 = 0.25 m (4c)
    xCam, yCam, zCam = camera.image_to_camera(
        fx=100.0, fy=200.0, u0=50.0, v0=50.0, baseline=0.5, disparity=10.0, u=60.0, v=40.0
    )
    assert (xCam, yCam, zCam) == pytest.approx((5.0, -0.5, 0.25))


def test_camera_to_world_by_hand():
    t = dict(tx=1.0, ty=2.0, tz=3.0)
    # pitch 0: a pure translation                                      (5a-5c)
    assert camera.camera_to_world(5.0, -0.5, 0.25, pitch=0.0, **t) == pytest.approx((6.0, 1.5, 3.25))
    # pitch 90 deg: X = zCam + tx = 1.25, Y = yCam + ty, Z = -xCam + tz = -2
    assert camera.camera_to_world(5.0, -0.5, 0.25, pitch=math.pi / 2, **t) == pytest.approx(
        (1.25, 1.5, -2.0)
    )
    # pitch 30 deg
    c, s = math.cos(math.pi / 6), math.sin(math.pi / 6)
    assert camera.camera_to_world(2.0, 0.0, 1.0, pitch=math.pi / 6, tx=0, ty=0, tz=0) == pytest.approx(
        (2 * c + s, 0.0, -2 * s + c)
    )


def test_positive_pitch_tilts_the_optical_axis_down():
    X, _, Z = camera.camera_to_world(1.0, 0.0, 0.0, pitch=0.2, tx=0.0, ty=0.0, tz=0.0)
    assert X > 0 and Z < 0


def test_focal_from_fov():
    assert camera.focal_from_fov(math.radians(90), 112) == pytest.approx(56.0)
    assert camera.focal_from_fov(math.radians(60), 112) == pytest.approx(56.0 / math.tan(math.radians(30)))
    fov = np.radians([50.0, 90.0, 150.0])
    assert camera.fov_from_focal(camera.focal_from_fov(fov, 112), 112) == pytest.approx(fov)


def test_world_image_world_round_trip():
    rng = np.random.default_rng(0)
    n = 1000
    p = dict(
        fx=rng.uniform(20, 400, n), fy=rng.uniform(20, 400, n), u0=rng.uniform(30, 80, n),
        v0=rng.uniform(30, 80, n), baseline=rng.uniform(0.05, 5, n),
        pitch=rng.uniform(-0.6, 0.6, n), tx=rng.normal(0, 3, n), ty=rng.normal(0, 3, n),
        tz=rng.normal(0, 1, n),
    )
    # a world point in front of the camera: build it from a random depth
    xCam, yCam, zCam = rng.uniform(1, 100, n), rng.normal(0, 5, n), rng.normal(0, 5, n)
    X, Y, Z = camera.camera_to_world(xCam, yCam, zCam, p["pitch"], p["tx"], p["ty"], p["tz"])
    u, v, d = camera.world_to_image(X, Y, Z, **p)
    X2, Y2, Z2 = camera.image_to_world(disparity=d, u=u, v=v, **p)
    np.testing.assert_allclose(np.stack([X2, Y2, Z2]), np.stack([X, Y, Z]), rtol=1e-9, atol=1e-9)


def test_rotation_matrix_matches_eq5_without_yaw_and_roll():
    pitch = 0.37
    point = np.array([3.0, -1.0, 0.5])
    expected = camera.camera_to_world(*point, pitch=pitch, tx=0.0, ty=0.0, tz=0.0)
    np.testing.assert_allclose(frames.rotation_matrix(pitch) @ point, expected)
    R = frames.rotation_matrix(0.1, 0.2, 0.3)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    # yaw turns the optical axis left (+y)
    assert (frames.rotation_matrix(yaw=0.3) @ [1.0, 0.0, 0.0])[1] > 0


def test_safe_divisor_keeps_sign_and_never_returns_zero():
    b = np.array([0.0, -0.0, 1e-9, -1e-9, 2.0, -2.0])
    floored = camera.safe_divisor(b, 1e-3)
    np.testing.assert_allclose(floored, [1e-3, 1e-3, 1e-3, -1e-3, 2.0, -2.0])
    with np.errstate(all="raise"):
        xCam = camera.depth_from_disparity(100.0, 0.5, np.array([0.0, 1e-12, -1e-12]))
    assert np.all(np.isfinite(xCam))
    assert xCam[2] < 0 < xCam[0]


def test_tensor_ops_agree_with_numpy():
    from keras import ops

    rng = np.random.default_rng(1)
    args = {name: rng.uniform(0.5, 2.0, 8).astype("float32") for name in camera.PARAMETERS}
    args.update(u=rng.uniform(0, 100, 8).astype("float32"), v=rng.uniform(0, 100, 8).astype("float32"))
    expected = camera.image_to_world(**args)
    got = camera.image_to_world(**{k: ops.convert_to_tensor(a) for k, a in args.items()},
                                ops=camera.tensor_ops())
    for e, g in zip(expected, got):
        np.testing.assert_allclose(ops.convert_to_numpy(g), e, rtol=1e-5)


def test_euler_from_rotation_inverts_rotation_matrix():
    rng = np.random.default_rng(2)
    for pitch, yaw, roll in rng.uniform(-1.2, 1.2, (50, 3)):
        R = frames.rotation_matrix(pitch, yaw, roll)
        assert frames.euler_from_rotation(R) == pytest.approx((pitch, yaw, roll), abs=1e-9)


def test_pixel_and_disparity_inverses_by_hand():
    # xCam 5, yCam -0.5, zCam 0.25 with fx 100, fy 200, (u0, v0) = (50, 50)
    u, v = camera.camera_to_pixel(5.0, -0.5, 0.25, 100.0, 200.0, 50.0, 50.0)
    assert (u, v) == pytest.approx((60.0, 40.0))
    assert camera.disparity_from_depth(100.0, 0.5, 5.0) == pytest.approx(10.0)
    assert np.isfinite(camera.fov_from_focal(0.0, 112)) and camera.fov_from_focal(0.0, 112) == pytest.approx(math.pi)


def test_square_pixel_fy_of_a_crop_and_resize():
    """A square-pixel camera (fx = fy = 500 px) cropped to 300 x 200 and
    resized to 100 x 100: fx becomes 500 / 3, fy 500 / 2 (by hand), and
    square_pixel_fy recovers fy from fx and the sides alone, as the real
    crops' labels have it (``StereoCamera.crop`` and ``resize``)."""
    from cpl_keras.stereo_camera import StereoCamera

    fx = 500.0 * 100 / 300
    assert camera.square_pixel_fy(fx, 300, 200, 100, 100) == pytest.approx(500.0 * 100 / 200)
    # a 1242 x 375 KITTI image squashed to 112 x 112: fy = fx * 1242 / 375
    assert camera.square_pixel_fy(1.0, 1242, 375, 112, 112) == pytest.approx(1242 / 375)
    # no squash, no change; arrays broadcast
    np.testing.assert_allclose(camera.square_pixel_fy([10.0, 20.0], 64, 48, 32, 24), [10.0, 20.0])
    rig = StereoCamera(fx=451.0, fy=451.0, u0=320.0, v0=240.0, width=640, height=480,
                       baseline=0.075, pitch=0.0, tx=0.0, ty=-0.075, tz=0.0)
    small = rig.crop(17, 30, 410, 260).resize(112, 112)
    assert camera.square_pixel_fy(small.fx, 410, 260, 112, 112) == pytest.approx(small.fy)
