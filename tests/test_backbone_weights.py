"""Towers from ImageNet weights (``--backbone-weights``,
``ModelOptions.backbone_weights``, ``cpl_keras.models.pretrained``).

Offline: both of Keras's file layouts are written here from a stock
InceptionV3 whose weights are random, and the ImageNet download is made to
fail (nothing is downloaded). The InceptionV3 builds and the training run are
``slow``; the refusals that planning makes are quick.
"""

import contextlib
import hashlib
import json
import os
import shutil

import numpy as np
import pytest

from cpl_keras.models import pretrained
from cpl_keras.models.options import ModelOptions, OptionsError
from helpers import interrupt_after_epoch, load_script, release_flat, write_stereo_fixture

#: The smallest image InceptionV3 takes (``variants.MIN_IMAGE_SIZE``).
SIZE = 75
#: The InceptionV3 layers that hold weights: 94 convolutions, 94 BatchNorms.
WEIGHTED_LAYERS = 188


# ---------------------------------------------------------------------------
# The files
# ---------------------------------------------------------------------------
@pytest.fixture(scope="module")
def small_files(tmp_path_factory):
    """What needs no InceptionV3: a tiny 75-px dataset ("data"), another
    network's weights in both layouts ("wrong", "wrong_legacy"), a text file."""
    import h5py
    import keras
    from keras.src.legacy.saving import legacy_h5_format

    folder = tmp_path_factory.mktemp("small_files")
    paths = {"data": write_stereo_fixture(folder / "data.h5", n=24, image_size=SIZE),
             "wrong": str(folder / "small.weights.h5"),
             "wrong_legacy": str(folder / "small.h5"), "text": str(folder / "notes.h5")}
    small = keras.Sequential([keras.Input((8, 8, 3)), keras.layers.Conv2D(4, 3)])
    small.save_weights(paths["wrong"])
    with h5py.File(paths["wrong_legacy"], "w") as f:
        legacy_h5_format.save_weights_to_hdf5_group(f, small)
    with open(paths["text"], "w") as f:
        f.write("not weights\n")
    return paths


@pytest.fixture(scope="module")
def weight_files(small_files, tmp_path_factory):
    """``small_files`` and InceptionV3(include_top=False) weights (random, not
    Keras's fresh ones) in both layouts, under names whose endings do not
    tell Keras the layout, and in Keras's legacy layout under the name of
    Keras's ImageNet file ("notop")."""
    import h5py
    import keras
    from keras.src.legacy.saving import legacy_h5_format

    folder = tmp_path_factory.mktemp("backbone_weights")
    stock = keras.applications.InceptionV3(include_top=False, weights=None,
                                           input_shape=(SIZE, SIZE, 3))
    rng = np.random.default_rng(0)  # (BatchNorm variances stay positive)
    stock.set_weights([w + rng.normal(0, 0.01, w.shape).astype(w.dtype)
                       for w in stock.get_weights()])
    paths = dict(small_files, legacy=str(folder / "legacy.weights.h5"),  # (Keras: Keras 3's)
                 keras3=str(folder / "keras3.bin"), notop=str(folder / pretrained.IMAGENET_FILE))
    with h5py.File(paths["legacy"], "w") as f:
        legacy_h5_format.save_weights_to_hdf5_group(f, stock)
    stock.save_weights(str(folder / "keras3.weights.h5"))
    os.rename(folder / "keras3.weights.h5", paths["keras3"])
    shutil.copy(paths["legacy"], paths["notop"])
    return paths


