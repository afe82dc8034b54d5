"""The tower backbones: sizes, feature counts and saving of the compact one."""

import os

import keras
import numpy as np
import pytest

from cpl_keras import build_model
from cpl_keras.models import backbones, fast_layers

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
    convolutions = [layer for layer in tower.layers if isinstance(layer, keras.layers.Conv2D)]
    assert kinds.count("BatchNormalization") == len(convolutions) == 1 + 3 * len(
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


# ---------------------------------------------------------------------------
# PatchConv2D: a "same" convolution larger than its input, as one matmul
# ---------------------------------------------------------------------------

def _conv_pair(kernel_size, input_shape, **kwargs):
    """A built Conv2D and a PatchConv2D with the same config and weights."""
    conv = keras.layers.Conv2D(5, kernel_size, **kwargs)
    conv.build(input_shape)
    patch = fast_layers.PatchConv2D.from_config(conv.get_config())
    patch.build(input_shape)
    patch.set_weights(conv.get_weights())
    return conv, patch


@pytest.mark.parametrize("kernel_size,spatial,padding,path", [
    ((3, 3), (2, 2), "same", "patches"), ((3, 3), (1, 1), "same", "patches"),
    ((5, 5), (2, 4), "same", "patches"), ((3, 2), (2, 1), "same", "patches"),
    ((1, 3), (2, 2), "same", "conv"), ((3, 3), (3, 3), "same", "conv"),
    ((3, 3), (2, 5), "same", "conv"), ((3, 3), (26, 24), "same", "tap-gradient"),
    ((3, 3), (26, 26), "valid", "tap-gradient"), ((3, 5), (26, 30), "valid", "tap-gradient"),
    ((3, 3), (25, 25), "valid", "conv"), ((2, 2), (26, 26), "same", "conv")])
def test_patch_conv2d_matches_conv2d_values_and_gradients(kernel_size, spatial, padding, path):
    if keras.backend.backend() != "jax":
        pytest.skip("gradients through jax.grad (other backends: checked in docs/performance.md)")
    import jax

    shape = (2,) + spatial + (fast_layers.TAP_GRADIENT_MIN_CHANNELS if path == "tap-gradient" else 3,)
    conv, patch = _conv_pair(kernel_size, shape, padding=padding, activation="relu")
    assert patch.path(shape) == path
    x = np.random.default_rng(0).standard_normal(shape).astype("float32")

    def outputs_and_gradients(layer):
        # one compiled program per layer (op by op, the patch paths' many
        # small operations each compiled on their own)
        def loss(kernel, bias, inputs):
            outputs, _ = layer.stateless_call([kernel, bias], [], inputs)
            return keras.ops.sum(outputs ** 2), outputs
        grad = jax.jit(jax.grad(loss, argnums=(0, 1, 2), has_aux=True))
        return grad(conv.kernel.value, conv.bias.value, x)

    (patch_gradients, patch_outputs), (conv_gradients, conv_outputs) = (
        outputs_and_gradients(patch), outputs_and_gradients(conv))
    np.testing.assert_allclose(np.asarray(patch_outputs), np.asarray(conv_outputs), atol=1e-5)
    for got, expected in zip(patch_gradients, conv_gradients):
        np.testing.assert_allclose(np.asarray(got), np.asarray(expected), rtol=1e-4, atol=1e-4)


def test_patch_conv2d_keeps_conv2d_for_strides_dilation_1x1_kernels_and_few_channels():
    channels = fast_layers.TAP_GRADIENT_MIN_CHANNELS
    assert fast_layers.PatchConv2D(5, 3, padding="same").path((1, 30, 30, channels)) == "tap-gradient"
    assert fast_layers.PatchConv2D(5, 3, padding="same").path((1, 30, 30, channels - 1)) == "conv"
    for shape in ((1, 2, 2, 4), (1, 30, 30, channels)):
        for kwargs in ({"strides": 2}, {"dilation_rate": 2}):
            assert fast_layers.PatchConv2D(5, 3, padding="same", **kwargs).path(shape) == "conv"
        assert fast_layers.PatchConv2D(5, 1, padding="same").path(shape) == "conv"


def test_patch_convolutions_change_neither_weights_nor_outputs(monkeypatch):
    """The clone draws no random numbers: a seeded model is the one the plain
    Conv2D towers give, weight for weight, and computes the same outputs."""
    size = 64  # small_resnet's last stage runs a 3x3 convolution on 2 x 2 maps
    patched = build_model("cpl-a", backbone="small_resnet", image_size=size, seed=3)
    tower = patched.get_layer("left_small_resnet")
    assert {layer.name: layer.path(layer.input.shape) for layer in tower.layers
            if isinstance(layer, fast_layers.PatchConv2D)} == {"stage4_b_conv": "patches"}
    monkeypatch.setattr(backbones, "with_faster_layers", lambda tower: tower)
    plain = build_model("cpl-a", backbone="small_resnet", image_size=size, seed=3)
    assert not any(isinstance(layer, fast_layers.PatchConv2D)
                   for layer in plain.get_layer("left_small_resnet").layers)
    assert [w.path for w in patched.weights] == [w.path for w in plain.weights]
    for a, b in zip(patched.get_weights(), plain.get_weights()):
        np.testing.assert_array_equal(a, b)
    rng = np.random.default_rng(0)
    x = {k: rng.uniform(0, 255, (2, size, size, 3)).astype("float32")
         for k in ("left_image", "right_image")}
    for a, b in zip(patched.predict(x, verbose=0), plain.predict(x, verbose=0)):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-4)


