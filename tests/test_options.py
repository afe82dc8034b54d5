"""The options records: ``models/options.py`` (ModelOptions) and
``training_options.py`` (TrainingOptions), and the switches they carry."""

import dataclasses

import numpy as np
import pytest

from cpl_keras.camera import FLOORS, TARGETS
from cpl_keras.models.options import ALWAYS_WRITTEN, ModelOptions, OptionsError, check_momentum
from cpl_keras.training_options import (
    RECIPES, TrainingError, TrainingOptions, recipe, split_fields,
)

SIZE = 32


def labels(n=50, seed=0):
    rng = np.random.default_rng(seed)
    return {name: rng.uniform(1.0, 3.0, n) for name in TARGETS}


@pytest.mark.parametrize("fields, message", [
    (dict(backbone="vgg"), "unknown backbone 'vgg'"),
    (dict(head_activation="tanh"), "unknown head activation 'tanh'"),
    (dict(disparity_head="exp"), "unknown disparity head 'exp'"),
    (dict(adaptive_weights="mean"), "unknown adaptive weights 'mean'"),
    (dict(head_norm=1), "head norm must be true or false"),
    (dict(alpha_rate=-1.0), "alpha rate must be a number >= 0"),
    (dict(disparity_ceiling=0.001), "disparity ceiling must be 'auto', None or a number"),
    (dict(disparity_start=float("nan")), "disparity start must be"),
    (dict(range_scales={"fx": 1.0}), "range scales must be"),
    (dict(variant="cpl-b"), "unknown variant 'cpl-b'"),
])
def test_a_bad_option_is_one_line_naming_it(fields, message):
    with pytest.raises(OptionsError, match=message) as error:
        ModelOptions(**fields)
    assert "\n" not in str(error.value)
    with pytest.raises(OptionsError, match="unknown model option 'pear'"):
        ModelOptions().replace(pear=1)
    with pytest.raises(dataclasses.FrozenInstanceError):
        ModelOptions().head_norm = True


@pytest.mark.parametrize("variant, fields, message", [
    ("cpl-a", dict(exp_disparity_head=True), "exp disparity head is MTL-Baseline's ablation"),
    ("deep-homo", dict(head_norm=True), "head norm applies to the regression heads"),
    ("deep-homo", dict(disparity_head="softplus"), "disparity head 'softplus' applies"),
    ("baseline", dict(point_errors="relative"), "apply to the camera projection loss"),
    ("cpl-u", dict(adaptive_weights="range"), "apply to Eq. 9's weights, which cpl-u"),
    ("cpl-a", dict(adaptive_weights="range", alpha_rate=3.0), "range weights are fixed"),
])
def test_the_variant_rules_are_checked_once(variant, fields, message):
    with pytest.raises(OptionsError, match=message):
        ModelOptions(**fields).for_variant(variant)


def test_the_build_config_of_the_defaults_is_the_one_of_every_earlier_run():
    """config.json's ``build`` for the paper's defaults has exactly the keys
    runs had before the record (so they resume), and a field added since
    appears only when set."""
    cpl_a = ModelOptions().for_variant("cpl-a").for_training_set(labels(), 2.0)
    assert cpl_a.to_config() == {
        "variant": "cpl-a", "backbone": "inception_v3", "as_released": False, "floors": dict(FLOORS),
        "bounded_pitch_head": True, "positive_focal_head": True, "disentangle": "exact",
        "disparity_ceiling": pytest.approx(2 * labels()["disparity"].max(), abs=1e-3),
        "alpha_rate": 10.0}
    baseline = ModelOptions().for_variant("baseline").for_training_set(labels(), 2.0)
    assert set(baseline.to_config()) == set(ALWAYS_WRITTEN) | {"variant"}
    assert baseline.to_config()["disparity_ceiling"] is None  # (its head is linear)
    # (the switches its network has no use for, recorded as off: as built)
    assert (baseline.positive_focal_head, baseline.disentangle) == (False, None)
    deep_homo = ModelOptions().for_variant("deep-homo")
    assert (deep_homo.bounded_pitch_head, deep_homo.positive_focal_head,
            deep_homo.disentangle) == (False, False, None)
    assert deep_homo.for_variant("deep-homo") == deep_homo  # (resolved once and for all)
    assert deep_homo.spec.name == "deep-homo"  # (the record keeps its variant)
    with pytest.raises(OptionsError, match="not resolved for a variant"):
        assert ModelOptions().spec is None
    with pytest.raises(OptionsError, match="these options are deep-homo's, not cpl-a's"):
        deep_homo.for_variant("cpl-a")
    released = ModelOptions(as_released=True).for_variant("cpl-a")
    assert released.bounded_pitch_head is False and released.positive_focal_head is False
    # the record reads back its own config (with the image size and seed beside it)
    again = ModelOptions.from_config(dict(cpl_a.to_config(), image_size=[32, 32], seed=0))
    assert again.for_variant("cpl-a").to_config() == cpl_a.to_config()
    new = ModelOptions(head_norm=True).for_variant("baseline")
    assert {"head_norm": True}.items() <= new.to_config().items()
    assert "disparity_head" not in new.to_config()


