"""cpl-keras: camera calibration through camera projection loss, in Keras 3.

The public entry points are ``build_model``, ``compile_model`` and
``load_model`` (a saved model.keras or run directory, ``safe_mode=True``:
``cpl_keras.saving``); the camera equations live in ``cpl_keras.camera``.
"""

import os

os.environ.setdefault("KERAS_BACKEND", "jax")

__version__ = "0.1.0"

__all__ = ["PARAMETERS", "TARGETS", "build_model", "compile_model", "load_model", "VARIANTS"]


def __getattr__(name):
    # The model factory imports Keras; load it only when asked for, so the
    # numpy-only parts (camera model, data generator) stay light; and the
    # camera model imports numpy, so ``from cpl_keras import cli`` (a
    # command's first line) takes milliseconds and its Ctrl-C guard is in
    # place at once.
    if name in ("PARAMETERS", "TARGETS"):
        from cpl_keras import camera

        return getattr(camera, name)
    if name in ("build_model", "compile_model", "VARIANTS"):
        from cpl_keras import models

        return getattr(models, name)
    if name == "load_model":
        from cpl_keras import saving

        return saving.load_model
    raise AttributeError(f"module 'cpl_keras' has no attribute {name!r}")
