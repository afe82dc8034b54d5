"""The authors' released CVGL data imported (cpl_keras.data.import_cvgl), the
split as released, and Tables 1 and 2 from the release's formats, on fixtures
written in those exact formats from the project's own renderer."""

import json
import os
import shutil

import numpy as np
import pytest

from cpl_keras.commands import import_cvgl
from cpl_keras.data import release_files
from cpl_keras.data.generate import generate_dataset
from cpl_keras.data.storage import StereoFile
from cpl_keras.datasets import make_split, targets_from_labels
from helpers import (
    load_script, release_episodes, release_flat, release_order, tsinghua_root,
)

PAIRS = 24


@pytest.fixture(scope="module")
def release(tmp_path_factory):
    """A rendered cvgl file of 24 pairs at 112 px and the same pairs in the
    release's formats: ``flat``, ``real`` (suffix r) and ``episodes``."""
    root = tmp_path_factory.mktemp("release")
    rendered = generate_dataset(str(root / "rendered.h5"), protocol="cvgl", pairs=PAIRS, seed=0,
                                image_size=112, workers=1, progress=False)
    return {"root": root, "rendered": rendered,
            "flat": release_flat(rendered, str(root / "flat")),
            "real": release_flat(rendered, str(root / "real"), suffix="r"),
            "episodes": release_episodes(rendered, str(root / "episodes"))}


def _import(*argv):
    return import_cvgl.main([str(a) for a in argv] + ["--no-progress"])


def test_flat_files_import_unchanged_in_the_release_order(release, tmp_path):
    out = tmp_path / "flat.h5"
    assert _import(release["flat"], "--out", out) == 0
    order = release_order(PAIRS)
    with StereoFile(release["rendered"]) as rendered, StereoFile(out) as imported:
        left, right = rendered.read_pairs(order)
        got_left, got_right = imported.read_pairs(np.arange(PAIRS))
        np.testing.assert_array_equal(got_left, left)        # BGR turned back into RGB
        np.testing.assert_array_equal(got_right, right)
        labels = imported.labels
        for name in release_files.LABEL_FILES:                # unchanged, float64
            stored = labels[f"{release_files.TARGET_OF_FILE[name]}_released"]
            assert stored.dtype == np.float64
            np.testing.assert_array_equal(stored, np.load(os.path.join(release["flat"],
                                                                       f"{name}.npy")))
        # the project's labels the release determines: the rendered file's own
        for name in ("fx", "fy", "u0", "v0", "baseline", "tx", "ty", "tz", "pitch"):
            np.testing.assert_allclose(labels[name], rendered.labels[name][order],
                                       rtol=1e-5, atol=1e-4, err_msg=name)
        assert len(np.unique(labels["config_id"])) == len(np.unique(
            rendered.labels["config_id"]))
        assert np.all(labels["u_released"] == 56) and np.all(labels["v_released"] == 56)
        meta = imported.metadata
        assert imported.as_released_only and meta["layout"] == "flat"
        assert meta["underived_labels"] == ["disparity", "X", "Y", "Z", "u", "v"]
        assert "--as-released" in meta["labels_note"]
        assert "disparity" not in labels and "X" not in labels
    # as released, the targets are the release's files themselves
    with StereoFile(out) as imported:
        targets = targets_from_labels(imported.labels, as_released=True)
        with pytest.raises(ValueError, match="release's only .*--as-released"):
            targets_from_labels(imported.labels)
    np.testing.assert_array_equal(targets["X"], np.load(os.path.join(release["flat"], "x.npy"))
                                  .astype(np.float32))


