"""The settings a training run is planned with (cpl_keras.training.planning):
every train.py flag reaches the run, the ablation switches are refused where
they do not apply, the drive split, target scaling and steps per execution
reach the model, and a run resumes with the settings it was made with.
"""

import json
import os

import numpy as np
import pytest

from cpl_keras.camera import TARGETS
from helpers import load_script, read_log


FLAG_CASES = {
    "as released": (["--as-released"], "cpl-a", lambda c: c["build"]["as_released"]
                    and c["bn_recompute_batches"] == 0 and c["weight_ema"] == 0.0
                    and c["build"]["disparity_ceiling"] is None
                    and not c["build"]["positive_focal_head"]
                    and not c["build"]["bounded_pitch_head"]),
    "cpl-u heads": (["--disentangle", "partial", "--linear-pitch-head",
                     "--disparity-ceiling", "300", "--point-errors", "relative"], "cpl-u",
                    lambda c: c["build"]["disentangle"] == "partial"
                    and c["build"]["point_errors"] == "relative"
                    and c["build"]["disparity_ceiling"] == 300.0
                    and c["build"]["bounded_pitch_head"] is False),
    "cpl-a heads": (["--linear-focal-head", "--alpha-rate", "3", "--weight-ema", "0.9",
                     "--head-activation", "leaky_relu_0.01", "--head-units"], "cpl-a",
                    lambda c: c["build"]["positive_focal_head"] is False
                    and c["build"]["head_activation"] == "leaky_relu_0.01"
                    and c["build"]["alpha_rate"] == 3.0 and c["weight_ema"] == 0.9),
    "cpl-a recipe": (["--recipe", "sound", "--adaptive-weights", "range", "--weight-decay",
                      "1e-4", "--head-activation", "relu"], "cpl-a",
                     lambda c: c["build"]["head_norm"] is True
                     and c["build"]["disparity_head"] == "softplus"
                     and c["build"]["disparity_start"] > 0 and c["clip_norm"] == 1.0
                     and not {"clip_norm", "weight_decay"} & set(c["build"])  # (training's)
                     and "head_activation" not in c["build"]  # (given: the recipe's overridden)
                     and c["build"]["adaptive_weights"] == "range"
                     and c["build"]["alpha_rate"] == 0.0 and c["weight_decay"] == 1e-4
                     and set(c["build"]["range_scales"]) == set(TARGETS)),
    "baseline steps": (["--target-scaling", "std", "--steps-per-execution", "2",
                        "--bn-recompute-batches", "0", "--split", "held-out-config",
                        "--augment", "photometric", "--exp-disparity-head"], "baseline",
                       lambda c: c["target_scaling"] == "std" and c["augment"] == "photometric"
                       and c["build"]["exp_disparity_head"] is True
                       and c["build"]["disparity_ceiling"] > 0
                       and c["bn_recompute_batches"] == 0 and c["split"] == "held-out-config"),
}


