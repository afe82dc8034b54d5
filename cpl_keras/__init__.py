"""cpl-keras: camera calibration through camera projection loss, in Keras 3.

The public entry points are ``build_model``, ``compile_model`` and
``load_model`` (a saved model.keras or run directory, ``safe_mode=True``:
``cpl_keras.saving``); the camera equations live in ``cpl_keras.camera``.

Importing the package sets ``$KERAS_BACKEND`` to "jax" unless it names a
backend (or to Keras's backend when Keras was imported first, so that the
processes the package starts use the same one), and checks the backend the
moment Keras is first imported (``cpl_keras.backend.check_backend``: one
line, ``BackendError``, when it is not installed). Started as ``python -m
cpl_keras.X``, it also sets the command's Ctrl-C guard before the
command's own imports and the package's (``_guard_module_start``: the
first statement, so no Ctrl-C after Python's own start-up ends in a
traceback from the package).
"""

import _signal
import os
import sys


def _module_prog():
    """``python -m cpl_keras.X`` as this process was started, else None."""
    argv = list(getattr(sys, "orig_argv", []))
    for i, arg in enumerate(argv[1:], 1):
        if arg.startswith(("-m", "-c")):
            module = arg[2:] or "".join(argv[i + 1:i + 2])
            ours = arg[1] == "m" and module.startswith("cpl_keras.")
            return f"python -m {module}" if ours else None
    return None


def _guard_module_start():
    """Started as ``python -m cpl_keras.X`` (runpy imports the packages
    above X while ``sys.argv[0]`` is "-m"): until X's ``cli.run`` sets its own
    guard, a Ctrl-C ends the process at once with X's line and exit 130
    (nothing is written yet), not with Python's KeyboardInterrupt traceback
    from inside the imports (exit 1, or death by SIGINT). Only builtin
    modules are used (``_signal``), so the guard is set before the package
    imports anything. Not in a process started with Ctrl-C ignored, nor
    outside the main thread."""
    prog = _module_prog() if getattr(sys, "argv", [])[:1] == ["-m"] else None
    if prog is None:
        return

    def at_start(signum, frame):
        _signal.signal(_signal.SIGINT, _signal.SIG_IGN)
        try:
            sys.stderr.write(f"{prog}: interrupted\n")  # (interrupts.interrupted's line)
            sys.stderr.flush()
        finally:
            os._exit(130)  # (interrupts.INTERRUPTED)

    try:
        if _signal.getsignal(_signal.SIGINT) is not _signal.SIG_IGN:
            _signal.signal(_signal.SIGINT, at_start)
    except ValueError:  # (not the main thread)
        pass


_guard_module_start()

from cpl_keras import backend as _backend  # noqa: E402  (after the guard)

if not os.environ.get("KERAS_BACKEND"):
    # (JAX, or Keras's backend when Keras was imported first; an empty value
    # would leave Keras to ~/.keras/keras.json's backend)
    os.environ["KERAS_BACKEND"] = _backend.keras_backend() if "keras" in sys.modules else "jax"
if os.environ["KERAS_BACKEND"] == "tensorflow":
    # (TensorFlow's start-up lines, "I tensorflow/core/util/port.cc:153] oneDNN
    # custom operations are on ...", are its INFO log: off unless asked for)
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "1")


class _KerasImport:
    """A finder on ``sys.meta_path`` that checks Keras's backend when
    ``keras`` is first imported (``backend.check_backend``), and JAX's
    environment when ``jax`` is (``backend.check_jax_environment``), then
    leaves the import to Python's own finders: wherever the package (or its
    caller) first imports Keras, a backend that is not installed, or an
    XLA_FLAGS or JAX_PLATFORMS that would stop JAX, is one line."""

    def find_spec(self, fullname, path=None, target=None):
        if fullname == "keras":
            _backend.check_backend()
        elif fullname == "jax":  # (XLA_FLAGS, JAX_PLATFORMS: before JAX starts)
            _backend.check_jax_environment()
        return None


if not any(type(finder).__name__ == "_KerasImport" for finder in sys.meta_path):
    sys.meta_path.insert(0, _KerasImport())

__version__ = "0.1.0"

__all__ = ["PARAMETERS", "TARGETS", "build_model", "compile_model", "load_model", "VARIANTS"]


def __getattr__(name):
    # The model factory imports Keras; load it only when asked for, so the
    # numpy-only parts (camera model, data generator) stay light; and the
    # camera model imports numpy, so ``from cpl_keras import cli`` (a
    # command's first line) takes milliseconds and its Ctrl-C guard is in
    # place at once.
    if name in ("PARAMETERS", "TARGETS"):
        from cpl_keras import camera

        return getattr(camera, name)
    if name in ("build_model", "compile_model", "VARIANTS"):
        from cpl_keras import models

        return getattr(models, name)
    if name == "load_model":
        from cpl_keras import saving

        return saving.load_model
    raise AttributeError(f"module 'cpl_keras' has no attribute {name!r}")