def test_auto_fields_are_read_off_the_training_labels():
    train = labels()
    options = ModelOptions(disparity_head="softplus", adaptive_weights="range")
    cpl_a = options.for_variant("cpl-a").for_training_set(train, 2.0)
    assert cpl_a.disparity_ceiling == pytest.approx(2 * train["disparity"].max(), abs=1e-3)
    assert cpl_a.disparity_start == pytest.approx(train["disparity"].mean(), abs=1e-3)
    assert cpl_a.range_scales["pitch"] == pytest.approx(np.abs(train["pitch"]).mean(), rel=1e-5)
    assert cpl_a.alpha_rate == 0.0  # (fixed)
    baseline = ModelOptions(disparity_head="softplus").for_variant("baseline")
    assert baseline.disparity_ceiling == "auto" and baseline.range_scales is None
    assert ModelOptions().for_variant("baseline").disparity_start is None


def test_recipes_are_sets_of_fields_of_the_two_records():
    assert recipe("paper") == {}
    model, training = split_fields(recipe("sound"))
    sound = ModelOptions(**model)
    assert (sound.head_activation, sound.head_norm, sound.disparity_head) == (
        "leaky_relu_0.01", True, "softplus")
    assert training == {"clip_norm": 1.0}  # (the optimiser's: the training record's)
    assert set(RECIPES) == {"paper", "sound"}
    with pytest.raises(TrainingError, match="unknown recipe 'fast'"):
        recipe("fast")
    assert not {"weight_decay", "clip_norm"} & {f.name for f in dataclasses.fields(ModelOptions)}


def test_training_options_are_checked_once_and_fields_go_to_their_record():
    assert TrainingOptions().epochs == 200
    for fields, message in ((dict(epochs=0), "epochs must be a positive integer"),
                            (dict(patience=-1), "patience must be a non-negative"),
                            (dict(weight_ema=1.0), "moving-average momentum must be in"),
                            (dict(monitor="acc"), "unknown monitor 'acc'"),
                            (dict(split="random"), "unknown split 'random'"),
                            (dict(weight_decay=-1e-4), "weight decay must be a number >= 0"),
                            (dict(clip_norm=0.0), "clip norm must be a positive number"),
                            (dict(clip_norm=True), "clip norm must be a positive number")):
        with pytest.raises(TrainingError, match=message):
            TrainingOptions(**fields)
    model, training = split_fields(dict(epochs=3, head_norm=True, seed=2, backbone="small"))
    assert model == {"head_norm": True, "backbone": "small"}
    assert training == {"epochs": 3, "seed": 2}
    with pytest.raises(TrainingError, match="unknown training option 'pear'"):
        split_fields(dict(pear=1))
    assert check_momentum(0) == 0.0
    with pytest.raises(ValueError, match="momentum must be in"):
        check_momentum(float("inf"))


