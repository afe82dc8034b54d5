"""The model factory: every network of the paper's Table 1 from one function.

``build_model(variant)`` returns a ``CalibrationModel`` with inputs
``left_image`` and ``right_image`` (float RGB pixel values 0..255) and the 13
outputs fx, fy, u0, v0, baseline, disparity, tx, ty, tz, pitch, X, Y, Z, in
the release's order.

Variants:

* ``baseline`` (MTL-Baseline): two towers, 13 regression heads; X, Y, Z are
  regressed directly.
* ``cpl-u`` (MTL-CPL-U): 12 heads (the 10 parameters and a pixel u, v); X, Y,
  Z come out of the camera equations as Lambda layers (Eqs. 4a-5c).
* ``cpl-a`` (MTL-CPL-A): CPL-U with adaptive weights.
* ``deep-homo``: the modified Deep-Homo network.

``as_released`` switches every place where the paper's text and the released
code differ:

============================  ===========================  ============================
                              as the paper writes it       as released
============================  ===========================  ============================
input scaling                 InceptionV3's, to [-1, 1]    raw 0..255 pixels
CPL-U loss                    disentangled, Eq. 7          MAE of the 13 outputs
CPL-A loss                    Eq. 9, learned alpha_i       MAE of the 13 outputs
CPL-A adaptive weights        per-term alpha_i (loss)      per-sample sigmoid gates
                                                           multiplying X, Y, Z
Deep-Homo input               grey level of each image     one channel of each image
pitch head                    clipped to +-pi/2            linear (a minimum every 2 pi)
CPL disparity head            exp(z), positive, below      linear
                              twice the largest training
                              label
CPL fx, fy heads              clipped at 1 px              linear (fy trapped below 0)
X, Y, Z terms of Eq. 7        reach only the pixel heads   (MAE: every head)
divisor floors                ``camera.FLOORS``            ``camera.RELEASED_FLOORS``
============================  ===========================  ============================

The bounded pitch head and the exact disentangling are this project's
readings of the paper (its "Parameterization" paragraph and Eq. 7); each has
its own argument, so either can be compared with the other form.

(The dataset side of the switch, the release's disparity and pitch labels, is
in ``cpl_keras.datasets``.)
"""

from __future__ import annotations

import contextlib
import math
import numbers
import random

import keras
import numpy as np

from cpl_keras import camera
from cpl_keras.layers import (
    MAX_OUTPUT, LambdaOps, PositiveDisparity, bounded_pitch, multiply, positive_focal,
    regression_head, stop_gradient,
)
from cpl_keras.models import backbones, deep_homo, variants
from cpl_keras.models.calibration_model import CalibrationModel
from cpl_keras.models.variants import (  # noqa: F401
    DISENTANGLE, HEAD_ACTIVATIONS, POINT_ERRORS, VARIANTS,
)

PIXEL_HEADS = ("u", "v")


