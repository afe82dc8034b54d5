"""The test suite's wall time, CPU time and slowest tests, in a clean clone.

    python bench/bench_suite.py                       # the whole suite, as CI runs it
    python bench/bench_suite.py -- -m "not slow"      # the quick selection
    python bench/bench_suite.py --here -- tests/test_camera.py

Clones the repository's committed HEAD into a temporary folder (``--here``:
this working tree instead), runs ``python -m pytest -q`` there with this
interpreter (its installed packages; the clone's own ``cpl_keras`` comes
first on the path, pyproject.toml's ``pythonpath``) and ``--durations``,
then prints the wall time, the user and system CPU time of pytest and
every process under it, pytest's last line, and the slowest tests with
their files. Exit status: pytest's. The figures of
paper_results/notes/pipeline-and-suite.md come from here.
"""

from __future__ import annotations

import argparse
import os
import re
import resource
import shutil
import subprocess
import sys
import tempfile
import time

from cpl_keras import cli

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
#: A ``--durations`` line: seconds, phase, node id.
DURATION = re.compile(r"^\s*([\d.]+)s (call|setup|teardown)\s+(.+?)\s*$")


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--here", action="store_true",
                        help="run in this working tree, not in a clean clone of HEAD")
    parser.add_argument("--slowest", type=int, default=20,
                        help="how many of the slowest tests to print (default 20)")
    parser.add_argument("pytest_args", nargs="*",
                        help="pytest's arguments (after --), added to -q")
    args = parser.parse_args(argv)
    if args.slowest < 1:
        parser.error(f"argument --slowest: must be a positive integer, got {args.slowest}")
    return args


def slowest(output, count):
    """The ``count`` slowest ``(seconds, phase, file, test)`` of pytest's
    ``--durations`` lines in ``output``."""
    rows = []
    for line in output.splitlines():
        match = DURATION.match(line)
        if match:
            seconds, phase, node = match.groups()
            path, _, test = node.partition("::")
            rows.append((float(seconds), phase, path, test))
    return sorted(rows, reverse=True)[:count]


def run_suite(folder, pytest_args, count):
    """Run pytest in ``folder``; ``(returncode, wall s, user s, system s, output)``."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                           f"--durations={count}", *pytest_args], cwd=folder, text=True,
                          stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                          env=dict(os.environ, KERAS_BACKEND="jax"))
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return (done.returncode, wall, after.ru_utime - before.ru_utime,
            after.ru_stime - before.ru_stime, done.stdout)


def main(argv=None):
    args = parse_args(argv)
    folder = REPO
    if not args.here:
        folder = tempfile.mkdtemp(prefix="cpl_keras_suite_clone_")
        subprocess.run(["git", "clone", "--quiet", REPO, folder], check=True)
    try:
        returncode, wall, user, system, output = run_suite(folder, args.pytest_args,
                                                           args.slowest)
    finally:
        if folder != REPO:
            shutil.rmtree(folder, ignore_errors=True)
    lines = output.rstrip().splitlines()
    print(f"pytest: {lines[-1] if lines else '(no output)'}")
    print(f"wall {wall:.0f} s, user CPU {user:.0f} s, system CPU {system:.0f} s "
          f"({os.cpu_count()} cores, load {os.getloadavg()[0]:.1f} at the end)")
    print(f"the {args.slowest} slowest:")
    for seconds, phase, path, test in slowest(output, args.slowest):
        print(f"  {seconds:7.1f} s  {phase:8s} {path}  {test}")
    if returncode != 0:
        print(output, file=sys.stderr)
    return returncode


if __name__ == "__main__":
    cli.run(main, "bench/bench_suite.py")