def test_episodes_import_with_the_release_labels_computed(release, tmp_path):
    """The raw episodes' labels, computed from params.txt and the images as
    the release did (fx from the fov, the differences, StereoBM's mean,
    X, Y, Z at (56, 56)), equal the rendered file's release labels."""
    out = tmp_path / "episodes.h5"
    assert _import(release["episodes"], "--out", out) == 0
    with StereoFile(release["rendered"]) as rendered, StereoFile(out) as imported:
        want = targets_from_labels(rendered.labels, as_released=True)
        got = targets_from_labels(imported.labels, as_released=True)
        carla = {c["config_id"]: c["carla"] for c in rendered.metadata["configurations"]}
        # each imported pair found in the rendered file by its rig and frame
        rig_of = {(round(c["x"], 9), round(c["fov_deg"], 9)): k for k, c in carla.items()}
        x = np.round(imported.labels["tx_released"] + 2.0, 9)
        for i in range(PAIRS):
            matches = [j for j in range(PAIRS)
                       if rendered.labels["frame_index"][j] == imported.labels["frame_index"][i]
                       and np.isclose(rendered.labels["tx_released"][j], x[i] - 2, atol=1e-4)]
            assert len(matches) == 1
            j = matches[0]
            for name in want:
                np.testing.assert_allclose(got[name][i], want[name][j], rtol=1e-4, atol=1e-4,
                                           err_msg=name)
            left, _ = rendered.read_pairs([j])
            np.testing.assert_array_equal(imported.read_pairs([i])[0], left)
        assert rig_of and imported.metadata["shuffle_seed"] == 0
        assert set(imported.labels["town_id"]) == {0, 1}


def test_real_set_files_import_as_released_only(release, tmp_path):
    out = tmp_path / "tdcb_release.h5"
    assert _import(release["real"], "--suffix", "r", "--out", out) == 0
    with StereoFile(out) as imported:
        left, _ = imported.read_pairs([0])
        np.testing.assert_array_equal(left[0], np.load(os.path.join(release["real"],
                                                                    "lir.npy"))[0])  # RGB kept
        assert imported.metadata["rig"] == "tsinghua-release"
        assert np.all(imported.labels["u_released"] == 5)
        assert "fx" not in imported.labels                   # full-resolution intrinsics
        targets = targets_from_labels(imported.labels, as_released=True)
    np.testing.assert_array_equal(targets["pitch"], np.load(os.path.join(
        release["real"], "pr.npy")).astype(np.float32))


def test_the_released_split_takes_the_first_seventy_percent():
    labels = {"fx": np.ones(10)}
    split = make_split(labels, "released", seed=5)
    assert split["train"].tolist() == list(range(7))
    assert split["val"].tolist() == split["test"].tolist() == [7, 8, 9]
    assert make_split(labels, "released", seed=0)["train"].tolist() == list(range(7))
    big = make_split({"fx": np.ones(123017)}, "released")
    assert len(big["train"]) == 86111 and len(big["test"]) == 36906   # the notebooks' counts


def _flat_copy(release, tmp_path):
    folder = tmp_path / "copy"
    shutil.copytree(release["flat"], folder)
    return folder


def _missing_label(f):
    os.remove(f / "tz.npy")


def _extra_file(f):
    np.save(f / "w.npy", np.zeros(PAIRS))


def _short_label(f):
    np.save(f / "d.npy", np.zeros(PAIRS - 1))


def _integer_label(f):
    np.save(f / "fx.npy", np.arange(PAIRS))


def _small_images(f):
    np.save(f / "li.npy", np.zeros((PAIRS, 64, 64, 3), np.uint8))


def _float_images(f):
    np.save(f / "ri.npy", np.zeros((PAIRS, 112, 112, 3), np.float32))


def _fewer_right_images(f):
    np.save(f / "ri.npy", np.zeros((PAIRS - 2, 112, 112, 3), np.uint8))


def _non_finite(f):
    values = np.load(f / "p.npy")
    values[3] = np.nan
    np.save(f / "p.npy", values)


def _not_npy(f):
    (f / "ty.npy").write_bytes(b"not an array")


def _neither_layout(f):
    for name in os.listdir(f):
        os.remove(f / name)
    (f / "notes.txt").write_text("nothing")


REFUSALS = {
    "missing label file": (_missing_label, "missing tz.npy"),
    "extra file": (_extra_file, "unexpected file w.npy"),
    "different lengths": (_short_label, "d.npy must be float (24,)"),
    "wrong dtype": (_integer_label, "fx.npy must be float"),
    "wrong image shape": (_small_images, "li.npy must be uint8 (N, 112, 112, 3)"),
    "images not uint8": (_float_images, "ri.npy must be uint8"),
    "fewer right images": (_fewer_right_images, "ri.npy has 22 rows, li.npy 24"),
    "non-finite labels": (_non_finite, "p.npy has 1 non-finite values"),
    "unreadable file": (_not_npy, "cannot read"),
    "neither layout": (_neither_layout, "is neither release layout"),
}


