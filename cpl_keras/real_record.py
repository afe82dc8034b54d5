"""A run's record on real cameras: which real rigs it trained on, which it
was scored on without having seen them, and how it did there against the
Average row. ``calibrate`` prints it on one line and puts it in its JSON
(``real_camera_record``), so that a confident answer from a model that was
never checked on a real camera does not look like any other.

The record lives in the run directory, ``real_cameras.json``
(``write_record``, from a Table 2 made for that one run on rigs it did not
train on: ``bench/leave_one_rig_out.py`` writes it for every model it
scores). A run without one was never validated on a real camera.
"""

from __future__ import annotations

import os

from cpl_keras import runs
from cpl_keras.files import read_json, write_json

#: The record's file name in a run directory.
RECORD = "real_cameras.json"


def write_record(run_dir, table, command=None):
    """Write ``run_dir``'s record from ``table``, a pooled ``Table2`` of that run
    (``evaluation.make_table2([run_dir], real_sets)``): per rig, its pairs,
    the median relative fx error and hFoV error of the run's row, and the
    Average row's relative fx error."""
    row = runs.read_run_config(run_dir).row
    rigs = {}
    for rig, part in table.rigs.items():
        model, average = part.rows[row], part.rows["Average"]
        rigs[rig] = {
            "pairs": int(model["num_pairs"]),
            "relative_fx_error": float(model["field"]["relative_fx_median"]),
            "average_relative_fx_error": float(average["field"]["relative_fx_median"]),
            "hfov_error_deg": float(model["field"]["hfov_error_deg_median"]),
        }
    write_json(os.path.join(run_dir, RECORD), {"rigs": rigs, "command": command,
                                               "measure": MEASURE})


#: What the record's figures are.
MEASURE = ("median over the rig's pairs of |fx' - fx| / fx (the network's fx head) and of the "
           "horizontal field-of-view error; the Average row predicts the training mean")


def summarise(run):
    """The record of ``run`` (a ``runs.Run``) for calibrate's output:
    ``validated`` (scored on a real rig it did not train on), ``rigs`` (each
    such rig's figures), ``trained_on_real_rigs`` and ``line``, one line
    that says it all."""
    record = read_json(os.path.join(run.run_dir, RECORD)) or {}
    rigs = record.get("rigs") or {}
    trained = [rig for rig in (run.config.data.training_rigs or [])]
    if rigs:
        worse = [rig for rig, r in rigs.items()
                 if r["relative_fx_error"] >= r["average_relative_fx_error"]]
        figures = ", ".join(
            f"{rig} {r['relative_fx_error']:.2f} (Average {r['average_relative_fx_error']:.2f})"
            for rig, r in sorted(rigs.items()))
        line = (f"real-camera record: median relative fx error on real rigs it never saw: "
                f"{figures}")
        if worse:
            line = "warning: " + line + f"; no better than the Average row on {len(worse)} of " \
                   f"{len(rigs)}"
    else:
        line = ("warning: real-camera record: never validated on a real camera (trained on "
                + (f"real rigs {', '.join(trained)} and " if trained else "")
                + "rendered scenes); on real rigs no model of this project has beaten the "
                "Average row without real training data, so treat fx, fy and the metres as "
                "guesses (--focal and --baseline take known values)")
    return {"validated": bool(rigs), "rigs": rigs, "trained_on_real_rigs": trained,
            "measure": record.get("measure") if rigs else None, "line": line}
