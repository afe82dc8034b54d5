"""Deep-Homo (DeTone et al., 2016) modified to regress the 13 targets.

As the release modified it: one channel of each image stacked to
(H, W, 2); eight 3x3 convolutions (64, 64, 64, 64, 128, 128, 128, 128) with
ReLU, batch normalisation after each pair and 2x2 max-pooling after the
first three pairs; Flatten, Dropout(0.75), Dense(1024) and Dense(13), both
linear. Trained with the Euclidean distance between the 13-vectors
(``cpl_keras.models.losses.euclidean_loss``), Adam 1.5e-3.

The 13 values are split into named outputs so every variant has the same
interface.

The convolutions are ``PatchConv2D`` layers: ``Conv2D``'s layer, weights and
outputs, with the kernel gradient of the 3x3 convolutions on the 112, 56 and
28 px maps computed as matrix products (one per kernel row) instead of
XLA:CPU's convolution with a window the size of the map, which took a third
of the training step; the 2x2 max-poolings are ``ViewMaxPooling2D``
layers, ``MaxPooling2D``'s values with an element-wise gradient instead of
XLA's select-and-scatter (paper_results/notes/deep-homo-speed.md: together a 1.64x
faster step).
"""

from __future__ import annotations

import keras

from cpl_keras.camera import TARGETS
from cpl_keras.layers import stack_channels, take
from cpl_keras.models.fast_layers import PatchConv2D, ViewMaxPooling2D


def deep_homo_outputs(left, right, as_released=False):
    """The Deep-Homo graph from the two (scaled) images to 13 named outputs."""
    # The release took one channel of OpenCV's BGR images (blue); as the
    # paper describes Deep-Homo, the inputs are grey images.
    channel = 2 if as_released else -1
    x = keras.layers.Lambda(
        stack_channels, arguments={"channel": channel}, name="stacked_channels"
    )([left, right])
    for pair, filters in enumerate((64, 64, 128, 128), start=1):
        for i in (1, 2):
            x = PatchConv2D(
                filters, 3, padding="same", activation="relu", name=f"conv{pair}_{i}"
            )(x)
        x = keras.layers.BatchNormalization(name=f"batch_norm{pair}")(x)
        if pair < 4:
            x = ViewMaxPooling2D(2, name=f"max_pool{pair}")(x)
    x = keras.layers.Flatten(name="flatten")(x)
    x = keras.layers.Dropout(0.75, name="dropout")(x)
    x = keras.layers.Dense(1024, name="dense_1024")(x)
    values = keras.layers.Dense(len(TARGETS), name="dense_13")(x)
    return [
        keras.layers.Lambda(take, arguments={"index": i}, name=name)(values)
        for i, name in enumerate(TARGETS)
    ]
