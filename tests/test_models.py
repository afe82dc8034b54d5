"""The model factory, the Lambda camera graph, losses and saving."""

import os

import keras
import numpy as np
import pytest
from keras import ops

from cpl_keras import TARGETS, build_model, camera, compile_model
from cpl_keras.models import losses
from cpl_keras.models import VARIANTS
from helpers import SIZE, batch


@pytest.mark.parametrize("as_released", [False, True])
@pytest.mark.parametrize("variant", VARIANTS)
def test_outputs_are_the_13_targets_in_release_order(variant, as_released):
    model = build_model(variant, backbone="small", image_size=SIZE, as_released=as_released)
    assert model.output_names == list(TARGETS)
    assert sorted(i.name for i in model.inputs) == ["left_image", "right_image"]
    x, _ = batch(2)
    out = model.predict(x, verbose=0)
    assert len(out) == 13 and all(o.shape == (2, 1) for o in out)


@pytest.mark.slow
def test_baseline_has_the_release_parameter_count_and_runs_inceptionv3():
    model = build_model("baseline", image_size=112)
    assert model.count_params() == 69_299_405
    assert model.get_layer("left_inception_v3").count_params() == 21_802_784
    rng = np.random.default_rng(0)
    x = {k: rng.uniform(0, 255, (1, 112, 112, 3)).astype("float32") for k in ("left_image", "right_image")}
    out = model.predict(x, verbose=0)  # (one compiled program: half the CPU of an eager call)
    assert len(out) == len(TARGETS) and all(np.isfinite(o).all() for o in out)


def test_cpl_variants_have_the_lambda_camera_graph():
    model = build_model("cpl-u", backbone="small", image_size=SIZE)
    names = {layer.name for layer in model.layers}
    assert {"xCam", "yCam", "zCam", "X", "Y", "Z", "u", "v"} <= names
    assert isinstance(model.get_layer("xCam"), keras.layers.Lambda)
    assert model.get_layer("xCam").function.__name__ == "safe_divide"
    baseline = build_model("baseline", backbone="small", image_size=SIZE)
    assert "xCam" not in {layer.name for layer in baseline.layers}


def test_camera_graph_computes_the_equations():
    """Feed the graph known parameters through a sub-model and compare with numpy."""
    model = build_model("cpl-u", backbone="small", image_size=SIZE)
    heads = list(camera.PARAMETERS) + ["u", "v"]
    graph = keras.Model([model.get_layer(h).output for h in heads],
                        [model.get_layer(q).output for q in ("X", "Y", "Z")])
    rng = np.random.default_rng(3)
    values = {h: rng.uniform(0.5, 3.0, (5, 1)).astype("float32") for h in heads}
    got = graph.predict([values[h] for h in heads], verbose=0)
    expected = camera.image_to_world(**values)
    for g, e in zip(got, expected):
        np.testing.assert_allclose(g, e, rtol=1e-5)


def _head_kernels(model, names):
    return {n: ops.convert_to_numpy(model.get_layer(n).kernel).copy() for n in names}


@pytest.mark.parametrize("variant,as_released", [
    ("cpl-u", False), ("cpl-a", False), ("cpl-u", True), ("cpl-a", True),
])
def test_gradients_reach_every_head_through_the_camera_graph(variant, as_released):
    model = compile_model(build_model(variant, backbone="small", image_size=SIZE,
                                      as_released=as_released, seed=0))
    heads = list(camera.PARAMETERS) + ["u", "v"]
    before = _head_kernels(model, heads)
    x, y = batch(8)
    # one step of the model's own loss moves every head, u and v only through the graph
    model.train_on_batch(x, y)
    after = _head_kernels(model, heads)
    for name in heads:
        assert np.abs(after[name] - before[name]).max() > 0, f"no gradient reached head {name}"


def test_no_nan_or_inf_with_disparity_or_focal_at_zero():
    model = compile_model(build_model("cpl-u", backbone="small", image_size=SIZE, seed=0))
    x, y = batch(4)
    for value in (0.0, 1e-9, -1e-9):
        for head in ("disparity", "fx"):
            layer = model.get_layer(head)
            layer.kernel.assign(np.zeros(layer.kernel.shape, "float32"))
            layer.bias.assign(np.full(layer.bias.shape, value, "float32"))
        out = model.predict(x, verbose=0)
        assert all(np.isfinite(o).all() for o in out), value
        loss = model.train_on_batch(x, y)
        assert np.all(np.isfinite(np.asarray(loss, dtype="float64"))), value
        assert all(np.isfinite(ops.convert_to_numpy(w)).all() for w in model.trainable_weights)


