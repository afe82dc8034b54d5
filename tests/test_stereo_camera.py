"""The stereo camera record (``cpl_keras.stereo_camera.StereoCamera``)."""

import dataclasses
import math

import numpy as np
import pytest

from cpl_keras import camera, frames
from cpl_keras.stereo_camera import LABELS, Point, StereoCamera

RIG = StereoCamera(fx=542.3, fy=541.6, u0=328.3, v0=246.9, width=640, height=480,
                   baseline=0.0836, pitch=0.0123, tx=-0.001, ty=-0.0836, tz=0.0007,
                   yaw=-0.004, roll=0.002)


def _crop_resize_by_formula(fx, fy, u0, v0, x0, y0, crop_width, crop_height, out_width,
                            out_height):
    """The intrinsics of a crop + resize as the real-set builders computed
    them before the camera record: focal lengths times the scales, the
    principal point through ``crop_resize_coordinate``."""
    sx = out_width / float(crop_width)
    sy = out_height / float(crop_height)
    return (fx * sx, fy * sy, float(frames.crop_resize_coordinate(u0, x0, sx)),
            float(frames.crop_resize_coordinate(v0, y0, sy)), sx, sy)


def test_camera_matrix_by_hand():
    assert RIG.K.tolist() == [[542.3, 0.0, 328.3], [0.0, 541.6, 246.9], [0.0, 0.0, 1.0]]
    assert RIG.K.dtype == np.float64


def test_a_record_is_frozen_and_checks_its_size():
    with pytest.raises(dataclasses.FrozenInstanceError):
        RIG.fx = 1.0
    with pytest.raises(ValueError, match="positive size"):
        dataclasses.replace(RIG, width=0)
    # numpy scalars become Python numbers (the JSON and the labels read them)
    cam = dataclasses.replace(RIG, fx=np.float32(2.5), width=np.int64(64))
    assert type(cam.fx) is float and cam.fx == 2.5 and type(cam.width) is int


def test_crop_and_resize_are_the_builders_arithmetic_to_the_bit():
    rng = np.random.default_rng(0)
    for _ in range(200):
        cw, ch = int(rng.integers(20, 640)), int(rng.integers(20, 480))
        x0, y0 = int(rng.integers(0, 640 - cw + 1)), int(rng.integers(0, 480 - ch + 1))
        size = int(rng.integers(32, 225))
        crop = RIG.crop(x0, y0, cw, ch)
        small = crop.resize(size, size)
        fx, fy, u0, v0, sx, sy = _crop_resize_by_formula(RIG.fx, RIG.fy, RIG.u0, RIG.v0, x0, y0,
                                                         cw, ch, size, size)
        assert (small.fx, small.fy, small.u0, small.v0) == (fx, fy, u0, v0)
        assert crop.resize_scales(size, size) == (sx, sy)
        assert (small.width, small.height) == (size, size)
        # baseline and pose do not change with the pixels
        assert small.to_labels()["pitch"] == RIG.pitch and small.baseline == RIG.baseline


def test_crop_uncrop_and_resize_round_trips():
    cropped = RIG.crop(17, 30, 410, 260)
    assert (cropped.u0, cropped.v0, cropped.width, cropped.height) == (RIG.u0 - 17, RIG.v0 - 30,
                                                                       410, 260)
    uncropped = cropped.uncrop(17, 30, 640, 480)
    assert (uncropped.u0, uncropped.v0) == pytest.approx((RIG.u0, RIG.v0), abs=1e-12)
    assert dataclasses.replace(uncropped, u0=RIG.u0, v0=RIG.v0) == RIG
    back = RIG.resize(112, 112).resize(640, 480)
    for name in ("fx", "fy", "u0", "v0"):
        assert getattr(back, name) == pytest.approx(getattr(RIG, name), rel=1e-12)
    # pixel centres at integers: the image's centre stays its centre, its
    # right and bottom edges (W - 0.5, H - 0.5) stay its edges
    centre = dataclasses.replace(RIG, u0=319.5, v0=239.5).resize(64, 48)
    assert (centre.u0, centre.v0) == pytest.approx((31.5, 23.5))
    edge = dataclasses.replace(RIG, u0=639.5, v0=479.5).resize(64, 48)
    assert (edge.u0, edge.v0) == pytest.approx((63.5, 47.5))


