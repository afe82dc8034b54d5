"""The core model tests under Keras's TensorFlow and PyTorch backends, where installed.

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
              "tests/test_training.py")


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
