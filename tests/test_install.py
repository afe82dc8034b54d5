"""The package as ``pip install .`` makes it (not editable): what it needs
beyond its modules comes with it as package data."""

import os
import shutil
import subprocess
import sys

import pytest

from helpers import REPO


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """``(target, env)``: the package installed into a folder of its own
    (``pip install --target``, not editable) and the environment that
    imports it from there; made once for this file's tests."""
    target = tmp_path_factory.mktemp("install") / "site"
    done = subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps",
                           "--target", str(target), REPO],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    return target, dict(os.environ, PYTHONPATH=str(target), KERAS_BACKEND="jax")


@pytest.mark.slow
def test_a_non_editable_install_prints_table_1_with_the_papers_column(installed, tmp_path):
    """The paper's tables were found three folders above the module, so an
    install outside the repository lost the paper's column without a word.
    Installed into a folder of its own and run from elsewhere, the rebuild of
    a published folder gives its Table 1 as committed, the paper's column
    in it."""
    target, env = installed
    assert (target / "cpl_keras" / "evaluation" / "paper_table1.csv").exists()
    folder = tmp_path / "compact-2000-ema"
    shutil.copytree(os.path.join(REPO, "paper_results", "compact-2000-ema"), folder)
    where = subprocess.run([sys.executable, "-c", "import cpl_keras; print(cpl_keras.__file__)"],
                           cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert where.stdout.startswith(str(target)), (where.stdout, where.stderr)
    rebuilt = subprocess.run([sys.executable, "-m", "cpl_keras.reproduce", "--from-predictions",
                              str(folder)], cwd=tmp_path, env=env, capture_output=True,
                             text=True, timeout=600)
    assert rebuilt.returncode == 0, rebuilt.stderr[-3000:]
    table = (folder / "table1_cvgl.md").read_text()
    assert "| MTL-CPL-A | **0.004** ± 0.001 (0.005) |" in table  # (0.005: the paper's fx)
    committed = open(os.path.join(REPO, "paper_results", "compact-2000-ema",
                                  "table1_cvgl.md")).read()
    assert table == committed


@pytest.mark.slow
def test_a_non_editable_installs_reproduction_writes_under_the_current_directory(
        installed, tmp_path):
    """cpl-reproduce's default output folder was three folders above the
    module: installed into a folder of its own, into that folder's
    ``paper_results/``. It is ``paper_results/`` of the current directory
    (the committed folder from the repository's root), with or without a
    preset, never inside the installed package."""
    target, env = installed
    shown = subprocess.run(
        [sys.executable, "-c",
         "import os, cpl_keras\n"
         "from cpl_keras.commands.reproduce import parse_args\n"
         "from cpl_keras.reproduce import default_folders\n"
         "print(cpl_keras.__file__)\n"
         "print(os.path.abspath(default_folders(None)[0]))\n"
         "print(os.path.abspath(parse_args(['--preset', 'cpu']).out))"],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert shown.returncode == 0, shown.stderr[-3000:]
    module, default, preset = shown.stdout.split()
    assert module.startswith(str(target))
    assert default == str(tmp_path / "paper_results")
    assert preset == str(tmp_path / "paper_results" / "cpu")
    for folder in (default, preset):
        assert not folder.startswith(str(target)), folder
