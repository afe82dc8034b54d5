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
import dataclasses
import math
import numbers
import random

import keras
import numpy as np

from cpl_keras import camera
from cpl_keras.layers import (
    MAX_OUTPUT, LambdaOps, PositiveDisparity, SoftplusDisparity, bounded_pitch, multiply,
    placeholder_arithmetic_quiet, positive_focal, regression_head, stop_gradient,
)
from cpl_keras.models import backbones, deep_homo, pretrained
from cpl_keras.models.calibration_model import CalibrationModel
from cpl_keras.models.options import ModelOptions, OptionsError
from cpl_keras.training_options import TrainingOptions
from cpl_keras.models.variants import (  # noqa: F401
    DISENTANGLE, HEAD_ACTIVATIONS, POINT_ERRORS, VARIANTS,
)

PIXEL_HEADS = ("u", "v")


def build_model(variant, options=None, *, image_size=112, seed=None, name=None, **fields):
    """Build one of the paper's networks.

    Args:
        variant: one of ``VARIANTS``.
        options: a ``ModelOptions`` (default: the paper's): the towers, the
            heads, the loss and its weights (``models.options``).
        image_size: side of the square input images, or ``(height, width)``
            or ``(height, width, 3)``. At least 75 for InceptionV3.
        seed: seeds Keras's initialisers when given. Python's and NumPy's
            global random generators are left as they were.
        name: the model's name (default: the variant).
        **fields: ``ModelOptions`` fields that replace those of ``options``
            (``build_model("cpl-a", backbone="small")``).

    With ``backbone_weights`` (``models.pretrained``) both towers start
    from that file's weights, checked against ``backbone_weights_sha256``
    when it is given.

    Raises ``ValueError`` (``OptionsError``, one line) for a bad option or
    weights file.
    """
    options = (options or ModelOptions()).replace(**fields)
    return _build_model(variant, options, image_size, seed, name, read_backbone_weights=True)


def build_from_config(variant, build, read_backbone_weights=True):
    """The model of config.json's ``variant`` and ``build`` (its options with
    ``image_size`` and ``seed`` beside them). ``read_backbone_weights``
    False leaves the towers randomly initialised whatever
    ``backbone_weights`` says (the file is not read): for a model whose
    weights are loaded next, as a resumed run's from its checkpoint; its
    settings are the same."""
    return _build_model(variant, ModelOptions.from_config(build), build["image_size"],
                        build.get("seed"), None, read_backbone_weights)


def _build_model(variant, options, image_size, seed, name, read_backbone_weights):
    """``build_model``'s work, the towers' weights file read or not."""
    options = options.for_variant(variant)
    if options.range_scales == "auto":
        raise OptionsError("range weights' scales are read off the training labels "
                           "(training sets them); give range_scales")
    # (without training labels, "auto" is the bound of ``layers.MAX_OUTPUT``
    # and the softplus head's own start)
    options = options.replace(**{name: None for name in ("disparity_ceiling", "disparity_start")
                                 if getattr(options, name) == "auto"})
    if options.disparity_ceiling is None and options.positive_disparity_head(variant):
        options = options.replace(disparity_ceiling=float(MAX_OUTPUT))  # (the bound, said)
    spec = options.spec
    minimum = spec.min_image_size or backbones.MIN_IMAGE_SIZE[options.backbone]
    height, width = _image_shape(image_size, minimum, options.backbone)
    weights = _backbone_weights_file(options) if read_backbone_weights else None
    with _seeded(seed), placeholder_arithmetic_quiet():
        return _build(spec, options, height, width, name, weights)


def _backbone_weights_file(options):
    """The path of ``options``' backbone weights file (checked against its
    checksum when the options hold one), or None."""
    if options.backbone_weights is None:
        return None
    path = pretrained.weights_file(options.backbone_weights)
    if options.backbone_weights_sha256 is not None:
        pretrained.check_checksum(path, options.backbone_weights_sha256)
    return path


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


def _build(spec, options, height, width, name, weights=None):
    left = keras.Input((height, width, 3), name="left_image")
    right = keras.Input((height, width, 3), name="right_image")
    scaled_left, scaled_right = _scale_inputs(left, right, options.as_released)
    loss = spec.training_loss(options.as_released)
    outputs = BUILDERS[spec.builder](spec, scaled_left, scaled_right, options, weights=weights,
                                     detach=loss.projection and options.disentangle == "exact")
    # (the record, resolved for its variant and these images, as the model
    # keeps it: every switch as this network uses it, ``ModelOptions.for_variant``)
    settings = dict(options.to_config(), image_size=[height, width], loss=loss.name)
    return CalibrationModel(
        inputs={"left_image": left, "right_image": right}, outputs=outputs,
        name=name or spec.name.replace("-", "_"), build_settings=settings,
    )


def _disparity_activation(spec, options):
    """The disparity head's output activation and its first bias (None: 0):
    the softplus head of ``options.disparity_head``; the CPL variants' exp
    head as the paper writes them (and MTL-Baseline's with
    ``exp_disparity_head``); else linear (MTL-Baseline, and as released)."""
    ceiling = MAX_OUTPUT if options.disparity_ceiling is None else options.disparity_ceiling
    if not options.positive_disparity_head(spec.name):
        return None, None
    if options.disparity_head == "softplus":
        head = SoftplusDisparity(ceiling=ceiling)
        return head, head.bias_for(options.disparity_start)
    return PositiveDisparity(ceiling=ceiling), None


def _features(left, right, options, weights=None):
    """The two towers' features (starting from the weights file ``weights``
    when given), LayerNorm-ed with ``options.head_norm``."""
    features = backbones.stereo_features(left, right, options.backbone, weights)
    if options.head_norm:
        features = keras.layers.LayerNormalization(name="head_norm")(features)
    return features


