"""The environment's mistakes named in one line: an XLA_FLAGS or a
JAX_PLATFORMS that would stop JAX (cpl_keras.backend.check_jax_environment),
never XLA's own fatal log line or a model blamed for it."""

import importlib.util
import json
import os
import subprocess
import sys

import pytest

from cpl_keras import backend
from helpers import REPO


@pytest.fixture
def fresh_check(monkeypatch, tmp_path):
    """``check_jax_environment`` as in a process that has not imported JAX
    yet (this one has: it is hidden, not unloaded), with its own cache
    directory and neither variable set."""
    monkeypatch.delitem(sys.modules, "jax", raising=False)
    monkeypatch.setattr(backend, "_jax_environment_checked", [])
    monkeypatch.setenv("CPL_KERAS_CACHE", str(tmp_path / "cache"))
    for name in backend.JAX_ENVIRONMENT:
        monkeypatch.delenv(name, raising=False)
    return tmp_path / "cache" / "jax-environment.json"


def test_an_xla_flags_xla_refuses_is_one_line_naming_it(fresh_check, monkeypatch):
    """XLA_FLAGS=garbage (a file name to XLA, and no such file) ended the
    process in XLA's fatal log line ("F1207 ... parse_flags_from_env.cc:171]
    Could not open file ...") with exit 1: now a BackendError that names the
    variable and quotes XLA's reason; nothing is kept of it."""
    monkeypatch.setenv("XLA_FLAGS", "garbage")
    with pytest.raises(backend.BackendError) as error:
        backend.check_jax_environment()
    message = str(error.value)
    assert message.startswith("XLA cannot start with XLA_FLAGS='garbage': Could not open file "
                              '"garbage" to read flags'), message
    assert message.endswith("; fix XLA_FLAGS (--name=value ..., or a file of them) or unset it")
    assert "\n" not in message and not fresh_check.exists()


@pytest.mark.skipif(importlib.util.find_spec("jax_plugins") is not None,
                    reason="a JAX platform plugin is installed (CUDA may start here)")
def test_a_jax_platform_this_machine_lacks_is_one_line_never_the_model(fresh_check, monkeypatch):
    """JAX_PLATFORMS=cuda on a machine without CUDA: "cannot load
    model.keras: AssertionError" came from deep in the model's loading; now
    a BackendError naming JAX_PLATFORMS and what to do."""
    monkeypatch.setenv("JAX_PLATFORMS", "cuda")
    with pytest.raises(backend.BackendError) as error:
        backend.check_jax_environment()
    assert str(error.value) == (
        "JAX cannot start with JAX_PLATFORMS='cuda': it found no device of those platforms; "
        "unset JAX_PLATFORMS to let JAX choose, or name a platform this machine has (cpu)")


def test_a_setting_that_works_is_tried_once(fresh_check, monkeypatch):
    """A working setting passes, is kept in the cache directory, and is not
    tried again (a trial takes a process of its own, seconds); unset,
    nothing is tried at all."""
    backend.check_jax_environment()        # (neither set: nothing tried, nothing kept)
    assert not fresh_check.exists()
    monkeypatch.setattr(backend, "_jax_environment_checked", [])
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false")
    monkeypatch.setenv("JAX_PLATFORMS", "cpu")
    backend.check_jax_environment()
    kept = json.loads(fresh_check.read_text())
    assert list(kept.values()) == [{"XLA_FLAGS": "--xla_cpu_multi_thread_eigen=false",
                                    "JAX_PLATFORMS": "cpu"}]

    def tried(setting):
        raise AssertionError("tried again")

    monkeypatch.setattr(backend, "_jax_trial_problem", tried)
    monkeypatch.setattr(backend, "_jax_environment_checked", [])
    backend.check_jax_environment()
    monkeypatch.setattr(backend, "_jax_environment_checked", [])
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=true")  # (another setting)
    with pytest.raises(AssertionError, match="tried again"):
        backend.check_jax_environment()


