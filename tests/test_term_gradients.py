"""Each loss term's gradient at the towers' shared features
(cpl_keras.training.gradients, train.py --term-gradients) and each head's
live units (cpl_keras.training.head_units, train.py --head-units)."""

import csv
import math
import os

import numpy as np
import pytest

from helpers import SIZE, batch

TARGETS = ("fx", "fy", "u0", "v0", "baseline", "disparity", "tx", "ty", "tz", "pitch",
           "X", "Y", "Z")
HEADS = TARGETS[:10]


def test_a_term_gradient_scales_with_its_eq9_weight_alone():
    """Doubling one alpha_i of Eq. 9 doubles that term's gradient at the
    features and leaves every other term's as it was; the features'
    gradient of a term agrees with a finite difference along it."""
    import jax

    from cpl_keras.models.factory import build_model
    from cpl_keras.training.gradients import TermGradients, weighted_terms

    x, y = batch(8)
    model = build_model("cpl-a", backbone="small", image_size=SIZE, seed=0)
    model.initialise_adaptive_weights(y)
    gradients = TermGradients(model)
    before = gradients(x, y)
    assert set(before) == {f"grad_{name}" for name in TARGETS}
    assert all(math.isfinite(v) and v >= 0 for v in before.values())
    s = np.array(model.log_variances.value)
    i = TARGETS.index("disparity")
    s[i] -= np.log(2.0) / model.alpha_rate  # alpha_disparity doubled
    model.log_variances.assign(s)
    after = gradients(x, y)
    for name in TARGETS:
        factor = 2.0 if name == "disparity" else 1.0
        assert after[f"grad_{name}"] == pytest.approx(factor * before[f"grad_{name}"],
                                                      rel=1e-4, abs=1e-9), name

    # the Jacobian's row of the pitch term against a finite difference
    features = gradients.towers.predict_on_batch(x)
    log_variances = model.log_variance_values()
    floor = model.log_variance_floor.value

    def pitch_term(values):
        outputs = gradients.heads(values, training=False)
        y_pred = dict(zip(model.output_names, outputs))
        return weighted_terms(model, y, y_pred, log_variances, floor)[TARGETS.index("pitch")]

    grad = np.asarray(jax.grad(pitch_term)(features))
    assert np.linalg.norm(grad) == pytest.approx(before["grad_pitch"], rel=1e-4)
    direction = grad / np.linalg.norm(grad)
    step = 1e-2
    slope = (float(pitch_term(features + step * direction))
             - float(pitch_term(features - step * direction))) / (2 * step)
    assert slope == pytest.approx(np.linalg.norm(grad), rel=0.05)


def test_training_logs_every_terms_gradient_each_epoch(stereo40, tmp_path):
    """``term_gradients=True``: log.csv has a finite ``grad_<target>`` for
    every target and epoch (MTL-Baseline: each output's MAE);
    ``head_units=True``: each head's ``dead_<head>`` (a share) and
    ``units_<head>`` (0-120) beside them. Deep-Homo has neither: refused
    before anything is written."""
    from cpl_keras.training import TrainingError, train

    run_dir = tmp_path / "run"
    train(stereo40, variant="baseline", run_dir=str(run_dir), backbone="small", epochs=2,
          batch_size=5, verbose=0, term_gradients=True, head_units=True, return_model=False)
    with open(os.path.join(run_dir, "log.csv")) as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 2
    for row in rows:
        values = [float(row[f"grad_{name}"]) for name in TARGETS]
        assert all(math.isfinite(v) for v in values) and max(values) > 0, row
        for head in HEADS:
            assert 0.0 <= float(row[f"dead_{head}"]) <= 1.0, row
            assert int(row[f"units_{head}"]) in range(121), row
    for flags in ({"term_gradients": True}, {"head_units": True}):
        with pytest.raises(TrainingError, match="deep-homo has neither"):
            train(stereo40, variant="deep-homo", run_dir=str(tmp_path / "homo"), epochs=1,
                  batch_size=5, verbose=0, return_model=False, **flags)
        assert not (tmp_path / "homo").exists()


