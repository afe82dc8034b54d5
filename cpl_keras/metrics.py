"""Evaluation metrics, per camera parameter (numpy only).

* ``mae``: mean absolute error.
* ``nmae``: normalised MAE as the paper's Eq. (NMAE) defines it,
  ``MAE / mean(|y|)``.
* ``nmae_signed``: ``MAE / mean(y)`` with the *signed* mean of the truth. This
  is what produced the paper's Table 1 (see REPRODUCTION_NOTES.md), which is why
  the paper shows negative NMAE for b, d, tx, tz and pitch.
* ``fov_threshold_curve``: the percentage of samples whose horizontal field of
  view (from fx and the image width, ``camera.fov_from_focal``) is within k
  degrees of the truth, for k = 0..5 (the release's FOV-threshold curve).

A metric whose denominator is zero is *undefined*: it is ``nan`` here,
``None`` in JSON (``json_value``) and ``"n/a"`` in tables (``format_value``);
never ``inf`` and never an exception. A denominator counts as zero when it is
exactly zero or when cancellation has left it below ``1e-12 * mean(|y|)``
(float64 round-off of a mean that is zero in exact arithmetic).
"""

from __future__ import annotations

import math

import numpy as np

from cpl_keras.camera import PARAMETERS, fov_from_focal

#: Thresholds (degrees) of the FOV-threshold curve.
FOV_THRESHOLDS_DEG = (0, 1, 2, 3, 4, 5)

#: Relative size below which a mean counts as a zero denominator.
ZERO_RELATIVE = 1e-12


def _pair(y_true, y_pred):
    y_true = np.asarray(y_true, dtype=np.float64).reshape(-1)
    y_pred = np.asarray(y_pred, dtype=np.float64).reshape(-1)
    if y_true.shape != y_pred.shape:
        raise ValueError(
            f"truth and prediction differ in length: {y_true.size} vs {y_pred.size}"
        )
    return y_true, y_pred


def _safe_ratio(numerator, denominator, scale):
    """``numerator / denominator``, or nan when the denominator is (numerically) zero."""
    if not (math.isfinite(numerator) and math.isfinite(denominator)):
        return math.nan
    if denominator == 0.0 or abs(denominator) <= ZERO_RELATIVE * scale:
        return math.nan
    return numerator / denominator


def mae(y_true, y_pred):
    """Mean absolute error; nan for empty input."""
    y_true, y_pred = _pair(y_true, y_pred)
    if y_true.size == 0:
        return math.nan
    return float(np.mean(np.abs(y_pred - y_true)))


def nmae(y_true, y_pred):
    """The paper's Eq. (NMAE): ``MAE(y, y_hat) / mean(|y|)`` (nan if mean(|y|) = 0)."""
    y_true, y_pred = _pair(y_true, y_pred)
    if y_true.size == 0:
        return math.nan
    scale = float(np.mean(np.abs(y_true)))
    return _safe_ratio(mae(y_true, y_pred), scale, scale)


def nmae_signed(y_true, y_pred):
    """``MAE / mean(y)`` with the signed mean: the convention behind the paper's
    Table 1 (negative when the truth is mostly negative; nan if mean(y) = 0)."""
    y_true, y_pred = _pair(y_true, y_pred)
    if y_true.size == 0:
        return math.nan
    scale = float(np.mean(np.abs(y_true)))
    return _safe_ratio(mae(y_true, y_pred), float(np.mean(y_true)), scale)


def fov_errors_deg(fx_true, fx_pred, width):
    """Absolute horizontal field-of-view error in degrees, per sample."""
    fx_true, fx_pred = _pair(fx_true, fx_pred)
    fov_true = np.degrees(fov_from_focal(fx_true, width))
    fov_pred = np.degrees(fov_from_focal(fx_pred, width))
    return np.abs(fov_pred - fov_true)


def percent_within(errors_deg, thresholds=FOV_THRESHOLDS_DEG):
    """Percentage of errors ``<= k`` for each threshold ``k`` (nan when empty).

    Non-finite errors count as outside every threshold.
    """
    errors = np.asarray(errors_deg, dtype=np.float64).reshape(-1)
    if errors.size == 0:
        return np.full(len(thresholds), np.nan)
    finite = np.where(np.isfinite(errors), errors, np.inf)
    return np.array([100.0 * np.mean(finite <= k) for k in thresholds])


