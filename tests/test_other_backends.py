"""The core model tests under Keras's TensorFlow and PyTorch backends, where installed,
and the one line that a backend which is not installed gets.

The package's model code is ``keras.ops`` only. These tests run the model,
camera, backbone and training test files in a subprocess with
``KERAS_BACKEND`` set to another backend (a test session of its own), and
the other backends' own faults: BatchNorm's statistics, steps per
execution, a run begun under JAX resumed. requirements.txt installs neither
TensorFlow nor PyTorch, so without them those tests are skipped; each runs
in an environment of its own (docs/performance.md, "Backends"):

    ~/cpl-runs/venv-tf/bin/python -m pytest -q -n 0 -rA tests/test_other_backends.py
    ~/cpl-runs/venv-torch/bin/python -m pytest -q -n 0 -rA tests/test_other_backends.py

A run met under another backend than the one it trained under, and
PyTorch's steps per execution, have tests in the JAX suite here too.
"""

import importlib.util
import json
import os
import subprocess
import sys

import pytest

from helpers import REPO

#: Test files that hold the core model tests; the ones that need JAX itself skip themselves.
CORE_TESTS = ("tests/test_models.py", "tests/test_camera.py", "tests/test_backbones.py",
              "tests/test_training.py", "tests/test_training_faults.py", "tests/test_planning.py",
              "tests/test_checkpointing.py")


@pytest.mark.slow
@pytest.mark.parametrize("backend", ["tensorflow", "torch"])
def test_core_model_tests_pass_under_another_backend(backend):
    if importlib.util.find_spec(backend) is None:
        pytest.skip(f"{backend} is not installed (docs/performance.md: the benchmark environment)")
    # (a test session of its own: the runs that this session's tests share,
    # trained under JAX, are not the other backend's, nor its runs this one's)
    env = {k: v for k, v in os.environ.items() if k != "CPL_KERAS_TEST_SESSION"}
    done = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider",
         "-m", "not slow", *CORE_TESTS],
        cwd=REPO, env=dict(env, KERAS_BACKEND=backend, TF_CPP_MIN_LOG_LEVEL="3"),
        capture_output=True, text=True, timeout=1800)
    assert done.returncode == 0, f"{backend}:\n{done.stdout[-4000:]}\n{done.stderr[-2000:]}"
    print(f"{backend}: {done.stdout.strip().splitlines()[-1]}")  # (-s shows the counts)


#: Builds the faithful model (InceptionV3 towers) and takes one training step.
ONE_STEP = """
import numpy as np
from cpl_keras import TARGETS, build_model, compile_model
model = compile_model(build_model("cpl-a", image_size=75, seed=0))
rng = np.random.default_rng(0)
x = {name: rng.uniform(0, 255, (2, 75, 75, 3)).astype("float32")
     for name in ("left_image", "right_image")}
y = {name: rng.uniform(1, 3, (2, 1)).astype("float32") for name in TARGETS}
model.initialise_adaptive_weights(y)
loss = model.train_on_batch(x, y, return_dict=True)["loss"]
assert np.isfinite(float(loss)), loss
print("one step", model.count_params(), float(loss))
"""


@pytest.mark.slow
@pytest.mark.parametrize("backend", ["tensorflow", "torch"])
def test_the_faithful_model_builds_and_trains_a_step_under_another_backend(backend):
    """Under PyTorch every tower build crashed (Keras lists no devices
    there, and the towers asked it which device they were on)."""
    if importlib.util.find_spec(backend) is None:
        pytest.skip(f"{backend} is not installed (docs/performance.md: the benchmark environment)")
    done = subprocess.run([sys.executable, "-c", ONE_STEP], cwd=REPO, capture_output=True,
                          text=True, timeout=900,
                          env=dict(os.environ, KERAS_BACKEND=backend, TF_CPP_MIN_LOG_LEVEL="3"))
    assert done.returncode == 0 and "one step" in done.stdout, done.stderr[-3000:]


#: Builds, saves, loads and runs a CPL model with every RuntimeWarning an error.
QUIET_NUMPY = """
import sys, warnings
import numpy as np
warnings.simplefilter("error", RuntimeWarning)
from cpl_keras import build_model, load_model
from cpl_keras.models.inference import predict_images
build_model("cpl-a", backbone="small", image_size=32, seed=0).save(sys.argv[1])
images = np.random.default_rng(0).integers(0, 256, (2, 32, 32, 3), dtype=np.uint8)
pred = predict_images(load_model(sys.argv[1]), images, images[::-1])
assert all(np.isfinite(v).all() for v in pred.values()), pred
print("quiet")
"""


