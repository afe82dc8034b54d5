"""Traps of the loss and of training from scratch, each closed by a default:
the bounded pitch head, the adaptive weights' start and floor, the exact
disentangling of Eq. 7, per-quantity divisor floors, BatchNorm statistics
that belong to the weights, local random seeding and sample weights."""

import json
import math
import os
import random

import jax
import keras
import numpy as np
import pytest
from keras import ops

from cpl_keras import TARGETS, build_model, camera, compile_model
from cpl_keras.models import losses
from cpl_keras.models.batchnorm import batchnorm_layers, recompute_batchnorm_statistics

from helpers import SIZE, batch


@pytest.fixture(scope="module")
def tiny_cvgl(stereo40):
    # 40 pairs -> 25 training pairs: five equal batches of 5
    return stereo40


# ---------------------------------------------------------------------------
# Pitch: one minimum
# ---------------------------------------------------------------------------
@pytest.mark.parametrize("variant", ["baseline", "cpl-u", "cpl-a"])
def test_pitch_head_is_bounded_by_default_and_linear_as_released(variant):
    x, _ = batch(2)
    for as_released, bounded in ((False, True), (True, False)):
        model = build_model(variant, backbone="small", image_size=SIZE, as_released=as_released,
                            seed=0)
        head = model.get_layer("pitch")
        head.kernel.assign(np.zeros(head.kernel.shape, "float32"))
        head.bias.assign(np.full(head.bias.shape, 40.0, "float32"))
        pitch = model.predict(x, verbose=0)[TARGETS.index("pitch")]
        if bounded:
            assert np.allclose(pitch, math.pi / 2)
        else:
            assert np.allclose(pitch, 40.0)
        assert model.build_settings["bounded_pitch_head"] is bounded


def _pitch_term(y, pitch_values):
    """L_pitch of Eq. 7 for one sample as a function of the predicted pitch
    (each value its own batch of one, mapped with jax.vmap)."""
    index = TARGETS.index("pitch")
    truth = {k: np.asarray(v, "float32")[:1] for k, v in y.items()}

    def term(pitch):
        return losses.projection_terms(truth, dict(truth, pitch=pitch.reshape(1, 1)))[index]

    values = np.asarray(pitch_values, "float32").reshape(-1, 1, 1)
    return np.asarray(jax.jit(jax.vmap(term))(values), "float64")


def _local_minima(values):
    inner = (values[1:-1] < values[:-2]) & (values[1:-1] < values[2:])
    return int(inner.sum())


def test_the_bounded_pitch_loss_has_only_true_minima_where_the_linear_one_has_far_ones():
    _, y = batch(1, seed=3)
    X, Y, Z = camera.image_to_world(**{k: y[k] for k in camera.PARAMETERS}, u=9.0, v=21.0)
    y.update(X=np.float32(X).reshape(1, 1), Y=np.float32(Y).reshape(1, 1),
             Z=np.float32(Z).reshape(1, 1))
    truth = float(y["pitch"][0, 0])
    linear = np.linspace(-20.0, 20.0, 801)  # radians, what an unbounded head can output
    assert _local_minima(_pitch_term(y, linear)) >= 3
    # In pitch, over the bounded head's range, one minimum: the truth.
    in_range = np.linspace(-math.pi / 2, math.pi / 2, 401)
    terms = _pitch_term(y, in_range)
    assert _local_minima(terms) == 1
    assert in_range[np.argmin(terms)] == pytest.approx(truth, abs=0.01)
    # In the head's pre-activation z: past the bound the output (and so the
    # loss) is that of the bound, no far minimum; the lowest loss is the truth.
    from cpl_keras.layers import bounded_pitch

    z = np.linspace(-8.0, 8.0, 1601).astype("float32")
    pitch = np.asarray(bounded_pitch(z))
    assert np.all(pitch[z <= -math.pi / 2] == np.float32(-math.pi / 2))
    assert np.all(pitch[z >= math.pi / 2] == np.float32(math.pi / 2))
    terms = _pitch_term(y, pitch)
    assert pitch[np.argmin(terms)] == pytest.approx(truth, abs=0.01)


