"""``analyses/forest_plot.py``: README's figure, its numbers from the committed predictions."""

from helpers import load_script


def test_the_committed_forest_numbers_are_what_the_predictions_give(capsys):
    script = load_script("analyses/forest_plot.py")
    assert script.main(["--check"]) == 0, capsys.readouterr().err
    # and the check can fail: other resamples give other intervals
    assert script.main(["--check", "--resamples", "50"]) == 1


def test_the_plateau_joins_the_figure_once_every_seed_is_published(tmp_path):
    """The plateau setting is left out while a seed of either variant is
    missing; with all published it is drawn from its records, like the
    50-epoch row (here the 50-epoch records stand in for it)."""
    import os

    script = load_script("analyses/forest_plot.py")
    source = os.path.join(script.REPO, "paper_results")
    for _, folder, _ in script.SETTINGS:
        os.makedirs(tmp_path / os.path.dirname(folder), exist_ok=True)
        os.symlink(os.path.join(source, folder), tmp_path / folder)
    runs = tmp_path / "fair-fight" / "inception-plateau" / "runs"
    os.makedirs(runs)
    published = os.path.join(source, "fair-fight", "inception", "runs")
    for arm in ("cpl-a", "baseline"):
        for seed in script.SEEDS:
            if (arm, seed) != ("cpl-a", 2):
                os.symlink(os.path.join(published, f"cvgl_{arm}-s{seed}"),
                           runs / f"cvgl_{arm}-s{seed}")
    assert script.settings(str(tmp_path)) == script.SETTINGS
    os.symlink(os.path.join(published, "cvgl_cpl-a-s2"), runs / "cvgl_cpl-a-s2")
    (label, folder, kind), = script.settings(str(tmp_path))[len(script.SETTINGS):]
    assert folder == "fair-fight/inception-plateau"
    plateau = script.setting_ratios(str(tmp_path / folder), 20, kind=kind)
    fifty = script.setting_ratios(os.path.join(source, "fair-fight", "inception"), 20,
                                  kind=kind)
    assert plateau == fifty and plateau["d"]["seeds"] == [0, 1, 2]
