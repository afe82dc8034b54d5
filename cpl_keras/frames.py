"""Coordinate frames around the camera model (numpy): 3D rotations and
their Euler angles, OpenCV's camera axes against the project's, and pixel
coordinates through a crop and resize.

The project's axes are the paper's (``cpl_keras.camera``): x forward, y
left, z up; a pixel (u, v) has u to the right and v down. A rig's extrinsics
are the right camera's pose in the left camera's frame, ``P_left = R_lr
P_right + t``; with yaw = roll = 0, ``R_lr`` is Eq. 5's rotation.
"""

from __future__ import annotations

import math

import numpy as np


# ---------------------------------------------------------------------------
# Full 3D rotation (numpy), for renderers of rigs with yaw and roll
# ---------------------------------------------------------------------------
def rotation_matrix(pitch=0.0, yaw=0.0, roll=0.0):
    """Camera-to-world rotation ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``.

    ``Ry(pitch)`` is the rotation of Eq. 5 (positive pitch tilts the optical
    axis down); yaw turns left about z (up), roll turns about x (forward). With
    yaw = roll = 0, ``R @ (xCam, yCam, zCam) + t`` equals ``camera_to_world``.
    """
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    cr, sr = math.cos(roll), math.sin(roll)
    Ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    Rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    Rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    return Rz @ Ry @ Rx


def euler_from_rotation(R):
    """(pitch, yaw, roll) of a rotation ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``,
    the inverse of ``rotation_matrix`` (pitch in [-pi/2, pi/2])."""
    R = np.asarray(R, dtype=np.float64)
    pitch = math.asin(max(-1.0, min(1.0, -R[2, 0])))
    yaw = math.atan2(R[1, 0], R[0, 0])
    roll = math.atan2(R[2, 1], R[2, 2])
    return pitch, yaw, roll


# ---------------------------------------------------------------------------
# OpenCV's camera frame, and pixel coordinates after a crop + resize (numpy):
# the arithmetic of ``cpl_keras.stereo_camera.StereoCamera``, whose record the
# real-data builders, calibrate and its exports, and the Geometric baseline use
# ---------------------------------------------------------------------------
#: OpenCV camera axes (x right, y down, z forward) -> project axes (x forward,
#: y left, z up): ``p_project = CV_TO_PROJECT @ p_opencv``.
CV_TO_PROJECT = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def opencv_pose_to_rig(R, T):
    """The right camera's pose in the left camera frame, project axes, from
    OpenCV's stereo extrinsics (``X_right = R X_left + T``, OpenCV axes).

    Returns ``(R_lr, t)`` with ``P_left = R_lr P_right + t`` (docs/data.md):
    ``R_lr = C R^T C^T`` and ``t = C (-R^T T)``, ``C = CV_TO_PROJECT``; ``t`` is
    the right camera centre in the left camera frame. Pitch, yaw and roll are
    ``euler_from_rotation(R_lr)``.
    """
    R = np.asarray(R, dtype=np.float64).reshape(3, 3)
    T = np.asarray(T, dtype=np.float64).reshape(3)
    return CV_TO_PROJECT @ R.T @ CV_TO_PROJECT.T, CV_TO_PROJECT @ (-R.T @ T)


def rig_to_opencv_pose(R_lr, t):
    """The inverse of ``opencv_pose_to_rig``: OpenCV's stereo extrinsics
    ``(R, T)`` (``X_right = R X_left + T``, OpenCV axes) from the right
    camera's pose in the left camera frame (project axes)."""
    R_lr = np.asarray(R_lr, dtype=np.float64).reshape(3, 3)
    t = np.asarray(t, dtype=np.float64).reshape(3)
    C = CV_TO_PROJECT
    R = C.T @ R_lr.T @ C
    return R, -R @ (C.T @ t)


def crop_resize_coordinate(x, start, scale):
    """A pixel coordinate after cropping at ``start`` and resizing by ``scale``.

    Pixel centres sit at integer coordinates, as in OpenCV and scikit-image,
    so a resize by ``scale`` maps ``x -> (x + 0.5) * scale - 0.5`` (the mapping
    ``cv2.resize`` uses). Applies to u, u0 (with the crop's x start and the
    horizontal scale) and to v, v0 (y start, vertical scale); a camera's
    crop and resize are ``StereoCamera.crop`` and ``StereoCamera.resize``.
    """
    return (np.asarray(x, dtype=np.float64) - start + 0.5) * scale - 0.5
