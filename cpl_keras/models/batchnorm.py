"""Recompute BatchNorm's moving statistics from training batches.

A BatchNormalization layer normalises with the batch's own statistics in
training mode and with exponential moving averages (momentum 0.99 in
InceptionV3) in inference mode. Trained from random initialisation, the
weights move faster than those averages follow, so the network that
validation, evaluation and the saved model run in inference mode is not the
one that was trained: for MTL-Baseline with InceptionV3 towers at 75 px after
200 steps, the loss was 260 in training mode and 1,610 in inference mode on
the same training batches, and 215 after recomputing the statistics.

``recompute_batchnorm_statistics(model, batches)`` replaces every moving mean
and variance by the average of the batch statistics over ``batches``, with
the current weights (the "precise BatchNorm" of Wu & Johnson, 2021). Training
calls it before every validation, so validation, the checkpoints and the
saved model all see statistics that belong to their weights.
"""

from __future__ import annotations

import keras
import numpy as np


def batchnorm_layers(model):
    """Every ``BatchNormalization`` layer of ``model``, nested models included."""
    return [layer for layer in model._flatten_layers(include_self=False, recursive=True)
            if isinstance(layer, keras.layers.BatchNormalization)]


def _batch_statistics_function(model, layers):
    """f(trainable_values, non_trainable_values, inputs) -> the layers' moving
    stats after one training-mode call with momentum 0 (that batch's own
    statistics). Traced with momentum 0 and cached on the model, so a run
    compiles it once."""
    cached = getattr(model, "_batch_statistics_function", None)
    if cached is not None:
        return cached
    positions = {id(v): i for i, v in enumerate(model.non_trainable_variables)}
    wanted = [positions[id(v)] for layer in layers
              for v in (layer.moving_mean, layer.moving_variance)]

    def statistics(trainable_values, non_trainable_values, inputs):
        _, values = model.stateless_call(
            trainable_values, non_trainable_values, inputs, training=True
        )
        return [values[i] for i in wanted]

    if keras.backend.backend() == "jax":
        import jax

        statistics = jax.jit(statistics)
    model._batch_statistics_function = statistics
    return statistics


def _to_numpy(value):
    """A tensor as a NumPy array, through Keras (a PyTorch tensor that
    requires a gradient is detached first: ``np.asarray`` called its
    ``numpy()``, which refuses one); a global array that spans other
    processes' devices is replicated, and its local copy is read."""
    if getattr(value, "is_fully_addressable", True) is False:
        value = value.addressable_data(0)
    return keras.ops.convert_to_numpy(value)


def recompute_batchnorm_statistics(model, batches, population=False, global_batch=None):
    """Set every BatchNorm layer's moving mean and variance to the average of
    its batch statistics over ``batches`` (an iterable of model inputs, or of
    ``(inputs, targets)`` tuples). Returns the number of batches used (0 when
    the model has no BatchNorm layer or ``batches`` is empty).

    With ``population`` the variance is that of all the batches' values
    together (the average of each batch's E[x^2], less the squared mean),
    which adds the spread of the batch means to the average batch variance.
    Training uses the average (Keras's own per-batch variance); on the
    faithful-2000 InceptionV3 MTL-CPL-A run the population variance gave a
    validation loss 5-8 % lower in each of 5 draws
    (``analyses/diagnose_inference_mode.py``). ``global_batch``: turns a
    process's part of a batch into the whole batch where several processes
    train together (``training.processes``); None: the batch is whole."""
    layers = batchnorm_layers(model)
    if not layers:
        return 0
    momenta = [layer.momentum for layer in layers]
    for layer in layers:
        layer.momentum = 0.0
    try:
        statistics = _batch_statistics_function(model, layers)
        trainable = [v.value for v in model.trainable_variables]
        non_trainable = [v.value for v in model.non_trainable_variables]
        sums, count = None, 0
        for batch in batches:
            inputs = batch[0] if isinstance(batch, tuple) else batch
            # (in a process group each process holds a part of the batch; the
            # statistics are those of the whole batch, on every process)
            if global_batch is not None:
                inputs = global_batch(inputs)
            stats = [np.asarray(_to_numpy(s), np.float64)
                     for s in statistics(trainable, non_trainable, inputs)]
            if population:
                # (mean, variance) -> (mean, E[x^2]) so that the average over
                # batches gives the variance of all their pairs together
                stats = [s + stats[i - 1] ** 2 if i % 2 else s for i, s in enumerate(stats)]
            sums = stats if sums is None else [a + b for a, b in zip(sums, stats)]
            count += 1
    finally:
        for layer, momentum in zip(layers, momenta):
            layer.momentum = momentum
    if not count:
        return 0
    variables = [v for layer in layers for v in (layer.moving_mean, layer.moving_variance)]
    averages = [total / count for total in sums]
    if population:
        averages = [np.maximum(a - averages[i - 1] ** 2, 0.0) if i % 2 else a
                    for i, a in enumerate(averages)]
    for variable, average in zip(variables, averages):
        variable.assign(average.astype(variable.dtype))
    return count
