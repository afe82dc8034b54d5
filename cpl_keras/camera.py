"""The pinhole stereo camera model of the paper, written once.

Coordinates follow the paper: x forward, y left, z up. A pixel (u, v) has u to
the right and v down, the principal point is (u0, v0). Angles are radians.

Every equation below is written against a small "op set" (add, sub, mul, div,
neg, sin, cos), so the same code runs on

* numpy arrays (``NUMPY``): the data generator and the metrics,
* backend tensors through ``keras.ops`` (``TENSOR``): losses,
* symbolic Keras tensors, one named ``Lambda`` layer per op
  (``cpl_keras.layers.LambdaOps``): the camera graph inside the model.

Each op takes a ``name``; only the Lambda op set uses it, to name the layer
after the quantity it computes, so ``model.summary()`` reads like the
equations.

Forward model (image -> camera -> world), paper Eqs. 4a-5c::

    xCam = fx * b / d                                   (4a)
    yCam = -(xCam / fx) * (u - u0)                      (4b)
    zCam =  (xCam / fy) * (v0 - v)                      (4c)
    X =  xCam * cos(pitch) + zCam * sin(pitch) + tx     (5a)
    Y =  yCam + ty                                      (5b)
    Z = -xCam * sin(pitch) + zCam * cos(pitch) + tz     (5c)

With Eq. 5 the optical axis (1, 0, 0) of a camera with pitch > 0 points to
(cos p, 0, -sin p): a positive pitch tilts the camera down.

Division is "safe": every divisor is floored away from zero, keeping its sign
(``safe_divisor``), so a predicted disparity or focal length at or near 0
gives large but finite values, never inf or NaN. The floor depends on the
quantity divided by (``FLOORS``): the graph divides by the disparity d
(Eq. 4a) and by the focal lengths fx, fy (Eqs. 4b-4c), all in pixels; the
inverse model divides by the depth xCam, in metres (``EPSILON``).
"""

from __future__ import annotations

import math

import numpy as np

#: Smallest magnitude of a divisor with no floor of its own (the inverse
#: model's depth xCam, metres).
EPSILON = 1e-3

#: Divisor floors of the camera graph, per quantity, in pixels, chosen from
#: the data's ranges so that no label is ever floored:
#:
#: * disparity: the smallest true disparity the rendered protocols can label
#:   is fx * b / depth = 32 px * 0.05 m / 200 m = 0.008 px (random protocol
#:   at 112 px: 120 deg fov, 5 cm baseline, label points within 200 m); the
#:   floor lies below it. Measured on 400 pairs each: 0.092 px (random),
#:   2.5 px (cvgl).
#: * focal: the widest rig (cvgl, 150 deg) has fx = 15 px at 112 px and
#:   2.1 px at the smallest image side the generator makes (16 px).
#:
#: The former common floor of 1e-3 (pixels and metres alike) had gradients
#: of fx * b / d^2 = 1e6 * fx * b just outside it; at the disparity floor it
#: is 4e4 * fx * b, and the floors' units are stated.
FLOORS = {"disparity": 5e-3, "focal": 1.0}

#: The release divided plainly. ``as_released`` keeps that, with a floor
#: small enough to change nothing a finite prediction can reach but still
#: keeping float32 values and gradients finite (never inf or NaN).
RELEASED_FLOORS = {"disparity": 1e-6, "focal": 1e-6}

#: The 10 camera parameters, in the release's order.
PARAMETERS = (
    "fx", "fy", "u0", "v0", "baseline", "disparity", "tx", "ty", "tz", "pitch",
)
#: The 13 regression targets (the model's outputs), in the release's order.
TARGETS = PARAMETERS + ("X", "Y", "Z")

#: Units of every label the project stores.
UNITS = {
    "fx": "px", "fy": "px", "u0": "px", "v0": "px", "u": "px", "v": "px",
    "disparity": "px", "disparity_released": "px",
    "baseline": "m", "tx": "m", "ty": "m", "tz": "m",
    "X": "m", "Y": "m", "Z": "m",
    "pitch": "rad", "yaw": "rad", "roll": "rad",
}


