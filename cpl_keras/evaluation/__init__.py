"""Evaluation: every score of the project, Tables 1 and 2, in one place.

* ``pairs``: a table's runs, the pairs a run is scored on and the truth it
  is scored against; ``EvaluationError``.
* ``forward_pass``: a run's outputs on a dataset file, a forward pass or the
  stored predictions that stand for it.
* ``table1``: the rows every table shares (Average, the release's buggy
  Average, the networks, Geometric) and Table 1: ``make_table``,
  ``table_rows`` (what it scores), ``table_from_rows`` (the scoring),
  ``evaluate_run`` (one run).
* ``table2``: Table 2 per real rig and pooled over the rigs:
  ``make_table2``, ``table2_rigs``, ``table2_from_rigs``.
* ``seeds``: one table over several seeds, mean ± spread
  (``aggregate_seeds``).

The scored tables are typed records (``tables``: ``Table1``, ``Table2``,
``table_from_json``); ``cpl_keras.report`` renders both
kinds (Markdown, CSV, JSON, plots). Runs are read through
``cpl_keras.runs``; real data through ``cpl_keras.real``.
"""

from cpl_keras.evaluation.forward_pass import (
    forget_model, predict_run, published, run_predictions, store_predictions,
)
from cpl_keras.evaluation.pairs import (
    EvaluationError, evaluation_indices, load_table_runs, open_dataset, truth_targets,
)
from cpl_keras.evaluation.seeds import SPREAD, SPREAD_METRICS, aggregate_seeds
from cpl_keras.evaluation.table1 import (
    PAPER_CONVENTION, PAPER_TABLES, ROWS, average_rows, evaluate_run, geometric_predictions,
    make_table, read_paper_table, score, table_from_rows, table_rows,
)
from cpl_keras.evaluation.tables import Table1, Table2, table_from_json
from cpl_keras.evaluation.table2 import (
    expand_data_paths, is_rectified, make_table2, rig_name, score_masked, table2_from_rigs,
    table2_rigs,
)

__all__ = [
    "aggregate_seeds",
    "average_rows",
    "evaluate_run",
    "evaluation_indices",
    "EvaluationError",
    "expand_data_paths",
    "forget_model",
    "geometric_predictions",
    "is_rectified",
    "load_table_runs",
    "make_table",
    "make_table2",
    "open_dataset",
    "PAPER_CONVENTION",
    "PAPER_TABLES",
    "predict_run",
    "published",
    "read_paper_table",
    "rig_name",
    "ROWS",
    "run_predictions",
    "score",
    "score_masked",
    "SPREAD",
    "SPREAD_METRICS",
    "store_predictions",
    "Table1",
    "Table2",
    "table_from_json",
    "table2_from_rigs",
    "table2_rigs",
    "table_from_rows",
    "table_rows",
    "truth_targets",
]
