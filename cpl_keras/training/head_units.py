"""Which regression heads still learn: the live units of each head's first
layer, on a fixed batch of training pairs.

Every head is Dense(120) -> Dense(84) -> Dense(1) (``layers.regression_head``;
ReLUs, the release's, or leaky ReLUs, ``--head-activation``). On a pair where
every unit of a ReLU head's first layer is at zero, the head puts out its
biases' value and no gradient from that pair reaches its first layer or,
through it, the towers: the head has died on that pair. A leaky unit below
zero still passes its slope's share of the gradient, so for a leaky head the
same count says how many pairs it reads on its small slope alone.

``HeadUnits(model)(x)`` -> per head ``h``:

* ``dead_<h>``: the share of the pairs with every first-layer unit at or
  below zero;
* ``units_<h>``: the first-layer units above zero for at least one pair (of
  120).

Logged every epoch with ``train.py --head-units`` (log.csv), it says when a
head dies; ``analyses/collapsed_heads.py --units`` measures the same on a
finished run's test pairs.
"""

from __future__ import annotations

import numpy as np

from cpl_keras import camera

#: The layer of a head whose units are counted (``layers.regression_head``).
FIRST_LAYER = "{}_dense_120"


def heads(model):
    """The regression heads of ``model`` (``camera.PARAMETERS`` order) whose
    first layer it has; empty for a model without them (Deep-Homo)."""
    names = {layer.name for layer in model.layers}
    return [name for name in camera.PARAMETERS if FIRST_LAYER.format(name) in names]


class HeadUnits:
    """``HeadUnits(model)(x)`` -> ``{"dead_<head>": share, "units_<head>": count}``
    for a batch ``x`` (the model's inputs), at the model's current weights
    (see the module docstring)."""

    def __init__(self, model):
        import keras

        self.heads = heads(model)
        if not self.heads:
            raise ValueError("the model has no regression heads to count units of")
        self.probe = keras.Model(model.inputs, [model.get_layer(FIRST_LAYER.format(h)).output
                                                for h in self.heads])

    def __call__(self, x):
        outputs = self.probe.predict_on_batch(x)
        logs = {}
        for head, values in zip(self.heads, outputs):
            values = np.asarray(values)
            logs[f"dead_{head}"] = float(np.mean(values.max(axis=1) <= 0))
            logs[f"units_{head}"] = int(np.sum(values.max(axis=0) > 0))
        return logs
