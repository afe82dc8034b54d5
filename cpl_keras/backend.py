"""Which Keras backend the package runs on, without importing Keras, and
the machine a run trains on (``machine``).

The package sets ``$KERAS_BACKEND`` ("jax" unless it is set) before Keras is
imported, and Keras reads that variable before its configuration file, so
the variable names the backend until Keras is imported; from then on Keras
says. Importing Keras (and JAX with it) takes seconds, which a command that
has nothing to compute (a finished run's ``train.py``) need not spend.
"""

from __future__ import annotations

import os
import platform
import sys
from importlib import metadata


def keras_backend():
    """The name of Keras's backend ("jax", "tensorflow", "torch", ...)."""
    keras = sys.modules.get("keras")
    if keras is not None:
        return keras.backend.backend()
    return os.environ.get("KERAS_BACKEND", "jax")


def machine():
    """The machine this process trains on, as a run's config.json records it
    (``machines``): the CPU model, its logical cores, the accelerators the
    backend sees (JAX only; none listed when JAX is not imported) and the
    versions of Keras and of the backend's package."""
    cpu = None
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            cpu = next((line.split(":", 1)[1].strip() for line in f
                        if line.startswith("model name")), None)
    except OSError:
        pass
    name = keras_backend()
    out = {"cpu": cpu or platform.processor() or platform.machine(),
           "cpu_count": os.cpu_count(), "keras_backend": name}
    for package in ("keras", {"tensorflow": "tensorflow", "torch": "torch"}.get(name, name)):
        try:
            out[package] = metadata.version(package)
        except metadata.PackageNotFoundError:
            out[package] = None
    jax = sys.modules.get("jax")
    if jax is not None and name == "jax":
        out["devices"] = sorted({f"{d.platform}:{d.device_kind}" for d in jax.devices()})
    return out