#: Thresholds (degrees) of the field-of-view error's AUC (GeoCalib, AnyCalib).
AUC_THRESHOLDS_DEG = (1, 5, 10)


def auc(errors, threshold):
    """Area under the cumulative error curve up to ``threshold``, normalised to
    [0, 1]: ``(1/t) * integral_0^t P(error <= x) dx = mean(max(0, 1 - e/t))``
    (non-finite errors count as beyond every threshold); nan when empty."""
    errors = np.asarray(errors, dtype=np.float64).reshape(-1)
    if errors.size == 0:
        return math.nan
    errors = np.where(np.isfinite(errors), errors, np.inf)
    return float(np.mean(np.maximum(0.0, 1.0 - errors / float(threshold))))


def focal_metrics(fx_true, fx_pred, fy_true, fy_pred, width, height):
    """The metrics calibration papers report beside NMAE, over the pairs given:
    median relative focal error ``|f - f*| / f*`` along u and v, median
    absolute horizontal and vertical field-of-view error (degrees, fx across
    ``width``, fy across ``height`` pixels), and the AUC of each FoV error at
    ``AUC_THRESHOLDS_DEG`` (a dict of plain floats; nan when empty)."""
    fx_true, fx_pred = _pair(fx_true, fx_pred)
    fy_true, fy_pred = _pair(fy_true, fy_pred)
    result = {}
    for axis, true, pred, size in (("h", fx_true, fx_pred, width), ("v", fy_true, fy_pred, height)):
        relative = np.abs(pred - true) / np.abs(true)
        errors = fov_errors_deg(true, pred, size)
        focal = "fx" if axis == "h" else "fy"
        result[f"relative_{focal}_median"] = float(np.median(relative)) if relative.size else math.nan
        result[f"{axis}fov_error_deg_median"] = float(np.median(errors)) if errors.size else math.nan
        for t in AUC_THRESHOLDS_DEG:
            result[f"{axis}fov_auc_{t}deg"] = auc(errors, t)
    return result


def fov_threshold_curve(fx_true, fx_pred, width, thresholds=FOV_THRESHOLDS_DEG):
    """Percentage of samples with ``|fov_pred - fov_true| <= k`` degrees, k in
    ``thresholds``; the fov is computed from fx across ``width`` pixels."""
    return percent_within(fov_errors_deg(fx_true, fx_pred, width), thresholds)


def parameter_metrics(truth, predictions, names=PARAMETERS):
    """``{name: {"mae", "nmae", "nmae_signed", "mean_abs", "mean"}}`` for ``names``.

    ``truth`` and ``predictions`` map a parameter name to a 1-D array.
    """
    out = {}
    for name in names:
        if name not in truth:
            raise ValueError(f"truth has no values for '{name}'")
        if name not in predictions:
            raise ValueError(f"predictions have no values for '{name}'")
        y_true, y_pred = _pair(truth[name], predictions[name])
        out[name] = {
            "mae": mae(y_true, y_pred),
            "nmae": nmae(y_true, y_pred),
            "nmae_signed": nmae_signed(y_true, y_pred),
            "mean_abs": float(np.mean(np.abs(y_true))) if y_true.size else math.nan,
            "mean": float(np.mean(y_true)) if y_true.size else math.nan,
        }
    return out


def json_value(x):
    """A float for JSON: ``None`` where the value is undefined (nan or inf)."""
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def jsonable(value):
    """``value`` (dicts, lists, numpy scalars and arrays) as plain JSON types,
    every float through ``json_value`` (undefined: ``None``)."""
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return json_value(value)
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist())
    return value


def format_value(x, decimals=3):
    """A table cell: ``x`` to ``decimals`` places, ``"n/a"`` where undefined."""
    if x is None:
        return "n/a"
    x = float(x)
    if not math.isfinite(x):
        return "n/a"
    return f"{x:.{decimals}f}"
