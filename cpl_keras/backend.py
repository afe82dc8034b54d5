"""Which Keras backend the package runs on, without importing Keras.

The package sets ``$KERAS_BACKEND`` ("jax" unless it is set) before Keras is
imported, and Keras reads that variable before its configuration file, so
the variable names the backend until Keras is imported; from then on Keras
says. Importing Keras (and JAX with it) takes seconds, which a command that
has nothing to compute (a finished run's ``train.py``) need not spend.
"""

from __future__ import annotations

import os
import sys


def keras_backend():
    """The name of Keras's backend ("jax", "tensorflow", "torch", ...)."""
    keras = sys.modules.get("keras")
    if keras is not None:
        return keras.backend.backend()
    return os.environ.get("KERAS_BACKEND", "jax")
