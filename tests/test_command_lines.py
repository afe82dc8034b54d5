"""Every command line checks its arguments before it imports Keras or JAX:
a bad flag is answered at once (one line, exit 2), not after the seconds
that importing them takes."""

import os
import subprocess
import sys

import pytest

from helpers import REPO, main_functions

#: Runs a command's main with a bad argument and reports, after its exit,
#: whether Keras or JAX was imported on the way.
PROBE = """
import runpy, sys
sys.argv = [{script!r}] + {argv!r}
try:
    if {script!r}.endswith(".py"):
        runpy.run_path({script!r}, run_name="__main__")
    else:
        runpy.run_module({script!r}, run_name="__main__", alter_sys=True)
except SystemExit as exit:
    code = exit.code
heavy = sorted(m for m in ("keras", "jax", "tensorflow", "torch") if m in sys.modules)
print("exit", code, "heavy", ",".join(heavy) or "none")
"""


@pytest.mark.parametrize("script, argv", [
    ("train.py", ["--bogus"]),
    ("train.py", ["--variant", "cpl-a", "--epochs", "0"]),
    ("train.py", ["--variant", "nope"]),
    ("evaluate.py", ["--bogus"]),
    ("evaluate.py", ["--reproduce", "--pairs", "0"]),
    ("cpl_keras.reproduce", ["--preset", "nope"]),
    ("cpl_keras.reproduce", ["--pairs", "0"]),
    ("cpl_keras.calibrate", ["--bogus"]),
    ("cpl_keras.data.generate", ["--pairs", "0"]),
    # a missing data file, as on a fresh clone, is refused before the model's imports
    ("bench/diagnose_heads.py", ["--data", "data/no-such-dataset.h5"]),
    ("bench/bench_batchnorm.py", ["--data", "data/no-such-dataset.h5"]),
])
def test_bad_arguments_are_refused_before_keras_or_jax_is_imported(script, argv):
    env = dict(os.environ, KERAS_BACKEND="jax")
    result = subprocess.run([sys.executable, "-c", PROBE.format(script=script, argv=argv)],
                            cwd=REPO, env=env, capture_output=True, text=True, timeout=120)
    assert result.stdout.strip() == "exit 2 heavy none", (result.stdout, result.stderr)
    assert result.stderr.count("\n") == 1 and ": error: " in result.stderr, result.stderr


#: An installed command (``console``'s function) with a bad argument: its
#: exit status and whether Keras or JAX was imported on the way.
CONSOLE_PROBE = """
import sys
sys.argv = [{name!r}, "--bogus"]
from cpl_keras import console
try:
    getattr(console, {function!r})()
except SystemExit as exit:
    code = exit.code
heavy = sorted(m for m in ("keras", "jax") if m in sys.modules)
print("exit", code, "heavy", ",".join(heavy) or "none")
"""


@pytest.mark.parametrize("name, prog", [
    ("train", "cpl-train"), ("evaluate", "cpl-evaluate"),
    ("reproduce", "python -m cpl_keras.reproduce"), ("calibrate", "python -m cpl_keras.calibrate"),
    ("graph", "python -m cpl_keras.graph"), ("generate", "python -m cpl_keras.data.generate"),
    ("real_build", "python -m cpl_keras.real.build"), ("mix", "python -m cpl_keras.data.mix"),
    ("learning_curves", "python -m cpl_keras.learning_curves"),
    ("chessboard", "python -m cpl_keras.real.chessboard"),
])
def test_installed_commands_refuse_a_bad_argument_in_one_line(name, prog):
    """The cpl-* commands (pyproject.toml's [project.scripts]) run their
    command's main: a bad flag is one line naming the command, exit 2."""
    env = dict(os.environ, KERAS_BACKEND="jax")
    result = subprocess.run([sys.executable, "-c", CONSOLE_PROBE.format(name=prog, function=name)],
                            cwd=REPO, env=env, capture_output=True, text=True, timeout=120)
    assert result.stdout.strip() == "exit 2 heavy none", (result.stdout, result.stderr)
    assert result.stderr.startswith(f"{prog}: error: "), result.stderr
    assert result.stderr.count("\n") == 1, result.stderr


class _Captured(Exception):
    pass


