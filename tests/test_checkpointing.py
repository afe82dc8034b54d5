"""Steady validation (cpl_keras.training.checkpointing's ``RunState``): the
BatchNorm statistics recomputed before every validation over fixed training
pairs (``trainer.batchnorm_pairs``), and the NMAE monitor that early stopping
and the kept epoch follow (``nmae_scores``).
"""

import dataclasses
import json
import os

import numpy as np
import pytest

from helpers import read_log


# ---------------------------------------------------------------------------
# Steady validation: fixed BatchNorm statistics, the NMAE monitor
# ---------------------------------------------------------------------------
def test_the_nmae_monitor_keeps_the_epoch_of_the_lowest_validation_nmae(stereo40, tmp_path):
    """The default monitor: log.csv has val_nmae_<p> = val MAE of p / the
    training split's mean |p| and val_nmae their sum; the kept epoch is the
    lowest val_nmae's, whatever val_loss did; config.json says so."""
    from cpl_keras.camera import PARAMETERS
    from cpl_keras.datasets import load_split, targets_from_labels
    from cpl_keras.data.storage import StereoFile
    from cpl_keras.training import train

    run_dir = str(tmp_path / "run")
    summary = train(stereo40, variant="cpl-u", run_dir=run_dir, epochs=3, batch_size=5,
                    backbone="small", verbose=0, patience=10, seed=2)
    rows = read_log(run_dir)
    split = load_split(os.path.join(run_dir, "split.npz"))
    with StereoFile(stereo40) as f:
        targets = targets_from_labels(f.labels)
    for row in rows:
        parts = {}
        for name in PARAMETERS:
            scale = float(np.mean(np.abs(targets[name][split["train"]].astype(np.float64))))
            parts[name] = float(row[f"val_{name}_mae"]) / (scale if scale > 1e-9 else 1.0)
            assert float(row[f"val_nmae_{name}"]) == pytest.approx(parts[name], rel=1e-6)
        assert float(row["val_nmae"]) == pytest.approx(sum(parts.values()), rel=1e-6)
    scores = [float(row["val_nmae"]) for row in rows]
    assert summary.config.best_epoch == 1 + int(np.argmin(scores))
    with open(os.path.join(run_dir, "config.json")) as f:
        config = json.load(f)
    assert config["monitor"] == "nmae" and config["bn_statistics"] == "fixed"
    assert config["best_score"] == pytest.approx(min(scores), rel=1e-6)
    best_row = rows[summary.config.best_epoch - 1]
    assert config["best_val_loss"] == pytest.approx(float(best_row["val_loss"]), rel=1e-6)


def test_fixed_batchnorm_statistics_do_not_depend_on_the_epoch(stereo40, tmp_path):
    """With ``bn_statistics="fixed"`` validation sees the same statistics for
    the same weights at every epoch (the same training pairs, population
    variance); the first batches of each epoch's order ("epoch", the
    earlier default) change with the epoch."""
    import keras

    from cpl_keras import models
    from cpl_keras.training.checkpointing import RunState
    from cpl_keras.models.batchnorm import batchnorm_layers
    from cpl_keras.training.planning import plan_run
    from cpl_keras.training.sequence import StereoSequence
    from cpl_keras.training.trainer import batchnorm_pairs

    plan = plan_run(stereo40, variant="baseline", run_dir=str(tmp_path / "r"), backbone="small",
                    batch_size=5, bn_recompute_batches=2)
    config = plan.config

    def with_config(**changes):  # (the training record's fields)
        return dataclasses.replace(plan, config=dataclasses.replace(
            config, training=dataclasses.replace(config.training, **changes)))

    pairs = batchnorm_pairs(plan)
    assert len(pairs) == 10 and set(pairs) <= set(plan.split["train"])
    np.testing.assert_array_equal(pairs, batchnorm_pairs(plan))
    other_seed = batchnorm_pairs(with_config(seed=config.training.seed + 1))
    assert not np.array_equal(pairs, other_seed)
    capped = batchnorm_pairs(with_config(bn_recompute_batches=1000))
    assert len(capped) == len(plan.split["train"]) // 5 * 5
    # shuffled, so that each batch mixes frames as training's do (file order
    # put neighbouring frames of one drive together)
    assert not np.array_equal(capped, np.sort(capped))

    model = models.build_model("baseline", backbone="small_resnet", image_size=32)
    train_seq = StereoSequence(stereo40, plan.split["train"], targets=plan.targets,
                               batch_size=5, shuffle=True, seed=0)
    fixed = StereoSequence(stereo40, pairs, targets=plan.targets, batch_size=5)
    layer = batchnorm_layers(model)[0]

    def statistics(state, epoch):
        train_seq.set_epoch(epoch)
        state.set_model(model)
        state.on_test_begin()
        return [np.array(keras.ops.convert_to_numpy(v))
                for v in (layer.moving_mean, layer.moving_variance)]

    steady = RunState(str(tmp_path / "a"), 5, train_seq, 2, bn_sequence=fixed)
    for a, b in zip(statistics(steady, 0), statistics(steady, 7)):
        np.testing.assert_array_equal(a, b)
    drawn = RunState(str(tmp_path / "b"), 5, train_seq, 2)
    first, later = statistics(drawn, 0), statistics(drawn, 7)
    assert not np.allclose(first[0], later[0])


def test_nmae_scores_read_either_mae_name_and_sum_the_parameters():
    from cpl_keras.training.checkpointing import nmae_scores

    logs = {"val_fx_mae": 2.0, "val_baseline_loss": 6.0, "val_loss": 9.0}
    scores = nmae_scores(logs, {"fx": 4.0, "baseline": 3.0, "pitch": 1.0})
    assert scores == {"val_nmae_fx": 0.5, "val_nmae_baseline": 2.0, "val_nmae": 2.5}
    assert nmae_scores({"val_loss": 1.0}, {"fx": 1.0}) == {}