def test_projection_terms_vanish_at_the_truth_and_isolate_each_parameter():
    _, y = batch(6)
    yt = {k: ops.convert_to_tensor(v) for k, v in y.items()}
    terms = [float(t) for t in losses.projection_terms(yt, yt)]
    assert max(terms) < 1e-4
    # an error in tx alone moves X by exactly that error: L_tx = (|dtx| + |dX|) / 13
    wrong = dict(yt, tx=yt["tx"] + 0.65)
    terms = [float(t) for t in losses.projection_terms(yt, wrong)]
    index = TARGETS.index("tx")
    assert terms[index] == pytest.approx(2 * 0.65 / 13, rel=1e-4)
    assert max(t for i, t in enumerate(terms) if i != index) < 1e-4


def test_relative_point_errors_are_the_metres_divided_by_the_true_depth():
    _, y = batch(6)
    yt = {k: ops.convert_to_tensor(v) for k, v in y.items()}
    depth = camera.depth_from_disparity(y["fx"], y["baseline"], y["disparity"])
    assert np.ptp(depth) > 1.0  # (pairs at different depths, so the division shows)
    for name, error in (("pitch", 0.02), ("disparity", 0.5), ("tx", 0.65)):
        wrong = dict(yt, **{name: yt[name] + error})
        index = TARGETS.index(name)
        per_pair = []
        for mode in ("metres", "relative"):
            # one pair at a time: 13 L_p minus the parameter's own error is its point error
            per_pair.append(np.array([
                13 * float(losses.projection_terms(
                    {k: v[i:i + 1] for k, v in yt.items()},
                    {k: v[i:i + 1] for k, v in wrong.items()}, point_errors=mode)[index]) - error
                for i in range(6)]))
        metres, relative = per_pair
        assert metres.min() > 1e-3, name
        np.testing.assert_allclose(relative, metres / depth[:, 0], rtol=2e-3, err_msg=name)
    # the graph's own terms too: L_X = |X' - X| / (13 xCam)
    wrong = dict(yt, X=yt["X"] + 2.0)
    term = float(losses.projection_terms(yt, wrong, point_errors="relative")[TARGETS.index("X")])
    assert term == pytest.approx(np.mean(2.0 / depth) / 13, rel=1e-4)
    with pytest.raises(ValueError, match="point_errors must be one of metres, relative"):
        losses.projection_terms(yt, yt, point_errors="depth")


def test_a_model_built_with_relative_point_errors_trains_with_them():
    x, y = batch(4)
    yt = {k: ops.convert_to_tensor(v) for k, v in y.items()}
    metres = build_model("cpl-a", backbone="small", image_size=SIZE, seed=0)
    relative = build_model("cpl-a", backbone="small", image_size=SIZE, seed=0,
                           point_errors="relative")
    assert "point_errors" not in metres.build_settings  # (as every model built before it)
    assert relative.build_settings["point_errors"] == "relative"
    # (one rule, in ModelOptions: the model refuses what training refuses)
    with pytest.raises(ValueError, match="apply to the camera projection loss"):
        build_model("baseline", backbone="small", image_size=SIZE, point_errors="relative")
    wrong = dict(yt, pitch=yt["pitch"] + 0.02)
    index = TARGETS.index("pitch")
    assert float(relative.projection_terms(yt, wrong)[index]) == pytest.approx(float(
        losses.projection_terms(yt, wrong, relative.floors, "relative")[index]))
    assert float(relative.projection_terms(yt, wrong)[index]) != pytest.approx(
        float(metres.projection_terms(yt, wrong)[index]))
    with pytest.raises(ValueError, match="unknown point errors .depth."):
        build_model("cpl-a", backbone="small", image_size=SIZE, point_errors="depth")