def test_on_an_accelerator_the_faster_layers_keep_the_plain_computations(monkeypatch):
    """The patch and view paths are for XLA:CPU; on a GPU or TPU each layer
    computes as Conv2D / MaxPooling2D and the towers are built without them."""
    assert fast_layers.on_accelerator() in (True, False)
    monkeypatch.setattr(fast_layers, "on_accelerator", lambda: False)
    channels = fast_layers.TAP_GRADIENT_MIN_CHANNELS
    conv = fast_layers.PatchConv2D(5, 3, padding="same")
    pool = fast_layers.ViewMaxPooling2D(3, strides=2)
    tower = backbones.TOWERS["small_resnet"](64, 64, "tower")
    assert conv.path((1, 2, 2, 4)) == "patches"
    assert conv.path((1, 30, 30, channels)) == "tap-gradient"
    assert pool.path((1, 9, 9, 2)) == "views"
    assert backbones.with_faster_layers(tower) is not tower
    monkeypatch.setattr(fast_layers, "on_accelerator", lambda: True)
    assert conv.path((1, 2, 2, 4)) == "conv"
    assert conv.path((1, 30, 30, channels)) == "conv"
    assert pool.path((1, 9, 9, 2)) == "pool"
    assert backbones.with_faster_layers(tower) is tower


@pytest.mark.slow
def test_inception_v3_at_112_takes_the_patch_paths_where_expected():
    """mixed9 and mixed10 each have one 3x3 convolution on 2 x 2 maps at 112 x 112
    (patches); the stem's three stride-1 3x3 convolutions on 53 x 53 and 24 x 24 maps
    get tap gradients; the 1x3, 3x1 and 1x7 kernels fit their maps in one dimension
    and stay Conv2D."""
    tower = backbones.with_faster_layers(
        backbones.TOWERS["inception_v3"](112, 112, "tower"))
    paths = {layer.name: (layer.path(layer.input.shape), tuple(layer.input.shape[1:]))
             for layer in tower.layers if isinstance(layer, fast_layers.PatchConv2D)}
    assert sorted(path for path, _ in paths.values()) == ["patches"] * 2 + ["tap-gradient"] * 3
    assert {shape for path, shape in paths.values() if path == "patches"} == {(2, 2, 448)}
    assert {shape for path, shape in paths.values() if path == "tap-gradient"} == {
        (55, 55, 32), (53, 53, 32), (26, 26, 80)}
    # the four 3x3, stride-2 max-poolings (the stem's two, mixed3's and
    # mixed8's) take views; no MaxPooling2D is left
    pools = [tuple(layer.input.shape[1:]) for layer in tower.layers
             if isinstance(layer, fast_layers.ViewMaxPooling2D)
             and layer.path(layer.input.shape) == "views"]
    assert pools == [(53, 53, 64), (24, 24, 192), (11, 11, 288), (5, 5, 768)]
    assert not any(type(layer) is keras.layers.MaxPooling2D for layer in tower.layers)


# ---------------------------------------------------------------------------
# ViewMaxPooling2D: max pooling as the maximum of strided views
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("pool_size,shape", [
    ((2, 2), (2, 8, 8, 3)), ((2, 2), (2, 9, 7, 3)), ((3, 3), (1, 9, 11, 2)),
    ((2, 3), (2, 6, 9, 4)), ((1, 2), (1, 3, 4, 1)), ((3, 3, 2), (2, 9, 9, 3)),
    ((3, 3, 2), (2, 8, 10, 3)), ((3, 2, 1), (1, 5, 6, 2))])