@pytest.mark.parametrize("case", sorted(REFUSALS))
def test_bad_release_files_are_refused_in_one_line(case, release, tmp_path, capsys):
    folder = _flat_copy(release, tmp_path)
    breaks, message = REFUSALS[case]
    breaks(folder)
    out = tmp_path / "x.h5"
    assert _import(folder, "--out", out) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err
    assert not os.path.exists(out) and not os.path.exists(str(out) + ".partial")


def test_bad_episodes_are_refused_in_one_line(release, tmp_path, capsys):
    root = tmp_path / "episodes"
    shutil.copytree(release["episodes"], root)
    episode = sorted((root / "Town1").iterdir())[0]
    first = sorted(episode.glob("RightRGB_*.png"))[0]
    os.remove(first)
    out = tmp_path / "x.h5"
    assert _import(root, "--out", out) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"has no {first.name}" in err[0], err
    (episode / "params.txt").write_text("fov: wide\n")
    assert _import(root, "--out", out) == 2
    assert "params.txt has 1 lines" in capsys.readouterr().err
    assert not os.path.exists(out)


def test_an_out_that_holds_another_dataset_is_refused(release, tmp_path, capsys):
    out = tmp_path / "x.h5"
    assert _import(release["flat"], "--out", out) == 0
    capsys.readouterr()
    assert _import(release["flat"], "--out", out) == 0            # the same import: kept
    assert "left as it is" in capsys.readouterr().err
    assert _import(release["real"], "--suffix", "r", "--out", out) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "holds another dataset" in err[0], err
    with StereoFile(out) as f:
        assert f.metadata["source"] == "cvgl-release"


def test_an_interrupted_import_continues(release, tmp_path, monkeypatch, capsys):
    from cpl_keras.data import import_cvgl as library

    out = tmp_path / "x.h5"
    monkeypatch.setattr(library, "BLOCK", 8)
    calls = []

    def stop_after_one_block():
        calls.append(1)
        if len(calls) == 1:
            raise KeyboardInterrupt

    monkeypatch.setattr(library.cli, "check_interrupt", stop_after_one_block)
    assert _import(release["flat"], "--out", out) == 130
    assert not os.path.exists(out) and os.path.exists(str(out) + ".partial")
    assert _import(release["flat"], "--out", out) == 0
    assert "resuming" in capsys.readouterr().err
    whole = tmp_path / "whole.h5"
    assert _import(release["flat"], "--out", whole) == 0
    with StereoFile(out) as a, StereoFile(whole) as b:
        np.testing.assert_array_equal(a.read_pairs(np.arange(PAIRS))[1],
                                      b.read_pairs(np.arange(PAIRS))[1])
        assert all(np.array_equal(a.labels[k], b.labels[k]) for k in b.labels)


@pytest.mark.slow
def test_train_as_released_then_tables_1_and_2_from_every_real_layout(release, tmp_path,
                                                                      capsys):
    """Import, train one epoch on the split as released (a plain run is
    refused in one line), Table 1 on the imported file, Table 2 from the
    release's r files and from the Tsinghua-Daimler folder layout."""
    from cpl_keras.commands import real_build

    data, real = tmp_path / "cvgl.h5", tmp_path / "tdcb_release.h5"
    assert _import(release["flat"], "--out", data) == 0
    assert _import(release["real"], "--suffix", "r", "--out", real) == 0
    train = load_script("train.py", "train_cli").main
    evaluate = load_script("evaluate.py", "evaluate_cli").main
    run = tmp_path / "run"
    base = ["--variant", "cpl-a", "--data", str(data), "--split", "released", "--backbone",
            "small", "--epochs", "1", "--run-dir", str(run), "--quiet"]
    capsys.readouterr()
    assert train(base) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--as-released" in err[0] and not run.exists(), err
    assert train(base + ["--as-released"]) == 0
    with open(run / "config.json") as f:
        config = json.load(f)
    assert config["split"] == "released"
    split = np.load(run / "split.npz")
    assert split["train"].tolist() == list(range(16))
    assert split["test"].tolist() == split["val"].tolist() == list(range(16, PAIRS))
    assert evaluate(["--table", "1", "--runs", str(run), "--out", str(tmp_path / "t1")]) == 0
    table1 = json.loads((tmp_path / "t1" / "table1.json").read_text())
    assert table1["num_pairs"] == 8 and "Geometric" not in json.dumps(table1["rows"])
    assert evaluate(["--table", "2", "--runs", str(run), "--data", str(real), "--out",
                     str(tmp_path / "t2")]) == 0
    table2 = json.loads((tmp_path / "t2" / "table2.json").read_text())
    assert table2["num_pairs"] == PAIRS
    tsinghua_root(tmp_path / "tdcb")
    assert real_build.main(["tsinghua", "--root", str(tmp_path / "tdcb"), "--out",
                            str(tmp_path / "tdcb.h5"), "--image-size", "112"]) == 0
    assert evaluate(["--table", "2", "--runs", str(run), "--data", str(tmp_path / "tdcb.h5"),
                     "--out", str(tmp_path / "t3")]) == 0
    assert (tmp_path / "t3" / "table2.md").exists()


