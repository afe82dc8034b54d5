"""The core model tests under Keras's TensorFlow and PyTorch backends, where installed,
and the one line that a backend which is not installed gets.

The package's model code is ``keras.ops`` only. These tests run the model,
camera, backbone and training test files in a subprocess with
``KERAS_BACKEND`` set to another backend. requirements.txt installs neither
TensorFlow nor PyTorch, so without them the tests are skipped; the
benchmark environment of docs/performance.md has both:

    bench-venv/bin/python -m pytest -q tests/test_other_backends.py
"""

import importlib.util
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
    done = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider",
         "-m", "not slow", *CORE_TESTS],
        cwd=REPO, env=dict(os.environ, KERAS_BACKEND=backend, TF_CPP_MIN_LOG_LEVEL="3"),
        capture_output=True, text=True, timeout=1800)
    assert done.returncode == 0, f"{backend}:\n{done.stdout[-4000:]}\n{done.stderr[-2000:]}"


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
