"""Published predictions: the files, tables scored from them alone, and a
table over several seeds as mean ± spread."""

import dataclasses
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from cpl_keras import evaluation, prediction_files, report, table_files
from cpl_keras.camera import TARGETS

SIZE = 32


@pytest.fixture(scope="module")
def published(tiny_run, tmp_path_factory):
    """Table 1 and Table 2 of the shared tiny run, scored in memory and
    published as predictions files into ``out/runs``."""
    from cpl_keras.real.middlebury import build_middlebury

    out = tmp_path_factory.mktemp("published")
    real = build_middlebury(out / "middlebury.h5", crops=3, image_size=SIZE, seed=0)
    context, rows = evaluation.table_rows(1, [tiny_run["run"]], geometric_max=3)
    files = table_files.table1_files(context, rows, out_dir=out, prefix="cvgl",
                                     stem="table1_cvgl", key="k1")
    run_list, rigs = evaluation.table2_rigs([tiny_run["run"]], [real], geometric_max=2)
    files.update(table_files.table2_files(run_list, rigs, out_dir=out, prefix="cvgl",
                                          stem="table2", key="k2"))
    paths = prediction_files.write_files(out / "runs", files)
    return {"out": out, "paths": paths, "tiny": tiny_run, "raw1": (context, rows),
            "raw2": (run_list, rigs),
            "table1": report.portable(evaluation.table_from_rows(context, rows), out),
            "table2": report.portable(evaluation.table2_from_rigs(run_list, rigs), out)}


def test_files_are_plain_arrays(published):
    names = sorted(os.path.basename(p) for p in published["paths"])
    assert names == sorted(
        [f"cvgl_{s}_predictions.npz" for s in ("average", "average-release", "run_baseline",
                                               "geometric")]
        + [f"cvgl_{s}_on_middlebury_predictions.npz" for s in ("average", "average-release",
                                                               "run_baseline", "geometric")])
    split = np.load(os.path.join(published["tiny"]["run"], "split.npz"))
    with np.load(published["out"] / "runs" / "cvgl_run_baseline_predictions.npz",
                 allow_pickle=False) as f:
        assert all(f[k].dtype != object for k in f.files)
        assert list(f["outputs"]) == list(TARGETS)
        assert f["pred"].dtype == np.float32 and f["pred"].shape == (len(split["test"]), 13)
        assert np.array_equal(f["indices"], split["test"])
        assert (str(f["row"]), str(f["variant"]), str(f["split"]), str(f["subset"])) == (
            "MTL-Baseline", "baseline", "paper", "test")
        assert str(f["dataset"]) == "cvgl.h5" and str(f["generator_version"])
        assert int(f["seed"]) == 0 and not bool(f["as_released"])
        assert str(f["source"]) == os.path.relpath(published["tiny"]["run"], published["out"])
        from cpl_keras.data.storage import StereoFile
        from cpl_keras.datasets import targets_from_labels

        with StereoFile(published["tiny"]["data"]) as data:
            fx = np.asarray(targets_from_labels(data.labels)["fx"], np.float64)[split["test"]]
        assert np.array_equal(f["truth"][:, 0], fx)


def test_tables_from_files_equal_the_tables_in_memory(published):
    tables = table_files.tables_from_files(published["paths"])
    assert list(tables) == ["table1_cvgl", "table2"]
    for stem in tables:
        assert json.dumps(tables[stem].to_json(), sort_keys=True) == \
            json.dumps(published[stem.split("_")[0]].to_json(), sort_keys=True), stem


def _second_seed(published, tmp_path):
    """The files again as seed 1, with other predictions of the run."""
    paths = []
    for path in published["paths"]:
        with np.load(path, allow_pickle=False) as f:
            arrays = {k: f[k] for k in f.files}
        arrays["seed"] = np.array(1, np.int64)
        if str(arrays["row"]) == "MTL-Baseline":
            arrays["pred"] = (arrays["pred"] * np.float32(1.1)).astype(np.float32)
        new = tmp_path / os.path.basename(path).replace("_predictions", "-s1_predictions")
        with open(new, "wb") as f:
            np.savez(f, **arrays)
        paths.append(str(new))
    return paths


