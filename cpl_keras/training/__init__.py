"""Training: planning a run, the training loop, its checkpoints and what it
prints, the batches and their augmentation, several runs at once.

``planning`` checks every argument before anything is written
(``plan_run``); ``trainer`` runs a plan (``train``: the run directory's
lifecycle, resume, the lock, data parallel); ``result`` is what a run ends
with (the final model.keras and config.json, ``TrainResult``, the summary
line); ``checkpointing`` is the trainer's callback (checkpoints, early
stopping, the NaN guard); ``state`` the run's resume state
(``backup/state.json``, ``TrainingState``); ``progress`` what it prints;
``sequence`` the batches (``StereoSequence``, Keras); ``augment`` the
photometric augmentation; ``parallel`` several runs at once, each in a
process of its own.

Importing this package imports no Keras (the command lines start without
it): ``sequence``, ``checkpointing`` and ``progress`` import Keras, and
``trainer`` and ``result`` import them where they use them.
"""

from cpl_keras.training.planning import TrainingError, plan_run
from cpl_keras.training.result import TrainResult, summary_line
from cpl_keras.training.trainer import train

__all__ = ["TrainResult", "TrainingError", "plan_run", "summary_line", "train"]
