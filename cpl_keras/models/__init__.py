"""The paper's networks: ``build_model`` / ``compile_model`` and their parts.

The names the command lines offer (``VARIANTS``, ``BACKBONES``, from
``variants``) come without Keras, so that arguments are checked before it
is imported; ``build_model``, ``compile_model``, ``CalibrationModel`` and
``LOSS_MODES`` import it on first use. Importing this package alone does not
register the custom functions and layers with Keras; ``cpl_keras.saving``
does (``cpl_keras.load_model(path)``, or ``import cpl_keras.saving`` before
``keras.saving.load_model(path, safe_mode=True)``).
"""

from cpl_keras.models.variants import BACKBONES, VARIANTS

__all__ = [
    "BACKBONES", "LOSS_MODES", "VARIANTS", "CalibrationModel", "build_model", "compile_model",
]
#: The names that import Keras, by the module that holds them.
_KERAS = {"LOSS_MODES": "calibration_model", "CalibrationModel": "calibration_model",
          "build_model": "factory", "compile_model": "factory"}


def __getattr__(name):
    if name in _KERAS:
        import importlib

        importlib.import_module("cpl_keras.models.factory")  # (registers the custom objects)
        return getattr(importlib.import_module(f"cpl_keras.models.{_KERAS[name]}"), name)
    raise AttributeError(f"module 'cpl_keras.models' has no attribute {name!r}")