# ---------------------------------------------------------------------------
# Op sets
# ---------------------------------------------------------------------------
class NumpyOps:
    """The op set on numpy arrays (and Python floats).

    ``floors`` maps a quantity the camera graph divides by (``"disparity"``,
    ``"focal"``) to its divisor floor; ``div(..., floor=key)`` uses it, and a
    division without a key uses ``epsilon``.
    """

    def __init__(self, epsilon=EPSILON, floors=None):
        self.epsilon = float(epsilon)
        self.floors = check_floors(FLOORS if floors is None else floors)

    def floor(self, key=None):
        """The divisor floor of quantity ``key`` (``epsilon`` for None)."""
        return self.epsilon if key is None else self.floors[key]

    def add(self, a, b, name=None):
        return np.add(a, b)

    def sub(self, a, b, name=None):
        return np.subtract(a, b)

    def mul(self, a, b, name=None):
        return np.multiply(a, b)

    def div(self, a, b, name=None, floor=None):
        return np.divide(a, safe_divisor(b, self.floor(floor), np))

    def neg(self, a, name=None):
        return np.negative(a)

    def sin(self, a, name=None):
        return np.sin(a)

    def cos(self, a, name=None):
        return np.cos(a)


class TensorOps(NumpyOps):
    """The op set on backend tensors, through ``keras.ops`` (imported lazily,
    so the numpy side never loads a deep-learning backend)."""

    def __init__(self, epsilon=EPSILON, floors=None):
        super().__init__(epsilon, floors)
        from keras import ops

        self._ops = ops

    def add(self, a, b, name=None):
        return self._ops.add(a, b)

    def sub(self, a, b, name=None):
        return self._ops.subtract(a, b)

    def mul(self, a, b, name=None):
        return self._ops.multiply(a, b)

    def div(self, a, b, name=None, floor=None):
        return self._ops.divide(a, safe_divisor(b, self.floor(floor), self._ops))

    def neg(self, a, name=None):
        return self._ops.negative(a)

    def sin(self, a, name=None):
        return self._ops.sin(a)

    def cos(self, a, name=None):
        return self._ops.cos(a)


def safe_divisor(b, epsilon=EPSILON, xp=np):
    """``b`` floored to magnitude ``epsilon``, keeping its sign (0 -> +epsilon).

    ``xp`` is ``numpy`` or ``keras.ops``. The floor is applied before the
    division, so neither the value nor its gradient can be inf or NaN.
    """
    small = xp.less(xp.abs(b), epsilon)
    floor = xp.where(xp.less(b, 0), -epsilon, epsilon)
    return xp.where(small, floor, b)


def check_floors(floors):
    """``floors`` as a dict of positive floats with the keys of ``FLOORS``."""
    if not isinstance(floors, dict) or set(floors) != set(FLOORS):
        raise ValueError(f"floors must be a dict with the keys {sorted(FLOORS)}, got {floors!r}")
    out = {}
    for key, value in floors.items():
        if isinstance(value, bool) or not isinstance(value, (int, float, np.floating)) or not (
            math.isfinite(float(value)) and float(value) > 0
        ):
            raise ValueError(f"the {key} floor must be a positive number, got {value!r}")
        out[key] = float(value)
    return out


NUMPY = NumpyOps()


def tensor_ops(epsilon=EPSILON, floors=None):
    """A ``TensorOps`` instance (keras.ops on the active backend)."""
    return TensorOps(epsilon, floors)


# ---------------------------------------------------------------------------
# Intrinsics
# ---------------------------------------------------------------------------
def focal_from_fov(fov, size):
    """Focal length in pixels from a field of view (radians) across ``size`` px:
    ``f = size / (2 tan(fov / 2))`` (CARLA's and the release's formula)."""
    return np.asarray(size, dtype=np.float64) / (2.0 * np.tan(np.asarray(fov) / 2.0))


def fov_from_focal(focal, size):
    """Field of view (radians) across ``size`` pixels for a focal length in px."""
    # arctan2 keeps a focal length of 0 finite (fov = pi) and its sign
    return 2.0 * np.arctan2(np.asarray(size, dtype=np.float64), 2.0 * np.asarray(focal, dtype=np.float64))