def test_view_max_pooling_matches_max_pooling_values_and_gradients(pool_size, shape):
    """Tiling and overlapping windows (pool, stride), with the last rows or
    columns that no window reaches."""
    if keras.backend.backend() != "jax":
        pytest.skip("gradients through jax.grad")
    import jax

    strides = pool_size[2] if len(pool_size) == 3 else None
    by_views = fast_layers.ViewMaxPooling2D(pool_size[:2], strides=strides)
    pool = keras.layers.MaxPooling2D(pool_size[:2], strides=strides)
    assert by_views.path(shape) == "views"
    x = np.random.default_rng(0).standard_normal(shape).astype("float32")  # no ties
    np.testing.assert_array_equal(np.asarray(by_views(x)), np.asarray(pool(x)))
    weights = np.random.default_rng(1).standard_normal(pool(x).shape).astype("float32")

    def gradient(layer):
        return np.asarray(jax.grad(lambda inputs: keras.ops.sum(layer(inputs) * weights))(x))

    # (an input in several windows sums their gradients, maybe in another order)
    np.testing.assert_allclose(gradient(by_views), gradient(pool), rtol=1e-6, atol=1e-6)


def test_view_max_pooling_splits_a_tied_window_and_keeps_pooling_for_same_padding():
    if keras.backend.backend() != "jax":
        pytest.skip("gradients through jax.grad")
    import jax

    by_views = fast_layers.ViewMaxPooling2D(2)
    x = np.array([[1.0, 1.0, 0.0, 5.0], [1.0, 1.0, 2.0, 0.0]], "float32")[None, :, :, None]
    gradient = np.asarray(jax.grad(lambda inputs: keras.ops.sum(by_views(inputs)))(x))[0, :, :, 0]
    np.testing.assert_array_equal(gradient, [[0.25, 0.25, 0, 1], [0.25, 0.25, 0, 0]])
    shape = (1, 8, 8, 1)
    assert fast_layers.ViewMaxPooling2D(3, strides=2).path(shape) == "views"
    assert fast_layers.ViewMaxPooling2D(2, padding="same").path(shape) == "pool"
    assert fast_layers.ViewMaxPooling2D(2).path((1, None, None, 1)) == "pool"
    with fast_layers.xla_layers_only():
        assert by_views.path(shape) == "pool"
        assert fast_layers.PatchConv2D(4, 3, padding="same").path((1, 30, 30, 64)) == "conv"
    assert by_views.path(shape) == "views"


def test_the_faster_layers_keep_their_registered_names():
    """Saved models name the layers ``cpl_keras>PatchConv2D`` and
    ``cpl_keras>ViewMaxPooling2D``; one saved when they lived in
    ``cpl_keras.models.backbones`` (its config's module) loads as well."""
    for layer in (fast_layers.PatchConv2D(4, 3, padding="same"), fast_layers.ViewMaxPooling2D(2)):
        name = type(layer).__name__
        assert keras.saving.get_registered_name(type(layer)) == f"cpl_keras>{name}"
        config = keras.saving.serialize_keras_object(layer)
        assert config["registered_name"] == f"cpl_keras>{name}"
        config["module"] = "cpl_keras.models.backbones"
        restored = keras.saving.deserialize_keras_object(config, safe_mode=True)
        assert type(restored) is type(layer) and restored.get_config() == layer.get_config()


def test_deep_homo_takes_the_kernel_gradient_path_on_its_larger_maps(monkeypatch):
    """Deep-Homo's convolutions are PatchConv2D: at 112 x 112 the 3x3
    convolutions with 64-128 input channels on the 112, 56 and 28 px maps
    take the matrix-product kernel gradient, conv1_1 (two input channels)
    and the 14 px pair stay XLA's; the weights are those the plain Conv2D
    layers draw with the same seed."""
    from cpl_keras.models import deep_homo

    model = build_model("deep-homo", image_size=112, seed=4)
    paths = {layer.name: layer.path(layer.input.shape) for layer in model.layers
             if isinstance(layer, fast_layers.PatchConv2D)}
    assert paths == {"conv1_1": "conv", "conv1_2": "tap-gradient",
                     "conv2_1": "tap-gradient", "conv2_2": "tap-gradient",
                     "conv3_1": "tap-gradient", "conv3_2": "tap-gradient",
                     "conv4_1": "conv", "conv4_2": "conv"}
    assert {layer.name: layer.path(layer.input.shape) for layer in model.layers
            if isinstance(layer, fast_layers.ViewMaxPooling2D)} == {
        "max_pool1": "views", "max_pool2": "views", "max_pool3": "views"}
    monkeypatch.setattr(deep_homo, "PatchConv2D", keras.layers.Conv2D)
    plain = build_model("deep-homo", image_size=112, seed=4)
    assert not any(isinstance(layer, fast_layers.PatchConv2D) for layer in plain.layers)
    assert [w.path for w in model.weights] == [w.path for w in plain.weights]
    for a, b in zip(model.get_weights(), plain.get_weights()):
        np.testing.assert_array_equal(a, b)