def test_a_command_under_a_bad_xla_flags_ends_in_one_line_and_exit_2(tiny_run, tmp_path):
    """The whole way: calibrate, loading a run's model (its first import of
    Keras), under XLA_FLAGS=garbage ends with its one line and exit 2, not
    XLA's fatal log line and exit 1."""
    env = dict(os.environ, XLA_FLAGS="garbage", CPL_KERAS_CACHE=str(tmp_path / "cache"))
    left = os.path.join(REPO, "cpl_keras", "real", "opencv_chessboard", "left01.jpg")
    done = subprocess.run([sys.executable, "-m", "cpl_keras.calibrate", left,
                           left.replace("left01", "right01"), "--run", tiny_run["run"]],
                          cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert (done.returncode, done.stdout) == (2, ""), done.stderr
    assert done.stderr.startswith("python -m cpl_keras.calibrate: error: XLA cannot start with "
                                  "XLA_FLAGS='garbage': Could not open file"), done.stderr
    assert done.stderr.count("\n") == 1, done.stderr


@pytest.mark.skipif(importlib.util.find_spec("tensorflow") is not None,
                    reason="TensorFlow is installed: a bare import of Keras works here")
def test_the_documented_keras_loader_snippet_runs_as_printed(tiny_run, tmp_path):
    """cpl_keras/saving.py's snippet (Keras's own loader after ``import
    cpl_keras.saving``) as printed, in a fresh process without
    KERAS_BACKEND and with the keras.json Keras writes on its first import
    (backend TensorFlow, not installed here): it loads the run's model. It
    showed ``import keras`` first, which ended in a 41-line traceback."""
    import ast

    import cpl_keras.saving

    doc = ast.get_docstring(ast.parse(open(cpl_keras.saving.__file__).read()))
    snippet = doc.split("::\n\n", 1)[1].split("\n\n", 1)[0]
    code = "\n".join(line[4:] for line in snippet.splitlines())
    code = code.replace('"runs/cpl-a-paper-s0/model.keras"',
                        repr(os.path.join(tiny_run["run"], "model.keras")))
    (tmp_path / "keras.json").write_text(json.dumps({"backend": "tensorflow"}))
    env = {k: v for k, v in os.environ.items() if k != "KERAS_BACKEND"}
    env["KERAS_HOME"] = str(tmp_path)
    done = subprocess.run([sys.executable, "-c", code + "\nprint(type(model).__name__)"],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert (done.returncode, done.stdout) == (0, "CalibrationModel\n"), done.stderr[-2000:]
    assert code.startswith("import cpl_keras.saving\nimport keras\n"), code


def test_a_figure_title_in_characters_no_font_has_draws_without_a_warning(tmp_path):
    """A training run's curves.png titled with a data file named in Japanese:
    matplotlib warned once per character ("UserWarning: Glyph 12487
    (\\N{KATAKANA LETTER DE}) missing from font(s) DejaVu Sans.", two lines
    each); the figure is drawn all the same, its boxes saying as much."""
    import warnings

    from cpl_keras.report.curves import plot_curves

    rows = [{"epoch": 0, "loss": 1.0, "val_loss": 1.2}, {"epoch": 1, "loss": 0.8, "val_loss": 1.0}]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        plot_curves(tmp_path / "curves.png", rows, 2, title="baseline on データ.h5 (paper split)")
    assert [str(w.message) for w in caught] == []
    assert (tmp_path / "curves.png").stat().st_size > 1000


@pytest.mark.parametrize("backend_name, given, level", [
    ("tensorflow", None, "1"), ("tensorflow", "0", "0"), ("jax", None, None)])
def test_tensorflows_start_up_lines_are_off_unless_asked_for(backend_name, given, level):
    """Under TensorFlow, its INFO log at start-up ("I tensorflow/core/util/
    port.cc:153] oneDNN custom operations are on ...", the CPU instructions
    it was not built for) came before every command's output: importing the
    package sets TF_CPP_MIN_LOG_LEVEL=1 unless it is set; other backends
    are left alone."""
    env = {k: v for k, v in os.environ.items() if k != "TF_CPP_MIN_LOG_LEVEL"}
    env["KERAS_BACKEND"] = backend_name
    if given is not None:
        env["TF_CPP_MIN_LOG_LEVEL"] = given
    done = subprocess.run([sys.executable, "-c", "import os, cpl_keras; "
                           "print(os.environ.get('TF_CPP_MIN_LOG_LEVEL'))"],
                          cwd=REPO, env=env, capture_output=True, text=True, timeout=60)
    assert done.stdout == f"{level}\n", done.stderr


def test_a_run_records_the_xla_flags_it_was_compiled_under(monkeypatch):
    """A run trained under XLA_FLAGS (an optimisation level: other digits)
    says so in its machine entry; one without them has no such key, so the
    runs recorded before stay equal to a resume without flags."""
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    assert "xla_flags" not in backend.machine()
    monkeypatch.setenv("XLA_FLAGS", " --xla_backend_optimization_level=0 ")
    assert backend.machine()["xla_flags"] == "--xla_backend_optimization_level=0"