def test_baseline_with_the_exp_disparity_head_of_the_cpl_variants():
    x, _ = batch(2)
    model = build_model("baseline", backbone="small", image_size=SIZE, seed=0,
                        exp_disparity_head=True, disparity_ceiling=50.0)
    assert model.build_settings["exp_disparity_head"] is True
    assert model.build_settings["disparity_ceiling"] == 50.0
    assert "exp_disparity_head" not in build_model("baseline", backbone="small",
                                                   image_size=SIZE).build_settings
    head = model.get_layer("disparity")
    head.kernel.assign(np.zeros(head.kernel.shape, "float32"))
    index = TARGETS.index("disparity")
    for bias, expected in ((-50.0, camera.FLOORS["disparity"]), (2.0, np.exp(2.0)), (9.0, 50.0)):
        head.bias.assign(np.full(head.bias.shape, bias, "float32"))
        np.testing.assert_allclose(model.predict(x, verbose=0)[index], expected, rtol=1e-5)
    for variant in ("cpl-a", "deep-homo"):
        with pytest.raises(ValueError, match="exp disparity head is MTL-Baseline.s ablation"):
            build_model(variant, backbone="small", image_size=SIZE, exp_disparity_head=True)


def test_leaky_relu_heads():
    """--head-activation leaky_relu: every regression head's two hidden
    layers (parameters, pixel heads, MTL-Baseline's X, Y, Z), recorded in
    the build settings only when not ReLU; with a first layer below zero on
    every input, ReLU's second layer is at zero, a leaky one's is not; not
    Deep-Homo."""
    x, _ = batch(2)
    for variant, heads in (("cpl-a", list(camera.PARAMETERS) + ["u", "v"]), ("baseline", TARGETS)):
        model = build_model(variant, backbone="small", image_size=SIZE, seed=0,
                            head_activation="leaky_relu")
        assert model.build_settings["head_activation"] == "leaky_relu"
        for head in heads:
            for units in (120, 84):
                layer = model.get_layer(f"{head}_dense_{units}")
                assert keras.activations.serialize(layer.activation) == "leaky_relu", head
        assert "head_activation" not in build_model(variant, backbone="small",
                                                    image_size=SIZE).build_settings
    relu = build_model("baseline", backbone="small", image_size=SIZE, seed=0)
    for built in (relu, model):
        layer = built.get_layer("pitch_dense_120")
        layer.kernel.assign(np.zeros(layer.kernel.shape, "float32"))
        layer.bias.assign(np.full(layer.bias.shape, -1.0, "float32"))
        probe = keras.Model(built.inputs, built.get_layer("pitch_dense_84").output)
        hidden = np.asarray(probe.predict(x, verbose=0))
        assert (hidden == 0).all() if built is relu else (hidden != 0).any()
    slight = build_model("cpl-a", backbone="small", image_size=SIZE, seed=0,
                         head_activation="leaky_relu_0.01")
    layer = slight.get_layer("pitch_dense_84")
    values = np.asarray(layer.activation(np.array([-2.0, 3.0], "float32")))
    np.testing.assert_allclose(values, [-0.02, 3.0], rtol=1e-6)
    for bad in (("deep-homo", "leaky_relu"), ("cpl-a", "tanh")):
        with pytest.raises(ValueError, match="head activation"):
            build_model(bad[0], backbone="small", image_size=SIZE, head_activation=bad[1])


def test_uniform_adaptive_and_euclidean_losses_by_hand():
    terms = [ops.convert_to_tensor(float(t)) for t in range(1, 14)]
    assert float(losses.uniform_projection_loss(terms)) == pytest.approx(7.0)
    s = ops.convert_to_tensor(np.log(np.arange(1, 14, dtype="float32")))
    # alpha_i = exp(-s_i) = 1 / i -> sum(alpha_i * i) = 13, plus sum(s_i) = log(13!)
    assert float(losses.adaptive_projection_loss(terms, s)) == pytest.approx(13 + np.log(6227020800.0), rel=1e-5)
    y_true = {n: np.zeros((2, 1), "float32") for n in TARGETS}
    y_pred = {n: np.full((2, 1), 2.0, "float32") for n in TARGETS}
    assert float(losses.euclidean_loss(y_true, y_pred)) == pytest.approx(2 * np.sqrt(13), rel=1e-6)


def test_cpl_a_learns_its_weights_and_they_cannot_collapse():
    model = compile_model(build_model("cpl-a", backbone="small", image_size=SIZE, seed=0))
    x, y = batch(8)
    start = model.adaptive_weights()
    assert start == pytest.approx({n: 1.0 for n in TARGETS})
    for _ in range(3):
        model.train_on_batch(x, y)
    learned = model.adaptive_weights()
    assert learned != pytest.approx(start)
    # Driving alpha_i = exp(-s_i) towards 0 costs s_i: with every term at 1 the
    # loss is smallest at alpha = 1 (s = 0) and grows as alpha collapses.
    terms = [ops.convert_to_tensor(1.0)] * 13
    at = lambda s: float(losses.adaptive_projection_loss(terms, ops.convert_to_tensor(np.full(13, s, "float32"))))
    assert at(0.0) == pytest.approx(13.0)
    assert at(0.0) < at(2.0) < at(20.0)
    assert at(0.0) < at(-2.0)