def build_model(variant, *, backbone="inception_v3", image_size=112, as_released=False,
                floors=None, bounded_pitch_head=None, positive_focal_head=None,
                disentangle="exact", alpha_rate=None, disparity_ceiling=None,
                point_errors="metres", exp_disparity_head=False, head_activation="relu",
                seed=None, name=None):
    """Build one of the paper's networks.

    Args:
        variant: one of ``VARIANTS``.
        backbone: ``"inception_v3"`` (the paper's), ``"small"`` (quick runs)
            or ``"small_resnet"`` (CPU-scale experiments); neither of the last
            two is the paper's (``backbones``). Deep-Homo has its own
            convolutional stack.
        image_size: side of the square input images, or ``(height, width)``
            or ``(height, width, 3)``. At least 75 for InceptionV3.
        as_released: reproduce the released code instead of the paper's text
            (see the module docstring).
        floors: the camera graph's divisor floors per quantity (default
            ``camera.FLOORS``; as released ``camera.RELEASED_FLOORS``).
        bounded_pitch_head: pitch = clip(z, -pi/2, pi/2), straight-through, for the MTL variants
            (default: True, as released False).
        positive_focal_head: fx, fy = clip(z, the focal floor, 1e5) with z's
            gradient (straight-through), for the CPL variants (default: True,
            as released False: linear heads; see ``layers.positive_focal``).
        disentangle: ``"exact"`` (the X, Y, Z terms of Eq. 7 reach only the
            pixel heads u, v) or ``"partial"`` (they reach every head the
            camera graph reads). CPL variants as the paper writes them only.
        alpha_rate: how fast MTL-CPL-A's adaptive weights move (default
            ``variants.ALPHA_RATE``; 1 is Eq. 9 trained like every other weight;
            0 freezes them at their first-batch balance; see ``CalibrationModel``).
        disparity_ceiling: the largest disparity (px) the CPL variants' exp
            head can output (``layers.PositiveDisparity``; default
            ``layers.MAX_OUTPUT``). Training sets it from its labels.
        point_errors: how the CPL losses measure Eq. 7's point errors:
            ``"metres"`` (the paper's) or ``"relative"`` (divided by each
            pair's ground-truth depth; an ablation, ``losses.POINT_ERRORS``).
        exp_disparity_head: MTL-Baseline only: its disparity head is the CPL
            variants' ``d = exp(z)`` with their floor and ``disparity_ceiling``
            instead of linear (an ablation; the CPL variants have it as the
            paper writes them).
        head_activation: the regression heads' hidden activation,
            ``"relu"`` (the release's) or a leaky ReLU (ablations;
            ``variants.HEAD_ACTIVATIONS``). Not Deep-Homo, whose head is its own.
        seed: seeds Keras's initialisers when given. Python's and NumPy's
            global random generators are left as they were.
        name: the model's name (default: the variant).
    """
    spec = variants.get(variant)
    _check_choice("backbone", backbone, backbones.BACKBONES)
    floors = camera.check_floors(
        (camera.RELEASED_FLOORS if as_released else camera.FLOORS) if floors is None else floors
    )
    if bounded_pitch_head is None:
        bounded_pitch_head = not as_released
    if positive_focal_head is None:
        positive_focal_head = not as_released
    alpha_rate = _alpha_rate(alpha_rate)
    _check_choice("disentangle", disentangle, DISENTANGLE)
    _check_choice("point_errors", point_errors, POINT_ERRORS)
    if exp_disparity_head and spec.builder != "direct":
        raise ValueError(f"exp_disparity_head is MTL-Baseline's ablation; {variant} has its "
                         f"own disparity head")
    _check_choice("head_activation", head_activation, HEAD_ACTIVATIONS)
    if head_activation != "relu" and spec.builder == "deep_homo":
        raise ValueError(f"head_activation applies to the regression heads; {variant} has "
                         f"its own")
    disparity = PositiveDisparity(ceiling=MAX_OUTPUT if disparity_ceiling is None
                                  else disparity_ceiling)
    minimum = spec.min_image_size or backbones.MIN_IMAGE_SIZE[backbone]
    height, width = _image_shape(image_size, minimum, backbone)
    with _seeded(seed):
        return _build(spec, backbone, height, width, bool(as_released), floors,
                      bool(bounded_pitch_head), bool(positive_focal_head), disentangle,
                      alpha_rate, disparity, point_errors, bool(exp_disparity_head),
                      head_activation, name)


@contextlib.contextmanager
def _seeded(seed):
    """Seed Keras's initialisers, leaving Python's and NumPy's global random
    generators as they were (``keras.utils.set_random_seed`` reseeds both)."""
    if seed is None:
        yield
        return
    python_state, numpy_state = random.getstate(), np.random.get_state()
    try:
        keras.utils.set_random_seed(int(seed))
        yield
    finally:
        random.setstate(python_state)
        np.random.set_state(numpy_state)


def _build(spec, backbone, height, width, as_released, floors, bounded_pitch_head,
           positive_focal_head, disentangle, alpha_rate, disparity, point_errors,
           exp_disparity_head, head_activation, name):
    left = keras.Input((height, width, 3), name="left_image")
    right = keras.Input((height, width, 3), name="right_image")
    scaled_left, scaled_right = _scale_inputs(left, right, as_released)
    loss = spec.training_loss(as_released)
    outputs = BUILDERS[spec.builder](
        spec, scaled_left, scaled_right, backbone=backbone, as_released=as_released,
        floors=floors, pitch_activation=bounded_pitch if bounded_pitch_head else None,
        positive_focal_head=positive_focal_head, disparity_activation=disparity,
        detach=loss.projection and disentangle == "exact",
        exp_disparity=disparity if exp_disparity_head else None, hidden=head_activation,
    )
    positive_disparity = loss.projection or exp_disparity_head
    settings = {
        "variant": spec.name, "backbone": backbone, "image_size": [height, width],
        "as_released": as_released, "floors": floors, "loss": loss.name,
        "bounded_pitch_head": bounded_pitch_head and spec.builder != "deep_homo",
        "positive_disparity_head": positive_disparity,
        "disparity_ceiling": disparity.ceiling if positive_disparity else None,
        "positive_focal_head": positive_focal_head and loss.projection and spec.camera_graph,
        "disentangle": disentangle if loss.projection else None,
    }
    if loss.adaptive:
        settings["alpha_rate"] = alpha_rate
    if loss.projection and point_errors != "metres":  # (models built before it: metres)
        settings["point_errors"] = point_errors
    if exp_disparity_head:
        settings["exp_disparity_head"] = True
    if head_activation != "relu":  # (models built before it: relu)
        settings["head_activation"] = head_activation
    return CalibrationModel(
        inputs={"left_image": left, "right_image": right}, outputs=outputs,
        name=name or spec.name.replace("-", "_"), build_settings=settings,
    )