def file_weights(path, classes):
    """``[(name in the file, [arrays])]`` of each InceptionV3 layer that holds
    weights, in the network's order, read with h5py alone (``classes``: those
    layers' class names in snake case, by which Keras 3's layout numbers them)."""
    import h5py

    found = []
    with h5py.File(path, "r") as f:
        if "layer_names" in f.attrs:  # legacy: a group per layer, in order
            for name in (n.decode() if isinstance(n, bytes) else n for n in f.attrs["layer_names"]):
                names = [w.decode() if isinstance(w, bytes) else w
                         for w in f[name].attrs["weight_names"]]
                if names:
                    found.append((name, [f[name][w][()] for w in names]))
            return found
        counts = {}  # Keras 3: layers/<class>[_k]/vars/<i>, numbered per class in order
        for base in classes:
            k = counts.get(base, 0)
            counts[base] = k + 1
            name = base if k == 0 else f"{base}_{k}"
            variables = f["layers"][name]["vars"]
            found.append((name, [variables[str(i)][()] for i in range(len(variables))]))
    return found


def tower_weights(model, side):
    """``[(layer name, [arrays])]`` of a tower's layers that hold weights, and
    their classes as Keras 3's layout names them (a PatchConv2D is a Conv2D)."""
    import keras

    layers = [layer for layer in model.get_layer(f"{side}_inception_v3").layers if layer.weights]
    classes = ["conv2d" if isinstance(layer, keras.layers.Conv2D) else "batch_normalization"
               for layer in layers]
    return [(layer.name, layer.get_weights()) for layer in layers], classes


def sha256(path):
    with open(path, "rb") as f:
        return hashlib.sha256(f.read()).hexdigest()


# ---------------------------------------------------------------------------
# The towers
# ---------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("layout", ["legacy", "keras3"])
def test_both_towers_start_from_the_file(weight_files, layout):
    """Every weighted layer of both towers (the faster layers swapped in)
    holds the file's weights, layer by layer in the network's order (names
    differ: Keras numbers them per process); the file is told by its
    contents, not its name."""
    from cpl_keras import build_model

    path = weight_files[layout]
    assert pretrained.layout(path) == layout
    model = build_model("cpl-a", image_size=SIZE, seed=0, backbone_weights=path)
    for side in ("left", "right"):
        got, classes = tower_weights(model, side)
        expected = file_weights(path, classes)
        assert len(got) == len(expected) == WEIGHTED_LAYERS
        for (name, values), (file_name, file_values) in zip(got, expected):
            assert len(values) == len(file_values), (side, name, file_name)
            for value, file_value in zip(values, file_values):
                np.testing.assert_array_equal(value, file_value, err_msg=f"{side} {name} "
                                              f"({file_name} in the file)")
    assert model.build_settings["backbone_weights"] == path


def test_the_option_is_recorded_only_when_given():
    assert "backbone_weights" not in ModelOptions().to_config()  # (runs of before read alike)
    assert ModelOptions(backbone_weights="imagenet").to_config()["backbone_weights"] == "imagenet"
    with pytest.raises(OptionsError, match="'small' has none"):
        ModelOptions(backbone="small", backbone_weights="imagenet")
    with pytest.raises(OptionsError, match="deep-homo has no towers"):
        ModelOptions(backbone_weights="imagenet").for_variant("deep-homo")
    with pytest.raises(OptionsError, match="64 lowercase hex"):
        ModelOptions(backbone_weights="imagenet", backbone_weights_sha256="abc")


# ---------------------------------------------------------------------------
# "imagenet": Keras's cache, else its download
# ---------------------------------------------------------------------------
def _no_download(*args, **kwargs):
    raise Exception(f"URL fetch failure on {pretrained.IMAGENET_URL}: None -- [Errno -3] "
                    f"Temporary failure in name resolution")


def test_imagenet_is_read_from_keras_cache(small_files, tmp_path, monkeypatch):
    """The cached file is used as it is, not downloaded (its contents are
    checked when the towers are built)."""
    import keras

    monkeypatch.setenv("KERAS_HOME", str(tmp_path))
    monkeypatch.setattr(keras.utils, "get_file", _no_download)
    (tmp_path / "models").mkdir()
    cached = tmp_path / "models" / pretrained.IMAGENET_FILE
    shutil.copy(small_files["wrong_legacy"], cached)
    assert pretrained.weights_file("imagenet") == str(cached)


