"""Keras building blocks of the camera graph, all registered for safe loading.

The camera equations of ``cpl_keras.camera`` run inside the model as one
``keras.layers.Lambda`` layer per operation (add, sub, mul, div, neg, sin,
cos), each named after the quantity it computes. The functions the Lambda
layers call are module-level and registered with
``keras.saving.register_keras_serializable``, so a saved ``.keras`` model
stores their names, not their bytecode, and loads with ``safe_mode=True``.
"""

from __future__ import annotations

import contextlib
import math

import keras
import numpy as np
from keras import ops

from cpl_keras import camera

PACKAGE = "cpl_keras"


# ---------------------------------------------------------------------------
# Registered op functions (what the Lambda layers call)
# ---------------------------------------------------------------------------
def _registered(name, op, arity, doc=None):
    """The module-level function ``name``: ``op(x)`` (``arity`` 1) or
    ``op(a, b)`` of ``inputs = [a, b]`` (``arity`` 2), registered under its
    name for safe loading."""
    if arity == 1:
        def function(x):
            return op(x)
    else:
        def function(inputs):
            a, b = inputs
            return op(a, b)
    function.__name__ = function.__qualname__ = name
    function.__doc__ = doc
    return keras.saving.register_keras_serializable(package=PACKAGE, name=name)(function)


add = _registered("add", ops.add, 2)
subtract = _registered("subtract", ops.subtract, 2)
multiply = _registered("multiply", ops.multiply, 2)
negative = _registered("negative", ops.negative, 1)
sin = _registered("sin", ops.sin, 1)
cos = _registered("cos", ops.cos, 1)
stop_gradient = _registered(
    "stop_gradient", ops.stop_gradient, 1,
    "``x`` forward, no gradient backward (the exact disentangling of Eq. 7).")


@keras.saving.register_keras_serializable(package=PACKAGE)
def safe_divide(inputs, epsilon=camera.EPSILON):
    """``a / b`` with ``b`` floored to magnitude ``epsilon``, sign kept."""
    a, b = inputs
    return ops.divide(a, camera.safe_divisor(b, epsilon, ops))


@keras.saving.register_keras_serializable(package=PACKAGE)
def bounded_pitch(x):
    """The pitch head's output: ``pitch = clip(z, -pi/2, pi/2)``, with the
    gradient of ``z`` (a straight-through clip).

    Pitch enters the camera graph only through sin and cos (Eqs. 5a, 5c), so
    with an unbounded head the projection terms have a minimum every 2 pi
    and a head can settle in a far one. Bounded to [-pi/2, pi/2], every
    pitch a camera rig can have, the loss has one minimum in pitch; the
    paper's "Parameterization" paragraph argues for such output
    parameterisations (the release's head was linear, ``as_released``).

    Why not a smooth squashing function: Adam moves every weight of the
    head's wide Dense layers by about the learning rate per step, so the
    pre-activation z swings by tens within the first steps. A (pi/2) tanh(z)
    head then saturates at -pi/2 with a vanishing gradient for good
    (measured: validation pitch MAE 1.27 rad after two epochs of
    MTL-Baseline and MTL-CPL-A, small_resnet, cvgl), and a (pi/2) sin(z) head
    turns chaotic (1.0 rad after two epochs). Clipped forward, identity
    backward, a z past the bound is pulled straight back: 0.09-0.11 rad
    after 300-480 steps of the same runs.
    """
    bound = math.pi / 2.0
    # forward: clip(x) exactly (x - x = 0); backward: d/dx = 1
    return ops.stop_gradient(ops.clip(x, -bound, bound)) + (x - ops.stop_gradient(x))