@pytest.mark.slow
@pytest.mark.parametrize("case", list(FLAG_CASES))
def test_every_training_flag_reaches_the_run(case, tiny_run, tmp_path):
    """The train.py options at tiny scale (several per run): the run
    finishes, its config records them, and model.keras loads (safe mode)
    as the model they ask for."""
    import keras

    flags, variant, check = FLAG_CASES[case]
    run_dir = tmp_path / "run"
    assert load_script("train.py").main(["--variant", variant, "--backbone", "small", "--data",
                                 tiny_run["data"], "--epochs", "1", "--batch-size", "5",
                                 "--quiet", "--run-dir", str(run_dir)] + flags) == 0
    config = json.loads((run_dir / "config.json").read_text())
    assert config["status"] == "finished" and config["epochs_run"] == 1
    assert check(config), config
    if config["split"] == "held-out-config":  # no rig of the test set in training
        from cpl_keras.data.storage import StereoFile
        from cpl_keras.datasets import load_split

        with StereoFile(tiny_run["data"]) as f:
            rig = np.asarray(f.labels["config_id"])
        split = load_split(str(run_dir / "split.npz"))
        assert not set(rig[split["test"]]) & set(rig[split["train"]])
    model = keras.saving.load_model(run_dir / "model.keras", safe_mode=True)
    assert model.build_settings["as_released"] == config["build"]["as_released"]
    ceiling = config["build"]["disparity_ceiling"]
    if ceiling is not None:
        assert model.get_layer("disparity").activation.ceiling == ceiling
    if case == "cpl-a heads":  # the default: twice the largest training disparity
        from cpl_keras.data.storage import StereoFile
        from cpl_keras.datasets import load_split

        with StereoFile(tiny_run["data"]) as f:
            disparity = np.asarray(f.labels["disparity"], np.float64)
        train_pairs = load_split(str(run_dir / "split.npz"))["train"]
        assert ceiling == pytest.approx(2 * disparity[train_pairs].max(), abs=1e-3)
    if "alpha_rate" in config["build"]:
        assert model.alpha_rate == config["build"]["alpha_rate"]
    assert model.build_settings.get("head_activation") == config["build"].get("head_activation")
    if case == "cpl-a recipe":  # (the softplus head and range weights, in safe mode)
        # (the training record's optimiser knobs, from the recipe and the command line)
        assert (model.optimizer.global_clipnorm, model.optimizer.weight_decay) == (1.0, 1e-4)
        assert model.get_layer("head_norm") is not None
        assert type(model.get_layer("disparity").activation).__name__ == "SoftplusDisparity"
        assert model.adaptive_weights()["u0"] == pytest.approx(
            1 / config["build"]["range_scales"]["u0"], rel=1e-5)
    if case == "cpl-a heads":  # (a registered activation, loaded in safe mode)
        slope = model.get_layer("pitch_dense_120").activation(np.array([-1.0], "float32"))
        np.testing.assert_allclose(np.asarray(slope), [-0.01], rtol=1e-6)
        log = (run_dir / "log.csv").read_text().splitlines()[0].split(",")  # --head-units
        assert {"dead_pitch", "units_pitch", "dead_fx"} <= set(log) and "grad_fx" not in log
    # metres, the default, is recorded by its absence, as in every run before the choice
    assert model.build_settings.get("point_errors") == config["build"].get("point_errors")
    assert config["build"].get("point_errors") == ("relative" if case == "cpl-u heads" else None)


def test_ablation_switches_are_refused_where_they_do_not_apply(tiny_run, tmp_path):
    from cpl_keras.training import TrainingError, plan_run

    for variant in ("baseline", "deep-homo"):
        with pytest.raises(TrainingError, match="point errors 'relative' apply to the camera "
                           f"projection loss, which {variant} does not train with"):
            plan_run(tiny_run["data"], variant=variant, run_dir=str(tmp_path / variant),
                     backbone="small", point_errors="relative")
    with pytest.raises(TrainingError, match="point errors"):
        plan_run(tiny_run["data"], variant="cpl-a", run_dir=str(tmp_path / "c"),
                 backbone="small", point_errors="depth")
    plan = plan_run(tiny_run["data"], variant="cpl-a", run_dir=str(tmp_path / "a"),
                    backbone="small", point_errors="relative")
    assert plan.config.build["point_errors"] == "relative"
    for variant in ("cpl-a", "deep-homo"):
        with pytest.raises(TrainingError, match="an exp disparity head is MTL-Baseline's "
                           f"ablation; {variant} has its own disparity head"):
            plan_run(tiny_run["data"], variant=variant, run_dir=str(tmp_path / variant),
                     backbone="small", exp_disparity_head=True)
    plain = plan_run(tiny_run["data"], variant="baseline", run_dir=str(tmp_path / "b"),
                     backbone="small")
    assert "exp_disparity_head" not in plain.config.build  # (as in every run before it)
    assert "head_activation" not in plain.config.build
    with pytest.raises(TrainingError, match="head activation 'leaky_relu' applies to the "
                       "regression heads; deep-homo has its own"):
        plan_run(tiny_run["data"], variant="deep-homo", run_dir=str(tmp_path / "h"),
                 head_activation="leaky_relu")
    with pytest.raises(TrainingError, match="head activation"):
        plan_run(tiny_run["data"], variant="cpl-a", run_dir=str(tmp_path / "h"),
                 backbone="small", head_activation="gelu")
    assert plain.config.build["disparity_ceiling"] is None
    assert not any(tmp_path.iterdir())