def square_pixel_fy(fx, source_width, source_height, input_width, input_height):
    """fy for a camera with square pixels (fx = fy on its own images), in the
    pixels of the model's input: the source image, ``source_width`` x
    ``source_height``, resized to ``input_width`` x ``input_height`` scales
    the two focal lengths by ``input_width / source_width`` and
    ``input_height / source_height``, so ``fy = fx * (input_height /
    source_height) / (input_width / source_width)``. Real cameras have square
    pixels; a squashed image's fy is then known from fx and the sizes."""
    scale_x = np.asarray(input_width, np.float64) / np.asarray(source_width, np.float64)
    scale_y = np.asarray(input_height, np.float64) / np.asarray(source_height, np.float64)
    return np.asarray(fx, np.float64) * scale_y / scale_x


# ---------------------------------------------------------------------------
# Forward model: image -> camera -> world (Eqs. 4a-5c)
# ---------------------------------------------------------------------------
def depth_from_disparity(fx, baseline, disparity, ops=NUMPY):
    """Eq. 4a: ``xCam = fx * b / d``, the depth of the point along x."""
    fx_b = ops.mul(fx, baseline, name="fx_times_baseline")
    return ops.div(fx_b, disparity, name="xCam", floor="disparity")


def camera_point(xCam, fx, fy, u0, v0, u, v, ops=NUMPY):
    """Eqs. 4b-4c: the camera-frame y and z of pixel (u, v) at depth xCam.

    ``yCam = -(xCam / fx) * (u - u0)`` and ``zCam = (xCam / fy) * (v0 - v)``.
    With ``xCam = 1`` this is the viewing ray of the pixel (paper Eq. 6).
    """
    xCam_over_fx = ops.div(xCam, fx, name="xCam_over_fx", floor="focal")
    u_minus_u0 = ops.sub(u, u0, name="u_minus_u0")
    yCam = ops.mul(
        ops.neg(xCam_over_fx, name="neg_xCam_over_fx"), u_minus_u0, name="yCam"
    )
    xCam_over_fy = ops.div(xCam, fy, name="xCam_over_fy", floor="focal")
    v0_minus_v = ops.sub(v0, v, name="v0_minus_v")
    zCam = ops.mul(xCam_over_fy, v0_minus_v, name="zCam")
    return yCam, zCam


def image_to_camera(fx, fy, u0, v0, baseline, disparity, u, v, ops=NUMPY):
    """Eqs. 4a-4c: pixel (u, v) with disparity d -> (xCam, yCam, zCam)."""
    xCam = depth_from_disparity(fx, baseline, disparity, ops)
    yCam, zCam = camera_point(xCam, fx, fy, u0, v0, u, v, ops)
    return xCam, yCam, zCam


def camera_to_world(xCam, yCam, zCam, pitch, tx, ty, tz, ops=NUMPY):
    """Eqs. 5a-5c: rotate by ``pitch`` about y, then translate by (tx, ty, tz)."""
    cos_p = ops.cos(pitch, name="cos_pitch")
    sin_p = ops.sin(pitch, name="sin_pitch")
    X = ops.add(
        ops.add(
            ops.mul(xCam, cos_p, name="xCam_cos_pitch"),
            ops.mul(zCam, sin_p, name="zCam_sin_pitch"),
            name="X_rotated",
        ),
        tx,
        name="X",
    )
    Y = ops.add(yCam, ty, name="Y")
    Z = ops.add(
        ops.add(
            ops.neg(ops.mul(xCam, sin_p, name="xCam_sin_pitch"), name="neg_xCam_sin_pitch"),
            ops.mul(zCam, cos_p, name="zCam_cos_pitch"),
            name="Z_rotated",
        ),
        tz,
        name="Z",
    )
    return X, Y, Z


def image_to_world(fx, fy, u0, v0, baseline, disparity, pitch, tx, ty, tz, u, v, ops=NUMPY):
    """Eqs. 4a-5c composed: pixel (u, v) and the 10 parameters -> (X, Y, Z)."""
    xCam, yCam, zCam = image_to_camera(fx, fy, u0, v0, baseline, disparity, u, v, ops)
    return camera_to_world(xCam, yCam, zCam, pitch, tx, ty, tz, ops)