@keras.saving.register_keras_serializable(package=PACKAGE)
def positive_disparity(x, floor=camera.FLOORS["disparity"]):
    """The CPL disparity head's output: ``d = exp(z)``, z clipped to
    [log floor, log 1e5] with the gradient of z (straight-through); models
    trained with a ceiling use ``PositiveDisparity``.

    The camera graph divides by the disparity (Eq. 4a), so the projection
    terms have a pole at d = 0. A linear head is trapped on its negative
    side, where |X(d) - X| falls as d -> -infinity (xCam = fx b / d tends to
    0 from below): measured, MTL-CPL-A's validation disparity MAE stayed at
    404 px while MTL-Baseline's fell to 32 px. A head clipped at the floor
    (max(z, floor), straight-through) avoids the trap but not the pole's
    gradient, fx b / d^2, millions of times that of |d' - d| for the pairs
    near the floor: in the random protocol (true disparities 0.09-40 px) the
    disparity MAE then grew from 54 to 440 px in four epochs. In log space
    the gradient of xCam is -xCam, the depth, and that of |d' - d| is d:
    both on the scale of the scene. Every true disparity is positive (the
    right camera's centre is ahead of or beside the left one in every rig
    and real set here).
    """
    return _positive(x, floor)


@keras.saving.register_keras_serializable(package=PACKAGE)
def positive_focal(x, floor=camera.FLOORS["focal"]):
    """The CPL focal-length heads' output: ``f = clip(z, floor, 1e5)`` with
    the gradient of z (a straight-through clip, as the pitch head's).

    The camera graph divides by fy (Eq. 4c: zCam = xCam (v0 - v) / fy), so
    fy's disentangled term has a pole at fy = 0, as the disparity's has at
    d = 0. A linear head that starts below 0 is trapped there: the
    projection part of the gradient, xCam |v0 - v| / fy'^2 per pair, pushes
    it away from the pole (towards -infinity, where |zCam| -> 0) and
    outweighs the direct part (1 per pair) near it. Measured with
    ``bench/diagnose_heads.py`` on InceptionV3 MTL-CPL-A (cvgl, seed 0): all
    16 fy outputs of the first batch at -1.1 px, the projection part 370
    times the direct one, fy at -30 px after 10 steps and still below 0
    after 80; the full run ended with fy NMAE 1.22 (paper_results/faithful).

    Clipped at the focal floor, the head's output is never negative and
    its gradient below the floor points up (the projected point of a 1 px
    focal length is far too high or low). Above the floor the head is the
    release's linear one: an ``exp(z)`` head, like the disparity's, swung
    fy between 4 and 593 px within 80 InceptionV3 steps and left fx at its
    floor (its ReLU layers dead); a focal length's labels (15-160 px at 112
    px) are far from the floor, unlike the disparity's (0.09-40 px). fx gets
    the same head (every focal length is positive, and the graph divides by
    it in Eq. 4b), though its own term has no pole (xCam is linear in fx).
    The release's heads were linear (``as_released``).
    """
    z = ops.stop_gradient(ops.clip(x, floor, MAX_OUTPUT))
    return z + (x - ops.stop_gradient(x))


#: The positive heads' largest output without a ceiling of their own (px).
MAX_OUTPUT = 1e5


def _positive(x, floor, ceiling=MAX_OUTPUT):
    """``exp(z)``, z clipped to [log floor, log ceiling], straight-through."""
    low, high = math.log(floor), math.log(ceiling)
    z = ops.stop_gradient(ops.clip(x, low, high)) + (x - ops.stop_gradient(x))
    return ops.exp(z)


