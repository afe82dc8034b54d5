"""The two-tower stereo feature extractor of the MTL models.

As released: one InceptionV3 per image (``include_top=False``, no weight
sharing), each flattened (2 x 2 x 2048 = 8192 features at 112 x 112) and the
two concatenated (16384 features).

Deviations, documented in the README:

* ``weights=None``: the paper starts from ImageNet weights, which cannot be
  downloaded here; the towers start from random initialisation.
* ``backbone="small"``: four strided 3x3 convolutions (16, 32, 64, 64
  filters) instead of InceptionV3, for quick runs and tests. Not the paper's.
"""

from __future__ import annotations

import keras

BACKBONES = ("inception_v3", "small")
#: The smallest image side each backbone accepts (InceptionV3's own limit is 75).
MIN_IMAGE_SIZE = {"inception_v3": 75, "small": 16}


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


def stereo_features(left, right, backbone):
    """Two towers (one per image), flattened and concatenated."""
    height, width = left.shape[1], left.shape[2]
    make_tower = {"inception_v3": inception_v3_tower, "small": small_tower}[backbone]
    left_features = make_tower(height, width, f"left_{backbone}")(left)
    right_features = make_tower(height, width, f"right_{backbone}")(right)
    left_features = keras.layers.Flatten(name="left_flatten")(left_features)
    right_features = keras.layers.Flatten(name="right_flatten")(right_features)
    return keras.layers.Concatenate(name="stereo_features")([left_features, right_features])
