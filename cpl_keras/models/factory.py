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
============================  ===========================  ============================

(The dataset side of the switch, the release's disparity and pitch labels, is
in ``cpl_keras.datasets``.)
"""

from __future__ import annotations

import numbers

import keras

from cpl_keras import camera
from cpl_keras.layers import LambdaOps, multiply, regression_head
from cpl_keras.models import backbones, deep_homo
from cpl_keras.models.calibration_model import CalibrationModel

VARIANTS = ("baseline", "cpl-u", "cpl-a", "deep-homo")
PIXEL_HEADS = ("u", "v")


def build_model(variant, *, backbone="inception_v3", image_size=112, as_released=False,
                epsilon=camera.EPSILON, seed=None, name=None):
    """Build one of the paper's networks.

    Args:
        variant: one of ``VARIANTS``.
        backbone: ``"inception_v3"`` (the paper's) or ``"small"`` (quick runs,
            not the paper's). Deep-Homo has its own convolutional stack.
        image_size: side of the square input images, or ``(height, width)``
            or ``(height, width, 3)``. At least 75 for InceptionV3.
        as_released: reproduce the released code instead of the paper's text
            (see the module docstring).
        epsilon: smallest divisor magnitude in the camera graph.
        seed: seeds Keras's initialisers when given.
        name: the model's name (default: the variant).
    """
    if variant not in VARIANTS:
        raise ValueError(f"unknown variant {variant!r}; choose one of {', '.join(VARIANTS)}")
    if backbone not in backbones.BACKBONES:
        raise ValueError(
            f"unknown backbone {backbone!r}; choose one of {', '.join(backbones.BACKBONES)}"
        )
    if not (isinstance(epsilon, numbers.Real) and epsilon > 0):
        raise ValueError(f"epsilon must be a positive number, got {epsilon!r}")
    minimum = deep_homo.MIN_IMAGE_SIZE if variant == "deep-homo" else backbones.MIN_IMAGE_SIZE[backbone]
    height, width = _image_shape(image_size, minimum, backbone)
    if seed is not None:
        keras.utils.set_random_seed(int(seed))

    left = keras.Input((height, width, 3), name="left_image")
    right = keras.Input((height, width, 3), name="right_image")
    scaled_left, scaled_right = _scale_inputs(left, right, as_released)

    if variant == "deep-homo":
        outputs = deep_homo.deep_homo_outputs(scaled_left, scaled_right, as_released)
        loss = "euclidean"
    else:
        features = backbones.stereo_features(scaled_left, scaled_right, backbone)
        if variant == "baseline":
            outputs = [regression_head(features, target) for target in camera.TARGETS]
            loss = "mae"
        else:
            outputs = camera_projection_outputs(features, variant, as_released, epsilon)
            loss = "mae" if as_released else {
                "cpl-u": "projection-uniform", "cpl-a": "projection-adaptive"
            }[variant]

    calibration = {
        "variant": variant, "backbone": backbone, "image_size": [height, width],
        "as_released": bool(as_released), "epsilon": float(epsilon), "loss": loss,
    }
    return CalibrationModel(
        inputs={"left_image": left, "right_image": right}, outputs=outputs,
        name=name or variant.replace("-", "_"), calibration=calibration,
    )


def camera_projection_outputs(features, variant, as_released, epsilon):
    """The CPL heads and the Lambda camera graph (Eqs. 4a-5c).

    12 heads predict the 10 parameters and a pixel (u, v) (unsupervised: no
    label is compared with it); the camera graph turns them into X, Y, Z.
    The released CPL-A multiplies X, Y, Z by per-sample sigmoid gates, each
    its own Dense(120) -> Dense(84) -> Dense(1, sigmoid) branch.
    """
    params = {name: regression_head(features, name) for name in camera.PARAMETERS}
    pixel = {name: regression_head(features, name) for name in PIXEL_HEADS}
    gated = as_released and variant == "cpl-a"
    rename = {q: f"{q}_projected" for q in ("X", "Y", "Z")} if gated else None
    X, Y, Z = camera.image_to_world(**params, **pixel, ops=LambdaOps(epsilon, rename))
    points = {"X": X, "Y": Y, "Z": Z}
    if gated:
        for q in ("X", "Y", "Z"):
            gate = regression_head(features, f"{q}_gate", activation="sigmoid")
            points[q] = keras.layers.Lambda(multiply, name=q)([points[q], gate])
    return [params[name] for name in camera.PARAMETERS] + [points[q] for q in ("X", "Y", "Z")]


def compile_model(model, *, learning_rate=None, jit_compile="auto", steps_per_execution=1):
    """Compile with the paper's optimiser and loss.

    Adam, lr 1e-3 (Deep-Homo 1.5e-3). Loss: the model's own (see
    ``CalibrationModel``): summed per-output MAE, the camera projection loss
    or the Euclidean loss. Every output's MAE is reported either way.
    """
    if not isinstance(model, CalibrationModel):
        raise ValueError("compile_model expects a model made by cpl_keras.build_model")
    if learning_rate is None:
        learning_rate = 1.5e-3 if model.calibration.get("variant") == "deep-homo" else 1e-3
    if not (isinstance(learning_rate, numbers.Real) and learning_rate > 0):
        raise ValueError(f"learning rate must be a positive number, got {learning_rate!r}")
    names = list(model.output_names)
    if model.loss_mode == "mae":
        loss, metrics = {name: "mae" for name in names}, None
    else:
        loss, metrics = None, {name: ["mae"] for name in names}
    model.compile(
        optimizer=keras.optimizers.Adam(learning_rate=learning_rate),
        loss=loss, metrics=metrics, jit_compile=jit_compile,
        steps_per_execution=steps_per_execution,
    )
    return model


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