def bounded_pitch_value(z):
    from cpl_keras.layers import bounded_pitch

    return bounded_pitch(np.float32(z))


def test_the_bounded_pitch_head_does_not_saturate():
    """Gradient descent on the head's pre-activation z, from far past the
    bound, comes back to the target (a tanh head stays stranded)."""
    assert float(bounded_pitch_value(-20.0)) == pytest.approx(-math.pi / 2)
    from cpl_keras.layers import bounded_pitch

    target = -0.31

    def descend(activation, z=-20.0, steps=400):
        grad = jax.jit(jax.grad(lambda z: (activation(z) - target) ** 2))
        for _ in range(steps):
            z = z - 0.1 * float(grad(z))
        return float(activation(z))

    assert descend(bounded_pitch) == pytest.approx(target, abs=0.01)
    assert descend(lambda z: (math.pi / 2) * ops.tanh(z)) == pytest.approx(-math.pi / 2, abs=1e-3)


# ---------------------------------------------------------------------------
# Eq. 9: balanced start, bounded below
# ---------------------------------------------------------------------------
def test_adaptive_weights_start_balanced_on_the_first_batch_and_are_floored():
    model = compile_model(build_model("cpl-a", backbone="small", image_size=SIZE, seed=0))
    x, y = batch(8)
    alphas = model.initialise_adaptive_weights(y)
    average = {k: np.broadcast_to(v.mean(0, keepdims=True), v.shape) for k, v in y.items()}
    off = {k: v * 1.01 for k, v in y.items()}
    terms = [float(a) + float(b) for a, b in zip(model.projection_terms(y, average),
                                                 model.projection_terms(y, off))]
    for name, term in zip(TARGETS, terms):
        assert alphas[name] * term == pytest.approx(1.0, rel=1e-3)
    # u0 and v0 are constant in this batch: Average's term is 0, the 1% term
    # keeps a finite scale
    assert max(alphas.values()) < 1e4
    s = ops.convert_to_numpy(model.log_variance_values())
    floor = ops.convert_to_numpy(model.log_variance_floor)
    assert np.allclose(s - floor, math.log(losses.ADAPTIVE_WEIGHT_RANGE), atol=1e-4)
    # A term at 0 can no longer drive the objective to minus infinity.
    zero_terms = [ops.convert_to_tensor(0.0)] * 13
    far_below = ops.convert_to_tensor(np.full(13, -60.0, "float32"))
    bounded = float(losses.adaptive_projection_loss(zero_terms, far_below, model.log_variance_floor))
    assert bounded == pytest.approx(float(floor.sum()), rel=1e-5)
    assert float(losses.adaptive_projection_loss(zero_terms, far_below)) == pytest.approx(-780.0)


def test_balanced_start_survives_save_and_load(tmp_path):
    model = compile_model(build_model("cpl-a", backbone="small", image_size=SIZE, seed=0))
    x, y = batch(8)
    alphas = model.initialise_adaptive_weights(y)
    path = str(tmp_path / "m.keras")
    model.save(path)
    loaded = keras.saving.load_model(path, safe_mode=True)
    assert loaded.adaptive_weights() == pytest.approx(alphas)
    assert np.allclose(ops.convert_to_numpy(loaded.log_variance_floor),
                       ops.convert_to_numpy(model.log_variance_floor))


# ---------------------------------------------------------------------------
# Eq. 7: each error charged to the parameter that made it
# ---------------------------------------------------------------------------
def _graph_gradients(model):
    """d(X + Y + Z)/d(head value) for every head, through the model's graph."""
    heads = list(camera.PARAMETERS) + ["u", "v"]
    graph = keras.Model([model.get_layer(h).output for h in heads],
                        [model.get_layer(q).output for q in ("X", "Y", "Z")])
    values = {h: np.full((1, 1), 1.3, "float32") for h in heads}
    values.update(u=np.full((1, 1), 10.0, "float32"), v=np.full((1, 1), 20.0, "float32"),
                  pitch=np.full((1, 1), 0.2, "float32"))

    def point_sum(inputs):
        return sum(ops.sum(o) for o in graph(inputs))

    grads = jax.grad(point_sum)([values[h] for h in heads])
    return {h: float(np.abs(g).sum()) for h, g in zip(heads, grads)}


