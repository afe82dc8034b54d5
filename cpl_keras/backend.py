"""Which Keras backend the package runs on, without importing Keras, and
the machine a run trains on (``machine``).

The package sets ``$KERAS_BACKEND`` ("jax" unless it is set) before Keras is
imported, and Keras reads that variable before its configuration file, so
the variable names the backend until Keras is imported; from then on Keras
says. Importing Keras (and JAX with it) takes seconds, which a command that
has nothing to compute (a finished run's ``train.py``) need not spend.

``check_backend()`` runs the moment Keras is first imported in a process
that imported the package (``cpl_keras/__init__.py`` hooks it into the
import): a ``$KERAS_BACKEND`` naming TensorFlow or PyTorch where neither is
installed is a ``BackendError``, one line that says to run with
``KERAS_BACKEND=jax``, instead of Keras's traceback from deep inside its
import. (An installed TensorFlow or PyTorch is used: the package runs
under either, docs/performance.md.)
"""

from __future__ import annotations

import importlib.util
import json
import os
import platform
import sys

from cpl_keras.errors import Error

#: The package that each of Keras's backends imports.
BACKEND_PACKAGES = {"jax": "jax", "tensorflow": "tensorflow", "torch": "torch",
                    "numpy": "numpy", "openvino": "openvino"}


class BackendError(Error):
    """Keras's configured backend cannot be loaded (one line naming
    ``KERAS_BACKEND=jax``)."""


def keras_backend():
    """The name of Keras's backend ("jax", "tensorflow", "torch", ...)."""
    keras = sys.modules.get("keras")
    if keras is not None:
        return keras.backend.backend()
    return os.environ.get("KERAS_BACKEND", "jax")


def configured_backend():
    """``(name, where it is set)`` of the backend Keras starts on when it is
    imported: ``$KERAS_BACKEND`` when set and not empty (the package sets it
    to "jax" when it is not), else the ``backend`` of Keras's configuration
    file (``$KERAS_HOME`` or ``~/.keras``, ``keras.json``), else Keras's
    default, TensorFlow."""
    name = os.environ.get("KERAS_BACKEND")
    if name:
        return name, f"KERAS_BACKEND={name}"
    folder = os.environ.get("KERAS_HOME") or os.path.join(os.path.expanduser("~"), ".keras")
    path = os.path.join(folder, "keras.json")
    try:
        with open(path) as f:
            return str(json.load(f)["backend"]), path
    except (OSError, ValueError, KeyError, TypeError):
        return "tensorflow", "Keras's default"


def check_backend():
    """``BackendError`` (one line) when Keras, not imported yet, would start
    on a backend that is not installed, or on no backend Keras has."""
    if "keras" in sys.modules:
        return
    name, source = configured_backend()
    package = BACKEND_PACKAGES.get(name)
    if package is None:
        raise BackendError(f"Keras has no backend {name!r} ({source}): run with "
                           "KERAS_BACKEND=jax, the package's backend")
    if importlib.util.find_spec(package) is None:
        if name == "jax":
            raise BackendError(f"Keras's backend is JAX ({source}), which is not installed: "
                               "pip install -r requirements.txt")
        raise BackendError(f"Keras's backend is {name} ({source}), which is not installed: "
                           "run with KERAS_BACKEND=jax, the package's backend "
                           f"(or install {package})")


def machine():
    """The machine this process trains on, as a run's config.json records it
    (``machines``): the CPU model, its logical cores, the accelerators the
    backend sees (JAX only; none listed when JAX is not imported) and the
    versions of Keras and of the backend's package."""
    import importlib.metadata  # (here: it would double ``import cpl_keras``'s time)

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
            out[package] = importlib.metadata.version(package)
        except importlib.metadata.PackageNotFoundError:
            out[package] = None
    jax = sys.modules.get("jax")
    if jax is not None and name == "jax":
        out["devices"] = sorted({f"{d.platform}:{d.device_kind}" for d in jax.devices()})
    return out
