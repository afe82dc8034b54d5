"""The paper's networks: ``build_model`` / ``compile_model`` and their parts.

The names the command lines offer (``VARIANTS``, ``BACKBONES``, from
``variants``) come without Keras, so that arguments are checked before it
is imported, and so do the training losses (``LOSSES``, ``LOSS_MODES``);
``build_model``, ``compile_model`` and ``CalibrationModel`` import it on
first use. Importing this package alone does not
register the custom functions and layers with Keras; ``cpl_keras.saving``
does (``cpl_keras.load_model(path)``, or ``import cpl_keras.saving`` before
``keras.saving.load_model(path, safe_mode=True)``).
"""

from cpl_keras.models.options import ModelOptions
from cpl_keras.models.variants import BACKBONES, LOSS_MODES, LOSSES, VARIANTS

__all__ = [
    "BACKBONES", "LOSSES", "LOSS_MODES", "VARIANTS", "CalibrationModel", "ModelOptions",
    "build_from_config", "build_model", "compile_model",
]
#: The names that import Keras, by the module that holds them.
_KERAS = {"CalibrationModel": "calibration_model", "build_from_config": "factory",
          "build_model": "factory", "compile_model": "factory"}


def __getattr__(name):
    if name in _KERAS:
        import importlib

        importlib.import_module("cpl_keras.models.factory")  # (registers the custom objects)
        return getattr(importlib.import_module(f"cpl_keras.models.{_KERAS[name]}"), name)
    raise AttributeError(f"module 'cpl_keras.models' has no attribute {name!r}")