def test_the_numpy_backend_builds_and_loads_a_model_without_raw_warnings(tmp_path):
    """Under ``KERAS_BACKEND=numpy`` a build or a load printed NumPy's
    overflow and invalid-value warnings (calibrate showed them): Keras infers
    each Lambda layer's output shape there from ``np.empty`` placeholders."""
    done = subprocess.run([sys.executable, "-c", QUIET_NUMPY, str(tmp_path / "m.keras")],
                          cwd=REPO, capture_output=True, text=True, timeout=300,
                          env=dict(os.environ, KERAS_BACKEND="numpy"))
    assert done.returncode == 0 and done.stdout == "quiet\n", done.stderr[-3000:]
    assert "Warning" not in done.stderr, done.stderr


# ---------------------------------------------------------------------------
# A backend that is not installed: one line, never Keras's traceback
# ---------------------------------------------------------------------------
def _missing_backend():
    """TensorFlow or PyTorch, whichever is not installed (None: both are)."""
    return next((b for b in ("tensorflow", "torch") if importlib.util.find_spec(b) is None), None)


def _python(args, tmp_path, **env):
    """``python ARGS`` in the repository with HOME a fresh folder and ``env``
    over this process's environment (a value of None: unset)."""
    environment = dict(os.environ, HOME=str(tmp_path / "home"))
    environment.pop("KERAS_HOME", None)
    for name, value in env.items():
        if value is None:
            environment.pop(name, None)
        else:
            environment[name] = value
    return subprocess.run([sys.executable, *args], cwd=REPO, env=environment,
                          capture_output=True, text=True, timeout=180)


def test_a_command_on_a_backend_that_is_not_installed_says_so_in_one_line(tmp_path):
    """``KERAS_BACKEND=tensorflow python train.py ...`` without TensorFlow:
    one line naming KERAS_BACKEND=jax, exit 2, no run directory (Keras's
    ModuleNotFoundError traceback from deep inside its import, before)."""
    from helpers import write_stereo_fixture

    backend = _missing_backend()
    if backend is None:
        pytest.skip("TensorFlow and PyTorch are both installed")
    data = write_stereo_fixture(tmp_path / "tiny.h5", n=20, image_size=32)
    run_dir = tmp_path / "run"
    done = _python(["train.py", "--variant", "baseline", "--backbone", "small", "--epochs", "1",
                    "--batch-size", "4", "--data", str(data), "--run-dir", str(run_dir)],
                   tmp_path, KERAS_BACKEND=backend)
    assert done.returncode == 2, done.stderr
    assert done.stderr.splitlines() == [
        f"train.py: error: Keras's backend is {backend} (KERAS_BACKEND={backend}), which is not "
        f"installed: run with KERAS_BACKEND=jax, the package's backend (or install {backend})"]
    assert not run_dir.exists()


def test_the_library_raises_its_backend_error_where_keras_is_first_imported(tmp_path):
    """``import cpl_keras.saving`` (the first import of Keras) on a backend
    that Keras does not have: ``BackendError``, a ``cpl_keras.errors.Error``."""
    done = _python(["-c", "import cpl_keras.saving"], tmp_path, KERAS_BACKEND="tensorflw")
    assert done.returncode == 1
    assert done.stderr.splitlines()[-1] == (
        "cpl_keras.backend.BackendError: Keras has no backend 'tensorflw' "
        "(KERAS_BACKEND=tensorflw): run with KERAS_BACKEND=jax, the package's backend")
    from cpl_keras.backend import BackendError
    from cpl_keras.errors import Error

    assert issubclass(BackendError, Error)


def test_keras_json_naming_another_backend_does_not_override_the_package(tmp_path):
    """~/.keras/keras.json saying TensorFlow, $KERAS_BACKEND unset or empty
    (an empty one left Keras to keras.json): the package runs on JAX."""
    (tmp_path / "home" / ".keras").mkdir(parents=True)
    (tmp_path / "home" / ".keras" / "keras.json").write_text('{"backend": "tensorflow"}\n')
    code = "import cpl_keras, keras; print(keras.backend.backend())"
    for value in (None, ""):
        done = _python(["-c", code], tmp_path, KERAS_BACKEND=value)
        assert (done.returncode, done.stdout) == (0, "jax\n"), done.stderr


def test_configured_backend_reads_keras_json_when_the_variable_is_empty(tmp_path, monkeypatch):
    from cpl_keras import backend

    (tmp_path / "keras.json").write_text('{"backend": "torch"}\n')
    monkeypatch.setenv("KERAS_HOME", str(tmp_path))
    monkeypatch.setenv("KERAS_BACKEND", "")
    assert backend.configured_backend() == ("torch", str(tmp_path / "keras.json"))
    monkeypatch.setenv("KERAS_BACKEND", "jax")
    assert backend.configured_backend() == ("jax", "KERAS_BACKEND=jax")


