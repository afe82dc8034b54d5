"""Test-suite set-up: the JAX backend, before any test module imports Keras,
and the expensive things several test files need, made once per session:

* ``tiny_run``: a finished run on 40 rendered cvgl pairs (the files that only
  read a run);
* ``stereo40``: the 40-pair, 32x32 fixture dataset the training, loss-health
  and learning-curve tests train on;
* ``variant_run(name)``: one run of each variant on ``stereo40``, trained at
  first use (the run-directory tests and the learning curves read the same
  MTL-CPL-A run instead of training it twice);
* ``real32``: every shipped real rig built at 32 px, one crop per pair (the
  Table 2 tests and the leave-one-rig-out test).

Each is read only: a test that changes a run copies it first.

Tests marked ``slow`` (the quick reproduction, InceptionV3 builds, data
parallelism, kill-and-resume, every train.py flag, the documented commands,
the benchmark scripts) are left out by ``pytest -m "not slow"``.
"""

import os

import pytest

os.environ.setdefault("KERAS_BACKEND", "jax")

TINY_SIZE = 32
#: The shared variant runs' settings: 40 pairs -> 25 train, 3 val, 12 test;
#: batches of 5 keep one shape (one compilation); 2 epochs.
VARIANT_RUN = dict(backbone="small", epochs=2, batch_size=5, seed=1, verbose=0)


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


@pytest.fixture(scope="session")
def stereo40(tmp_path_factory):
    """``write_stereo_fixture(n=40, image_size=32)``: random images, labels of
    4 configurations. A path; read it, never write into it."""
    from test_datasets import write_stereo_fixture

    return write_stereo_fixture(tmp_path_factory.mktemp("stereo40") / "tiny.h5", n=40,
                                image_size=32)


@pytest.fixture(scope="session")
def variant_run(stereo40, tmp_path_factory):
    """``variant_run(variant)`` -> ``{"run_dir", "summary"}``: that variant
    trained on ``stereo40`` with ``VARIANT_RUN``'s settings, once per session
    (at its first use). Read it; copy the folder to change it."""
    made = {}

    def get(variant):
        if variant not in made:
            from cpl_keras.training import train

            run_dir = str(tmp_path_factory.mktemp("variant_runs") / variant)
            summary = train(stereo40, variant=variant, run_dir=run_dir, **VARIANT_RUN)
            made[variant] = {"run_dir": run_dir, "summary": summary}
        return made[variant]

    return get


@pytest.fixture(scope="session")
def real32(tmp_path_factory):
    """A folder of the shipped real sets (chessboard 13 pairs, Middlebury 1,
    OAK-D 12) at 32x32, ``real.build all --crops 1``. Read only."""
    from cpl_keras.real import build

    real = tmp_path_factory.mktemp("real32")
    assert build.main(["all", "--out-dir", str(real), "--crops", "1", "--image-size",
                       str(TINY_SIZE)]) == 0
    return real