def test_imagenet_offline_fails_in_one_line_naming_the_url(small_files, tmp_path, monkeypatch,
                                                           capsys):
    import keras

    monkeypatch.setenv("KERAS_HOME", str(tmp_path / "keras"))
    monkeypatch.setattr(keras.utils, "get_file", _no_download)
    with pytest.raises(pretrained.WeightsError) as raised:
        pretrained.weights_file("imagenet")
    message = str(raised.value)
    assert "\n" not in message and pretrained.IMAGENET_URL in message
    assert "--backbone-weights FILE" in message and "name resolution" in message
    run_dir = tmp_path / "run"
    assert _train(small_files, "imagenet", run_dir) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and pretrained.IMAGENET_URL in err
    assert not run_dir.exists()


# ---------------------------------------------------------------------------
# train.py: refusals, the run's record, resuming
# ---------------------------------------------------------------------------
def _train(weight_files, weights, run_dir, *extra, variant="cpl-a", data=None):
    """train.py's exit status with ``--backbone-weights weights`` (None: none)."""
    argv = ["--variant", variant, "--data", data or weight_files["data"], "--epochs", "1",
            "--batch-size", "4", "--bn-recompute-batches", "0", "--weight-ema", "0",
            "--run-dir", str(run_dir), "--quiet", *extra]
    if weights is not None:
        argv += ["--backbone-weights", weights]
    return load_script("train.py").main(argv)


def _refused(capsys, status, run_dir, *words):
    err = capsys.readouterr().err
    assert status == 2 and err.count("\n") == 1 and err.startswith("train.py: error:"), err
    assert all(word in err for word in words), err
    assert not os.path.exists(run_dir)


@pytest.mark.parametrize("what, words", [
    ("missing", ["missing.h5", "no such"]), ("text", ["notes.h5", "not an HDF5 file"]),
])
def test_a_missing_or_non_hdf5_file_is_refused(small_files, tmp_path, capsys, what, words):
    path = small_files["text"] if what == "text" else str(tmp_path / "missing.h5")
    _refused(capsys, _train(small_files, path, tmp_path / "run"), tmp_path / "run", *words)


def test_other_backbones_and_deep_homo_are_refused(small_files, tmp_path, capsys):
    run_dir = tmp_path / "run"
    for backbone in ("small", "small_resnet"):
        status = _train(small_files, small_files["wrong"], run_dir, "--backbone", backbone)
        _refused(capsys, status, run_dir, f"backbone '{backbone}' has none")
    status = _train(small_files, small_files["wrong"], run_dir, variant="deep-homo")
    _refused(capsys, status, run_dir, "deep-homo has no towers")


@pytest.mark.slow
def test_a_wrong_weights_file_is_refused(small_files, tmp_path, capsys):
    """Another network's weights: refused when the towers are built, before
    anything is written."""
    run_dir = tmp_path / "run"
    status = _train(small_files, small_files["wrong"], run_dir)
    _refused(capsys, status, run_dir, small_files["wrong"], "not InceptionV3's weights")


@pytest.fixture(scope="module")
def release_data(tmp_path_factory):
    """24 rendered cvgl pairs written in the authors' release format and
    imported (``cpl_keras.data.import_cvgl``): the paper's own inputs, as a
    user who has them would train on them."""
    from cpl_keras.commands import import_cvgl
    from cpl_keras.data.generate import generate_dataset

    folder = tmp_path_factory.mktemp("release")
    rendered = generate_dataset(str(folder / "rendered.h5"), protocol="cvgl", pairs=24, seed=0,
                                image_size=112, workers=1, progress=False)
    release_flat(rendered, str(folder / "flat"))
    out = str(folder / "cvgl_release.h5")
    assert import_cvgl.main([str(folder / "flat"), "--out", out, "--no-progress"]) == 0
    return out


