"""bench/bench_suite_xla.py: its settings and its CPU-time measurement (no model);
bench/bench_suite.py's slowest tests; the bench scripts' imports."""

import ast
import importlib.util
import os
import sys

import pytest

from cpl_keras.errors import Error

PATH = os.path.join(os.path.dirname(os.path.dirname(__file__)), "bench", "bench_suite_xla.py")
spec = importlib.util.spec_from_file_location("bench_suite_xla", PATH)
bench = importlib.util.module_from_spec(spec)
spec.loader.exec_module(bench)


def test_default_settings_compare_xla_defaults_with_level_0():
    args = bench.parse_args([])
    assert args.settings == [("default", ""), ("level-0", "--xla_backend_optimization_level=0")]
    args = bench.parse_args(["--flags", "a=", "--flags", "b=--x=1 --y=2", "--pytest", "t.py",
                             "-k", "z"])
    assert args.settings == [("a", ""), ("b", "--x=1 --y=2")]
    assert args.pytest == ["t.py", "-k", "z"]
    for bad in (["--flags", "no-equals-sign"], ["--flags", "=--x"], ["--rounds", "0"]):
        with pytest.raises(SystemExit):
            bench.parse_args(bad)


def test_cpu_seconds_counts_the_child_and_passes_the_flags():
    spin = "import os, time\nt = time.process_time()\nwhile time.process_time() - t < 0.3: pass\n"
    check = "assert os.environ['XLA_FLAGS'] == '--z'\n"
    assert bench.cpu_seconds([sys.executable, "-c", spin + check], "--z") >= 0.25
    with pytest.raises(Error, match=r"failed \(exit 1\) with XLA_FLAGS='--w': AssertionError"):
        bench.cpu_seconds([sys.executable, "-c", spin + check], "--w")


def _bench_suite():
    path = os.path.join(os.path.dirname(PATH), "bench_suite.py")
    spec = importlib.util.spec_from_file_location("bench_suite", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_bench_suite_lists_the_slowest_tests_with_their_files_and_whole_ids():
    """bench/bench_suite.py: pytest's --durations lines, slowest first, the
    node id split into file and test (parameters with spaces kept)."""
    suite = _bench_suite()
    output = ("===== slowest 3 durations =====\n"
              "112.00s setup    tests/test_reproduce.py::test_quick_reproduction_end_to_end\n"
              "14.30s call     tests/test_training.py::test_flag[cpl-a heads]\n"
              "0.50s teardown tests/test_camera.py::test_round_trip\n"
              "537 passed in 404.59s (0:06:44)\n")
    assert suite.slowest(output, 2) == [
        (112.0, "setup", "tests/test_reproduce.py", "test_quick_reproduction_end_to_end"),
        (14.3, "call", "tests/test_training.py", "test_flag[cpl-a heads]")]
    with pytest.raises(SystemExit):
        suite.parse_args(["--slowest", "0"])
    assert suite.parse_args(["--", "-m", "not slow"]).pytest_args == ["-m", "not slow"]


def test_no_bench_script_edits_sys_path():
    """The bench scripts import the installed package as a command does;
    bench_suite.py put the repository on ``sys.path`` by hand, the last one
    that did."""
    folder = os.path.dirname(PATH)
    scripts = sorted(name for name in os.listdir(folder) if name.endswith(".py"))
    assert "bench_suite.py" in scripts and len(scripts) > 10
    editing = []
    for name in scripts:
        with open(os.path.join(folder, name)) as f:
            tree = ast.parse(f.read())
        editing += [f"{name}:{node.lineno}" for node in ast.walk(tree)
                    if isinstance(node, ast.Attribute) and node.attr == "path"
                    and isinstance(node.value, ast.Name) and node.value.id == "sys"]
    assert editing == []