def _deep_homo_outputs(spec, left, right, *, as_released, **_):
    return deep_homo.deep_homo_outputs(left, right, as_released)


def _direct_outputs(spec, left, right, *, backbone, pitch_activation, exp_disparity=None,
                    hidden="relu", **_):
    """Two towers and one regression head per target (X, Y, Z regressed too);
    the disparity's is linear, or ``exp_disparity`` (``build_model``'s
    ``exp_disparity_head``)."""
    features = backbones.stereo_features(left, right, backbone)
    activations = {"pitch": pitch_activation, "disparity": exp_disparity}
    return [regression_head(features, target, activation=activations.get(target), hidden=hidden)
            for target in camera.TARGETS]


def _camera_graph_outputs(spec, left, right, *, backbone, as_released, floors,
                          pitch_activation, positive_focal_head, disparity_activation, detach,
                          hidden="relu", **_):
    features = backbones.stereo_features(left, right, backbone)
    return camera_projection_outputs(features, spec.name, as_released, floors, pitch_activation,
                                     detach=detach, positive_focal_head=positive_focal_head,
                                     disparity_activation=disparity_activation, hidden=hidden)


#: How each variant's outputs are made (``variants.Variant.builder``).
BUILDERS = {"deep_homo": _deep_homo_outputs, "direct": _direct_outputs,
            "camera_graph": _camera_graph_outputs}


def camera_projection_outputs(features, variant, as_released, floors, pitch_activation=None,
                              detach=False, positive_focal_head=None,
                              disparity_activation=None, hidden="relu"):
    # (the disparity head is positive where the projection loss trains it:
    # as the paper writes it; see ``layers.PositiveDisparity``; likewise the
    # focal heads unless ``positive_focal_head`` is False, ``layers.positive_focal``)
    """The CPL heads and the Lambda camera graph (Eqs. 4a-5c).

    12 heads predict the 10 parameters and a pixel (u, v) (unsupervised: no
    label is compared with it); the camera graph turns them into X, Y, Z.
    With ``detach`` the graph reads the 10 parameters through
    ``stop_gradient`` (same values), so the X, Y, Z terms of Eq. 7 train
    only the pixel heads: each error is charged to the parameter that made
    it. The released CPL-A multiplies X, Y, Z by per-sample sigmoid gates,
    each its own Dense(120) -> Dense(84) -> Dense(1, sigmoid) branch.
    """
    if positive_focal_head is None:
        positive_focal_head = not as_released
    focal = positive_focal if positive_focal_head else None
    activations = {"pitch": pitch_activation,
                   "disparity": None if as_released
                   else disparity_activation or PositiveDisparity(),
                   "fx": focal, "fy": focal}
    params = {name: regression_head(features, name, activation=activations.get(name),
                                    hidden=hidden)
              for name in camera.PARAMETERS}
    pixel = {name: regression_head(features, name, hidden=hidden) for name in PIXEL_HEADS}
    graph_params = params
    if detach:
        graph_params = {
            name: keras.layers.Lambda(stop_gradient, name=f"{name}_detached")(tensor)
            for name, tensor in params.items()
        }
    gated = as_released and variants.get(variant).released_gates
    rename = {q: f"{q}_projected" for q in ("X", "Y", "Z")} if gated else None
    X, Y, Z = camera.image_to_world(**graph_params, **pixel, ops=LambdaOps(floors, rename))
    points = {"X": X, "Y": Y, "Z": Z}
    if gated:
        for q in ("X", "Y", "Z"):
            gate = regression_head(features, f"{q}_gate", activation="sigmoid", hidden=hidden)
            points[q] = keras.layers.Lambda(multiply, name=q)([points[q], gate])
    return [params[name] for name in camera.PARAMETERS] + [points[q] for q in ("X", "Y", "Z")]