def test_compile_model_uses_the_paper_optimiser():
    model = compile_model(build_model("cpl-u", backbone="small", image_size=SIZE))
    assert isinstance(model.optimizer, keras.optimizers.Adam)
    assert float(model.optimizer.learning_rate) == pytest.approx(1e-3)
    homo = compile_model(build_model("deep-homo", image_size=SIZE))
    assert float(homo.optimizer.learning_rate) == pytest.approx(1.5e-3)
    assert homo.loss_mode == "euclidean"
    assert build_model("cpl-a", backbone="small", image_size=SIZE, as_released=True).loss_mode == "mae"
    with pytest.raises(ValueError, match="learning rate"):
        compile_model(model, learning_rate=-1.0)


@pytest.mark.parametrize("variant", ["cpl-a", "deep-homo"])
def test_keras_file_and_weights_round_trip(variant, tmp_path):
    model = compile_model(build_model(variant, backbone="small", image_size=SIZE, seed=0))
    x, y = batch(4)
    model.train_on_batch(x, y)
    expected = model.predict(x, verbose=0)

    path = os.fspath(tmp_path / "model.keras")
    model.save(path)
    loaded = keras.saving.load_model(path, safe_mode=True)
    assert loaded.build_settings == model.build_settings
    for a, b in zip(expected, loaded.predict(x, verbose=0)):
        np.testing.assert_array_equal(a, b)
    if variant == "cpl-a":
        assert loaded.adaptive_weights() == model.adaptive_weights()

    weights = os.fspath(tmp_path / "best.weights.h5")
    model.save_weights(weights)
    fresh = build_model(variant, backbone="small", image_size=SIZE, seed=123)
    fresh.load_weights(weights)
    for a, b in zip(expected, fresh.predict(x, verbose=0)):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("kwargs,message", [
    (dict(variant="mtl-x"), "unknown variant"),
    (dict(variant="baseline", image_size=74), "below the minimum of 75"),
    (dict(variant="baseline", image_size=(112, 112, 4)), "3 channels"),
    (dict(variant="baseline", image_size=(112, 112, 1)), "3 channels"),
    (dict(variant="baseline", backbone="resnet"), "unknown backbone"),
    (dict(variant="cpl-u", backbone="small", image_size=8), "below the minimum of 16"),
    (dict(variant="cpl-u", backbone="small", image_size="big"), "image_size must be"),
    (dict(variant="cpl-u", backbone="small", floors={"disparity": 0.0, "focal": 1.0}),
     "disparity floor must be a positive number"),
    (dict(variant="cpl-u", backbone="small", floors={"disparity": 1.0}), "floors must be a dict"),
    (dict(variant="cpl-u", backbone="small", disentangle="some"), "unknown disentangle"),
])
def test_bad_arguments_raise_a_clear_value_error(kwargs, message):
    variant = kwargs.pop("variant")
    with pytest.raises(ValueError, match=message):
        build_model(variant, **kwargs)


def test_every_head_reaches_x_y_z_through_the_camera_graph():
    """Perturb each head's value alone: X, Y, Z must move (the graph connects them)."""
    model = build_model("cpl-u", backbone="small", image_size=SIZE)
    heads = list(camera.PARAMETERS) + ["u", "v"]
    graph = keras.Model([model.get_layer(h).output for h in heads],
                        [model.get_layer(q).output for q in ("X", "Y", "Z")])
    base = {h: np.full((1, 1), 1.3, "float32") for h in heads}
    base.update(u=np.full((1, 1), 10.0, "float32"), v=np.full((1, 1), 20.0, "float32"),
                pitch=np.full((1, 1), 0.2, "float32"))
    reference = np.concatenate(graph.predict([base[h] for h in heads], verbose=0), axis=1)
    for head in heads:
        moved = dict(base, **{head: base[head] + 0.5})
        point = np.concatenate(graph.predict([moved[h] for h in heads], verbose=0), axis=1)
        assert np.abs(point - reference).max() > 1e-3, f"{head} does not reach X, Y, Z"