def test_exact_disentangling_charges_x_y_z_only_to_the_pixel_heads():
    exact = _graph_gradients(build_model("cpl-u", backbone="small", image_size=SIZE))
    partial = _graph_gradients(build_model("cpl-u", backbone="small", image_size=SIZE,
                                           disentangle="partial"))
    for name in camera.PARAMETERS:
        assert exact[name] == 0.0, name
        assert partial[name] > 0.0, name
    for name in ("u", "v"):
        assert exact[name] > 0.0 and partial[name] > 0.0


def test_exact_disentangling_keeps_the_forward_values():
    x, _ = batch(3)
    a = build_model("cpl-a", backbone="small", image_size=SIZE, seed=1)
    b = build_model("cpl-a", backbone="small", image_size=SIZE, seed=1, disentangle="partial")
    for pa, pb in zip(a.predict(x, verbose=0), b.predict(x, verbose=0)):
        np.testing.assert_array_equal(pa, pb)


# ---------------------------------------------------------------------------
# Divisor floors per quantity
# ---------------------------------------------------------------------------
def test_each_division_of_the_graph_has_its_quantitys_floor():
    model = build_model("cpl-u", backbone="small", image_size=SIZE)
    floor = {layer.name: layer.arguments.get("epsilon") for layer in model.layers
             if isinstance(layer, keras.layers.Lambda) and layer.arguments}
    assert floor["xCam"] == camera.FLOORS["disparity"]
    assert floor["xCam_over_fx"] == floor["xCam_over_fy"] == camera.FLOORS["focal"]
    released = build_model("cpl-u", backbone="small", image_size=SIZE, as_released=True)
    assert released.get_layer("xCam").arguments["epsilon"] == camera.RELEASED_FLOORS["disparity"]
    assert camera.FLOORS["disparity"] != camera.FLOORS["focal"]


def test_gradient_at_the_disparity_floor_is_bounded():
    """d xCam / d d = -fx b / d^2 just outside the floor (fx b = 100 px m)."""
    ops_set = camera.tensor_ops()
    grad = jax.grad(lambda d: ops.sum(camera.depth_from_disparity(50.0, 2.0, d, ops_set)))
    outside = float(np.abs(grad(np.float32(camera.FLOORS["disparity"] * 1.01))))
    assert outside < 1e7
    inside = float(np.abs(grad(np.float32(camera.FLOORS["disparity"] * 0.5))))
    assert inside == 0.0 and np.isfinite(outside)