def test_train_command_line_routes_recipe_and_options_to_the_record():
    from cpl_keras.commands import train

    parser = train.build_parser()
    args = parser.parse_args(["--variant", "baseline", "--recipe", "sound",
                              "--head-activation", "relu", "--linear-pitch-head",
                              "--disparity-ceiling", "none"])
    model, training = train.records(args, False, 0, 200, "small")
    assert model.head_activation == "relu"  # (given: overrides the recipe's)
    assert model.head_norm is True and training.clip_norm == 1.0
    assert model.bounded_pitch_head is False and model.disparity_ceiling is None
    plain = train.records(parser.parse_args(["--variant", "cpl-a"]), False, 0, 200,
                          "inception_v3")
    assert plain == (ModelOptions(), TrainingOptions())
    given = parser.parse_args(["--variant", "cpl-a", "--lr", "0.01", "--time-budget", "60",
                               "--augment", "photometric", "--weight-decay", "0.001"])
    _, training = train.records(given, False, 0, 200, "small")
    assert (training.learning_rate, training.time_budget_s, training.augment,
            training.weight_decay) == (0.01, 60.0, "photometric", 0.001)


# ---------------------------------------------------------------------------
# The switches in the model (Keras)
# ---------------------------------------------------------------------------
def test_softplus_disparity_head_starts_at_its_start_and_stays_positive():
    from keras import ops

    from cpl_keras import build_model
    from cpl_keras.layers import SoftplusDisparity

    head = SoftplusDisparity(ceiling=1000.0)
    for start in (0.5, 30.0, 495.195):
        assert float(head(ops.convert_to_tensor(head.bias_for(start)))) == pytest.approx(
            start, rel=1e-5)
    values = np.asarray(head(ops.convert_to_tensor([-1e4, 0.0, 1e6], "float32")))
    assert np.all(np.isfinite(values)) and values[0] >= FLOORS["disparity"]
    assert values[2] == 1000.0
    model = build_model("baseline", backbone="small", image_size=SIZE, seed=0,
                        disparity_head="softplus", disparity_start=300.0, head_norm=True)
    assert model.get_layer("head_norm") is not None
    x = np.random.default_rng(0).uniform(0, 255, (2, SIZE, SIZE, 3)).astype("float32")
    disparity = model.predict({"left_image": x, "right_image": x}, verbose=0)[
        TARGETS.index("disparity")]
    assert np.all(np.abs(disparity - 300.0) < 30.0)  # (the bias sets it; small weights move it)


def test_range_weights_are_fixed_at_the_inverse_scales_and_survive_saving(tmp_path):
    import keras

    import cpl_keras.saving  # noqa: F401
    from cpl_keras import build_model

    scales = {name: float(i + 1) for i, name in enumerate(TARGETS)}
    model = build_model("cpl-a", backbone="small", image_size=SIZE, seed=0,
                        adaptive_weights="range", range_scales=scales)
    expected = {name: 1.0 / scale for name, scale in scales.items()}
    assert model.adaptive_weights() == pytest.approx(expected, rel=1e-5)
    assert not model.log_variances.trainable
    y = {name: np.full((4, 1), 2.0, "float32") for name in TARGETS}
    assert model.initialise_adaptive_weights(y) == pytest.approx(expected, rel=1e-5)
    path = tmp_path / "range.keras"
    model.save(path)
    loaded = keras.saving.load_model(path, safe_mode=True)
    assert loaded.adaptive_weights() == pytest.approx(expected, rel=1e-5)
    with pytest.raises(OptionsError, match="range weights' scales are read off"):
        build_model("cpl-a", backbone="small", image_size=SIZE, adaptive_weights="range")


def test_weight_decay_and_clip_norm_reach_the_optimiser():
    import keras

    from cpl_keras import build_model, compile_model

    model = compile_model(build_model("cpl-a", backbone="small", image_size=SIZE, seed=0),
                          TrainingOptions(weight_decay=1e-4, clip_norm=1.0))
    assert isinstance(model.optimizer, keras.optimizers.AdamW)
    assert model.optimizer.weight_decay == pytest.approx(1e-4)
    assert model.optimizer.global_clipnorm == 1.0
    assert not model.optimizer._use_weight_decay(model.log_variances)  # (Eq. 9's own)
    plain = compile_model(build_model("baseline", backbone="small", image_size=SIZE, seed=0))
    assert type(plain.optimizer) is keras.optimizers.Adam
    assert plain.optimizer.global_clipnorm is None
