"""The forward pass of a trained network on image arrays: what calibration
and evaluation both run (``predict_images``), and the input size a model
takes (``model_image_shape``). numpy only; the model brings Keras."""

from __future__ import annotations

import numpy as np

from cpl_keras import distributed
from cpl_keras.camera import TARGETS


def model_image_shape(model):
    """(height, width) the model takes."""
    shape = model.inputs[0].shape
    return int(shape[1]), int(shape[2])


def predict_images(model, left, right, batch_size=32):
    """Forward pass on uint8 image arrays (n, H, W, 3): dict name -> (n,) float64.

    Every batch the model sees has ``batch_size`` pairs: a shorter last batch
    (or a set smaller than one batch) is filled up with copies of its last
    pair and their outputs dropped. Inference treats each pair on its own, so
    the outputs are the same; the model's forward pass is compiled once, not
    once for every set size it meets (a compilation costs seconds, more than
    the filled-up rows). Not inside a group of several processes
    (``distributed.refuse_prediction``): prediction runs after training."""
    distributed.refuse_prediction()
    left, right = np.asarray(left), np.asarray(right)
    out = {name: [] for name in TARGETS}
    for start in range(0, len(left), batch_size):
        count = min(batch_size, len(left) - start)
        rows = np.minimum(np.arange(start, start + batch_size), start + count - 1)
        inputs = {"left_image": np.asarray(left[rows], np.float32),
                  "right_image": np.asarray(right[rows], np.float32)}
        pred = model.predict_on_batch(inputs)
        if not isinstance(pred, dict):
            pred = dict(zip(model.output_names, pred if isinstance(pred, (list, tuple)) else [pred]))
        for name in TARGETS:
            out[name].append(np.asarray(pred[name], np.float64).reshape(-1)[:count])
    return {name: np.concatenate(values) if values else np.zeros(0) for name, values in out.items()}
