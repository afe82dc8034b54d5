"""A stereo camera as one small immutable record: ``StereoCamera``.

The paper's camera (Eqs. 4a-5c) is a pinhole model shared by both cameras of
a rig: intrinsics ``fx, fy, u0, v0`` (pixels of its images, ``width`` x
``height``, pixel centres at integer coordinates), the ``baseline`` (m) and
the right camera's pose in the left camera frame (``pitch``; ``yaw``,
``roll`` where a real rig has them; ``tx, ty, tz`` in metres; project axes,
x forward, y left, z up; docs/data.md). What one does with a camera is a
method of the record (a crop or a resize gives a new record)::

    camera = StereoCamera(fx=451.0, fy=451.0, u0=319.5, v0=239.5, width=640, height=480,
                          baseline=0.075, pitch=0.0, tx=0.0, ty=-0.075, tz=0.0)
    camera.K                                    # 3x3 numpy
    small = camera.crop(10, 20, 400, 300).resize(112, 112)
    R, T = camera.to_opencv_pose()              # X_right = R X_left + T, OpenCV axes
    camera.to_world(u, v, disparity)            # Eqs. 4a-5c: X, Y, Z
    camera.to_labels(disparity=12.5)            # the datasets' label names
    camera.fov_deg                              # (horizontal, vertical)

The arithmetic is written once elsewhere: ``cpl_keras.camera``'s equations
and ``fov_from_focal``; ``cpl_keras.frames``'s ``crop_resize_coordinate``
(a resize of pixel coordinates) and ``opencv_pose_to_rig`` /
``rig_to_opencv_pose`` (OpenCV's axes and extrinsics). The disparity belongs to a pair's scene,
not to the camera: ``to_labels`` takes it, ``from_labels`` leaves it out.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import numpy as np

from cpl_keras.camera import PARAMETERS, TARGETS, fov_from_focal, image_to_world
from cpl_keras.frames import (
    crop_resize_coordinate, euler_from_rotation, opencv_pose_to_rig, rig_to_opencv_pose,
    rotation_matrix,
)

#: The intrinsics' names.
INTRINSICS = ("fx", "fy", "u0", "v0")
#: The camera's fields among the label names, in PARAMETERS order (all but
#: the disparity), then the rotations the paper's model leaves out.
LABELS = tuple(name for name in PARAMETERS if name != "disparity") + ("yaw", "roll")


@dataclasses.dataclass(frozen=True, kw_only=True)
class StereoCamera:
    """A stereo rig's shared pinhole camera and the right camera's pose."""

    fx: float        #: focal length along u (px)
    fy: float        #: focal length along v (px)
    u0: float        #: principal point u (px; pixel centres at integers)
    v0: float        #: principal point v (px)
    width: int       #: the images' width (px)
    height: int      #: the images' height (px)
    baseline: float  #: distance between the camera centres (m)
    pitch: float     #: the right camera's pitch in the left camera frame (rad; Eq. 5)
    tx: float        #: the right camera's centre in the left camera frame, forward (m)
    ty: float        #: to the left (m)
    tz: float        #: up (m)
    yaw: float = 0.0   #: the right camera's yaw (rad; a real rig's; the paper's model has none)
    roll: float = 0.0  #: its roll (rad)

    def __post_init__(self):
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            cast = int if field.name in ("width", "height") else float
            object.__setattr__(self, field.name, cast(value))
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"a camera's images need a positive size, got "
                             f"{self.width}x{self.height}")

    @property
    def K(self):
        """The camera matrix ``[[fx, 0, u0], [0, fy, v0], [0, 0, 1]]``."""
        return np.array([[self.fx, 0.0, self.u0], [0.0, self.fy, self.v0], [0.0, 0.0, 1.0]])

    def crop(self, x0, y0, width, height):
        """The camera of the window ``(x0, y0, width, height)`` of its
        images: the principal point moves by the window's corner."""
        return dataclasses.replace(self, u0=self.u0 - x0, v0=self.v0 - y0, width=width,
                                   height=height)

    def uncrop(self, x0, y0, width, height):
        """The inverse of ``crop``: the camera of the ``width`` x ``height``
        images this one is the window at ``(x0, y0)`` of."""
        return dataclasses.replace(self, u0=self.u0 + x0, v0=self.v0 + y0, width=width,
                                   height=height)

    def resize_scales(self, width, height):
        """``(sx, sy)`` of a resize of its images to ``width`` x ``height``
        (a disparity, a difference of u coordinates, scales by ``sx``)."""
        return width / float(self.width), height / float(self.height)

    def resize(self, width, height):
        """The camera of its images resized to ``width`` x ``height``: focal
        lengths and principal point scale per axis, pixel centres staying at
        integers (``frames.crop_resize_coordinate``)."""
        sx, sy = self.resize_scales(width, height)
        return dataclasses.replace(
            self, fx=self.fx * sx, fy=self.fy * sy,
            u0=crop_resize_coordinate(self.u0, 0, sx), v0=crop_resize_coordinate(self.v0, 0, sy),
            width=width, height=height)

    def to_world(self, u, v, disparity):
        """Eqs. 4a-5c with this camera: the point ``(X, Y, Z)`` (left camera
        frame, metres) of pixel ``(u, v)`` at ``disparity`` (the paper's model:
        pitch, no yaw or roll)."""
        return image_to_world(self.fx, self.fy, self.u0, self.v0, self.baseline, disparity,
                              self.pitch, self.tx, self.ty, self.tz, u, v)

    def to_opencv_pose(self):
        """OpenCV's stereo extrinsics ``(R, T)``: ``X_right = R X_left + T``
        (OpenCV axes, metres)."""
        return rig_to_opencv_pose(rotation_matrix(self.pitch, self.yaw, self.roll),
                                  [self.tx, self.ty, self.tz])

    @classmethod
    def from_opencv_pose(cls, R, T, K, width, height, baseline=None):
        """The camera of OpenCV's intrinsics ``K`` and stereo extrinsics
        ``(R, T)`` (``X_right = R X_left + T``): pitch, yaw and roll of the
        right camera's rotation in the left camera frame, ``(tx, ty, tz)`` its
        centre there; the baseline ``|t|`` unless given."""
        R_lr, t = opencv_pose_to_rig(R, T)
        pitch, yaw, roll = euler_from_rotation(R_lr)
        K = np.asarray(K, dtype=np.float64)
        return cls(fx=K[0, 0], fy=K[1, 1], u0=K[0, 2], v0=K[1, 2], width=width, height=height,
                   baseline=np.linalg.norm(t) if baseline is None else baseline,
                   pitch=pitch, yaw=yaw, roll=roll, tx=t[0], ty=t[1], tz=t[2])

    def to_labels(self, disparity=None):
        """The label dict the datasets use: PARAMETERS' names in order (the
        disparity, a scene's, only when given), then ``yaw`` and ``roll``."""
        labels = {name: getattr(self, name) for name in LABELS}
        if disparity is None:
            return labels
        return {name: float(disparity) if name == "disparity" else labels[name]
                for name in PARAMETERS + ("yaw", "roll")}

    @classmethod
    def from_labels(cls, labels, width, height):
        """The camera of a label dict (PARAMETERS' names; ``yaw``, ``roll``
        when present, else 0) or vector (PARAMETERS' or TARGETS' order) of
        images ``width`` x ``height``; the disparity is left out."""
        if not isinstance(labels, Mapping):
            values = np.asarray(labels, dtype=np.float64).reshape(-1)
            if len(values) not in (len(PARAMETERS), len(TARGETS)):
                raise ValueError(f"a label vector holds {len(PARAMETERS)} or {len(TARGETS)} "
                                 f"values, got {len(values)}")
            labels = dict(zip(TARGETS, values))
        return cls(width=width, height=height,
                   **{name: labels.get(name, 0.0) if name in ("yaw", "roll") else labels[name]
                      for name in LABELS})

    @property
    def fov(self):
        """``(horizontal, vertical)`` field of view (radians) from fx, fy
        and the image size."""
        return (float(fov_from_focal(self.fx, self.width)),
                float(fov_from_focal(self.fy, self.height)))

    @property
    def fov_deg(self):
        """``fov`` in degrees."""
        return tuple(float(np.degrees(angle)) for angle in self.fov)


@dataclasses.dataclass(frozen=True)
class Point:
    """A point in the left camera frame (metres; x forward, y left, z up)."""

    X: float
    Y: float
    Z: float

    def __post_init__(self):
        for name in ("X", "Y", "Z"):
            object.__setattr__(self, name, float(getattr(self, name)))

    def as_dict(self):
        return {"X": self.X, "Y": self.Y, "Z": self.Z}
