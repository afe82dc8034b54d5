"""The paper's networks: ``build_model`` / ``compile_model`` and their parts.

Importing this package registers every custom function and layer, so a
saved model loads with ``keras.saving.load_model(path, safe_mode=True)``.
"""

from cpl_keras.models.backbones import BACKBONES
from cpl_keras.models.calibration_model import LOSS_MODES, CalibrationModel
from cpl_keras.models.factory import VARIANTS, build_model, compile_model

__all__ = [
    "BACKBONES", "LOSS_MODES", "VARIANTS", "CalibrationModel", "build_model", "compile_model",
]
