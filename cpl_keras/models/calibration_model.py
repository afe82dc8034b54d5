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
  paper writes it); see ``cpl_keras.models.losses``.
* ``"euclidean"``: Deep-Homo's Euclidean distance between the 13-vectors.
"""

from __future__ import annotations

import keras
import numpy as np
from keras import ops

from cpl_keras import camera
from cpl_keras.models import losses
from cpl_keras.layers import PACKAGE
from cpl_keras.models.options import ModelOptions
from cpl_keras.models.variants import LOSS_MODES, LOSSES
#: The log-variance floor before ``initialise_adaptive_weights``: none.
NO_FLOOR = -1e4


def saved_options(settings):
    """The ``ModelOptions`` of a model's ``build_settings``: the record it
    was built with, read with what a model saved before a setting existed
    was built with where that is not the record's default (the one place
    that says so): one divisor floor ``epsilon`` before per-quantity floors,
    Eq. 9's weights moving at rate 1 before the alpha rate; the keys beside
    the record (``image_size``, ``loss``, ...) left out."""
    settings = dict(settings)
    if "floors" not in settings:
        epsilon = float(settings.get("epsilon", camera.EPSILON))
        settings["floors"] = {key: epsilon for key in camera.FLOORS}
    if LOSSES[settings["loss"]].adaptive:
        settings.setdefault("alpha_rate", 1.0)
    for name in ("disparity_ceiling", "disparity_start", "range_scales"):
        settings.setdefault(name, None)  # (a built model's "auto" is resolved: None is left out)
    return ModelOptions.from_config(settings)


@keras.saving.register_keras_serializable(package=PACKAGE)
class CalibrationModel(keras.Model):
    """A functional model with the 13 calibration outputs and its own loss.

    Args:
        *args, **kwargs: as for a functional ``keras.Model`` (inputs, outputs).
        build_settings: the model's ``ModelOptions`` resolved for its
            variant (``to_config()``) with ``image_size`` and ``loss`` (a
            LOSS_MODE) beside it, kept in the model's config under that
            name; read as ``options`` (``saved_options``: a model saved by
            an earlier version reads with what it was built with).
        calibration: the same dict under its former name, as models saved
            before the rename hold it in their config (read, never written).
    """

    def __init__(self, *args, build_settings=None, calibration=None, **kwargs):
        super().__init__(*args, **kwargs)
        if build_settings is not None and calibration is not None:
            raise ValueError("give build_settings or the former calibration, not both")
        self.build_settings = dict(build_settings or calibration or {"loss": "mae"})
        if self.build_settings["loss"] not in LOSS_MODES:
            raise ValueError(f"unknown loss mode {self.build_settings['loss']!r}")
        self.options = saved_options(self.build_settings)
        if self.training_loss.adaptive:
            # s_i of Eq. 9 (alpha_i = exp(-s_i)), one per disentangled term,
            # stored divided by the alpha rate (``log_variance_values``), and
            # their floors (set with the starting values, see
            # ``initialise_adaptive_weights``; until then no floor).
            # (an alpha rate of 0: the weights frozen at their first-batch
            # balance, Eq. 9 as a fixed range normalisation)
            self.log_variances = self.add_weight(
                shape=(len(camera.TARGETS),), initializer="zeros",
                name="log_variances", trainable=self.alpha_rate > 0,
            )
            self.log_variance_floor = self.add_weight(
                shape=(len(camera.TARGETS),),
                initializer=keras.initializers.Constant(NO_FLOOR),
                name="log_variance_floor", trainable=False,
            )
            if self.range_scales is not None:
                # Eq. 9 read as a fixed range normalisation: alpha_i = 1 / mean|y_i|
                # of the training split (``ModelOptions.adaptive_weights``)
                self.log_variances.assign(np.log(np.asarray(
                    [self.range_scales[name] for name in camera.TARGETS], "float32")))

    @property
    def loss_mode(self):
        """The name of its training loss (``LOSS_MODES``)."""
        return self.build_settings["loss"]

    @property
    def training_loss(self):
        """Its training loss (``variants.Loss``)."""
        return LOSSES[self.build_settings["loss"]]

    @property
    def alpha_rate(self):
        """How fast Eq. 9's weights move: ``s_i = alpha_rate * w_i`` with
        ``w_i`` the trained variable, so Adam, whose step is about the
        learning rate whatever the gradient's scale, moves ``log alpha_i``
        ``alpha_rate`` times as fast as an ordinary weight. 1 is Eq. 9
        trained like every other weight (models saved before the rate
        existed); see ``variants.ALPHA_RATE``. 0: the weights do not move
        at all after ``initialise_adaptive_weights`` (``s_i = w_i``, not
        trained): Eq. 9 as a fixed normalisation of the terms' ranges."""
        return float(self.options.alpha_rate or 0.0)

    @property
    def range_scales(self):
        """mean|y_i| per target where Eq. 9's weights are fixed at
        1 / mean|y_i| (``adaptive_weights="range"``), else None."""
        scales = self.options.range_scales
        return None if scales is None else dict(scales)

    def _scale(self):
        """``s_i / w_i``: the alpha rate, or 1 for frozen weights (rate 0)."""
        return self.alpha_rate or 1.0

    def log_variance_values(self):
        """The tensor of Eq. 9's s_i (alpha_i = exp(-s_i)), in TARGETS order."""
        return self._scale() * self.log_variances.value

    def adaptive_weights(self):
        """The learned alpha_i of Eq. 9 by target name (None for other modes)."""
        if not self.training_loss.adaptive:
            return None
        alphas = ops.convert_to_numpy(ops.exp(-self.log_variance_values()))
        return {name: float(a) for name, a in zip(camera.TARGETS, alphas)}

    @property
    def floors(self):
        """The camera graph's divisor floors (``camera.FLOORS`` keys)."""
        return dict(self.options.floors)

    def projection_terms(self, y, y_pred):
        """The 13 disentangled terms of Eq. 7 for targets ``y`` (dict), with
        the point errors the model was built with (``losses.POINT_ERRORS``)."""
        return losses.projection_terms(y, self._as_dict(y_pred), self.floors,
                                       self.options.point_errors)

    def initialise_adaptive_weights(self, y):
        """Start Eq. 9's weights balanced at the Average baseline's level.

        ``y`` is a batch of targets (dict by name). Each term L_i is computed
        with every target predicted as its mean over the batch (what the
        Average baseline does), plus the term of a 1% error in every target
        (so that a target that is constant in the data, such as u0 in the
        cvgl protocol, whose Average term is 0, still has a scale), and
        ``s_i = log L_i`` (alpha_i = 1 / L_i): every weighted term starts
        near 1 where a network has learned nothing;
        the floor ``log(losses.ADAPTIVE_WEIGHT_RANGE)`` below it lets alpha_i
        grow until its term is that many times better than Average. (The
        untrained network's own terms are no measure: a disparity head near 0
        puts X at fx b / d, millions of metres.) A no-op for other loss
        modes. Returns the alphas.
        """
        if not self.training_loss.adaptive:
            return None
        if self.range_scales is not None:
            return self.adaptive_weights()  # (fixed from the training split)
        y = {name: ops.convert_to_tensor(np.asarray(y[name], "float32")) for name in camera.TARGETS}
        average = {name: ops.broadcast_to(ops.mean(v, axis=0, keepdims=True), ops.shape(v))
                   for name, v in y.items()}
        one_percent = {name: v * 1.01 for name, v in y.items()}
        terms = [a + b for a, b in zip(self.projection_terms(y, average),
                                       self.projection_terms(y, one_percent))]
        start, floor = losses.initial_log_variances(
            [float(ops.convert_to_numpy(t)) for t in terms]
        )
        self.log_variances.assign(start / self._scale())
        self.log_variance_floor.assign(floor)
        return self.adaptive_weights()

    def _as_dict(self, y_pred):
        if isinstance(y_pred, dict):
            return y_pred
        return dict(zip(self.output_names, y_pred))

    def compute_loss(self, x=None, y=None, y_pred=None, sample_weight=None, training=True):
        kind = self.training_loss
        if kind.per_output:
            return super().compute_loss(x, y, y_pred, sample_weight, training)
        if sample_weight is not None:
            raise ValueError(
                f"the {kind.name} loss couples all 13 outputs and takes no sample_weight; "
                "pass none (or train with the 'mae' loss)"
            )
        y_pred = self._as_dict(y_pred)
        if not kind.projection:
            loss = losses.euclidean_loss(y, y_pred)
        elif kind.adaptive:
            loss = losses.adaptive_projection_loss(
                self.projection_terms(y, y_pred), self.log_variance_values(),
                self.log_variance_floor)
        else:
            loss = losses.uniform_projection_loss(self.projection_terms(y, y_pred))
        if self.losses:
            loss = loss + ops.sum(self.losses)
        return loss

    def get_config(self):
        config = super().get_config()
        config["build_settings"] = dict(self.build_settings)
        return config
