"""``ModelOptions``: every knob of a network and its objective, in one record.

As a keras-hub backbone carries every argument in one ``get_config()``, a
model here is one frozen ``ModelOptions``: the towers, the heads, the loss
and its weights (the optimiser's knobs are training's,
``training_options.TrainingOptions``, as keras-hub keeps them in
``compile()``). The record is checked once, when it is made;
``for_variant`` adds the rules that depend on the variant, records the
variant and fills in the defaults (the paper's, or the release's with
``as_released``) and what the variant's network does with each switch (a
switch its network has no use for is recorded as off: Deep-Homo's pitch
head is not bounded); ``for_training_set`` fills in what is read off the
training labels (the disparity head's ceiling and start, the range weights).
``to_config()`` is config.json's ``build`` (with the image size and seed
beside it, the variant above it) and a built model's ``build_settings``
(with its image size and loss beside it); ``from_config`` reads either
back: a field whose value is its default is left out of the config, so the
runs made before it existed resume and load as they were.

A new switch is one field here (with its check in ``_check``) and one
argparse line in ``cpl_keras/commands/train.py`` (docs/layout.md).

Imports no Keras: the command lines and planning check a record before
Keras is loaded.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import re

import numpy as np

from cpl_keras import camera
from cpl_keras.errors import Error
from cpl_keras.models import variants
from cpl_keras.models.variants import (
    ALPHA_RATE, BACKBONES, DISENTANGLE, HEAD_ACTIVATIONS, POINT_ERRORS,
)

#: The disparity head: "default" as the paper writes each variant (the CPL
#: variants' d = exp(z) up to a ceiling, MTL-Baseline's linear) or "softplus",
#: d = floor + softplus(z) up to the ceiling, starting at the training mean,
#: for every MTL variant alike (``layers.SoftplusDisparity``).
DISPARITY_HEADS = ("default", "softplus")
#: MTL-CPL-A's weights alpha_i of Eq. 9: "learned" (the paper's, with the
#: log-variance form of ``models.losses``) or "range", fixed at
#: 1 / mean|y_i| of the training split (Eq. 9 read as the range normalisation
#: it is given for; the paper's NMAE denominators).
ADAPTIVE_WEIGHTS = ("learned", "range")
#: The fields always written to config.json's ``build`` (those of the first
#: runs); every other field is written only where it is not its default.
ALWAYS_WRITTEN = ("backbone", "as_released", "floors", "bounded_pitch_head",
                  "positive_focal_head", "disentangle", "disparity_ceiling")
#: The backbones whose towers can start from ImageNet weights
#: (``backbone_weights``): InceptionV3's, the paper's.
PRETRAINED_BACKBONES = ("inception_v3",)


class OptionsError(Error):
    """A bad option (one-line message naming it)."""


@dataclasses.dataclass(frozen=True)
class ModelOptions:
    """The knobs of one network (every default is the paper's).

    variant: the network's variant (``variants.VARIANTS``), set by
        ``for_variant`` (None: not yet resolved for one).
    backbone: the towers (``variants.BACKBONES``; ``"inception_v3"`` is the
        paper's). as_released: the released code's choices where it differs
        from the paper's text (``factory``'s module docstring).
    floors: the camera graph's divisor floors (None: ``camera.FLOORS``, as
        released ``camera.RELEASED_FLOORS``).
    bounded_pitch_head, positive_focal_head: pitch clipped to +-pi/2, fx, fy
        clipped at the focal floor (None: True, as released False).
    disentangle: "exact" or "partial" (``models.losses``). point_errors:
        "metres" or "relative" (an ablation). alpha_rate: how fast
        MTL-CPL-A's weights move (None: ``variants.ALPHA_RATE``).
    disparity_ceiling: the positive disparity head's largest output in px
        ("auto", the default: twice the largest training label, set by
        ``for_training_set``, or ``layers.MAX_OUTPUT`` without training
        labels; None: ``layers.MAX_OUTPUT``).
    exp_disparity_head: MTL-Baseline with the CPL variants' exp head (an
        ablation). head_activation: the heads' hidden activation
        (``variants.HEAD_ACTIVATIONS``).
    head_norm: a LayerNorm of the towers' features before the heads.
    disparity_head: ``DISPARITY_HEADS``; disparity_start: the softplus
        head's first output in px ("auto", the default: the training mean, or
        as None without training labels; None: its floor plus log 2).
    adaptive_weights: ``ADAPTIVE_WEIGHTS``; range_scales: mean|y_i| per
        target for "range" ("auto", the default: from the training split).
    backbone_weights: the towers' initial weights: None, random
        initialisation (this project's default, by necessity: the paper's
        are ImageNet's); "imagenet", Keras's InceptionV3 ImageNet file
        (cached or downloaded); or the path of such a file
        (``models.pretrained``). backbone_weights_sha256: that file's
        checksum (set by planning, recorded in config.json; a build from
        the file checks it).
    """

    variant: str | None = None
    backbone: str = "inception_v3"
    as_released: bool = False
    floors: dict | None = None
    bounded_pitch_head: bool | None = None
    positive_focal_head: bool | None = None
    disentangle: str = "exact"
    point_errors: str = "metres"
    alpha_rate: float | None = None
    disparity_ceiling: float | str | None = "auto"
    exp_disparity_head: bool = False
    head_activation: str = "relu"
    head_norm: bool = False
    disparity_head: str = "default"
    disparity_start: float | str | None = "auto"
    adaptive_weights: str = "learned"
    range_scales: dict | str | None = "auto"
    backbone_weights: str | None = None
    backbone_weights_sha256: str | None = None

    def __post_init__(self):
        _check(self)

    # -- making and reading ------------------------------------------------
    @classmethod
    def from_config(cls, config):
        """The record of a config dict (config.json's ``build``; keys that
        are not fields, the image size and seed, are left to the caller)."""
        names = {field.name for field in dataclasses.fields(cls)}
        return cls(**{key: value for key, value in config.items() if key in names})

    def replace(self, **fields):
        """A checked copy with ``fields`` changed (OptionsError naming an
        unknown one)."""
        unknown = sorted(set(fields) - {field.name for field in dataclasses.fields(self)})
        if unknown:
            raise OptionsError(f"unknown model option {unknown[0]!r}")
        return dataclasses.replace(self, **fields)

    def to_config(self):
        """config.json's ``build`` fields: the first runs' fields always, the
        others where they are not their defaults (so old runs compare equal)."""
        config = {}
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if field.name in ALWAYS_WRITTEN or (value != field.default and value is not None):
                config[field.name] = dict(value) if isinstance(value, dict) else value
        return config

    # -- resolving ---------------------------------------------------------
    def for_variant(self, variant):
        """This record for ``variant``: its rules checked (OptionsError, one
        line), the variant recorded, the defaults that depend on it filled
        in, and each switch as the variant's network uses it (``_as_built``).
        A record resolved for ``variant`` comes back unchanged."""
        if self.variant not in (None, variant):
            raise OptionsError(f"these options are {self.variant}'s, not {variant}'s")
        spec = variants.get(variant)
        loss = spec.training_loss(self.as_released)
        deep_homo = spec.builder == "deep_homo"
        if self.exp_disparity_head and spec.builder != "direct":
            raise OptionsError(f"an exp disparity head is MTL-Baseline's ablation; {variant} "
                               f"has its own disparity head")
        for name, on in (("head activation " + repr(self.head_activation),
                          self.head_activation != "relu"),
                         ("head norm", self.head_norm),
                         ("disparity head " + repr(self.disparity_head),
                          self.disparity_head != "default")):
            if on and deep_homo:
                raise OptionsError(f"{name} applies to the regression heads; {variant} has "
                                   f"its own")
        if self.backbone_weights is not None and deep_homo:
            raise OptionsError(f"backbone weights start the two towers; {variant} has no "
                               f"towers")
        if self.point_errors != "metres" and not loss.projection:
            raise OptionsError(f"point errors {self.point_errors!r} apply to the camera "
                               f"projection loss, which {variant} does not train with")
        if self.adaptive_weights != "learned" and not loss.adaptive:
            raise OptionsError(f"adaptive weights {self.adaptive_weights!r} apply to Eq. 9's "
                               f"weights, which {variant} does not train with")
        if self.adaptive_weights == "range" and self.alpha_rate not in (None, 0):
            raise OptionsError("range weights are fixed; give no alpha rate with them")
        floors = self.floors
        if floors is None:
            floors = camera.RELEASED_FLOORS if self.as_released else camera.FLOORS
        alpha_rate = None
        if loss.adaptive:
            alpha_rate = 0.0 if self.adaptive_weights == "range" else float(
                ALPHA_RATE if self.alpha_rate is None else self.alpha_rate)
        positive = self.positive_disparity_head(variant)
        bounded, focal = (
            (not self.as_released) if given is None else bool(given)
            for given in (self.bounded_pitch_head, self.positive_focal_head))
        return dataclasses.replace(
            self, variant=variant, floors=dict(floors), alpha_rate=alpha_rate,
            disparity_ceiling=self.disparity_ceiling if positive else None,
            disparity_start=self.disparity_start if self.disparity_head == "softplus" else None,
            range_scales=self.range_scales if self.adaptive_weights == "range" else None,
            **_as_built(spec, loss, bounded, focal, self.disentangle),
        )

    @property
    def spec(self):
        """The variant's spec (``variants.get``) of a record resolved for one
        (OptionsError before ``for_variant``)."""
        if self.variant is None:
            raise OptionsError("these options are not resolved for a variant (for_variant)")
        return variants.get(self.variant)

    def positive_disparity_head(self, variant):
        """Whether ``variant``'s disparity head is a positive one with a
        ceiling (the CPL variants' exp head as the paper writes them,
        MTL-Baseline's with ``exp_disparity_head``, or the softplus head)."""
        spec = variants.get(variant)
        if self.as_released or spec.builder == "deep_homo":
            return False
        return (spec.training_loss(self.as_released).projection or self.exp_disparity_head
                or self.disparity_head == "softplus")

    def for_training_set(self, labels, ceiling_factor):
        """This (``for_variant``) record with its "auto" fields read off the
        training split's targets ``labels`` (name -> array): the disparity
        ceiling (``ceiling_factor`` times the largest label), the softplus
        head's start (the mean) and the range weights' scales (mean|y_i|)."""
        fields = {}
        if self.disparity_ceiling == "auto":
            fields["disparity_ceiling"] = round(
                ceiling_factor * float(np.max(labels["disparity"])), 3)
        if self.disparity_start == "auto":
            fields["disparity_start"] = round(float(np.mean(labels["disparity"])), 3)
        if self.range_scales == "auto":
            fields["range_scales"] = {
                name: float(f"{max(float(np.mean(np.abs(labels[name]))), 1e-6):.6g}")
                for name in camera.TARGETS}
        return dataclasses.replace(self, **fields)


def _as_built(spec, loss, bounded, focal, disentangle):
    """The switches the variant's network has a use for, as given; the
    others off, as its network is built (``factory._build``): Deep-Homo
    regresses its pitch unbounded; only the camera projection loss's
    variants (with the camera graph) have the focal floor and disentangle
    their terms."""
    return dict(bounded_pitch_head=bounded and spec.builder != "deep_homo",
                positive_focal_head=focal and loss.projection and spec.camera_graph,
                disentangle=disentangle if loss.projection else None)


def check_momentum(value, error=ValueError):
    """The rule of the weights' moving-average momentum, written once (the
    optimiser's, training's and the presets'): a number in [0, 1) (0: off).
    Returns it as a float; raises ``error`` (one line) otherwise."""
    if not (_number(value, 0) and value < 1):
        raise error(f"the weights' moving-average momentum must be in [0, 1), got {value!r}")
    return float(value)


def _check(options):
    """Every rule of one record that needs no variant (OptionsError, one line)."""
    if options.variant is not None:
        _choice("variant", options.variant, variants.VARIANTS)
    _choice("backbone", options.backbone, BACKBONES)
    if options.disentangle is not None:  # (None: a variant without the projection loss)
        _choice("disentangle", options.disentangle, DISENTANGLE)
    _choice("point errors", options.point_errors, POINT_ERRORS)
    _choice("head activation", options.head_activation, HEAD_ACTIVATIONS)
    _choice("disparity head", options.disparity_head, DISPARITY_HEADS)
    _choice("adaptive weights", options.adaptive_weights, ADAPTIVE_WEIGHTS)
    for name in ("as_released", "exp_disparity_head", "head_norm"):
        if not isinstance(getattr(options, name), bool):
            raise OptionsError(f"{name.replace('_', ' ')} must be true or false, "
                               f"got {getattr(options, name)!r}")
    for name in ("bounded_pitch_head", "positive_focal_head"):
        if getattr(options, name) not in (None, True, False):
            raise OptionsError(f"{name.replace('_', ' ')} must be true, false or None, "
                               f"got {getattr(options, name)!r}")
    if options.floors is not None:
        try:
            camera.check_floors(options.floors)
        except ValueError as error:
            raise OptionsError(str(error)) from None
    if options.alpha_rate is not None and not _number(options.alpha_rate, 0):
        raise OptionsError(f"alpha rate must be a number >= 0 (0: frozen), "
                           f"got {options.alpha_rate!r}")
    floor = camera.FLOORS["disparity"]
    if options.disparity_ceiling not in (None, "auto") and not (
            _number(options.disparity_ceiling, floor) and options.disparity_ceiling > floor):
        raise OptionsError(f"disparity ceiling must be 'auto', None or a number of pixels "
                           f"above {floor:g}, got {options.disparity_ceiling!r}")
    if options.disparity_start not in (None, "auto") and not (
            _number(options.disparity_start, floor) and options.disparity_start > floor):
        raise OptionsError(f"disparity start must be 'auto', None or a number of pixels "
                           f"above {floor:g}, got {options.disparity_start!r}")
    scales = options.range_scales
    if scales not in (None, "auto") and not (
            isinstance(scales, dict) and set(scales) == set(camera.TARGETS)
            and all(_number(v, 0) and v > 0 for v in scales.values())):
        raise OptionsError("range scales must be 'auto', None or a positive number for each "
                           f"of {', '.join(camera.TARGETS)}")
    _check_backbone_weights(options)


def _check_backbone_weights(options):
    """The rules of ``backbone_weights`` and its checksum (OptionsError)."""
    weights, checksum = options.backbone_weights, options.backbone_weights_sha256
    if weights is not None:
        if not (isinstance(weights, str) and weights.strip()):
            raise OptionsError(f"backbone weights must be 'imagenet' or a weights file's path, "
                               f"got {weights!r}")
        if options.backbone not in PRETRAINED_BACKBONES:
            raise OptionsError(f"backbone weights are ImageNet's InceptionV3 weights; backbone "
                               f"{options.backbone!r} has none (use backbone "
                               f"{PRETRAINED_BACKBONES[0]})")
    if checksum is not None and not (
            weights is not None and isinstance(checksum, str)
            and re.fullmatch("[0-9a-f]{64}", checksum)):
        raise OptionsError(f"backbone weights' sha256 must be 64 lowercase hex digits, beside "
                           f"backbone weights; got {checksum!r}")


def _choice(what, value, choices):
    if value not in choices:
        raise OptionsError(f"unknown {what} {value!r}; choose one of {', '.join(choices)}")


def _number(value, least):
    """A finite real number >= ``least`` (not a bool)."""
    return (not isinstance(value, bool) and isinstance(value, numbers.Real)
            and math.isfinite(value) and value >= least)
