"""Test-suite set-up: the JAX backend, before any test module imports Keras."""

import os

os.environ.setdefault("KERAS_BACKEND", "jax")
