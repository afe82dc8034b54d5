"""``--weight-ema``: validation, the kept epoch and the saved model use the
optimizer's moving average of the weights, training itself is unchanged,
and a run stopped after an epoch resumes to the same end."""

import csv
import os

import pytest

#: MTL-CPL-A on the session's 40-pair fixture: 25 training pairs in batches
#: of 5, 3 validation pairs, every epoch kept (patience 100).
TINY = dict(variant="cpl-a", backbone="small", batch_size=5, seed=1, verbose=0, patience=100)


def _log(run_dir):
    with open(os.path.join(run_dir, "log.csv")) as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def runs_compared(stereo40, tmp_path_factory):
    """The same 3 epochs with the average (momentum 0.5, so that it moves
    within 15 steps) and without it: their run directories."""
    from cpl_keras.training import train

    root = tmp_path_factory.mktemp("ema")
    made = {}
    for name, momentum in (("averaged", 0.5), ("trained", 0.0)):
        made[name] = str(root / name)
        summary = train(stereo40, run_dir=made[name], epochs=3, weight_ema=momentum, **TINY)
        assert summary.config.status == "finished"
    return made


def test_training_is_unchanged_and_validation_uses_the_average(runs_compared):
    averaged, trained = _log(runs_compared["averaged"]), _log(runs_compared["trained"])
    # the weights trained are the same: every epoch's training loss (the swap
    # for validation is undone before the next epoch)
    for a, t in zip(averaged, trained):
        assert float(a["loss"]) == pytest.approx(float(t["loss"]), rel=1e-4)
    # validation saw other weights: the average
    assert any(abs(float(a["val_fx_mae"]) / float(t["val_fx_mae"]) - 1) > 1e-3
               for a, t in zip(averaged, trained))
    import json
    config = json.load(open(os.path.join(runs_compared["averaged"], "config.json")))
    assert config["weight_ema"] == 0.5
    assert json.load(open(os.path.join(runs_compared["trained"], "config.json")))[
        "weight_ema"] == 0.0


def test_the_saved_model_is_the_validated_average(runs_compared, stereo40):
    """model.keras scores the validation pairs as its kept epoch's log row did."""
    from cpl_keras import runs
    from cpl_keras.training.sequence import StereoSequence

    run = runs.load_run(runs_compared["averaged"])
    model = runs.load_model(run)
    rows = _log(runs_compared["averaged"])
    kept = rows[run.config.best_epoch - 1]
    from cpl_keras.data.storage import StereoFile
    from cpl_keras.datasets import targets_from_labels

    with StereoFile(stereo40) as f:
        targets = targets_from_labels(f.labels)
    val = StereoSequence(stereo40, run.split["val"], targets=targets, batch_size=5)
    try:
        scores = model.evaluate(val, return_dict=True, verbose=0)
    finally:
        val.close()
    for name in ("fx", "disparity", "pitch"):
        assert scores[f"{name}_mae"] == pytest.approx(float(kept[f"val_{name}_mae"]), rel=1e-4)


def test_a_run_stopped_after_an_epoch_resumes_to_the_same_end(runs_compared, stereo40,
                                                              tmp_path, monkeypatch):
    from cpl_keras.training import train
    from helpers import interrupt_after_epoch

    run_dir = str(tmp_path / "run")
    interrupt_after_epoch(monkeypatch, 2)  # as a kill right after epoch 2's commit
    with pytest.raises(KeyboardInterrupt):
        train(stereo40, run_dir=run_dir, epochs=3, weight_ema=0.5, **TINY)
    monkeypatch.undo()
    assert train(stereo40, run_dir=run_dir, epochs=3, weight_ema=0.5,
                 **TINY).config.epochs_run == 3
    for resumed, whole in zip(_log(run_dir), _log(runs_compared["averaged"])):
        for key in ("loss", "val_loss", "val_fx_mae", "val_disparity_mae"):
            assert float(resumed[key]) == pytest.approx(float(whole[key]), rel=1e-4), key
    with pytest.raises(Exception, match="moving-average momentum"):
        train(stereo40, run_dir=str(tmp_path / "bad"), epochs=1, weight_ema=1.0, **TINY)
    assert not os.path.exists(tmp_path / "bad")


def test_the_default_momentum_and_runs_made_before_it(runs_compared, stereo40, tmp_path):
    """Left at its default the momentum is WEIGHT_EMA (0 as released), and a
    run directory resumes with its own (a run made without the average is
    not refused); a momentum given that differs from the run's is refused."""
    from cpl_keras.training import TrainingError, planning, train

    plan = planning.plan_run(stereo40, variant="cpl-a", backbone="small",
                             run_dir=str(tmp_path / "new"))
    assert plan.config.training.weight_ema == planning.WEIGHT_EMA == 0.99
    assert planning.plan_run(stereo40, variant="cpl-a", backbone="small", as_released=True,
                             run_dir=str(tmp_path / "new")).config.training.weight_ema == 0.0
    assert not os.path.exists(tmp_path / "new")
    trained = runs_compared["trained"]
    assert planning.plan_run(stereo40, run_dir=trained, epochs=3, **{
        k: v for k, v in TINY.items() if k != "verbose"}).config.training.weight_ema == 0.0
    with pytest.raises(TrainingError, match="weight_ema: 0.0 there, 0.5 now"):
        train(stereo40, run_dir=trained, epochs=3, weight_ema=0.5, **TINY)