def compile_model(model, *, learning_rate=None, jit_compile="auto", steps_per_execution=1,
                  target_scale=None, weight_ema=0.0):
    """Compile with the paper's optimiser and loss.

    Adam, lr 1e-3 (Deep-Homo 1.5e-3). Loss: the model's own (see
    ``CalibrationModel``): summed per-output MAE, the camera projection loss
    or the Euclidean loss. Every output's MAE is reported either way.

    ``target_scale`` (name -> positive number, e.g. the training standard
    deviations) divides each output's MAE by its scale: standardised
    targets, so that targets in hundreds of pixels or metres do not drown
    those in radians. Not the paper's (it summed the raw MAEs); only for the
    per-output MAE loss.

    ``weight_ema`` (0 <= m < 1; 0, the paper's, is off): the optimizer also
    keeps an exponential moving average of the trainable weights, momentum
    m, updated after every step (Keras's ``use_ema``); training
    (``cpl_keras.training``) validates and keeps those averaged weights.
    """
    if not isinstance(model, CalibrationModel):
        raise ValueError("compile_model expects a model made by cpl_keras.build_model")
    if learning_rate is None:
        learning_rate = variants.get(model.build_settings.get("variant")).learning_rate
    if not (isinstance(learning_rate, numbers.Real) and learning_rate > 0):
        raise ValueError(f"learning rate must be a positive number, got {learning_rate!r}")
    if not (isinstance(weight_ema, numbers.Real) and 0 <= weight_ema < 1):
        raise ValueError(f"the weights' moving-average momentum must be in [0, 1), "
                         f"got {weight_ema!r}")
    names = list(model.output_names)
    loss_weights = None
    if model.training_loss.per_output:
        loss, metrics = {name: "mae" for name in names}, None
    else:
        loss, metrics = None, {name: ["mae"] for name in names}
    if target_scale is not None:
        if not model.training_loss.per_output:
            raise ValueError(
                f"target scaling applies to the per-output MAE loss, not {model.loss_mode!r}"
            )
        bad = [n for n in names if not (isinstance(target_scale.get(n), numbers.Real)
                                        and math.isfinite(target_scale[n]) and target_scale[n] > 0)]
        if bad:
            raise ValueError(f"target scale must be a positive number for {', '.join(bad)}")
        loss_weights = {name: 1.0 / float(target_scale[name]) for name in names}
        metrics = {name: ["mae"] for name in names}  # the unscaled MAE in the logs
    model.compile(
        optimizer=keras.optimizers.Adam(learning_rate=learning_rate, use_ema=weight_ema > 0,
                                        ema_momentum=float(weight_ema) or 0.99),
        loss=loss, loss_weights=loss_weights, metrics=metrics, jit_compile=jit_compile,
        steps_per_execution=steps_per_execution,
    )
    return model


def _scale_inputs(left, right, as_released):
    if as_released:
        return left, right  # the release fed raw 0..255 pixels
    scale = keras.layers.Rescaling(1.0 / 127.5, offset=-1.0, name="input_scaling")
    return scale(left), scale(right)


def _check_choice(what, value, choices):
    """Raise ValueError (one line) unless ``value`` is one of ``choices``."""
    if value not in choices:
        raise ValueError(f"unknown {what} {value!r}; choose one of {', '.join(choices)}")


def _alpha_rate(alpha_rate):
    """MTL-CPL-A's adaptive weights' rate as a float (default
    ``variants.ALPHA_RATE``); ValueError unless a finite number >= 0."""
    if alpha_rate is None:
        alpha_rate = variants.ALPHA_RATE
    if isinstance(alpha_rate, bool) or not (isinstance(alpha_rate, numbers.Real)
                                            and math.isfinite(alpha_rate) and alpha_rate >= 0):
        raise ValueError(f"alpha rate must be a number >= 0 (0: frozen), got {alpha_rate!r}")
    return float(alpha_rate)


def _image_shape(image_size, minimum, backbone):
    if isinstance(image_size, numbers.Integral) and not isinstance(image_size, bool):
        shape = (int(image_size), int(image_size))
    elif isinstance(image_size, (tuple, list)) and len(image_size) in (2, 3) and all(
        isinstance(s, numbers.Integral) for s in image_size
    ):
        if len(image_size) == 3 and image_size[2] != 3:
            raise ValueError(
                f"images must have 3 channels (RGB), got {image_size[2]} in image_size={tuple(image_size)}"
            )
        shape = (int(image_size[0]), int(image_size[1]))
    else:
        raise ValueError(
            f"image_size must be an int, (height, width) or (height, width, 3); got {image_size!r}"
        )
    if min(shape) < minimum:
        raise ValueError(
            f"image size {shape[0]}x{shape[1]} is below the minimum of {minimum} "
            f"for this model (backbone {backbone!r})"
        )
    return shape