def test_the_paper_release_preset_trains_the_paper_s_four_networks_as_released():
    """``--preset paper-release``: the four networks of Table 1, each as
    released on the split as released, the MTL towers from ImageNet
    weights (Deep-Homo has none), with the paper's settings."""
    from cpl_keras.reproduce.jobs import training_arguments
    from cpl_keras.reproduce.plan import run_jobs
    from cpl_keras.reproduce.presets import settings

    config = settings(preset="paper-release")
    assert (config.epochs, config.batch_size, config.patience, config.backbone) == (
        200, 16, 5, "inception_v3")
    jobs = run_jobs(config, 0)
    assert [job.variant for job in jobs] == ["baseline", "cpl-u", "cpl-a", "deep-homo"]
    assert all(job.released and job.split == "released" for job in jobs)
    weights = {job.variant: training_arguments(config, "r", job)["backbone_weights"]
               for job in jobs}
    assert weights == {"baseline": "imagenet", "cpl-u": "imagenet", "cpl-a": "imagenet",
                       "deep-homo": None}
    assert settings(preset="paper-release", split="paper").split == "paper"
    assert settings(preset="paper-release", backbone="small",
                    backbone_weights="none").backbone_weights is None


@pytest.mark.slow
def test_the_paper_release_preset_runs_end_to_end_on_the_release_formats(release, tmp_path,
                                                                         capsys):
    """Its dry run at tiny size: the flat files with the real set's r files
    beside them, and a Tsinghua-Daimler folder, to REPORT.md with Table 1
    on the release's data and Table 2 on both real layouts."""
    from cpl_keras.commands import reproduce

    folder = _flat_copy(release, tmp_path)
    for name in os.listdir(release["real"]):
        shutil.copy(os.path.join(release["real"], name), folder)
    tsinghua_root(tmp_path / "tdcb")
    out = tmp_path / "out"
    argv = ["--preset", "paper-release", "--release-dir", str(folder), "--tsinghua",
            str(tmp_path / "tdcb"), "--backbone", "small", "--backbone-weights", "none",
            "--epochs", "1", "--allow-cpu", "--out", str(out), "--data-dir",
            str(tmp_path / "data"), "--runs-dir", str(tmp_path / "runs")]
    with pytest.raises(SystemExit) as refused:                # no --release-dir for others
        reproduce.main(["--preset", "cpu"] + argv[2:])
    assert refused.value.code == 2
    assert "--release-dir is read by --preset paper-release only" in capsys.readouterr().err
    assert reproduce.main(argv) == 0
    summary = json.loads((out / "reproduce.json").read_text())
    assert [r["name"] for r in summary["runs"]] == ["cvgl_baseline", "cvgl_cpl-u", "cvgl_cpl-a",
                                                   "cvgl_deep-homo"]
    assert all(r["as_released"] and r["split"] == "released" for r in summary["runs"])
    table2 = json.loads((out / "table2.json").read_text())
    assert set(table2["rigs"]) == {"tsinghua-release", "tsinghua"}
    report = (out / "REPORT.md").read_text()
    assert "the authors' released CVGL data" in report and "`released`" in report