def test_a_table_over_seeds_is_mean_and_spread(published, tmp_path):
    seed1 = _second_seed(published, tmp_path)
    one = table_files.tables_from_files(seed1)
    tables = table_files.tables_from_files(published["paths"] + seed1)
    table = tables["table1_cvgl"]
    assert table.seeds == [0, 1]
    first, second = published["table1"], one["table1_cvgl"]
    a = first.rows["MTL-Baseline"]["targets"]["fx"]["nmae"]
    b = second.rows["MTL-Baseline"]["targets"]["fx"]["nmae"]
    assert a != b
    row = table.rows["MTL-Baseline"]
    assert row["targets"]["fx"]["nmae"] == pytest.approx((a + b) / 2)
    assert row["spread"]["targets"]["fx"]["nmae"] == pytest.approx(abs(a - b) / np.sqrt(2))
    assert row["per_seed"]["1"]["targets"]["fx"]["nmae"] == b
    assert row["num_pairs"] == 2 * first.rows["MTL-Baseline"]["num_pairs"]
    geo = table.rows["Geometric"]
    assert geo["failures"]["num_pairs"] == 6 and set(geo["priors"]) == {"seed 0", "seed 1"}
    # same rows on both seeds: spread 0 where the predictions did not change
    assert table.rows["Average"]["spread"]["targets"]["fx"]["nmae"] == 0
    md = report.markdown(table)
    assert "mean ± spread over 2 seeds" in md and " ± " in md.split("| MTL-Baseline |")[1]
    csv = report.csv_text(table).splitlines()
    assert any(line.startswith("MTL-Baseline,nmae_spread,") for line in csv)
    assert len(csv) == 1 + 4 * 6
    json.dumps(table.to_json(), allow_nan=False)                               # strict JSON
    # Table 2: per rig and pooled, each a mean over the seeds
    t2 = tables["table2"]
    assert t2.seeds == [0, 1] and t2.rigs["middlebury"].seeds == [0, 1]
    assert "spread" in t2.rigs["middlebury"].rows["MTL-Baseline"]
    assert len(t2.fov_points["middlebury"]["MTL-Baseline"]["true_deg"]) == 6
    written = report.write_outputs(str(tmp_path / "t2"), "table2", t2, "cmd")
    assert all(os.path.getsize(p) for p in written)
    assert "± " in open(tmp_path / "t2" / "table2.md").read()


def test_bad_files_are_one_line_errors(published, tmp_path):
    good = published["paths"][0]

    def fails(path, match):
        with pytest.raises(prediction_files.PredictionsError) as info:
            table_files.tables_from_files([path])
        message = str(info.value)
        assert "\n" not in message and match in message, message

    fails(tmp_path / "none_predictions.npz", "predictions file not found")
    truncated = tmp_path / "truncated_predictions.npz"
    truncated.write_bytes(open(good, "rb").read()[:300])
    fails(truncated, "not a readable predictions file")
    with np.load(good, allow_pickle=False) as f:
        arrays = {k: f[k] for k in f.files}
    for name, change, match in (
            ("pickled", {"source": np.array([{"a": 1}], dtype=object)}, "not a readable"),
            ("short", {"pred": arrays["pred"][:, :12]}, "'pred' has shape"),
            ("order", {"outputs": np.array(TARGETS[::-1])}, "outputs"),
            ("missing", {"truth": None}, "no truth")):
        bad = dict(arrays, **change)
        bad = {k: v for k, v in bad.items() if v is not None}
        path = tmp_path / f"{name}_predictions.npz"
        with open(path, "wb") as f:
            np.savez(f, **bad)
        fails(path, match)
    twice = tmp_path / "twice_predictions.npz"
    shutil.copy(good, twice)
    with pytest.raises(prediction_files.PredictionsError, match="are both row"):
        table_files.tables_from_files([good, str(twice)])


def _with_deep_homo(published, tmp_path):
    """Seed 0's rows and a Deep-Homo run trained on seed 0 only (the tiny
    run's predictions, changed): ``(table1, table2, paths)``, the tables
    scored in memory and the predictions files."""
    (context, rows), (run_list, rigs) = published["raw1"], published["raw2"]
    run = tmp_path / "runs" / "deep-homo-s0"
    run.mkdir(parents=True)
    config = json.loads((Path(published["tiny"]["run"]) / "config.json").read_text())
    (run / "config.json").write_text(json.dumps(dict(config, variant="deep-homo")))

    def deep_homo(raw):
        pred = evaluation.published({k: raw.pred[k] * 0.9 for k in TARGETS})
        return dataclasses.replace(raw, source=str(run), pred=pred)

    context = dict(context, runs=context["runs"] + [str(run)])
    rows = dict(rows, **{"Deep-Homo": deep_homo(rows["MTL-Baseline"])})
    run_list = list(run_list) + [str(run)]
    rigs = [dataclasses.replace(rig, rows=dict(rig.rows, **{
        "Deep-Homo": deep_homo(rig.rows["MTL-Baseline"])})) for rig in rigs]
    out = published["out"]
    files = table_files.table1_files(context, rows, out_dir=out, prefix="cvgl",
                                     stem="table1_cvgl", key="k1", suffix="-s0")
    files.update(table_files.table2_files(run_list, rigs, out_dir=out, prefix="cvgl",
                                          stem="table2", key="k2", suffix="-s0"))
    paths = prediction_files.write_files(tmp_path / "seed0", files)
    return (report.portable(evaluation.table_from_rows(context, rows), out),
            report.portable(evaluation.table2_from_rigs(run_list, rigs), out), paths)


