"""Non-learned baselines (the Average predictor of Workman et al.)."""

from cpl_keras.baselines.average import average_predictions, training_statistics

__all__ = ["average_predictions", "training_statistics"]