# ---------------------------------------------------------------------------
# A run made under one backend, met under another: named in its line
# ---------------------------------------------------------------------------
def _as_if_trained_under(run_dir, name):
    """Edit the run's config.json as if it had been trained under ``name``."""
    path = os.path.join(run_dir, "config.json")
    with open(path) as f:
        config = json.load(f)
    config["keras_backend"] = name
    for machine in config.get("machines") or []:
        machine["keras_backend"] = name
    with open(path, "w") as f:
        json.dump(config, f)


def test_a_finished_run_of_another_backend_names_it_in_its_line(tiny_run, tmp_path, capsys):
    """``KERAS_BACKEND=torch python train.py --variant cpl-a`` on the
    demonstration run trained under JAX said "already finished" and no more;
    the line says which backend trained it (here the other way round: a run
    recorded as PyTorch's, met under JAX), and a run of this backend says nothing."""
    from helpers import load_script, writable_copy

    ours, theirs = str(tmp_path / "ours"), str(tmp_path / "theirs")
    for run_dir in (ours, theirs):
        writable_copy(tiny_run["run"], run_dir)
    _as_if_trained_under(theirs, "torch")
    lines = {}
    for run_dir in (ours, theirs):
        assert load_script("train.py").main([
            "--variant", "baseline", "--backbone", "small", "--epochs", "1", "--batch-size", "8",
            "--data", tiny_run["data"], "--run-dir", run_dir]) == 0
        (lines[run_dir],) = capsys.readouterr().out.splitlines()
    assert lines[theirs].startswith("already finished, left as it is: best epoch 1 of 1, ")
    assert lines[theirs].endswith(f", trained under torch, not jax, run directory: {theirs}")
    assert lines[ours] == lines[theirs].replace(", trained under torch, not jax", "").replace(
        theirs, ours)


def test_a_resume_of_a_run_begun_under_another_backend_says_so(stereo40, tmp_path, monkeypatch,
                                                                capsys):
    """A run begun under PyTorch (its config.json says so), resumed under
    JAX: its weights load (Keras's weights files are the same under every
    backend), the resume's line names the backend it trained under until
    now, and config.json lists both, in order."""
    from cpl_keras.training import summary_line, train
    from helpers import interrupt_after_epoch

    run_dir = str(tmp_path / "run")
    settings = dict(variant="baseline", run_dir=run_dir, backbone="small", epochs=2,
                    batch_size=5, verbose=0, return_model=False)
    interrupt_after_epoch(monkeypatch, 1)
    with pytest.raises(KeyboardInterrupt):
        train(stereo40, **settings)
    monkeypatch.undo()
    _as_if_trained_under(run_dir, "torch")
    capsys.readouterr()
    result = train(stereo40, **settings)
    assert f"Resuming {run_dir} after epoch 1 (trained under torch until now)\n" in \
        capsys.readouterr().err
    assert result.config.status == "finished" and result.config.epochs_run == 2
    with open(os.path.join(run_dir, "config.json")) as f:
        config = json.load(f)
    assert [m["keras_backend"] for m in config["machines"]] == ["torch", "jax"]
    assert config["keras_backend"] == "jax"
    assert ", trained under torch and jax, run directory: " in summary_line(result)


# ---------------------------------------------------------------------------
# --steps-per-execution above 1 under PyTorch: one line, before any file
# ---------------------------------------------------------------------------
def test_steps_per_execution_above_one_is_refused_under_pytorch(tiny_run, tmp_path,
                                                                 monkeypatch, capsys):
    """Keras's PyTorch trainer runs one step per call: ``--steps-per-execution
    2`` there ended in Keras's traceback at the first step, exit 1, with the
    run directory made. Refused in one line, exit 2, nothing written (the
    backend in use is read as PyTorch here; the real one is
    test_pytorch_refuses_steps_per_execution_before_any_file)."""
    from cpl_keras import backend
    from cpl_keras.training import TrainingError, train
    from helpers import load_script

    monkeypatch.setattr(backend, "keras_backend", lambda: "torch")
    run_dir = tmp_path / "run"
    assert load_script("train.py").main([
        "--variant", "baseline", "--backbone", "small", "--epochs", "1", "--batch-size", "8",
        "--data", tiny_run["data"], "--run-dir", str(run_dir), "--steps-per-execution", "2"]) == 2
    assert capsys.readouterr().err.splitlines() == [STEPS_REFUSED]
    assert not run_dir.exists()
    with pytest.raises(TrainingError, match=r"must be 1 under PyTorch .*, got 3"):
        train(tiny_run["data"], variant="baseline", run_dir=str(run_dir), steps_per_execution=3)
    assert not run_dir.exists()


