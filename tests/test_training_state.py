"""A run's resume state (backup/state.json) as a record: ``training.state``."""

import os

import pytest

from cpl_keras import runs
from cpl_keras.training import TrainingError
from cpl_keras.training.state import TrainingState, read_state, write_state

# A state.json as every version so far has written it (a cpl-a run stopped
# after its second epoch; each row cut to a few of its logged values).
OLD_STATE = """{
  "epoch": 2,
  "best": 9.491355639179075,
  "best_epoch": 0,
  "wait": 1,
  "stopped": null,
  "rows": [
    {
      "epoch": 0,
      "loss": 247.6885528564453,
      "val_loss": 226.9884796142578,
      "alpha_fx": 0.8053007125854492,
      "wall_time_s": 5.925,
      "load_average": 5.67
    },
    {
      "epoch": 1,
      "loss": 166.8650360107422,
      "val_loss": 225.0625762939453,
      "alpha_fx": 0.7682852745056152,
      "wall_time_s": 5.998,
      "load_average": 5.67
    }
  ],
  "checkpoint": "epoch-0002",
  "best_weights": "best-0000",
  "wall_time_s": 5.998335116000817
}
"""


def _run_dir_with_state(tmp_path, text):
    run_dir = tmp_path / "run"
    (run_dir / runs.BACKUP).mkdir(parents=True, exist_ok=True)
    (run_dir / runs.STATE).write_text(text)
    return str(run_dir)


def test_an_old_state_json_loads_into_the_record_and_writes_back_byte_identical(tmp_path):
    run_dir = _run_dir_with_state(tmp_path, OLD_STATE)
    state = read_state(run_dir)
    assert (state.epoch, state.best, state.best_epoch, state.wait) == (2, 9.491355639179075, 0, 1)
    assert state.stopped is None and state.other == {}
    assert (state.checkpoint, state.best_weights) == ("epoch-0002", "best-0000")
    assert [row["epoch"] for row in state.rows] == [0, 1] and state.rows[1]["loss"] == 166.8650360107422
    assert state.wall_time_s == 5.998335116000817
    os.remove(os.path.join(run_dir, runs.STATE))
    write_state(run_dir, state)
    assert (tmp_path / "run" / runs.STATE).read_text() == OLD_STATE
    # a key of another version is kept, and written back where it was
    extra = OLD_STATE.replace('"wall_time_s": 5.998335116000817\n',
                              '"wall_time_s": 5.998335116000817,\n  "note": [1, "x"]\n')
    extra = extra.replace('[1, "x"]', '[\n    1,\n    "x"\n  ]')
    run_dir = _run_dir_with_state(tmp_path, extra)
    state = read_state(run_dir)
    assert state.other == {"note": [1, "x"]} and state.epoch == 2
    write_state(run_dir, state)
    assert (tmp_path / "run" / runs.STATE).read_text() == extra != OLD_STATE


def test_no_state_json_is_a_fresh_runs_state(tmp_path):
    state = read_state(str(tmp_path))
    assert state == TrainingState()
    # the keys and values a fresh run has always started from
    assert state.to_dict() == {
        "epoch": 0, "best": None, "best_epoch": None, "wait": 0, "stopped": None,
        "rows": [], "checkpoint": None, "best_weights": None, "wall_time_s": 0.0}
    assert TrainingState().rows is not state.rows  # (no list shared between records)


def test_a_trained_runs_state_json_round_trips_and_agrees_with_its_config(tiny_run, tmp_path):
    source = os.path.join(tiny_run["run"], runs.STATE)
    run_dir = _run_dir_with_state(tmp_path, open(source).read())
    state = read_state(run_dir)
    write_state(run_dir, state)
    with open(source, "rb") as f:
        assert (tmp_path / "run" / runs.STATE).read_bytes() == f.read()
    config = runs.read_run_config(tiny_run["run"])
    assert state.epoch == config.epochs_run == len(state.rows) == 1
    assert state.best_epoch + 1 == config.best_epoch and state.stopped == config.stopped


MALFORMED = {
    "not JSON": ('{"epoch": 2,', "cannot read {path}: Expecting property name"),
    "not an object": ("[1, 2]\n", "{path} is not a training state: a JSON object expected, "
                      "got list"),
    "epoch a text": ('{"epoch": "2"}', "{path}: 'epoch' must be a whole number >= 0, got '2'"),
    "epoch negative": ('{"epoch": -1}', "{path}: 'epoch' must be a whole number >= 0"),
    "wait a truth value": ('{"wait": true}', "{path}: 'wait' must be a whole number >= 0"),
    "a row without its epoch": ('{"rows": [{"loss": 1.0}]}', "{path}: 'rows' must be a list "
                                "of objects, each with a whole-number 'epoch' >= 0"),
    "stopped a number": ('{"stopped": 3}', "{path}: 'stopped' must be a text or null, got 3"),
}


@pytest.mark.parametrize("case", list(MALFORMED))
def test_a_malformed_state_json_is_one_line_naming_the_file(case, tmp_path):
    text, expected = MALFORMED[case]
    run_dir = _run_dir_with_state(tmp_path, text)
    with pytest.raises(TrainingError) as raised:
        read_state(run_dir)
    message = str(raised.value)
    assert "\n" not in message
    assert message.startswith(expected.format(path=os.path.join(run_dir, runs.STATE))), message


def test_a_run_with_a_malformed_state_json_is_refused_in_one_line(stereo40, tmp_path,
                                                                  monkeypatch):
    """Resuming an unfinished run whose state.json is damaged: one line,
    and the run directory as it was."""
    from cpl_keras.training import train
    from helpers import interrupt_after_epoch

    run_dir = str(tmp_path / "run")
    options = dict(variant="baseline", backbone="small", epochs=2, batch_size=5, verbose=0)
    interrupt_after_epoch(monkeypatch, 1)
    with pytest.raises(KeyboardInterrupt):
        train(stereo40, run_dir=run_dir, **options)
    monkeypatch.undo()
    state = os.path.join(run_dir, runs.STATE)
    with open(state) as f:
        text = f.read()
    with open(state, "w") as f:
        f.write(text.replace('"epoch": 1,', '"epoch": "one",', 1))
    backup = sorted(os.listdir(os.path.join(run_dir, runs.BACKUP)))
    with pytest.raises(TrainingError, match=r"state\.json: 'epoch' must be a whole number"):
        train(stereo40, run_dir=run_dir, **options)
    assert sorted(os.listdir(os.path.join(run_dir, runs.BACKUP))) == backup
    # mended, the run resumes and ends
    with open(state, "w") as f:
        f.write(text)
    assert train(stereo40, run_dir=run_dir, **options).config.epochs_run == 2