def test_head_units_count_the_first_layers_live_units():
    """HeadUnits: per head, the share of pairs with every first-layer unit at
    or below zero and the units above zero for some pair, as a forward pass
    of that layer gives them; a first layer pushed below zero on every pair
    is dead on all of them with no unit alive."""
    import keras

    from cpl_keras.models.factory import build_model
    from cpl_keras.training.head_units import HeadUnits, heads

    x, _ = batch(6)
    model = build_model("cpl-a", backbone="small", image_size=SIZE, seed=0)
    assert heads(model) == list(HEADS)
    counts = HeadUnits(model)(x)
    assert set(counts) == {f"{k}_{h}" for h in HEADS for k in ("dead", "units")}
    first = keras.Model(model.inputs, model.get_layer("fx_dense_120").output)
    values = np.asarray(first.predict_on_batch(x))
    assert counts["dead_fx"] == pytest.approx(np.mean(values.max(axis=1) <= 0))
    assert counts["units_fx"] == int(np.sum(values.max(axis=0) > 0)) > 0
    layer = model.get_layer("pitch_dense_120")
    kernel, bias = layer.get_weights()
    layer.set_weights([kernel, np.full_like(bias, -1e6)])
    dead = HeadUnits(model)(x)
    assert dead["dead_pitch"] == 1.0 and dead["units_pitch"] == 0
    assert dead["units_fx"] == counts["units_fx"]
    with pytest.raises(ValueError, match="no regression heads"):
        HeadUnits(build_model("deep-homo", image_size=SIZE, seed=0))


def test_the_term_gradients_page_from_logs(tmp_path, capsys):
    """analyses/term_gradients.py: per run and term the median norm, the
    median share and the epochs a term was largest and smallest, from a
    log.csv (RUN/log.csv or a published RUN_log.csv); a log without the
    gradient columns is one line, exit 2, and nothing written."""
    import json

    from helpers import assert_refuses_a_bare_log, load_script

    script = load_script("analyses/term_gradients.py")
    run = tmp_path / "runs" / "cvgl_cpl-a-s0"
    run.mkdir(parents=True)
    norms = [{t: 1.0 for t in TARGETS} for _ in range(3)]
    norms[0]["v0"], norms[1]["v0"], norms[2]["disparity"] = 10.0, 10.0, 22.0
    norms[0]["ty"], norms[1]["ty"], norms[2]["ty"] = 0.5, 0.25, 0.125
    with open(str(run) + "_log.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["epoch", "loss"] + [f"grad_{t}" for t in TARGETS]
                        + [f"alpha_{t}" for t in TARGETS])
        for epoch, row in enumerate(norms, 1):
            writer.writerow([epoch, 1.0] + [row[t] for t in TARGETS] + [2.0] * len(TARGETS))
    out = tmp_path / "page.md"
    assert script.main(["--run", f"A={run}", "--out", str(out)]) == 0
    summary = json.loads((tmp_path / "page.json").read_text())["A"]
    assert summary["epochs"] == [1, 2, 3]
    v0, ty = summary["terms"]["v0"], summary["terms"]["ty"]
    assert (v0["epochs_largest"], summary["terms"]["disparity"]["epochs_largest"]) == (2, 1)
    assert ty["epochs_smallest"] == 3 and ty["median_norm"] == 0.25
    assert v0["median_share"] == pytest.approx(10.0 / (10.0 + 11 * 1.0 + 0.5))  # epoch 1
    assert summary["alphas"]["fx"] == 2.0
    assert "| v0 | 10 | 0.465 | 2 | 0 | 2 |" in out.read_text()
    # --until: the first epochs alone (v0 largest in both)
    assert script.main(["--run", f"A={run}", "--until", "2", "--out", str(out)]) == 0
    first = json.loads((tmp_path / "page.json").read_text())["A"]
    assert first["epochs"] == [1, 2] and first["terms"]["v0"]["epochs_largest"] == 2
    assert first["terms"]["disparity"]["epochs_largest"] == 0 and "--until 2" in out.read_text()
    assert_refuses_a_bare_log(script, tmp_path, capsys, "no grad_<target> columns")
