"""The fair fight's published runs as rows of test predictions with their
truths, from committed files alone (no dataset).

A fair-fight record (``paper_results/fair-fight/<towers>/runs/cvgl_<arm>-s<seed>/``)
stores its predictions on its test pairs but not their labels. Every run of
the fair fight, and of ``inception-2000-ema``, trained on the same dataset
file with the paper's split and seeds 0-2, so a seed's test pairs are the
same in both; ``inception-2000-ema``'s table-row predictions files store
their truths. ``rows`` joins the two, and refuses (ValueError, one line) a
record whose dataset file or test pairs differ from the truths' file.
"""

from __future__ import annotations

import glob
import os

import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
#: Where the truths come from: a folder of table-row predictions files of the same dataset.
TRUTHS = os.path.join(REPO, "paper_results", "inception-2000-ema")


def truths(seed, folder=TRUTHS):
    """``(dataset file name, indices, {parameter: truth})`` of ``seed``'s
    test pairs, from MTL-Baseline's table-row predictions file in ``folder``."""
    from cpl_keras import prediction_files

    item = prediction_files.load(os.path.join(folder, "runs",
                                              f"cvgl_baseline-s{seed}_predictions.npz"))
    return item.dataset, np.asarray(item.raw.indices), item.raw.truth


def record_predictions(record):
    """``(dataset file name, indices, {parameter: prediction})`` of a published record."""
    from cpl_keras.camera import PARAMETERS

    found = glob.glob(os.path.join(record, "predictions", "*.npz"))
    if len(found) != 1:
        raise ValueError(f"{record}: {len(found)} predictions files, one expected")
    with np.load(found[0], allow_pickle=False) as stored:
        outputs = [str(x) for x in stored["outputs"]]
        pred = stored["pred"]
        return (str(stored["dataset"]), np.asarray(stored["indices"]),
                {p: pred[:, outputs.index(p)] for p in PARAMETERS})


def rows(runs_folder, arm, seeds=None, truth_folder=TRUTHS):
    """``{seed: {"indices", "truth", "pred"}}`` of ``arm``'s records in
    ``runs_folder`` (``cvgl_<arm>-s<seed>``; every seed published, or ``seeds``)."""
    records = {int(path.rsplit("-s", 1)[1]): path
               for path in glob.glob(os.path.join(runs_folder, f"cvgl_{arm}-s*"))
               if os.path.isdir(path) and path.rsplit("-s", 1)[1].isdigit()}
    out = {}
    for seed in sorted(records if seeds is None else seeds):
        if seed not in records:
            raise ValueError(f"{runs_folder}: no record of {arm} seed {seed}")
        dataset, indices, pred = record_predictions(records[seed])
        truth_dataset, truth_indices, truth = truths(seed, truth_folder)
        if dataset != truth_dataset or not np.array_equal(indices, truth_indices):
            raise ValueError(f"{records[seed]}: its test pairs are not those of "
                             f"{truth_folder}'s seed {seed} ({dataset}, "
                             f"{len(indices)} pairs)")
        out[seed] = {"indices": indices, "truth": truth, "pred": pred}
    return out
