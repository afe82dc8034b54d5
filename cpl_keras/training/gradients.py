"""Which loss term drives the towers: the gradient that each term of a
variant's loss sends into the shared features.

Both towers end in one feature vector (the ``stereo_features`` layer) that
every head reads, so what the towers learn is the sum of what each loss
term asks of that vector. ``term_gradient_norms`` measures each term's
share on a fixed batch of training pairs: the norm of the gradient of the
term, weighted as the loss weights it, with respect to the features
(through the heads and, for the CPL variants, the camera graph; the towers
themselves are not differentiated, so it costs a forward pass of the towers
and a Jacobian of the small heads). The terms:

* MTL-Baseline (``mae``): each output's mean absolute error (the loss is
  their sum);
* MTL-CPL-U (``projection-uniform``): the 13 disentangled terms of Eq. 7,
  divided by 13 as Eq. 7's mean divides them;
* MTL-CPL-A (``projection-adaptive``): the same terms times Eq. 9's weight
  ``alpha_i = exp(-s_i)`` (the regulariser ``s_i`` does not reach the
  features).

Deep-Homo's Euclidean loss is one term: it has none to compare. The
Jacobian needs the JAX backend (Keras has no backend-neutral one).
"""

from __future__ import annotations

import numpy as np

from cpl_keras import camera
from cpl_keras.backend import keras_backend

#: The layer whose output both towers feed and every head reads.
FEATURES = "stereo_features"


def supported(model):
    """Whether ``term_gradient_norms`` applies to ``model``: a loss of several
    terms, shared features, the JAX backend."""
    loss = getattr(model, "training_loss", None)
    return (keras_backend() == "jax" and loss is not None
            and (loss.per_output or loss.projection)
            and any(layer.name == FEATURES for layer in model.layers))


def weighted_terms(model, y, y_pred, log_variances=None, floor=None):
    """The 13 terms of ``model``'s loss, in ``camera.TARGETS`` order, each
    weighted as the loss weights it (see the module docstring). ``y``,
    ``y_pred``: dicts of (batch, 1) tensors; ``log_variances`` and ``floor``:
    Eq. 9's ``s_i`` and their floors (MTL-CPL-A)."""
    from keras import ops

    if model.training_loss.per_output:
        return [ops.mean(ops.abs(y_pred[name] - ops.cast(y[name], "float32")))
                for name in camera.TARGETS]
    terms = model.projection_terms(y, y_pred)
    if not model.training_loss.adaptive:
        return [term / float(len(terms)) for term in terms]
    s = ops.maximum(log_variances, floor)
    return [ops.exp(-s[i]) * term for i, term in enumerate(terms)]


class TermGradients:
    """``TermGradients(model)(x, y)`` -> ``{"grad_<target>": norm}`` for a
    batch ``x`` (the model's inputs) and its targets ``y`` (dict), at the
    model's current weights. The heads' Jacobian is compiled once; the
    weights are its arguments, so every epoch reuses it."""

    def __init__(self, model):
        import jax
        import keras

        if not supported(model):
            raise ValueError(f"no terms to compare for a model with the "
                             f"{getattr(model, 'loss_mode', None)!r} loss on "
                             f"{keras_backend()!r}")
        self.model = model
        features = model.get_layer(FEATURES).output
        self.towers = keras.Model(model.inputs, features)
        self.heads = keras.Model(features, model.outputs)
        names = model.output_names

        def norms(trainable, non_trainable, feature_values, y, log_variances, floor):
            def terms(values):
                outputs, _ = self.heads.stateless_call(trainable, non_trainable, values,
                                                       training=False)
                y_pred = dict(zip(names, outputs))
                return jax.numpy.stack(weighted_terms(model, y, y_pred, log_variances, floor))

            jacobian = jax.jacrev(terms)(feature_values)  # (terms, batch, features)
            return jax.numpy.sqrt(jax.numpy.sum(jacobian ** 2, axis=(1, 2)))

        self._norms = jax.jit(norms)

    def __call__(self, x, y):
        model = self.model
        feature_values = self.towers.predict_on_batch(x)
        adaptive = model.training_loss.adaptive
        zeros = np.zeros(len(camera.TARGETS), "float32")
        log_variances = model.log_variance_values() if adaptive else zeros
        floor = model.log_variance_floor.value if adaptive else zeros
        y = {name: np.asarray(y[name], "float32") for name in camera.TARGETS}
        norms = self._norms([v.value for v in self.heads.trainable_variables],
                            [v.value for v in self.heads.non_trainable_variables],
                            feature_values, y, log_variances, floor)
        return {f"grad_{name}": float(value)
                for name, value in zip(camera.TARGETS, np.asarray(norms))}