def test_drive_split_flag_reaches_the_split(tiny_run, tmp_path, capsys):
    """--split drive is the drive split: on 40 cvgl pairs of nearly as many
    rigs it has no validation frames, and says so (exit 2, nothing written)."""
    assert load_script("train.py").main(["--variant", "baseline", "--backbone", "small", "--data",
                                 tiny_run["data"], "--quiet", "--run-dir", str(tmp_path / "run"),
                                 "--split", "drive"]) == 2
    assert "drive split of 40 pairs leaves the val set empty" in capsys.readouterr().err
    assert not (tmp_path / "run").exists()


def test_target_scaling_and_steps_per_execution_reach_the_compiled_model(tiny_run, tmp_path,
                                                                         monkeypatch):
    """train.py --target-scaling std --steps-per-execution 2: the model is
    compiled with two steps per call (one under PyTorch, where Keras runs no
    more and two are refused: test_other_backends.py), and its validation
    loss is the sum of the per-output MAEs each divided by the target's
    standard deviation over the training split (worked out here), not their
    plain sum."""
    import keras

    from cpl_keras import models
    from cpl_keras.camera import TARGETS
    from cpl_keras.data.storage import StereoFile
    from cpl_keras.datasets import load_split, targets_from_labels

    compiled = []
    compile_model = models.compile_model

    def recording(model, *args, **kwargs):
        compiled.append(model)
        return compile_model(model, *args, **kwargs)

    monkeypatch.setattr(models, "compile_model", recording)
    run_dir = tmp_path / "run"
    steps = 1 if keras.backend.backend() == "torch" else 2
    assert load_script("train.py").main(["--variant", "baseline", "--backbone", "small", "--data",
                                 tiny_run["data"], "--epochs", "1", "--batch-size", "4",
                                 "--quiet", "--run-dir", str(run_dir), "--target-scaling", "std",
                                 "--steps-per-execution", str(steps)]) == 0
    assert len(compiled) == 1 and compiled[0].steps_per_execution == steps
    with StereoFile(tiny_run["data"]) as f:
        targets = targets_from_labels(f.labels)
    train_pairs = load_split(str(run_dir / "split.npz"))["train"]
    std = {name: float(np.std(np.asarray(targets[name], np.float64)[train_pairs]))
           for name in TARGETS}
    (row,) = read_log(run_dir)
    scaled = sum(float(row[f"val_{name}_mae"]) / (std[name] if std[name] > 1e-6 else 1.0)
                 for name in TARGETS)
    plain = sum(float(row[f"val_{name}_mae"]) for name in TARGETS)
    assert abs(scaled - plain) > 0.1 * plain  # (a test that can tell)
    assert float(row["val_loss"]) == pytest.approx(scaled, rel=1e-4)


def test_a_run_made_before_the_new_defaults_resumes_with_its_own(stereo40, tmp_path):
    """A run directory of before ``bn_statistics`` and ``monitor`` (its
    config.json has neither) is resumed with what it ran with, unless the
    call names other settings."""
    from cpl_keras.training.planning import TrainingError, plan_run
    from cpl_keras.training import train

    run_dir = str(tmp_path / "old")
    train(stereo40, variant="baseline", run_dir=run_dir, epochs=1, batch_size=5,
          backbone="small", verbose=0, bn_statistics="epoch", monitor="loss")
    path = os.path.join(run_dir, "config.json")
    with open(path) as f:
        config = json.load(f)
    for key in ("bn_statistics", "monitor", "best_score"):
        config.pop(key)
    config["bn_recompute_batches"] = 16
    with open(path, "w") as f:
        json.dump(config, f)
    plan = plan_run(stereo40, variant="baseline", run_dir=run_dir, epochs=1, batch_size=5,
                    backbone="small")
    training = plan.config.training
    assert (training.bn_statistics, training.monitor,
            training.bn_recompute_batches) == ("epoch", "loss", 16)
    with pytest.raises(TrainingError, match="holds a different run .monitor"):
        plan_run(stereo40, variant="baseline", run_dir=run_dir, epochs=1, batch_size=5,
                 backbone="small", monitor="nmae")
