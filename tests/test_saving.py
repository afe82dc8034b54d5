"""A saved model loads as the README says, in a fresh Python process
(cpl_keras.saving): ``cpl_keras.load_model(path)``, or Keras's loader with
``safe_mode=True`` after ``import cpl_keras.saving``."""

import os
import re
import subprocess
import sys

import pytest

from helpers import REPO

#: The recipes README.md names, each loading PATH in a process of its own.
RECIPES = {
    "cpl_keras.load_model": "import cpl_keras\nmodel = cpl_keras.load_model(PATH)",
    "cpl_keras.load_model of a run directory":
        "import cpl_keras\nmodel = cpl_keras.load_model(RUN)",
    "import cpl_keras.saving":
        "import keras\nimport cpl_keras.saving\n"
        "model = keras.saving.load_model(PATH, safe_mode=True)",
}


def _load(code, tiny_run):
    path = os.path.join(tiny_run["run"], "model.keras")
    script = (f"PATH, RUN = {path!r}, {tiny_run['run']!r}\n" + code
              + "\nprint(type(model).__name__, len(model.outputs))\n")
    env = dict(os.environ, KERAS_BACKEND="jax", PYTHONPATH=REPO)
    return subprocess.run([sys.executable, "-c", script], cwd=str(tiny_run["root"]), env=env,
                          text=True, capture_output=True, timeout=180)


@pytest.mark.parametrize("recipe", sorted(RECIPES))
def test_a_fresh_process_loads_a_saved_model_as_documented(tiny_run, recipe):
    done = _load(RECIPES[recipe], tiny_run)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["CalibrationModel", "13"], done.stdout


def test_the_plain_package_import_does_not_register_and_the_readme_does_not_say_it_does(
        tiny_run):
    """``import cpl_keras`` (or ``cpl_keras.models``) alone keeps Keras out
    of the light commands, so it registers nothing: Keras's loader then
    fails, and the README must name an import that registers."""
    done = _load("import keras\nimport cpl_keras.models\n"
                 "model = keras.saving.load_model(PATH, safe_mode=True)", tiny_run)
    assert done.returncode != 0 and "CalibrationModel" in done.stderr
    with open(os.path.join(REPO, "README.md")) as f:
        readme = " ".join(f.read().split())
    assert "cpl_keras.load_model(path)" in readme
    assert re.search(r"after `import cpl_keras\.saving`", readme)
    assert not re.search(r"after `import cpl_keras\.models`", readme)


def test_load_model_names_a_missing_or_corrupt_file(tmp_path):
    from cpl_keras import runs, saving

    with pytest.raises(runs.RunError, match="no saved model at"):
        saving.load_model(tmp_path / "nothing.keras")
    broken = tmp_path / "model.keras"
    broken.write_bytes(b"not a zip archive")
    with pytest.raises(runs.RunError, match="truncated or corrupt"):
        saving.load_model(tmp_path)


def test_a_model_saved_under_the_former_config_key_still_loads(tiny_run, tmp_path):
    """``CalibrationModel.build_settings`` was saved as ``calibration`` in
    the model's config before it had its name: such a ``model.keras`` loads
    with ``safe_mode=True``, its settings the same, and writes the new key."""
    import json
    import zipfile

    with zipfile.ZipFile(os.path.join(tiny_run["run"], "model.keras")) as saved:
        config = json.loads(saved.read("config.json"))
        settings = config["config"].pop("build_settings")
        config["config"]["calibration"] = settings
        old = tmp_path / "old.keras"
        with zipfile.ZipFile(old, "w") as out:
            for item in saved.infolist():
                out.writestr(item, json.dumps(config) if item.filename == "config.json"
                             else saved.read(item.filename))
    code = ("import json\nimport keras\nimport cpl_keras.saving\n"
            f"model = keras.saving.load_model({str(old)!r}, safe_mode=True)\n"
            "config = model.get_config()\n"
            "print(json.dumps([model.build_settings, 'calibration' in config, "
            "config['build_settings'] == model.build_settings]))\n")
    done = subprocess.run([sys.executable, "-c", code], cwd=str(tmp_path), text=True,
                          env=dict(os.environ, KERAS_BACKEND="jax", PYTHONPATH=REPO),
                          capture_output=True, timeout=180)
    assert done.returncode == 0, done.stderr
    loaded, old_key_written, new_key_written = json.loads(done.stdout.splitlines()[-1])
    assert loaded == settings and settings["variant"] == "baseline"
    assert not old_key_written and new_key_written
