"""The tower backbones: sizes, feature counts and saving of the compact one."""

import os

import keras
import numpy as np
import pytest

from cpl_keras import build_model
from cpl_keras.models import backbones

#: Flattened features of ONE tower: {backbone: {image side: features}}.
FEATURES_PER_TOWER = {
    "inception_v3": {75: 1 * 1 * 2048, 112: 2 * 2 * 2048},
    "small": {16: 1 * 1 * 64, 112: 7 * 7 * 64},
    "small_resnet": {16: 1 * 1 * 128, 112: 4 * 4 * 128},
}


def test_every_backbone_is_registered_with_a_minimum_size_and_a_tower():
    assert set(backbones.BACKBONES) == set(FEATURES_PER_TOWER)
    assert set(backbones.MIN_IMAGE_SIZE) == set(backbones.BACKBONES)
    assert set(backbones.TOWERS) == set(backbones.BACKBONES)
    assert backbones.BACKBONES[0] == "inception_v3"  # the paper's, the default


@pytest.mark.parametrize("backbone", [
    pytest.param(name, marks=pytest.mark.slow) if name == "inception_v3" else name
    for name in sorted(FEATURES_PER_TOWER)])
@pytest.mark.parametrize("which", ["minimum", 112])
def test_stereo_features_have_the_expected_size(backbone, which):
    size = backbones.MIN_IMAGE_SIZE[backbone] if which == "minimum" else which
    left = keras.Input((size, size, 3))
    right = keras.Input((size, size, 3))
    features = backbones.stereo_features(left, right, backbone)
    assert tuple(features.shape) == (None, 2 * FEATURES_PER_TOWER[backbone][size])
    model = keras.Model([left, right], features)
    # two towers, no weight sharing
    towers = [layer for layer in model.layers if isinstance(layer, keras.Model)]
    assert [t.name for t in towers] == [f"left_{backbone}", f"right_{backbone}"]
    assert not {id(v) for v in towers[0].weights} & {id(v) for v in towers[1].weights}


def test_small_resnet_has_batch_norm_residual_stages_and_no_input_scaling():
    """Inputs arrive scaled to [-1, 1]: the tower must not rescale them again."""
    tower = backbones.TOWERS["small_resnet"](16, 16, "tower")
    kinds = [type(layer).__name__ for layer in tower.layers]
    assert not set(kinds) & {"Rescaling", "Normalization"}
    assert kinds.count("Add") == len(backbones.SMALL_RESNET_WIDTHS)
    assert kinds.count("BatchNormalization") == kinds.count("Conv2D") == 1 + 3 * len(
        backbones.SMALL_RESNET_WIDTHS)


def test_small_resnet_rejects_images_below_its_minimum():
    with pytest.raises(ValueError, match="below the minimum of 16"):
        build_model("baseline", backbone="small_resnet", image_size=15)


@pytest.mark.parametrize("variant", ["baseline", "cpl-a"])
def test_compact_backbone_model_saves_and_loads_with_identical_predictions(tmp_path, variant):
    size = backbones.MIN_IMAGE_SIZE["small_resnet"]
    model = build_model(variant, backbone="small_resnet", image_size=size, seed=0)
    rng = np.random.default_rng(0)
    x = {k: rng.uniform(0, 255, (2, size, size, 3)).astype("float32")
         for k in ("left_image", "right_image")}
    # move the BatchNormalization statistics off their initial values
    model(x, training=True)
    moving_mean = model.get_layer("left_small_resnet").get_layer("stem_bn").moving_mean
    assert np.any(keras.ops.convert_to_numpy(moving_mean) != 0)
    before = model.predict(x, verbose=0)
    path = os.path.join(tmp_path, "model.keras")
    model.save(path)
    loaded = keras.saving.load_model(path, safe_mode=True)
    after = loaded.predict(x, verbose=0)
    assert loaded.count_params() == model.count_params()
    for b, a in zip(before, after):
        np.testing.assert_array_equal(b, a)
