"""``CalibrationModel``: a functional Keras model that knows its training loss.

Keras compiles one loss per output. The camera projection loss of Eqs. 7
and 9 and Deep-Homo's Euclidean loss couple all 13 outputs, so the model
computes them itself in ``compute_loss``. The loss mode, the build
arguments and (for Eq. 9) the learned log-variances are part of the model,
so a ``.keras`` file restores all of it with ``safe_mode=True``.

Loss modes:

* ``"mae"``: Keras's per-output MAE, summed (the release; MTL-Baseline).
* ``"projection-uniform"``: Eq. 7 (MTL-CPL-U as the paper writes it).
* ``"projection-adaptive"``: Eq. 9 with learned weights (MTL-CPL-A as the
  paper writes it); see ``cpl_keras.losses``.
* ``"euclidean"``: Deep-Homo's Euclidean distance between the 13-vectors.
"""

from __future__ import annotations

import keras
from keras import ops

from cpl_keras import camera, losses
from cpl_keras.layers import PACKAGE

LOSS_MODES = ("mae", "projection-uniform", "projection-adaptive", "euclidean")


@keras.saving.register_keras_serializable(package=PACKAGE)
class CalibrationModel(keras.Model):
    """A functional model with the 13 calibration outputs and its own loss.

    Args:
        *args, **kwargs: as for a functional ``keras.Model`` (inputs, outputs).
        calibration: dict of the build arguments (variant, backbone,
            image_size, as_released, epsilon) and ``loss`` (a LOSS_MODE).
    """

    def __init__(self, *args, calibration=None, **kwargs):
        super().__init__(*args, **kwargs)
        self.calibration = dict(calibration or {"loss": "mae"})
        if self.calibration["loss"] not in LOSS_MODES:
            raise ValueError(f"unknown loss mode {self.calibration['loss']!r}")
        if self.calibration["loss"] == "projection-adaptive":
            # s_i of Eq. 9 (alpha_i = exp(-s_i)), one per disentangled term.
            self.log_variances = self.add_weight(
                shape=(len(camera.TARGETS),), initializer="zeros",
                name="log_variances", trainable=True,
            )

    @property
    def loss_mode(self):
        return self.calibration["loss"]

    def adaptive_weights(self):
        """The learned alpha_i of Eq. 9 by target name (None for other modes)."""
        if self.loss_mode != "projection-adaptive":
            return None
        alphas = ops.convert_to_numpy(ops.exp(-self.log_variances.value))
        return {name: float(a) for name, a in zip(camera.TARGETS, alphas)}

    def _as_dict(self, y_pred):
        if isinstance(y_pred, dict):
            return y_pred
        return dict(zip(self.output_names, y_pred))

    def compute_loss(self, x=None, y=None, y_pred=None, sample_weight=None, training=True):
        mode = self.loss_mode
        if mode == "mae":
            return super().compute_loss(x, y, y_pred, sample_weight, training)
        y_pred = self._as_dict(y_pred)
        epsilon = self.calibration.get("epsilon", camera.EPSILON)
        if mode == "euclidean":
            loss = losses.euclidean_loss(y, y_pred)
        else:
            terms = losses.projection_terms(y, y_pred, epsilon)
            if mode == "projection-uniform":
                loss = losses.uniform_projection_loss(terms)
            else:
                loss = losses.adaptive_projection_loss(terms, self.log_variances)
        if self.losses:
            loss = loss + ops.sum(self.losses)
        return loss

    def get_config(self):
        config = super().get_config()
        config["calibration"] = dict(self.calibration)
        return config