# ---------------------------------------------------------------------------
# BatchNorm statistics that belong to the weights
# ---------------------------------------------------------------------------
def test_recomputed_batchnorm_statistics_are_the_batch_averages():
    inputs = keras.Input((3,))
    hidden = keras.layers.Dense(4, name="dense")(inputs)
    outputs = keras.layers.BatchNormalization(name="bn")(hidden)
    model = keras.Model(inputs, outputs)
    rng = np.random.default_rng(0)
    batches = [rng.normal(5.0, 2.0, (8, 3)).astype("float32") for _ in range(5)]
    assert recompute_batchnorm_statistics(model, batches) == 5
    dense = keras.Model(inputs, hidden)
    activations = [dense.predict(b, verbose=0) for b in batches]
    bn = model.get_layer("bn")
    np.testing.assert_allclose(ops.convert_to_numpy(bn.moving_mean),
                               np.mean([a.mean(0) for a in activations], 0), rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(ops.convert_to_numpy(bn.moving_variance),
                               np.mean([a.var(0) for a in activations], 0), rtol=1e-3, atol=1e-5)
    assert bn.momentum == pytest.approx(0.99)
    assert batchnorm_layers(model) == [bn]
    # population=True: the variance of all the batches' pairs together (the
    # spread of the batch means included), here with batches of unequal means
    shifted = [b + 3.0 * i for i, b in enumerate(batches)]
    assert recompute_batchnorm_statistics(model, shifted, population=True) == 5
    everything = np.concatenate([dense.predict(b, verbose=0) for b in shifted])
    np.testing.assert_allclose(ops.convert_to_numpy(bn.moving_mean), everything.mean(0),
                               rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(ops.convert_to_numpy(bn.moving_variance), everything.var(0),
                               rtol=1e-3, atol=1e-4)


@pytest.mark.slow
def test_deep_homo_saved_by_training_has_statistics_of_its_weights(tmp_path, tiny_cvgl,
                                                                  variant_run):
    """The session's Deep-Homo run (the default: statistics recomputed after
    every epoch) saves its BatchNorm's population statistics of the saved
    weights; a run without the recompute (as released) lags behind them."""
    from cpl_keras.datasets import load_split
    from cpl_keras.training.sequence import StereoSequence
    from cpl_keras.training import train

    def first_bn_mean(run_dir):
        model = keras.saving.load_model(os.path.join(run_dir, "model.keras"), safe_mode=True)
        bn = model.get_layer("batch_norm1")
        conv = keras.Model(model.inputs, bn.input)
        split = load_split(os.path.join(run_dir, "split.npz"))
        seq = StereoSequence(tiny_cvgl, split["train"], batch_size=5)
        means = [conv.predict(seq[i][0], verbose=0).mean(axis=(0, 1, 2)) for i in range(len(seq))]
        seq.close()
        return ops.convert_to_numpy(bn.moving_mean), np.mean(means, axis=0)

    shared = variant_run("deep-homo")
    assert shared["summary"]["status"] == "finished"
    assert json.loads(open(os.path.join(shared["run_dir"], "config.json")).read())[
        "bn_recompute_batches"] >= 5  # every one of the 5 training batches
    recomputed, truth = first_bn_mean(shared["run_dir"])
    np.testing.assert_allclose(recomputed, truth, rtol=0.05, atol=1e-3 * np.abs(truth).max())
    lagged = str(tmp_path / "r0")  # Keras's moving average, as released
    summary = train(tiny_cvgl, variant="deep-homo", run_dir=lagged, epochs=1, batch_size=5,
                    backbone="small", seed=0, bn_recompute_batches=0, verbose=0)
    assert summary.config.status == "finished"
    lagging, truth = first_bn_mean(lagged)
    assert np.abs(lagging - truth).max() > 0.3 * np.abs(truth).max()


# ---------------------------------------------------------------------------
# Seeds and sample weights
# ---------------------------------------------------------------------------
def test_build_model_leaves_python_and_numpy_random_state_alone():
    random.seed(7)
    np.random.seed(7)
    expected = (random.random(), np.random.rand())
    random.seed(7)
    np.random.seed(7)
    a = build_model("cpl-u", backbone="small", image_size=SIZE, seed=123)
    assert (random.random(), np.random.rand()) == expected
    b = build_model("cpl-u", backbone="small", image_size=SIZE, seed=123)
    for wa, wb in zip(a.get_weights(), b.get_weights()):
        np.testing.assert_array_equal(wa, wb)


@pytest.mark.parametrize("variant", ["cpl-u", "cpl-a", "deep-homo"])
def test_coupled_losses_refuse_sample_weights_loudly(variant):
    model = compile_model(build_model(variant, backbone="small", image_size=SIZE, seed=0))
    x, y = batch(4)
    with pytest.raises(ValueError, match="sample_weight"):
        model.fit(x, y, sample_weight=np.ones(4, "float32"), epochs=1, verbose=0)


@pytest.mark.parametrize("protocol", ["cvgl", "random"])
def test_no_label_of_the_rendered_data_is_floored(protocol, tmp_path):
    from cpl_keras.data.generate import generate_dataset
    from cpl_keras.data.storage import StereoFile

    path = generate_dataset(str(tmp_path / "d.h5"), protocol=protocol, pairs=24, seed=0,
                            image_size=16, workers=1)
    with StereoFile(path) as f:
        labels = f.labels
    assert np.abs(labels["disparity"]).min() > camera.FLOORS["disparity"]
    assert min(np.abs(labels["fx"]).min(), np.abs(labels["fy"]).min()) > camera.FLOORS["focal"]


def test_standardised_targets_divide_each_mae_by_its_scale():
    model = build_model("baseline", backbone="small", image_size=SIZE, seed=0)
    x, y = batch(8)
    scale = {name: float(k + 1) for k, name in enumerate(TARGETS)}
    compile_model(model, target_scale=scale)
    logs = model.evaluate(x, y, verbose=0, return_dict=True)
    expected = sum(logs[f"{name}_mae"] / scale[name] for name in TARGETS)
    assert logs["loss"] == pytest.approx(expected, rel=1e-4)
    with pytest.raises(ValueError, match="per-output MAE"):
        compile_model(build_model("cpl-u", backbone="small", image_size=SIZE), target_scale=scale)
    with pytest.raises(ValueError, match="positive number for fx"):
        compile_model(model, target_scale=dict(scale, fx=0.0))


def test_training_records_target_scaling_and_refuses_it_for_the_projection_loss(tiny_cvgl,
                                                                                 tmp_path):
    from cpl_keras.training import TrainingError, plan_run

    plan = plan_run(tiny_cvgl, variant="baseline", run_dir=str(tmp_path / "b"),
                    backbone="small", target_scaling="std")
    assert plan.config.training.target_scaling == "std"
    with pytest.raises(TrainingError, match="target scaling"):
        plan_run(tiny_cvgl, variant="cpl-u", run_dir=str(tmp_path / "c"), backbone="small",
                 target_scaling="std")
    assert not (tmp_path / "b").exists() and not (tmp_path / "c").exists()


def test_cpl_disparity_head_is_positive_in_log_space_and_linear_as_released():
    x, _ = batch(2)
    for as_released in (False, True):
        model = build_model("cpl-u", backbone="small", image_size=SIZE, as_released=as_released,
                            seed=0)
        head = model.get_layer("disparity")
        head.kernel.assign(np.zeros(head.kernel.shape, "float32"))
        for bias, expected in ((-50.0, camera.FLOORS["disparity"]), (2.0, math.exp(2.0))):
            head.bias.assign(np.full(head.bias.shape, bias, "float32"))
            d = model.predict(x, verbose=0)[TARGETS.index("disparity")]
            if as_released:
                assert np.allclose(d, bias)
            else:
                assert np.allclose(d, expected, rtol=1e-5)
    # the gradient of z is never cut, even below the floor
    from cpl_keras.layers import positive_disparity

    assert float(jax.grad(lambda z: positive_disparity(z))(np.float32(-50.0))) > 0


def test_cpl_disparity_head_stops_at_its_ceiling_and_keeps_the_gradient(tmp_path):
    """Above the ceiling the head outputs the ceiling (not exp(z)), with the
    gradient of z (straight-through); the ceiling survives a safe-mode save
    and load; a ceiling at or below the floor is refused."""
    import keras

    from cpl_keras.layers import MAX_OUTPUT, PositiveDisparity

    x, _ = batch(2)
    model = build_model("cpl-a", backbone="small", image_size=SIZE, seed=0,
                        disparity_ceiling=300.0)
    head = model.get_layer("disparity")
    head.kernel.assign(np.zeros(head.kernel.shape, "float32"))
    for bias, expected in ((math.log(250.0), 250.0), (math.log(900.0), 300.0), (30.0, 300.0)):
        head.bias.assign(np.full(head.bias.shape, bias, "float32"))
        d = model.predict(x, verbose=0)[TARGETS.index("disparity")]
        assert np.allclose(d, expected, rtol=1e-5), (bias, d)
    path = tmp_path / "m.keras"
    model.save(path)
    loaded = keras.saving.load_model(path, safe_mode=True)
    assert loaded.get_layer("disparity").activation.ceiling == 300.0
    assert np.allclose(loaded.predict(x, verbose=0)[TARGETS.index("disparity")], 300.0)
    assert model.build_settings["disparity_ceiling"] == 300.0
    # without one, the bound of before: 1e5 px
    assert build_model("cpl-u", backbone="small", image_size=SIZE).build_settings[
        "disparity_ceiling"] == MAX_OUTPUT
    head = PositiveDisparity(ceiling=300.0)
    assert float(jax.grad(lambda z: head(z))(np.float32(30.0))) > 0
    for bad in (0.001, float("inf"), -5.0):
        with pytest.raises(ValueError, match="disparity ceiling"):
            PositiveDisparity(ceiling=bad)


# ---------------------------------------------------------------------------
# Focal lengths: positive heads (the pole of Eq. 4c)
# ---------------------------------------------------------------------------
def _fy_term_gradient(fy_pred, xCam=20.0, v0=56.0, v=70.0, fy=60.0, pitch=0.2):
    """d L_fy / d fy' of one pair by hand (Eq. 7, every other parameter true):
    zCam' = xCam (v0 - v) / fy', X' and Z' move with it through Eqs. 5a, 5c."""
    z_true = xCam * (v0 - v) / fy
    z_pred = xCam * (v0 - v) / fy_pred
    dz = -xCam * (v0 - v) / fy_pred ** 2
    direct = math.copysign(1.0, fy_pred - fy)
    projection = (math.copysign(1.0, (z_pred - z_true) * math.sin(pitch)) * math.sin(pitch)
                  + math.copysign(1.0, (z_pred - z_true) * math.cos(pitch)) * math.cos(pitch)) * dz
    return direct / 13.0, projection / 13.0


def test_fy_term_has_a_pole_that_traps_a_negative_linear_head():
    """The code's gradient of L_fy matches the hand derivation, and below 0
    the projection part pushes fy' further down, outweighing the direct part
    near the pole: the InceptionV3 MTL-CPL-A failure (all fy outputs < 0)."""
    fx = 60.0
    truth = {"fx": fx, "fy": 60.0, "u0": 56.0, "v0": 56.0, "baseline": 0.5, "pitch": 0.2,
             "tx": 0.5, "ty": 0.1, "tz": 0.2}
    truth["disparity"] = fx * truth["baseline"] / 20.0                     # xCam = 20 m
    truth["X"], truth["Y"], truth["Z"] = camera.image_to_world(**truth, u=40.0, v=70.0)
    y = {k: ops.convert_to_tensor(np.full((1, 1), v, "float32")) for k, v in truth.items()}
    index = TARGETS.index("fy")
    for fy_pred in (-1.1, -5.0, -30.0, 30.0):
        grad = jax.grad(lambda p: losses.projection_terms(y, dict(y, fy=p))[index])(
            np.full((1, 1), fy_pred, "float32"))
        direct, projection = _fy_term_gradient(fy_pred)
        assert float(grad[0, 0]) == pytest.approx(direct + projection, rel=1e-4)
        if fy_pred < 0:
            assert projection > 0          # gradient descent moves fy' down, away from 0
    assert _fy_term_gradient(-1.1)[1] > 100 * abs(_fy_term_gradient(-1.1)[0])


def test_positive_focal_head_escapes_the_trap_a_linear_head_falls_into():
    """Adam on one head output z, from just below 0 (where the InceptionV3
    heads started): fy' = z stays below 0, fy' = positive_focal(z) reaches
    the label."""
    from cpl_keras.layers import positive_focal

    truth = {"fx": 60.0, "fy": 60.0, "u0": 56.0, "v0": 56.0, "baseline": 0.5, "pitch": 0.2,
             "tx": 0.5, "ty": 0.1, "tz": 0.2, "disparity": 1.5}
    truth["X"], truth["Y"], truth["Z"] = camera.image_to_world(**truth, u=40.0, v=70.0)
    y = {k: ops.convert_to_tensor(np.full((1, 1), v, "float32")) for k, v in truth.items()}
    index = TARGETS.index("fy")

    def train(head, z):
        term = jax.jit(jax.grad(lambda z: losses.projection_terms(y, dict(y, fy=head(z)))[index]))
        optimizer = keras.optimizers.Adam(learning_rate=0.5)
        variable = keras.Variable(np.full((1, 1), z, "float32"))
        optimizer.build([variable])
        for _ in range(2000):
            optimizer.apply([term(variable.value)], [variable])
        return float(head(variable.value)[0, 0])

    assert train(lambda z: z, -1.1) < 0
    assert train(positive_focal, -1.1) == pytest.approx(60.0, rel=0.05)


@pytest.mark.parametrize("variant", ["cpl-u", "cpl-a"])
def test_focal_heads_are_positive_by_default_and_linear_as_released(variant):
    x, _ = batch(2)
    for kwargs, positive in (({}, True), ({"as_released": True}, False),
                             ({"positive_focal_head": False}, False)):
        model = build_model(variant, backbone="small", image_size=SIZE, seed=0, **kwargs)
        for name in ("fx", "fy"):
            head = model.get_layer(name)
            head.kernel.assign(np.zeros(head.kernel.shape, "float32"))
            head.bias.assign(np.full(head.bias.shape, -3.0, "float32"))
        out = model.predict(x, verbose=0)
        for name in ("fx", "fy"):
            value = out[TARGETS.index(name)]
            # -3 is below the 1 px floor: clipped there
            assert np.allclose(value, camera.FLOORS["focal"] if positive else -3.0)
        assert model.build_settings["positive_focal_head"] is positive
    baseline = build_model("baseline", backbone="small", image_size=SIZE, seed=0)
    assert baseline.build_settings["positive_focal_head"] is False   # regresses fy directly


# ---------------------------------------------------------------------------
# Eq. 9: how fast the adaptive weights move
# ---------------------------------------------------------------------------
@pytest.mark.parametrize("rate", [1.0, 10.0])
def test_alpha_rate_scales_the_step_of_the_adaptive_weights(rate):
    """Adam's first step moves every weight by the learning rate (m / sqrt(v)
    is +-1 after one step), so log alpha_i moves by rate x lr."""
    model = compile_model(build_model("cpl-a", backbone="small", image_size=SIZE, seed=0,
                                      alpha_rate=rate), learning_rate=1e-3)
    x, y = batch(8)
    model.initialise_adaptive_weights(y)
    before = ops.convert_to_numpy(model.log_variance_values())
    model.train_on_batch(x, y)
    step = np.abs(ops.convert_to_numpy(model.log_variance_values()) - before)
    moved = step[step > 0]
    assert len(moved) >= 10
    assert np.allclose(moved, rate * 1e-3, rtol=1e-2)
    assert model.build_settings["alpha_rate"] == rate
    with pytest.raises(ValueError, match="alpha rate"):
        build_model("cpl-a", backbone="small", image_size=SIZE, alpha_rate=-1.0)


def test_alpha_rate_zero_freezes_the_weights_at_their_first_batch_balance():
    """Eq. 9 as a fixed range normalisation: with an alpha rate of 0 the
    weights start balanced on the first batch (alpha_i = 1 / L_i, as
    always) and no training step moves them, while the heads train."""
    model = compile_model(build_model("cpl-a", backbone="small", image_size=SIZE, seed=0,
                                      alpha_rate=0.0), learning_rate=1e-3)
    x, y = batch(8)
    start = model.initialise_adaptive_weights(y)
    rated = build_model("cpl-a", backbone="small", image_size=SIZE, seed=0, alpha_rate=1.0)
    assert start == pytest.approx(rated.initialise_adaptive_weights(y), rel=1e-5)
    heads = ops.convert_to_numpy(model.get_layer("fx").kernel)
    for _ in range(2):
        model.train_on_batch(x, y)
    assert model.adaptive_weights() == start
    assert not np.allclose(ops.convert_to_numpy(model.get_layer("fx").kernel), heads)
    assert "log_variances" not in [v.name for v in model.trainable_variables]