STEPS_REFUSED = ("train.py: error: steps per execution must be 1 under PyTorch "
                 "(KERAS_BACKEND=torch), got 2: Keras runs one step per call there")


# ---------------------------------------------------------------------------
# Under PyTorch and TensorFlow themselves (slow; where installed)
# ---------------------------------------------------------------------------
def _installed(backend):
    if importlib.util.find_spec(backend) is None:
        pytest.skip(f"{backend} is not installed (docs/performance.md: the benchmark environment)")


#: BatchNorm's statistics recomputed (training's step before every
#: validation), checked against the batches' own averages.
BATCHNORM = """
import keras, numpy as np
from cpl_keras.models.batchnorm import recompute_batchnorm_statistics
inputs = keras.Input((3,))
hidden = keras.layers.Dense(4)(inputs)
model = keras.Model(inputs, keras.layers.BatchNormalization(name="bn")(hidden))
batches = [np.random.default_rng(i).normal(5, 2, (8, 3)).astype("float32") for i in range(3)]
assert recompute_batchnorm_statistics(model, batches) == 3
dense = keras.Model(inputs, hidden)
means = np.mean([keras.ops.convert_to_numpy(dense(b)).mean(0) for b in batches], 0)
got = keras.ops.convert_to_numpy(model.get_layer("bn").moving_mean)
np.testing.assert_allclose(got, means, rtol=1e-4, atol=1e-5)
print("statistics", keras.backend.backend())
"""


@pytest.mark.slow
@pytest.mark.parametrize("backend", ["tensorflow", "torch"])
def test_batchnorm_statistics_are_recomputed_under_another_backend(backend):
    """Under PyTorch every validation of a run with BatchNorm failed:
    ``np.asarray`` called ``numpy()`` on a tensor that requires a gradient."""
    _installed(backend)
    done = subprocess.run([sys.executable, "-c", BATCHNORM], cwd=REPO, capture_output=True,
                          text=True, timeout=300,
                          env=dict(os.environ, KERAS_BACKEND=backend, TF_CPP_MIN_LOG_LEVEL="3"))
    assert done.returncode == 0 and done.stdout == f"statistics {backend}\n", done.stderr[-3000:]


@pytest.mark.slow
def test_pytorch_refuses_steps_per_execution_before_any_file(tiny_run, tmp_path):
    """``KERAS_BACKEND=torch python train.py --steps-per-execution 2``: one
    line, exit 2, no run directory (Keras's traceback at the first step,
    exit 1, and a run directory left, before)."""
    _installed("torch")
    run_dir = tmp_path / "run"
    done = _python(["train.py", "--variant", "baseline", "--backbone", "small", "--epochs", "1",
                    "--batch-size", "8", "--data", tiny_run["data"], "--run-dir", str(run_dir),
                    "--steps-per-execution", "2"], tmp_path, KERAS_BACKEND="torch")
    assert (done.returncode, done.stderr.splitlines()) == (2, [STEPS_REFUSED]), done.stderr
    assert not run_dir.exists()


@pytest.mark.slow
@pytest.mark.parametrize("backend", ["tensorflow", "torch"])
def test_a_run_begun_under_jax_resumes_and_finishes_under_another_backend(
        backend, stereo40, tmp_path, monkeypatch):
    """Resumed under another backend, a run begun under JAX loads its
    checkpoint whole (weights and optimizer: no variable skipped), says in
    its lines which backend trained it until now, and finishes; config.json
    lists both backends, in order."""
    from cpl_keras.training import train
    from helpers import interrupt_after_epoch

    _installed(backend)
    run_dir = str(tmp_path / "run")
    interrupt_after_epoch(monkeypatch, 1)
    with pytest.raises(KeyboardInterrupt):
        train(stereo40, variant="cpl-a", run_dir=run_dir, backbone="small", epochs=2,
              batch_size=5, verbose=0, return_model=False)
    monkeypatch.undo()
    done = _python(["train.py", "--variant", "cpl-a", "--backbone", "small", "--epochs", "2",
                    "--batch-size", "5", "--quiet", "--data", stereo40, "--run-dir", run_dir],
                   tmp_path, KERAS_BACKEND=backend, TF_CPP_MIN_LOG_LEVEL="3")
    assert done.returncode == 0, done.stderr[-3000:]
    assert f"Resuming {run_dir} after epoch 1 (trained under jax until now)\n" in done.stderr
    assert "Skipping variable loading" not in done.stderr, done.stderr[-3000:]
    assert f", trained under jax and {backend}, run directory: {run_dir}" in done.stdout
    with open(os.path.join(run_dir, "config.json")) as f:
        config = json.load(f)
    assert [m["keras_backend"] for m in config["machines"]] == ["jax", backend]
    assert config["status"] == "finished" and config["epochs_run"] == 2