def test_every_option_of_every_command_has_help_text(monkeypatch):
    """``--help`` explains every option and argument of every command (and
    of real.build's subcommands)."""
    import argparse

    def capture(self, args=None, namespace=None):
        raise _Captured(self)

    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", capture)
    missing = []
    for name, main in main_functions().items():
        with pytest.raises(_Captured) as caught:
            main([])
        parsers = [(name, caught.value.args[0])]
        while parsers:
            label, parser = parsers.pop()
            for action in parser._actions:
                if isinstance(action, argparse._SubParsersAction):
                    parsers += [(f"{label} {sub}", p) for sub, p in action.choices.items()]
                elif not isinstance(action, argparse._HelpAction) and not action.help:
                    missing.append(f"{label}: {action.option_strings or action.dest}")
    assert not missing, missing


#: subprocess functions that start a command and wait for it
STARTS_AND_WAITS = ("run", "call", "check_call", "check_output")


def test_every_subprocess_a_test_waits_for_has_a_timeout():
    """A hung command fails its test instead of blocking the suite:
    ``subprocess.run`` (``call``, ``check_call``, ``check_output``) and every
    ``communicate`` / ``wait`` in tests/ carry a ``timeout``."""
    import ast
    import glob

    missing = []
    for path in sorted(glob.glob(os.path.join(REPO, "tests", "*.py"))):
        with open(path) as f:
            tree = ast.parse(f.read())
        for node in ast.walk(tree):
            if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)):
                continue
            name, base = node.func.attr, node.func.value
            if name in STARTS_AND_WAITS and getattr(base, "id", None) != "subprocess":
                continue
            if name in STARTS_AND_WAITS + ("communicate", "wait") and \
                    not any(k.arg == "timeout" for k in node.keywords):
                missing.append(f"{os.path.basename(path)}:{node.lineno} {name}")
    assert not missing, missing


def test_worker_counts_beyond_the_cpus_are_refused_when_parsed(capsys):
    """--workers 100000 started a storm of processes; now train.py,
    data.generate and the reproduction refuse more workers than CPUs in one
    line (exit 2) before anything starts, and take the CPUs' own number."""
    cpus = os.cpu_count() or 1
    mains = main_functions()
    for name, argv in (("train.py", ["--variant", "baseline", "--workers"]),
                       ("data.generate", ["--pairs", "4", "--out", "x.h5", "--workers"]),
                       ("reproduce", ["--quick", "--workers"])):
        with pytest.raises(SystemExit) as stop:
            mains[name](argv + [str(cpus + 1)])
        assert stop.value.code == 2, name
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and f"must be at most {cpus}, the CPUs of this machine" in err[0], err
    from cpl_keras import cli

    assert cli.worker_count(str(cpus)) == cpus


def test_an_empty_output_path_is_refused_when_parsed(capsys, tmp_path):
    """``--run-dir ""`` trained into the default run directory; every output
    path of the commands now refuses an empty one in one line (exit 2)."""
    mains = main_functions()
    for name, argv in (("train.py", ["--variant", "baseline", "--run-dir", ""]),
                       ("evaluate.py", ["--out", " "]),
                       ("data.generate", ["--pairs", "4", "--out", ""]),
                       ("calibrate", ["a.png", "b.png", "--json-out", ""]),
                       ("data.mix", ["--out", ""])):
        with pytest.raises(SystemExit) as stop:
            mains[name](argv)
        assert stop.value.code == 2, name
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "must name a file or folder, got an empty path" in err[0], err


def test_a_reader_gone_from_the_pipe_ends_a_command_silently_with_141():
    """``python -m cpl_keras.real.chessboard --pair 01 | head -1`` ended with
    ``error: [Errno 32] Broken pipe`` and 2; now as any Unix tool: nothing
    on stderr, 141 (128 + SIGPIPE)."""
    process = subprocess.Popen([sys.executable, "-m", "cpl_keras.real.chessboard", "--pair",
                                "01"], cwd=REPO, stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, env=dict(os.environ, KERAS_BACKEND="jax"))
    process.stdout.close()
    err = process.stderr.read().decode()
    assert process.wait(timeout=120) == 141, err
    assert err == ""
