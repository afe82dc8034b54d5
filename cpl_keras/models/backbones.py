"""The two-tower stereo feature extractor of the MTL models.

As released: one InceptionV3 per image (``include_top=False``, no weight
sharing), each flattened (2 x 2 x 2048 = 8192 features at 112 x 112) and the
two concatenated (16384 features).

Deviations, documented in the README:

* ``weights=None``: the paper starts from ImageNet weights, which cannot be
  downloaded here; the towers start from random initialisation unless a
  weights file is given (``ModelOptions.backbone_weights``,
  ``cpl_keras.models.pretrained``: both towers start from it).
* ``backbone="small"``: four strided 3x3 convolutions (16, 32, 64, 64
  filters) instead of InceptionV3, for quick runs and tests. Not the paper's.
* ``backbone="small_resnet"``: a small ResNet (a strided stem and four
  residual stages with BatchNormalization, 16, 32, 64, 128 channels) for
  CPU-scale experiments; it trained about 20x faster than InceptionV3 on a
  2-core CPU at 112 x 112 (``bench/bench_backbones.py``, docs/training.md;
  about 14x since ``PatchConv2D`` sped InceptionV3 up).
  Not the paper's. keras.applications' MobileNetV3Small, MobileNetV2 and
  EfficientNetB0 were measured too and were only 0.5-3x faster than
  InceptionV3 here (XLA:CPU's depthwise convolutions are slow).

Inputs arrive already scaled to [-1, 1] (or raw pixels as released): no
tower adds input scaling of its own.

Speed, not arithmetic: where XLA:CPU's convolution kernels are slow for a
shape, the towers' convolutions are ``PatchConv2D`` layers that compute the
same function with the same weights through matrix products over image
patches: a 3x3 convolution on InceptionV3's 2 x 2 maps (about 20x faster) and
the kernel gradients of its stem; and its max-poolings are
``ViewMaxPooling2D`` layers, whose gradient is element-wise instead of
XLA's select-and-scatter (both in ``cpl_keras.models.fast_layers``;
docs/performance.md; measured in
paper_results/notes/performance-measurements.md). ``with_faster_layers``
swaps them into a tower.
"""

from __future__ import annotations

import contextlib
import random

import keras
import numpy as np

from cpl_keras.models import pretrained
from cpl_keras.models.fast_layers import PatchConv2D, ViewMaxPooling2D
from cpl_keras.models.variants import BACKBONES, MIN_IMAGE_SIZE  # noqa: E402,F401

#: Channels of the small ResNet's four residual stages (the stem has the first).
SMALL_RESNET_WIDTHS = (16, 32, 64, 128)


def inception_v3_tower(height, width, name):
    """InceptionV3 without its classifier, randomly initialised."""
    return keras.applications.InceptionV3(
        include_top=False, weights=None, input_shape=(height, width, 3), name=name
    )


def small_tower(height, width, name):
    """A small CNN for quick runs: 4 strided convolutions, 1/16 resolution."""
    inputs = keras.Input((height, width, 3))
    x = inputs
    for i, filters in enumerate((16, 32, 64, 64), start=1):
        x = keras.layers.Conv2D(
            filters, 3, strides=2, padding="same", activation="relu", name=f"conv{i}"
        )(x)
    return keras.Model(inputs, x, name=name)


def small_resnet_tower(height, width, name, widths=SMALL_RESNET_WIDTHS):
    """A small ResNet for CPU-scale runs, 1/32 resolution.

    A 3x3 stride-2 stem (``widths[0]`` channels, BatchNormalization, ReLU),
    then one basic residual block per entry of ``widths``, each stage
    halving the resolution: two 3x3 convolutions with BatchNormalization (the
    first strided) and a strided 1x1 projection shortcut with
    BatchNormalization, added, then ReLU. Ends at ceil(side / 32) squared
    positions by ``widths[-1]`` channels (4 x 4 x 128 = 2048 features at 112).
    """
    layers = keras.layers

    def conv_bn(x, filters, kernel, strides, prefix):
        x = layers.Conv2D(filters, kernel, strides=strides, padding="same", use_bias=False,
                          name=f"{prefix}_conv")(x)
        return layers.BatchNormalization(name=f"{prefix}_bn")(x)

    inputs = keras.Input((height, width, 3))
    x = layers.ReLU(name="stem_relu")(conv_bn(inputs, widths[0], 3, 2, "stem"))
    for i, filters in enumerate(widths, start=1):
        shortcut = conv_bn(x, filters, 1, 2, f"stage{i}_shortcut")
        y = layers.ReLU(name=f"stage{i}_a_relu")(conv_bn(x, filters, 3, 2, f"stage{i}_a"))
        y = conv_bn(y, filters, 3, 1, f"stage{i}_b")
        x = layers.ReLU(name=f"stage{i}_out")(layers.Add(name=f"stage{i}_add")([y, shortcut]))
    return keras.Model(inputs, x, name=name)


TOWERS = {
    "inception_v3": inception_v3_tower, "small": small_tower,
    "small_resnet": small_resnet_tower,
}


def with_faster_layers(tower):
    """``tower`` with each Conv2D for which ``PatchConv2D`` takes another path
    as a ``PatchConv2D`` and each MaxPooling2D that ``ViewMaxPooling2D``
    computes from views as one (same names, same weights; ``tower`` itself
    when there is none).

    The clone is made without drawing from any random generator, so the
    layers built after it initialise as they would without it.
    """
    def faster(layer):
        """The faster class for ``layer``, or None."""
        if type(layer) is keras.layers.Conv2D:
            patch = PatchConv2D.from_config(layer.get_config())
            return PatchConv2D if patch.path(layer.input.shape) != "conv" else None
        if type(layer) is keras.layers.MaxPooling2D:
            pool = ViewMaxPooling2D.from_config(layer.get_config())
            return ViewMaxPooling2D if pool.path(layer.input.shape) != "pool" else None
        return None

    def clone(layer):
        return (faster(layer) or type(layer)).from_config(layer.get_config())

    with _random_state_kept():  # new layers draw their initialisers' seeds
        if not any(faster(layer) for layer in tower.layers):
            return tower
        patched = keras.models.clone_model(tower, clone_function=clone)
    patched.set_weights(tower.get_weights())
    return patched


@contextlib.contextmanager
def _random_state_kept():
    """Python's, NumPy's and Keras's global random state as they were after the block."""
    # (private: Keras has no public way to read and set its global seed
    # generator's state; tests/test_private_apis.py checks it is there)
    from keras.src.random.seed_generator import global_seed_generator

    python_state, numpy_state = random.getstate(), np.random.get_state()
    keras_state = global_seed_generator().state.numpy()
    try:
        yield
    finally:
        random.setstate(python_state)
        np.random.set_state(numpy_state)
        global_seed_generator().state.assign(keras_state)


def stereo_features(left, right, backbone, weights=None):
    """Two towers (one per image, no weight sharing), flattened and
    concatenated; with ``weights``, the path of a weights file
    (``pretrained.load_into``), each tower starts from its weights."""
    height, width = left.shape[1], left.shape[2]
    make_tower = TOWERS[backbone]
    features, values = {}, None
    for side, image in (("left", left), ("right", right)):
        tower = make_tower(height, width, f"{side}_{backbone}")
        if weights is not None and values is None:
            values = pretrained.load_into(tower, weights)
        elif values is not None:
            tower.set_weights(values)
        features[side] = with_faster_layers(tower)(image)
    return keras.layers.Concatenate(name="stereo_features")(
        [keras.layers.Flatten(name=f"{side}_flatten")(features[side])
         for side in ("left", "right")])
