"""The package as ``pip install .`` makes it (not editable): what it needs
beyond its modules comes with it as package data."""

import os
import shutil
import subprocess
import sys

import pytest

from helpers import REPO


@pytest.mark.slow
def test_a_non_editable_install_prints_table_1_with_the_papers_column(tmp_path):
    """The paper's tables were found three folders above the module, so an
    install outside the repository lost the paper's column without a word.
    Installed into a folder of its own and run from elsewhere, the rebuild of
    a published folder gives its Table 1 as committed, the paper's column
    in it."""
    target = tmp_path / "site"
    done = subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps",
                           "--target", str(target), REPO],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    assert (target / "cpl_keras" / "evaluation" / "paper_table1.csv").exists()
    folder = tmp_path / "compact-2000-ema"
    shutil.copytree(os.path.join(REPO, "paper_results", "compact-2000-ema"), folder)
    env = dict(os.environ, PYTHONPATH=str(target), KERAS_BACKEND="jax")
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
