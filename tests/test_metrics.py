"""Metrics against values worked out by hand."""

import json
import math

import numpy as np
import pytest

from cpl_keras import metrics
from cpl_keras.camera import PARAMETERS


def test_mae_and_nmae_by_hand():
    y = [1.0, 2.0, 3.0, 6.0]
    y_hat = [2.0, 2.0, 1.0, 6.0]          # |errors| = 1, 0, 2, 0
    assert metrics.mae(y, y_hat) == pytest.approx(0.75)
    assert metrics.nmae(y, y_hat) == pytest.approx(0.75 / 3.0)        # mean|y| = 3
    assert metrics.nmae_signed(y, y_hat) == pytest.approx(0.75 / 3.0)


def test_signed_mean_gives_negative_nmae():
    y = [-4.0, -2.0, 2.0]
    y_hat = [-3.0, -2.0, 0.0]             # |errors| = 1, 0, 2 -> MAE 1
    assert metrics.mae(y, y_hat) == pytest.approx(1.0)
    assert metrics.nmae(y, y_hat) == pytest.approx(1.0 / (8.0 / 3.0))   # 0.375
    assert metrics.nmae_signed(y, y_hat) == pytest.approx(1.0 / (-4.0 / 3.0))  # -0.75
    assert metrics.nmae_signed(y, y_hat) < 0


def test_zero_denominator_is_undefined_not_inf():
    y = [-1.0, 1.0]                        # signed mean 0, mean|y| = 1
    y_hat = [0.0, 0.0]
    assert metrics.nmae(y, y_hat) == pytest.approx(1.0)
    assert math.isnan(metrics.nmae_signed(y, y_hat))
    zeros = [0.0, 0.0, 0.0]                # both denominators 0 (e.g. pitch = 0)
    assert metrics.mae(zeros, [1.0, -1.0, 0.0]) == pytest.approx(2.0 / 3.0)
    assert math.isnan(metrics.nmae(zeros, [1.0, -1.0, 0.0]))
    assert math.isnan(metrics.nmae_signed(zeros, [1.0, -1.0, 0.0]))
    # float64 cancellation of a mean that is exactly zero counts as zero
    assert math.isnan(metrics.nmae_signed([0.1, 0.2, -0.3], [0.0, 0.0, 0.0]))


def test_undefined_values_in_json_and_tables():
    assert metrics.json_value(math.nan) is None
    assert metrics.json_value(math.inf) is None
    assert metrics.json_value(np.float32(0.5)) == 0.5
    assert metrics.format_value(math.nan) == "n/a"
    assert metrics.format_value(None) == "n/a"
    assert metrics.format_value(-0.12345) == "-0.123"
    assert json.dumps({"x": metrics.json_value(math.nan)}) == '{"x": null}'


def test_fov_threshold_curve_by_hand():
    width = 100.0
    fx_true = np.full(5, 50.0)             # fov = 2 atan(100 / 100) = 90 degrees
    fov_pred = np.array([90.0, 90.5, 91.5, 93.6, 120.0])   # errors 0, .5, 1.5, 3.6, 30
    fx_pred = (width / 2.0) / np.tan(np.radians(fov_pred) / 2.0)
    errors = metrics.fov_errors_deg(fx_true, fx_pred, width)
    np.testing.assert_allclose(errors, [0.0, 0.5, 1.5, 3.6, 30.0], atol=1e-9)
    curve = metrics.fov_threshold_curve(fx_true, fx_pred, width)
    np.testing.assert_allclose(curve, [20.0, 40.0, 60.0, 60.0, 80.0, 80.0])


def test_percent_within_handles_nonfinite_and_empty():
    np.testing.assert_allclose(metrics.percent_within([0.5, np.nan], (1,)), [50.0])
    assert np.isnan(metrics.percent_within([], (0, 1))).all()


def test_parameter_metrics_and_bad_input():
    truth = {name: np.array([1.0, -3.0]) for name in PARAMETERS}
    pred = {name: np.array([2.0, -3.0]) for name in PARAMETERS}
    table = metrics.parameter_metrics(truth, pred)
    assert set(table) == set(PARAMETERS)
    row = table["pitch"]
    assert row["mae"] == pytest.approx(0.5)
    assert row["nmae"] == pytest.approx(0.25)            # mean|y| = 2
    assert row["nmae_signed"] == pytest.approx(-0.5)     # mean y = -1
    with pytest.raises(ValueError, match="differ in length"):
        metrics.mae([1.0, 2.0], [1.0])
    with pytest.raises(ValueError, match="'fx'"):
        metrics.parameter_metrics({}, pred)


def test_focal_metrics_by_hand():
    """Relative focal error, FoV error and its AUC on values worked out here:
    width 100 px, fx* = 50 px (hFoV 90 deg); predictions 50, 55, 40, 100."""
    import math

    from cpl_keras import metrics

    true = np.full(4, 50.0)
    pred = np.array([50.0, 55.0, 40.0, 100.0])
    m = metrics.focal_metrics(true, pred, true, pred * 2, 100, 100)
    assert m["relative_fx_median"] == pytest.approx(np.median([0, 0.1, 0.2, 1.0]))
    fov = [2 * math.degrees(math.atan(50 / f)) for f in pred]          # 90, 84.29, 102.68, 53.13
    errors = np.abs(np.array(fov) - 90.0)
    assert m["hfov_error_deg_median"] == pytest.approx(np.median(errors))
    # AUC@5: mean(max(0, 1 - e/5)): only the exact pair and none of the others
    assert m["hfov_auc_5deg"] == pytest.approx(np.mean(np.maximum(0, 1 - errors / 5)))
    assert m["hfov_auc_1deg"] == pytest.approx(0.25)                   # the exact pair only
    assert m["hfov_auc_10deg"] == pytest.approx(np.mean(np.maximum(0, 1 - errors / 10)))
    assert 0.25 < m["hfov_auc_10deg"] < 0.5
    # fy predicted at twice fx's prediction: relative errors 1, 1.2, 0.6, 3
    assert m["relative_fy_median"] == pytest.approx(np.median([1.0, 1.2, 0.6, 3.0]))
    assert metrics.auc([], 5) != metrics.auc([], 5)                    # nan when empty
    assert metrics.auc([np.inf, 0.0], 5) == pytest.approx(0.5)