def test_a_row_of_one_seed_in_a_table_over_seeds(published, tmp_path):
    """A run trained on the first seed only (the cpu preset's Deep-Homo and
    MTL-CPL-A as released) is a row of seed 0's tables alone: in the table
    over seeds it is that seed's values, with its seeds and no spread; the
    tables from the files equal the tables scored in memory."""
    table1_s0, table2_s0, seed0 = _with_deep_homo(published, tmp_path)
    seed1 = _second_seed(published, tmp_path)
    tables = table_files.tables_from_files(seed0 + seed1)
    one = table_files.tables_from_files(seed1)
    # exact: the files give what the rows scored in memory give
    for stem, in_memory in (("table1_cvgl", table1_s0), ("table2", table2_s0)):
        expected = evaluation.aggregate_seeds([in_memory, one[stem]], [0, 1])
        assert json.dumps(tables[stem].to_json(), sort_keys=True) == \
            json.dumps(expected.to_json(), sort_keys=True)
    table = tables["table1_cvgl"]
    assert table.seeds == [0, 1]
    assert list(table.rows) == ["Average", "Average (release bug)", "Deep-Homo",
                                   "MTL-Baseline", "Geometric"]
    deep = table.rows["Deep-Homo"]
    assert deep["seeds"] == [0] and "spread" not in deep and list(deep["per_seed"]) == ["0"]
    alone = table1_s0.rows["Deep-Homo"]
    assert deep["targets"] == alone["targets"] and deep["fov_within_deg"] == alone["fov_within_deg"]
    assert deep["num_pairs"] == alone["num_pairs"]
    both = table.rows["MTL-Baseline"]
    assert both["seeds"] == [0, 1] and "spread" in both
    assert both["num_pairs"] == 2 * alone["num_pairs"]
    # Markdown: x ± s for the rows of both seeds, a plain x marked (1 seed)
    md = report.markdown(table)
    line = md.split("| Deep-Homo (1 seed) |")[1].split("\n")[0]
    assert " ± " not in line and line.count(" | ") == len(report.COLUMNS) - 1
    assert " ± " in md.split("| MTL-Baseline |")[1].split("\n")[0]
    assert "Deep-Homo: seed 0" in md and "without spread" in md
    released = dataclasses.replace(table, seeds=[0, 1, 2], rows={
        "MTL-CPL-A (as released)": {"seeds": [0]}, "MTL-CPL-U": {"seeds": [0, 2]}})
    assert report.row_label(released, "MTL-CPL-A (as released)") == \
        "MTL-CPL-A (as released, 1 seed)"
    assert report.row_label(released, "MTL-CPL-U") == "MTL-CPL-U (2 seeds)"
    # CSV: spread lines only over 2+ seeds, every line ends with its row's seeds
    csv = report.csv_text(table).splitlines()
    assert csv[0].endswith(",theta_p,seeds")
    deep_lines = [c for c in csv if c.startswith("Deep-Homo,")]
    assert [c.split(",")[1] for c in deep_lines] == ["mae", "nmae", "nmae_signed"]
    assert all(c.endswith(",0") for c in deep_lines)
    assert all(c.endswith(",0 1") for c in csv if c.startswith("MTL-Baseline,"))
    assert len(csv) == 1 + 4 * 6 + 3
    json.dumps(table.to_json(), allow_nan=False)
    # Table 2: per rig and pooled, and its FOV points of the one seed
    t2 = tables["table2"]
    for sub in [t2] + list(t2.rigs.values()):
        assert sub.rows["Deep-Homo"]["seeds"] == [0]
        assert "spread" not in sub.rows["Deep-Homo"] and "spread" in sub.rows["MTL-Baseline"]
    points = t2.fov_points["middlebury"]
    assert len(points["Deep-Homo"]["true_deg"]) == 3 and len(points["MTL-Baseline"]["true_deg"]) == 6
    written = report.write_outputs(str(tmp_path / "t2"), "table2", t2, "cmd")
    assert all(os.path.getsize(p) for p in written)
    text = open(tmp_path / "t2" / "table2.md").read()
    # pooled and rig: 2 NMAE tables, the FOV table and the field's metrics; and
    # the pooled table on shared pairs (the Geometric row ran on fewer): 2 NMAE tables
    assert t2.shared is not None and t2.shared.rows["Deep-Homo"]["seeds"] == [0]
    assert text.count("| Deep-Homo (1 seed) |") == 2 * 4 + 2