def _deep_homo_outputs(spec, left, right, options, detach=False, weights=None):
    return deep_homo.deep_homo_outputs(left, right, options.as_released)


def _direct_outputs(spec, left, right, options, detach=False, weights=None):
    """Two towers and one regression head per target (X, Y, Z regressed too);
    the disparity's is linear unless ``options`` give it a positive one."""
    features = _features(left, right, options, weights)
    disparity, bias = _disparity_activation(spec, options)
    activations = {"pitch": bounded_pitch if options.bounded_pitch_head else None,
                   "disparity": disparity}
    return [regression_head(features, target, activation=activations.get(target),
                            hidden=options.head_activation,
                            bias=bias if target == "disparity" else None)
            for target in camera.TARGETS]


def _camera_graph_outputs(spec, left, right, options, detach=False, weights=None):
    features = _features(left, right, options, weights)
    return camera_projection_outputs(features, spec, options, detach=detach)


#: How each variant's outputs are made (``variants.Variant.builder``).
BUILDERS = {"deep_homo": _deep_homo_outputs, "direct": _direct_outputs,
            "camera_graph": _camera_graph_outputs}


def camera_projection_outputs(features, spec, options, detach=False):
    """The CPL heads and the Lambda camera graph (Eqs. 4a-5c).

    12 heads predict the 10 parameters and a pixel (u, v) (unsupervised: no
    label is compared with it); the camera graph turns them into X, Y, Z.
    With ``detach`` the graph reads the 10 parameters through
    ``stop_gradient`` (same values), so the X, Y, Z terms of Eq. 7 train
    only the pixel heads: each error is charged to the parameter that made
    it. The disparity head is positive where the projection loss trains it
    (as the paper writes it; ``layers.PositiveDisparity``), and so are the
    focal heads unless ``options.positive_focal_head`` is False
    (``layers.positive_focal``). The released CPL-A multiplies X, Y, Z by
    per-sample sigmoid gates, each its own Dense(120) -> Dense(84) ->
    Dense(1, sigmoid) branch.
    """
    focal = positive_focal if options.positive_focal_head else None
    disparity, bias = _disparity_activation(spec, options)
    activations = {"pitch": bounded_pitch if options.bounded_pitch_head else None,
                   "disparity": disparity, "fx": focal, "fy": focal}
    hidden = options.head_activation
    params = {name: regression_head(features, name, activation=activations.get(name),
                                    hidden=hidden, bias=bias if name == "disparity" else None)
              for name in camera.PARAMETERS}
    pixel = {name: regression_head(features, name, hidden=hidden) for name in PIXEL_HEADS}
    graph_params = params
    if detach:
        graph_params = {
            name: keras.layers.Lambda(stop_gradient, name=f"{name}_detached")(tensor)
            for name, tensor in params.items()
        }
    gated = options.as_released and spec.released_gates
    rename = {q: f"{q}_projected" for q in ("X", "Y", "Z")} if gated else None
    X, Y, Z = camera.image_to_world(**graph_params, **pixel,
                                    ops=LambdaOps(options.floors, rename))
    points = {"X": X, "Y": Y, "Z": Z}
    if gated:
        for q in ("X", "Y", "Z"):
            gate = regression_head(features, f"{q}_gate", activation="sigmoid", hidden=hidden)
            points[q] = keras.layers.Lambda(multiply, name=q)([points[q], gate])
    return [params[name] for name in camera.PARAMETERS] + [points[q] for q in ("X", "Y", "Z")]


def compile_model(model, training=None, *, jit_compile="auto", steps_per_execution=1,
                  target_scale=None, **fields):
    """Compile with the paper's optimiser and loss, as ``training`` (a
    ``TrainingOptions``; None: the paper's) and ``fields`` of it by name
    (``learning_rate=...``, ``weight_ema=...``) say.

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
    unknown = sorted(set(fields) - set(TrainingOptions.recorded_fields()))
    if unknown:
        raise TypeError(f"compile_model() got an unexpected keyword argument {unknown[0]!r}")
    training = dataclasses.replace(training or TrainingOptions(), **fields)
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
        optimizer=_optimizer(model, training),
        loss=loss, loss_weights=loss_weights, metrics=metrics, jit_compile=jit_compile,
        steps_per_execution=steps_per_execution,
    )
    return model


def _optimizer(model, training):
    """Adam at ``training``'s learning rate (None: the variant's, the
    paper's); AdamW with its ``weight_decay`` (not on Eq. 9's weights), a
    global gradient-norm clip with its ``clip_norm``, and the moving average
    of the weights with its ``weight_ema`` > 0."""
    learning_rate = training.learning_rate
    if learning_rate is None:
        learning_rate = model.options.spec.learning_rate
    weight_ema = training.weight_ema or 0.0
    common = dict(learning_rate=learning_rate, use_ema=weight_ema > 0,
                  ema_momentum=float(weight_ema) or 0.99, global_clipnorm=training.clip_norm)
    if not training.weight_decay:
        return keras.optimizers.Adam(**common)
    optimizer = keras.optimizers.AdamW(weight_decay=float(training.weight_decay), **common)
    optimizer.exclude_from_weight_decay(var_names=["log_variances"])
    return optimizer


def _scale_inputs(left, right, as_released):
    if as_released:
        return left, right  # the release fed raw 0..255 pixels
    scale = keras.layers.Rescaling(1.0 / 127.5, offset=-1.0, name="input_scaling")
    return scale(left), scale(right)


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