# ---------------------------------------------------------------------------
# Inverse model: world -> camera -> image
# ---------------------------------------------------------------------------
def world_to_camera(X, Y, Z, pitch, tx, ty, tz, ops=NUMPY):
    """Inverse of Eqs. 5a-5c (the rotation's transpose)."""
    dX = ops.sub(X, tx)
    dY = ops.sub(Y, ty)
    dZ = ops.sub(Z, tz)
    cos_p, sin_p = ops.cos(pitch), ops.sin(pitch)
    xCam = ops.sub(ops.mul(dX, cos_p), ops.mul(dZ, sin_p))
    zCam = ops.add(ops.mul(dX, sin_p), ops.mul(dZ, cos_p))
    return xCam, dY, zCam


def camera_to_pixel(xCam, yCam, zCam, fx, fy, u0, v0, ops=NUMPY):
    """Inverse of Eqs. 4b-4c: the pixel (u, v) where a camera point projects."""
    u = ops.sub(u0, ops.mul(fx, ops.div(yCam, xCam)))
    v = ops.sub(v0, ops.mul(fy, ops.div(zCam, xCam)))
    return u, v


def disparity_from_depth(fx, baseline, xCam, ops=NUMPY):
    """Inverse of Eq. 4a: ``d = fx * b / xCam``."""
    return ops.div(ops.mul(fx, baseline), xCam)


def camera_to_image(xCam, yCam, zCam, fx, fy, u0, v0, baseline, ops=NUMPY):
    """Inverse of Eqs. 4a-4c: camera point -> pixel (u, v) and disparity d."""
    u, v = camera_to_pixel(xCam, yCam, zCam, fx, fy, u0, v0, ops)
    return u, v, disparity_from_depth(fx, baseline, xCam, ops)


def world_to_image(X, Y, Z, fx, fy, u0, v0, baseline, pitch, tx, ty, tz, ops=NUMPY):
    """Inverse of Eqs. 4a-5c: world point -> pixel (u, v) and disparity d."""
    xCam, yCam, zCam = world_to_camera(X, Y, Z, pitch, tx, ty, tz, ops)
    return camera_to_image(xCam, yCam, zCam, fx, fy, u0, v0, baseline, ops)


#: The paper's equation behind each named quantity of the camera graph.
EQUATIONS = {
    "fx_times_baseline": ("4a", "fx * b"),
    "xCam": ("4a", "xCam = fx * b / d"),
    "xCam_over_fx": ("4b", "xCam / fx"),
    "neg_xCam_over_fx": ("4b", "-(xCam / fx)"),
    "u_minus_u0": ("4b", "u - u0"),
    "yCam": ("4b", "yCam = -(xCam / fx) * (u - u0)"),
    "xCam_over_fy": ("4c", "xCam / fy"),
    "v0_minus_v": ("4c", "v0 - v"),
    "zCam": ("4c", "zCam = (xCam / fy) * (v0 - v)"),
    "cos_pitch": ("5a, 5c", "cos(pitch)"),
    "sin_pitch": ("5a, 5c", "sin(pitch)"),
    "xCam_cos_pitch": ("5a", "xCam * cos(pitch)"),
    "zCam_sin_pitch": ("5a", "zCam * sin(pitch)"),
    "X_rotated": ("5a", "xCam * cos(pitch) + zCam * sin(pitch)"),
    "X": ("5a", "X = xCam * cos(pitch) + zCam * sin(pitch) + tx"),
    "Y": ("5b", "Y = yCam + ty"),
    "xCam_sin_pitch": ("5c", "xCam * sin(pitch)"),
    "neg_xCam_sin_pitch": ("5c", "-xCam * sin(pitch)"),
    "zCam_cos_pitch": ("5c", "zCam * cos(pitch)"),
    "Z_rotated": ("5c", "-xCam * sin(pitch) + zCam * cos(pitch)"),
    "Z": ("5c", "Z = -xCam * sin(pitch) + zCam * cos(pitch) + tz"),
}