@keras.saving.register_keras_serializable(package=PACKAGE)
class PositiveDisparity:
    """The CPL disparity head's activation with a ceiling: ``d = exp(z)``, z
    clipped to [log floor, log ceiling], straight-through (as
    ``positive_disparity``, whose ceiling is ``MAX_OUTPUT``).

    Why a ceiling: in inference mode a few pairs' exp(z) explode. On the
    faithful-2000 InceptionV3 MTL-CPL-A run's 140 validation pairs
    (``analyses/diagnose_inference_mode.py``), the median absolute disparity
    error was 132-148 px under every BatchNorm statistics tried, but the MAE
    ran 364-7,210 px with the statistics of one 256-pair recompute or
    another, from one to five pairs predicted at up to 1e5 px (the training
    labels end at 2,085 px); clipped at twice the largest training label the
    MAE ran 296-534 px. Those few pairs moved the validation loss by 2.6x
    between epochs, so early stopping kept an early epoch. Training sets the
    ceiling from its labels (``planning.DISPARITY_CEILING_FACTOR``); the
    compact towers' predictions stay below it (the largest on cpu-8000's
    test pairs: 2,413 px against a ceiling of 4,171).
    """

    def __init__(self, floor=camera.FLOORS["disparity"], ceiling=MAX_OUTPUT):
        floor, ceiling = float(floor), float(ceiling)
        if not (0 < floor < ceiling and math.isfinite(ceiling)):
            raise ValueError(f"disparity ceiling must be a finite number above the floor "
                             f"({floor:g}), got {ceiling!r}")
        self.floor, self.ceiling = floor, ceiling

    def __call__(self, x):
        return _positive(x, self.floor, self.ceiling)

    def get_config(self):
        return {"floor": self.floor, "ceiling": self.ceiling}

    @classmethod
    def from_config(cls, config):
        return cls(**config)


@keras.saving.register_keras_serializable(package=PACKAGE)
class SoftplusDisparity(PositiveDisparity):
    """A disparity head that every MTL variant can share (``ModelOptions``'s
    ``disparity_head="softplus"``; not the paper's): ``d = floor +
    softplus(z)``, capped at ``ceiling`` straight-through.

    Positive, as the camera graph needs (Eq. 4a divides by d), but linear in
    z above its floor, so an MAE on d trains it as it trains MTL-Baseline's
    linear head; the exp head (``PositiveDisparity``) moves d by a factor per
    step instead, and with the compact towers MTL-Baseline given that head
    lost as much on the disparity as the CPL variants
    (paper_results/inception-2000-ablations/README.md). Its last bias starts
    at ``bias_for(start)``, so the head first puts out ``start`` (the
    training mean) instead of the floor. Its floor, ceiling and config are
    ``PositiveDisparity``'s.
    """

    def __call__(self, x):
        d = self.floor + ops.softplus(x)
        return ops.stop_gradient(ops.minimum(d, self.ceiling)) + (d - ops.stop_gradient(d))

    def bias_for(self, start):
        """The z at which the head puts out ``start`` px (None: 0, the
        floor plus log 2)."""
        if start is None:
            return None
        excess = max(float(start) - self.floor, 1e-3)
        # (the inverse of softplus, log(exp(x) - 1), without overflow)
        return excess + math.log(-math.expm1(-excess))


@keras.saving.register_keras_serializable(package=PACKAGE)
def take(x, index=0):
    """Column ``index`` of a (batch, n) tensor, kept as (batch, 1)."""
    return x[:, index : index + 1]


@keras.saving.register_keras_serializable(package=PACKAGE)
def stack_channels(inputs, channel=-1):
    """Deep-Homo's input: one channel of each image, stacked to (H, W, 2).

    ``channel=-1`` takes the luma (ITU-R BT.601 grey) of each RGB image;
    ``channel=k`` takes channel k as it is (the release took one channel of
    OpenCV's BGR images).
    """
    left, right = inputs
    if channel < 0:
        weights = ops.convert_to_tensor([0.299, 0.587, 0.114], dtype=left.dtype)
        left = ops.sum(left * weights, axis=-1, keepdims=True)
        right = ops.sum(right * weights, axis=-1, keepdims=True)
    else:
        left = left[..., channel : channel + 1]
        right = right[..., channel : channel + 1]
    return ops.concatenate([left, right], axis=-1)


# The op name of each registered function, as ``inspect`` shows it.
OP_NAMES = {
    add: "add", subtract: "sub", multiply: "mul", safe_divide: "div",
    negative: "neg", sin: "sin", cos: "cos",
}


