"""``analyses/forest_plot.py``: README's figure, its numbers from the committed predictions."""

from helpers import load_script


def test_the_committed_forest_numbers_are_what_the_predictions_give(capsys):
    script = load_script("analyses/forest_plot.py")
    assert script.main(["--check"]) == 0, capsys.readouterr().err
    # and the check can fail: other resamples give other intervals
    assert script.main(["--check", "--resamples", "50"]) == 1
