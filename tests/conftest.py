"""Test-suite set-up: the JAX backend, before any test module imports Keras,
and one tiny trained run shared by the test files that only read a run.

Tests marked ``slow`` (the quick reproduction, InceptionV3 builds, data
parallelism, kill-and-resume) are left out by ``pytest -m "not slow"``.
"""

import os

import pytest

os.environ.setdefault("KERAS_BACKEND", "jax")

TINY_SIZE = 32


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory):
    """A finished MTL-Baseline run (small backbone, 1 epoch) on 40 rendered
    cvgl pairs of 32x32: ``{"root", "data", "run"}``. Read it, never write
    into it."""
    from cpl_keras.data.generate import generate_dataset
    from cpl_keras.training import train

    root = tmp_path_factory.mktemp("tiny_run")
    data = generate_dataset(root / "cvgl.h5", protocol="cvgl", pairs=40, seed=0,
                            image_size=TINY_SIZE, workers=1, progress=False)
    run = root / "run_baseline"
    train(data, variant="baseline", run_dir=run, epochs=1, batch_size=8, backbone="small",
          verbose=0)
    return {"root": root, "data": str(data), "run": str(run)}
