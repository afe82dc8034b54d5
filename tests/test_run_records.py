"""A run is three typed records (``runs.RunConfig``: the model's
``ModelOptions``, the ``TrainingOptions``, the data's ``DataFacts``): the
record a run keeps and the model built from it say the same, config.json
stays flat and every committed one loads, and a new training switch is one
field, one argparse line and its use."""

import glob
import json
import os
import shutil
import subprocess
import sys

import pytest

from cpl_keras import runs
from cpl_keras.models.options import ModelOptions
from cpl_keras.models.variants import VARIANTS

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
#: Every committed config.json (the published runs and the tests' fixtures).
COMMITTED = sorted(glob.glob(os.path.join(REPO, "paper_results", "**", "config.json"),
                             recursive=True))


def _as_built(model):
    """What the built network does, read off its layers."""
    from cpl_keras.layers import bounded_pitch, positive_focal

    names = {layer.name for layer in model.layers}

    def activation(name):  # (Deep-Homo's outputs are slices of one head: no activation)
        return getattr(model.get_layer(name), "activation", None) if name in names else None

    return {
        "bounded_pitch_head": activation("pitch") is bounded_pitch,
        "positive_focal_head": activation("fx") is positive_focal,
        "disentangle": "exact" if any(n.endswith("_detached") for n in names)
        else "partial" if model.training_loss.projection else None,
        "disparity_ceiling": getattr(activation("disparity"), "ceiling", None),
        "as_released": "input_scaling" not in names,
    }


@pytest.mark.parametrize("variant, released", [(v, False) for v in VARIANTS]
                         + [("cpl-a", True), ("baseline", True)])
def test_the_record_and_the_built_model_agree_for_every_variant(variant, released, tiny_run,
                                                                 tmp_path):
    """The model record a run keeps (config.json's ``build``) is the built
    model's ``build_settings`` (its ``to_config()``), and each switch is
    what the network does: no switch recorded on that the network has no
    use for (Deep-Homo's pitch is not bounded, MTL-Baseline has no focal
    floor and no disentangled terms)."""
    from cpl_keras.models import build_from_config
    from cpl_keras.models.calibration_model import saved_options
    from cpl_keras.training import plan_run

    plan = plan_run(tiny_run["data"], variant=variant, run_dir=str(tmp_path / "run"),
                    backbone="small", as_released=released)
    record = plan.config.model
    assert record.variant == variant
    model = build_from_config(variant, plan.config.build)
    assert saved_options(model.build_settings) == record
    assert {k: v for k, v in model.build_settings.items()
            if k not in ("image_size", "loss")} == record.to_config()
    built = _as_built(model)
    assert built == {name: getattr(record, name) for name in built}, (built, record)
    # read back from config.json, the same record
    runs.write_config(str(tmp_path), plan.config)
    assert runs.read_run_config(str(tmp_path)) == plan.config


def test_config_json_stays_flat_and_every_committed_one_loads():
    """The records are nested in memory and flat on disk: the variant,
    ``build``, the data's facts and the training record's fields side by
    side; a config.json of every earlier layout loads (the optimiser's
    knobs of before, in ``build``, are read as the training record's)."""
    assert len(COMMITTED) >= 50
    for path in COMMITTED:
        with open(path) as f:
            raw = json.load(f)
        config = runs.RunConfig.from_dict(raw, path)
        flat = config.to_dict()
        assert not any(isinstance(value, (runs.DataFacts, ModelOptions))
                       for value in flat.values())
        assert flat["data"] == raw["data"] and flat["variant"] == raw["variant"], path
        for key in ("seed", "epochs", "batch_size", "patience", "split"):
            assert flat[key] == raw[key] == getattr(config.training, key), (path, key)
        # (the optimiser's knobs: in ``build`` before, beside it now)
        assert config.training.clip_norm == raw.get("clip_norm", raw["build"].get("clip_norm"))
        assert "clip_norm" not in flat["build"] and flat["clip_norm"] == config.training.clip_norm
        assert runs.RunConfig.from_dict(flat, path) == config, path


def test_a_config_json_with_a_bad_setting_is_one_line_naming_the_file(tmp_path):
    with open(COMMITTED[0]) as f:
        raw = json.load(f)
    (tmp_path / "config.json").write_text(json.dumps(dict(raw, epochs=0)))
    with pytest.raises(runs.RunError, match=r"config.json: epochs must be a positive integer"):
        runs.read_run_config(str(tmp_path))
    (tmp_path / "config.json").write_text(json.dumps(dict(raw, build=dict(
        raw["build"], backbone="vgg"))))
    with pytest.raises(runs.RunError, match=r"config.json: unknown backbone 'vgg'"):
        runs.read_run_config(str(tmp_path))


#: A new optimiser switch, added as docs/layout.md says: the three edits.
NEW_SWITCH = {
    "training_options.py": ("    clip_norm: float | None = None\n",
                            "    clip_norm: float | None = None\n    amsgrad: bool = False\n"),
    "commands/train.py": (
        '    parser.add_argument("--clip-norm", type=cli.positive_float, help=HIDDEN)\n',
        '    parser.add_argument("--clip-norm", type=cli.positive_float, help=HIDDEN)\n'
        '    parser.add_argument("--amsgrad", action="store_true", default=None, help=HIDDEN)\n'),
    "models/factory.py": ("global_clipnorm=training.clip_norm)",
                          "global_clipnorm=training.clip_norm, amsgrad=training.amsgrad)"),
}
SCRIPT = """
import json, sys
import cpl_keras, keras
from cpl_keras.commands.train import main
assert cpl_keras.__file__.startswith(sys.argv[1]), cpl_keras.__file__
args = ["--variant", "cpl-a", "--backbone", "small", "--data", sys.argv[2], "--epochs", "1",
        "--batch-size", "5", "--quiet", "--run-dir", sys.argv[3]]
first = main(args + ["--amsgrad"])
model = cpl_keras.load_model(sys.argv[3])
config = json.load(open(sys.argv[3] + "/config.json"))
again = main(args)
print(json.dumps([first, model.optimizer.amsgrad, config["amsgrad"], again]))
"""


@pytest.mark.slow
def test_a_new_training_switch_is_one_field_one_argparse_line_and_its_use(tiny_run, tmp_path):
    """On a copy of the package with a new optimiser switch (``amsgrad``)
    added by one field of ``TrainingOptions``, one argparse line and its use
    in the optimiser, and nothing else: train.py takes it, config.json
    records it, the optimiser gets it, and the run directory resumes only
    with the same value."""
    root = tmp_path / "copy"
    shutil.copytree(os.path.join(REPO, "cpl_keras"), root / "cpl_keras",
                    ignore=shutil.ignore_patterns("__pycache__"))
    for name, (old, new) in NEW_SWITCH.items():
        path = root / "cpl_keras" / name
        text = path.read_text()
        assert text.count(old) == 1, name
        path.write_text(text.replace(old, new))
    result = subprocess.run(
        [sys.executable, "-c", SCRIPT, str(root), tiny_run["data"], str(tmp_path / "run")],
        capture_output=True, text=True, cwd=tmp_path, timeout=600,
        env=dict(os.environ, PYTHONPATH=str(root), KERAS_BACKEND="jax"))
    assert result.returncode == 0, result.stderr[-3000:]
    first, optimiser, recorded, again = json.loads(result.stdout.strip().splitlines()[-1])
    assert (first, optimiser, recorded) == (0, True, True)
    assert again == 2 and "holds a different run (amsgrad: True there, False now)" in (
        result.stderr)
