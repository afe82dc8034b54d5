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

``check_jax_environment()`` runs there too (and when JAX itself is first
imported): ``XLA_FLAGS`` or ``JAX_PLATFORMS``, when set, are tried once in a
process of their own, since XLA ends a process on a bad flag with its own
fatal log line and a platform this machine lacks failed later as
"cannot load model.keras: AssertionError"; either is a ``BackendError``
naming the variable. A setting that works is remembered in the cache
directory, so each is tried once.
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import os
import platform
import re
import subprocess
import sys

from cpl_keras import files
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
    if name == "jax":
        check_jax_environment()
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


#: What JAX and XLA read at start, whose mistakes ``check_jax_environment`` names.
JAX_ENVIRONMENT = ("XLA_FLAGS", "JAX_PLATFORMS")
#: The trial of them, in a process of its own: JAX's devices, or the error.
_JAX_TRIAL = ("import json\ntry:\n    import jax\n    devices = jax.devices()\n"
              "except Exception as error:\n"
              "    print(json.dumps({'error': f'{type(error).__name__}: {error}'}))\n"
              "else:\n    print(json.dumps({'platforms': sorted({d.platform for d in devices})}))\n")
#: Seconds the trial may take (a GPU's start included).
JAX_TRIAL_S = 300
#: XLA's log lines (``F1207 14:30:21.5 31693 parse_flags_from_env.cc:171] ...``).
_XLA_LOG = re.compile(r"^[EF]\d{4} [\d:.]+\s+\d+ \S+\] (.*)$", re.M)
_jax_environment_checked = []


def _trial_key(setting):
    """What the verdict on ``setting`` depends on: the values (an XLA_FLAGS
    file's text too), this Python and its JAX, the machine."""
    import importlib.metadata  # (here: it would double ``import cpl_keras``'s time)

    flags = setting.get("XLA_FLAGS", "")
    text = ""
    if flags and not flags.lstrip().startswith("--"):
        try:
            with open(flags.strip(), encoding="utf-8", errors="replace") as f:
                text = f.read()
        except OSError:
            text = None
    try:
        jaxlib = importlib.metadata.version("jaxlib")
    except importlib.metadata.PackageNotFoundError:
        jaxlib = None
    said = json.dumps([setting, text, sys.executable, jaxlib, platform.node()], sort_keys=True)
    return hashlib.sha256(said.encode()).hexdigest()


def _trials_path():
    """Where the settings that worked are kept: the cache directory's
    ``jax-environment.json`` (``cpl_keras.cache``'s folder, found alike)."""
    folder = os.environ.get("CPL_KERAS_CACHE") or os.path.join(
        os.path.expanduser("~"), ".cache", "cpl_keras")
    return os.path.join(folder, "jax-environment.json")


def _jax_trial_problem(setting):
    """The one line that says why JAX cannot start under ``setting``, or None."""
    try:
        done = subprocess.run([sys.executable, "-c", _JAX_TRIAL], capture_output=True,
                              text=True, timeout=JAX_TRIAL_S,
                              env=dict(os.environ, **setting))
    except subprocess.TimeoutExpired:
        return None  # (slow, not broken: JAX says more in this process)
    said = done.stdout.strip().splitlines()[-1:] if done.stdout.strip() else []
    outcome = json.loads(said[0]) if said and said[0].startswith("{") else {}
    if "platforms" in outcome:
        return None
    named = ", ".join(f"{name}={value!r}" for name, value in setting.items() if value)
    logged = _XLA_LOG.findall(done.stderr)
    if logged:  # (XLA ended it: its flags)
        reason = " ".join(logged[0].split())[:300]
        return (f"XLA cannot start with {named}: {reason}; fix XLA_FLAGS "
                "(--name=value ..., or a file of them) or unset it")
    reason = outcome.get("error") or (done.stderr.strip().splitlines() or ["no reason given"])[-1]
    if reason.strip() in ("AssertionError:", "AssertionError"):
        reason = "it found no device of those platforms"
    if setting.get("JAX_PLATFORMS"):
        return (f"JAX cannot start with {named}: {' '.join(reason.split())[:300]}; unset "
                "JAX_PLATFORMS to let JAX choose, or name a platform this machine has (cpu)")
    return f"JAX cannot start with {named}: {' '.join(reason.split())[:300]}"


def check_jax_environment():
    """``BackendError`` (one line, naming the variable) when ``XLA_FLAGS``
    or ``JAX_PLATFORMS``, set, would stop JAX: tried once per setting, in a
    process of its own, before JAX starts here; a setting that worked is
    remembered (``_trials_path``). Unset, nothing is tried."""
    if _jax_environment_checked or "jax" in sys.modules:
        return
    setting = {name: os.environ.get(name, "") for name in JAX_ENVIRONMENT}
    if not any(setting.values()):
        _jax_environment_checked.append(True)
        return
    key, path = _trial_key(setting), _trials_path()
    try:
        worked = files.read_json(path, default={})
    except (OSError, ValueError):  # (unreadable: tried again, and rewritten)
        worked = {}
    if not isinstance(worked, dict) or key not in worked:
        problem = _jax_trial_problem(setting)
        if problem:
            raise BackendError(problem)
        worked = dict(worked) if isinstance(worked, dict) else {}
        worked[key] = {name: value for name, value in setting.items() if value}
        if not files.cannot_write(os.path.dirname(path)):
            try:
                os.makedirs(os.path.dirname(path), exist_ok=True)
                files.write_json(path, worked)
            except OSError:  # (unkept: tried again next time)
                pass
    _jax_environment_checked.append(True)


def machine():
    """The machine this process trains on, as a run's config.json records it
    (``machines``): the CPU model, its logical cores, the accelerators the
    backend sees (JAX only; none listed when JAX is not imported), the
    versions of Keras and of the backend's package and, when set,
    ``XLA_FLAGS`` (``xla_flags``: flags such as an optimisation level
    change how XLA compiles, and so the digits a training gives)."""
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
    if os.environ.get("XLA_FLAGS", "").strip():
        out["xla_flags"] = os.environ["XLA_FLAGS"].strip()
    jax = sys.modules.get("jax")
    if jax is not None and name == "jax":
        out["devices"] = sorted({f"{d.platform}:{d.device_kind}" for d in jax.devices()})
    return out