#: The paper's experiment on the imported release: its split, as released.
RELEASE_ARGS = ("--split", "released", "--as-released")


@pytest.fixture(scope="module")
def half_run(weight_files, release_data, tmp_path_factory):
    """train.py with --backbone-weights on the imported release (its split,
    as released), 2 epochs, stopped after the first (as a kill would):
    ``(run_dir, its weights file)``."""
    folder = tmp_path_factory.mktemp("half_run")
    weights = str(folder / pretrained.IMAGENET_FILE)
    shutil.copy(weight_files["notop"], weights)
    run_dir = folder / "run"
    with pytest.MonkeyPatch.context() as monkeypatch:
        interrupt_after_epoch(monkeypatch, 1)
        assert _train(weight_files, weights, run_dir, "--epochs", "2", *RELEASE_ARGS,
                      data=release_data) == 130
    return run_dir, weights


@pytest.mark.slow
def test_the_run_records_the_file_and_its_checksum(half_run):
    run_dir, weights = half_run
    with open(run_dir / "config.json") as f:
        build = json.load(f)["build"]
    assert build["backbone_weights"] == weights  # (its absolute path)
    assert build["backbone_weights_sha256"] == sha256(weights)
    assert build["backbone"] == "inception_v3" and build["as_released"] is True
    with open(run_dir / "config.json") as f:
        assert json.load(f)["split"] == "released"


@pytest.mark.slow
def test_a_resume_with_other_weights_is_refused(weight_files, half_run, capsys):
    run_dir, weights = half_run
    with open(run_dir / "config.json") as f:
        before = f.read()
    for other in (weight_files["legacy"], None):
        capsys.readouterr()
        assert _train(weight_files, other, run_dir, "--epochs", "2", *RELEASE_ARGS,
                      data=half_run_data(run_dir)) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "holds a different run (build:" in err
    with open(run_dir / "config.json") as f:
        assert f.read() == before


@pytest.fixture(scope="module")
def resumed_run(weight_files, half_run, tmp_path_factory):
    """``half_run`` resumed by the same command with its weights file gone:
    ``(run_dir, weights, train.py's exit status)``."""
    run_dir, weights = half_run
    with _moved_away(weights, tmp_path_factory.mktemp("away")):
        status = _train(weight_files, weights, run_dir, "--epochs", "2", *RELEASE_ARGS,
                        data=half_run_data(run_dir))
    return run_dir, weights, status


def half_run_data(run_dir):
    """The dataset ``half_run`` trained on (its config.json's)."""
    with open(os.path.join(run_dir, "config.json")) as f:
        return json.load(f)["data"]


@contextlib.contextmanager
def _moved_away(path, folder):
    """``path`` moved into ``folder`` for the block, then back."""
    away = os.path.join(folder, "away.h5")
    os.rename(path, away)
    try:
        yield
    finally:
        os.rename(away, path)


@pytest.mark.slow
def test_a_resumed_run_reads_no_weights_file(resumed_run):
    """Resumed from its checkpoint, the run reads no weights file (its
    weights come from the checkpoint) and keeps its record of the file."""
    run_dir, weights, status = resumed_run
    assert status == 0
    with open(run_dir / "config.json") as f:
        config = json.load(f)
    assert config["status"] == "finished" and config["epochs_run"] == 2
    assert config["build"]["backbone_weights_sha256"] == sha256(weights)


@pytest.mark.slow
def test_the_saved_model_loads_without_the_weights_file(resumed_run, tmp_path):
    from cpl_keras import load_model

    run_dir, weights, _ = resumed_run
    with _moved_away(weights, tmp_path):
        model = load_model(str(run_dir))  # (safe_mode=True)
    assert model.build_settings["backbone_weights"] == weights
    assert model.build_settings["backbone_weights_sha256"] == sha256(weights)
