"""cpl-keras: camera calibration through camera projection loss, in Keras 3.

The public entry points are ``build_model`` and ``compile_model``; the camera
equations live in ``cpl_keras.camera``.
"""

import os

os.environ.setdefault("KERAS_BACKEND", "jax")

from cpl_keras.camera import PARAMETERS, TARGETS  # noqa: E402

__version__ = "0.1.0"

__all__ = ["PARAMETERS", "TARGETS", "build_model", "compile_model", "VARIANTS"]


def __getattr__(name):
    # The model factory imports Keras; load it only when asked for, so the
    # numpy-only parts (camera model, data generator) stay light.
    if name in ("build_model", "compile_model", "VARIANTS"):
        from cpl_keras import models

        return getattr(models, name)
    raise AttributeError(f"module 'cpl_keras' has no attribute {name!r}")