# ---------------------------------------------------------------------------
# The CPL losses against a second implementation of the paper's equations
# ---------------------------------------------------------------------------
def _paper_point(p, u, v):
    """Eqs. 4a-5c written out again here, in numpy: pixel and parameters to
    the world point (xCam = fx b / d; yCam, zCam from the pixel's offset to
    the principal point; then the pitch rotation and the translation)."""
    x_cam = p["fx"] * p["baseline"] / p["disparity"]
    y_cam = x_cam * (p["u0"] - u) / p["fx"]
    z_cam = x_cam * (p["v0"] - v) / p["fy"]
    c, s = np.cos(p["pitch"]), np.sin(p["pitch"])
    return (x_cam * c + z_cam * s + p["tx"], y_cam + p["ty"], -x_cam * s + z_cam * c + p["tz"])


def _paper_terms(truth, pred, u, v):
    """Eq. 7's 13 disentangled terms: parameter p predicted alone, the rest
    at the truth, the point re-projected; X, Y, Z by themselves; each /13."""
    parameters = ("fx", "fy", "u0", "v0", "baseline", "disparity", "pitch", "tx", "ty", "tz")
    terms = []
    for name in parameters:
        X, Y, Z = _paper_point(dict(truth, **{name: pred[name]}), u, v)
        terms.append(np.mean(np.abs(pred[name] - truth[name]) + np.abs(X - truth["X"])
                             + np.abs(Y - truth["Y"]) + np.abs(Z - truth["Z"])) / 13)
    order = list(parameters) + ["X", "Y", "Z"]
    terms += [np.mean(np.abs(pred[k] - truth[k])) / 13 for k in ("X", "Y", "Z")]
    return dict(zip(order, terms))


def _rig_batch(n=6, seed=3):
    """Consistent labels (the point made from a pixel by the equations above)
    and a prediction off by a few per cent in every output."""
    rng = np.random.default_rng(seed)
    truth = {"fx": rng.uniform(80, 120, n), "fy": rng.uniform(80, 120, n),
             "u0": rng.uniform(50, 60, n), "v0": rng.uniform(50, 60, n),
             "baseline": rng.uniform(0.3, 0.6, n), "disparity": rng.uniform(2, 20, n),
             "pitch": rng.uniform(-0.2, 0.2, n), "tx": rng.uniform(-1, 1, n),
             "ty": rng.uniform(-1, 1, n), "tz": rng.uniform(0.5, 2, n)}
    u, v = rng.uniform(0, 112, n), rng.uniform(0, 112, n)
    truth["X"], truth["Y"], truth["Z"] = _paper_point(truth, u, v)
    pred = {k: val * rng.uniform(0.9, 1.1, n) for k, val in truth.items()}
    return truth, pred, u, v


@pytest.mark.parametrize("variant", ["cpl-u", "cpl-a"])
def test_cpl_losses_equal_eq7_and_eq9_computed_independently(variant):
    """The model's loss on a batch equals Eq. 7 (MTL-CPL-U: the mean of the
    13 terms) or Eq. 9 (MTL-CPL-A: sum of exp(-s_i) L_i + s_i at chosen
    weights) computed by the numpy code above, not by the package's."""
    truth, pred, u, v = _rig_batch()
    model = build_model(variant, backbone="small", image_size=32)
    expected_terms = _paper_terms(truth, pred, u, v)
    as_tensors = {k: ops.convert_to_tensor(val[:, None].astype(np.float32))
                  for k, val in truth.items()}
    pred_tensors = {k: ops.convert_to_tensor(val[:, None].astype(np.float32))
                    for k, val in pred.items()}
    loss = float(ops.convert_to_numpy(model.compute_loss(y=as_tensors, y_pred=pred_tensors)))
    terms = np.array([expected_terms[k] for k in TARGETS])
    if variant == "cpl-u":
        expected = terms.mean()
    else:
        s = np.linspace(-1.0, 1.5, len(TARGETS))
        model.log_variances.assign((s / model.alpha_rate).astype(np.float32))
        model.log_variance_floor.assign(np.full(len(TARGETS), -50.0, np.float32))
        loss = float(ops.convert_to_numpy(model.compute_loss(y=as_tensors, y_pred=pred_tensors)))
        expected = np.sum(np.exp(-s) * terms + s)
    assert loss == pytest.approx(expected, rel=2e-5)
    assert terms.min() > 0 and np.ptp(terms) > 0.01 * terms.max()  # (a test that can tell)
