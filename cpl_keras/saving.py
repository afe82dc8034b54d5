"""Saved models: ``load_model(path)``.

Importing this module registers every custom function and layer of the
package with Keras (it imports ``cpl_keras.models.factory``), so after
``import cpl_keras.saving`` Keras's own loader works too::

    import cpl_keras.saving
    import keras
    model = keras.saving.load_model("runs/cpl-a-paper-s0/model.keras", safe_mode=True)

in that order: importing the package first sets ``KERAS_BACKEND=jax``,
while Keras on its own starts on the backend of ``~/.keras/keras.json``
(TensorFlow, as Keras writes that file on its first import), and a bare
``import keras`` ends in a 41-line ``No module named 'tensorflow'`` where
TensorFlow is not installed (or set ``KERAS_BACKEND=jax`` yourself).

``cpl_keras.load_model(path)`` (this module's ``load_model``, reached
without importing Keras until it is called) does the same in one step. The
package does not register on ``import cpl_keras``: that would import Keras
and JAX for the commands that need neither (a finished run's ``train.py``,
the data generator).
"""

from __future__ import annotations

import os

import cpl_keras.models.factory  # noqa: F401  (registers the custom functions and layers)
from cpl_keras import runs


def load_model(path):
    """The saved model at ``path``, a ``.keras`` file or a run directory
    (its ``model.keras``), loaded with ``safe_mode=True``. ``runs.RunError``
    (one line) when the file is missing, truncated or not a model."""
    path = os.fspath(path)
    if os.path.isdir(path):
        path = os.path.join(path, runs.MODEL)
    if not os.path.isfile(path):
        raise runs.RunError(f"no saved model at {path}")
    return runs.load_model_file(path)