def test_opencv_pose_round_trip_and_convention():
    R, T = RIG.to_opencv_pose()
    assert np.allclose(R @ R.T, np.eye(3)) and np.linalg.det(R) == pytest.approx(1.0)
    # the conversions of camera.py, once
    R_expected, T_expected = frames.rig_to_opencv_pose(
        frames.rotation_matrix(RIG.pitch, RIG.yaw, RIG.roll), [RIG.tx, RIG.ty, RIG.tz])
    assert np.array_equal(R, R_expected) and np.array_equal(T, T_expected)
    back = StereoCamera.from_opencv_pose(R, T, RIG.K, RIG.width, RIG.height)
    for name in LABELS:
        if name != "baseline":     # (|t| unless given)
            assert getattr(back, name) == pytest.approx(getattr(RIG, name), abs=1e-12)
    assert back.baseline == pytest.approx(math.hypot(RIG.tx, RIG.ty, RIG.tz))
    assert StereoCamera.from_opencv_pose(R, T, RIG.K, 640, 480, baseline=0.2).baseline == 0.2
    # a right camera 0.3 m to the right (OpenCV x), no rotation: T = -0.3 x
    # in OpenCV's axes, the project's ty = -0.3 (y left)
    lateral = StereoCamera.from_opencv_pose(np.eye(3), [-0.3, 0.0, 0.0], np.eye(3), 8, 8)
    assert (lateral.tx, lateral.ty, lateral.tz) == pytest.approx((0.0, -0.3, 0.0))
    assert lateral.baseline == pytest.approx(0.3) and lateral.pitch == pytest.approx(0.0)


def test_labels_round_trip():
    labels = RIG.to_labels()
    assert list(labels) == list(LABELS)
    assert StereoCamera.from_labels(labels, 640, 480) == RIG
    with_disparity = RIG.to_labels(disparity=12.5)
    assert list(with_disparity) == list(camera.PARAMETERS) + ["yaw", "roll"]
    assert with_disparity["disparity"] == 12.5
    # a vector in TARGETS (or PARAMETERS) order; yaw and roll are then 0
    vector = [with_disparity[name] for name in camera.PARAMETERS] + [1.0, 2.0, 3.0]
    from_vector = StereoCamera.from_labels(np.array(vector), 640, 480)
    assert from_vector == dataclasses.replace(RIG, yaw=0.0, roll=0.0)
    assert StereoCamera.from_labels(vector[:10], 640, 480) == from_vector
    with pytest.raises(ValueError, match="10 or 13"):
        StereoCamera.from_labels(vector[:9], 640, 480)


def test_field_of_view_and_the_camera_equations():
    square = StereoCamera(fx=320.0, fy=240.0, u0=319.5, v0=239.5, width=640, height=480,
                          baseline=0.1, pitch=0.0, tx=0.0, ty=-0.1, tz=0.0)
    assert square.fov == pytest.approx((math.pi / 2, math.pi / 2))     # fx = W / 2: 90 deg
    assert square.fov_deg == pytest.approx((90.0, 90.0))
    assert RIG.fov_deg[0] == float(np.degrees(camera.fov_from_focal(RIG.fx, 640)))
    assert RIG.to_world(300.0, 200.0, 40.0) == camera.image_to_world(
        RIG.fx, RIG.fy, RIG.u0, RIG.v0, RIG.baseline, 40.0, RIG.pitch, RIG.tx, RIG.ty, RIG.tz,
        300.0, 200.0)


def test_point_record():
    point = Point(1.0, -2.0, 0.5)
    assert point.as_dict() == {"X": 1.0, "Y": -2.0, "Z": 0.5}
    with pytest.raises(dataclasses.FrozenInstanceError):
        point.X = 0.0