def test_a_table_row_is_a_record_and_a_malformed_one_is_refused():
    """A table's rows are frozen records with named fields, made where the
    table gathers them (Table 1's ``table_rows``) and refused when their
    arrays do not fit together."""
    from cpl_keras.table_rows import Rig, Row, RowError

    assert [f.name for f in dataclasses.fields(Row)] == [
        "source", "as_released", "indices", "truth", "pred", "defined", "priors", "statuses",
        "degenerate"]
    assert sorted(f.name for f in dataclasses.fields(Rig)) == sorted(Rig.CONTEXT + ("rows",))
    n = 3
    arrays = {k: np.zeros(n) for k in TARGETS}
    row = Row(source="run", as_released=False, indices=np.arange(n), truth=arrays, pred=arrays)
    with pytest.raises(dataclasses.FrozenInstanceError):
        row.source = "other"
    with pytest.raises(RowError, match="pred lacks fx"):
        Row(source="run", as_released=False, indices=np.arange(n), truth=arrays,
            pred={k: v for k, v in arrays.items() if k != "fx"})
    with pytest.raises(RowError, match=r"truth\['fx'\] has shape \(2,\), not \(3,\)"):
        Row(source="run", as_released=False, indices=np.arange(n), pred=arrays,
            truth=dict(arrays, fx=np.zeros(2)))
    with pytest.raises(RowError, match="2 statuses for 3 pairs"):
        Row(source="run", as_released=False, indices=np.arange(n), truth=arrays, pred=arrays,
            priors={}, statuses=[{}, {}])
    with pytest.raises(RowError, match="row Average is not a Row"):
        Rig(rig="r", data="r.h5", data_description="", data_source=None, rectified=True,
            width=8, num_pairs=n, rows={"Average": {"source": "run"}})


def test_the_tables_rows_are_records_from_where_they_are_made(published):
    """``table_rows`` and ``table2_rigs`` give records, and a file read back
    gives the same record types (``RowFile``, its ``raw`` a ``Row``)."""
    from cpl_keras.table_rows import Rig, Row

    (_, rows), (_, rigs) = published["raw1"], published["raw2"]
    assert rows and all(isinstance(row, Row) for row in rows.values())
    assert rigs and all(isinstance(rig, Rig) for rig in rigs)
    assert all(isinstance(row, Row) for rig in rigs for row in rig.rows.values())
    item = prediction_files.load(published["paths"][0])
    assert isinstance(item, prediction_files.RowFile) and isinstance(item.raw, Row)


COMMITTED = sorted(Path(__file__).resolve().parents[1].glob("paper_results/**/runs/*_predictions.npz"))


def test_committed_predictions_files_read_into_records_and_write_back_the_same_arrays():
    """Every committed predictions file reads into a ``RowFile`` whose arrays
    (``row_arrays``) are the file's: the same names in the same order, the
    same dtypes, shapes and values (a string's width aside: a published
    file's paths were rewritten in place, within the width they had)."""
    assert len(COMMITTED) > 50
    geometric = 0
    for path in COMMITTED:
        arrays = prediction_files.row_arrays(prediction_files.load(path))
        with np.load(path, allow_pickle=False) as f:
            assert list(arrays) == list(f.files), path
            for name in f.files:
                old, new = f[name], np.asarray(arrays[name])
                same_type = old.dtype.kind == new.dtype.kind == "U" or old.dtype == new.dtype
                assert same_type and old.shape == new.shape, (path, name)
                assert np.array_equal(old, new, equal_nan=old.dtype.kind == "f"), (path, name)
        geometric += "_geometric" in path.name
    assert geometric > 5