class LambdaOps:
    """The camera op set on symbolic Keras tensors: every op is a named Lambda.

    ``floors`` are the divisor floors per quantity (``camera.FLOORS``).

    ``rename`` maps a quantity's name to the layer name to use instead (the
    released CPL-A gates X, Y, Z after the camera graph, so there the graph's
    last layers are called ``X_projected`` and so on).
    """

    def __init__(self, floors=None, rename=None):
        self.floors = camera.check_floors(camera.FLOORS if floors is None else floors)
        self.rename = dict(rename or {})

    def _layer(self, function, inputs, name, arguments=None):
        if name is None:
            raise ValueError("every camera-graph op needs the name of the quantity it computes")
        layer = keras.layers.Lambda(
            function, arguments=arguments, name=self.rename.get(name, name)
        )
        return layer(inputs)

    def add(self, a, b, name=None):
        return self._layer(add, [a, b], name)

    def sub(self, a, b, name=None):
        return self._layer(subtract, [a, b], name)

    def mul(self, a, b, name=None):
        return self._layer(multiply, [a, b], name)

    def div(self, a, b, name=None, floor=None):
        epsilon = camera.EPSILON if floor is None else self.floors[floor]
        return self._layer(safe_divide, [a, b], name, {"epsilon": epsilon})

    def neg(self, a, name=None):
        return self._layer(negative, a, name)

    def sin(self, a, name=None):
        return self._layer(sin, a, name)

    def cos(self, a, name=None):
        return self._layer(cos, a, name)


@contextlib.contextmanager
def placeholder_arithmetic_quiet():
    """NumPy's floating-point warnings off within the block: where a model
    is built or loaded. Keras's NumPy backend finds a Lambda layer's output
    shape by calling its function on ``np.empty`` arrays (whatever the
    memory held), and the overflows and 0/0 of those placeholder values,
    not of any image, reached the user as raw RuntimeWarnings. The model's
    own outputs are not computed here."""
    with np.errstate(all="ignore"):
        yield


def is_camera_layer(layer):
    """True for the Lambda layers of the camera graph."""
    return isinstance(layer, keras.layers.Lambda) and layer.function in OP_NAMES


@keras.saving.register_keras_serializable(package=PACKAGE)
def slight_leaky_relu(x):
    """A leaky ReLU of slope 0.01 below zero (``--head-activation leaky_relu_0.01``)."""
    return keras.activations.leaky_relu(x, negative_slope=0.01)


#: ``variants.HEAD_ACTIVATIONS`` -> the Dense layers' activation.
HIDDEN_ACTIVATIONS = {"relu": "relu", "leaky_relu": "leaky_relu",
                      "leaky_relu_0.01": slight_leaky_relu}


def regression_head(features, name, activation=None, hidden="relu", bias=None):
    """The release's per-quantity head: Dense(120, relu) -> Dense(84, relu) -> Dense(1).

    ``hidden``: the two hidden layers' activation (``variants.HEAD_ACTIVATIONS``;
    the leaky ones are ablations). With ReLU, on a pair where every unit
    of the first layer is at zero the head puts out its biases' value, the
    same for every such pair, and no gradient passes it from that pair
    (measured on InceptionV3 MTL-CPL-A's pitch head:
    paper_results/inception-2000-ablations/collapsed-heads.md).
    ``bias``: the last layer's starting bias (None: 0).
    """
    hidden = HIDDEN_ACTIVATIONS[hidden]
    x = keras.layers.Dense(120, activation=hidden, name=f"{name}_dense_120")(features)
    x = keras.layers.Dense(84, activation=hidden, name=f"{name}_dense_84")(x)
    start = "zeros" if bias is None else keras.initializers.Constant(float(bias))
    return keras.layers.Dense(1, activation=activation, bias_initializer=start, name=name)(x)
