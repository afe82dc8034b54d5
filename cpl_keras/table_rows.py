"""A table's rows before they are scored, as typed records.

``Row`` is one row of Table 1 or of one rig of Table 2 on its pairs: what a
method (a trained run, the Average rows, the Geometric baseline) predicted,
the truth it is scored against and where that truth exists. ``Rig`` is one
real rig of Table 2: its dataset file's facts and its rows. They are made
where the tables gather their rows (``evaluation.table_rows``,
``evaluation.table2_rigs``), scored into the tables' JSON and Markdown
(``evaluation.table_from_rows``, ``evaluation.table2_from_rigs``), and
written and read back as predictions files (``cpl_keras.prediction_files``,
``cpl_keras.table_files``). A malformed row is refused when it is made
(``RowError``, one line). numpy only.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from cpl_keras.camera import TARGETS
from cpl_keras.errors import Error


class RowError(Error):
    """A table row whose arrays do not fit together (one line)."""


@dataclasses.dataclass(frozen=True, kw_only=True, eq=False)
class Row:
    """One table row on its pairs (n = ``len(indices)``)."""

    # the run directory, or what a baseline is computed from
    source: str
    # whether the row is scored against the release's targets
    as_released: bool
    # (n,) the pairs' indices in the dataset file
    indices: np.ndarray
    # target name -> (n,) array, for every target: the truth, the predictions
    truth: dict
    pred: dict
    # target name -> (n,) bool: where the truth exists (None: on every pair)
    defined: dict | None = None
    # the Geometric row: its fallbacks, each pair's stage failures, and (Table 2)
    # the columns it leaves undefined on a rectified rig
    priors: dict | None = None
    statuses: list | None = None
    degenerate: list | None = None

    def __post_init__(self):
        if not isinstance(self.source, str):
            raise RowError(f"a row's source is a string, not {type(self.source).__name__}")
        if np.ndim(self.indices) != 1:
            raise RowError(f"{self.source}: indices of shape {np.shape(self.indices)}, not (n,)")
        n = len(self.indices)
        for field in ("truth", "pred") + (("defined",) if self.defined is not None else ()):
            arrays = getattr(self, field)
            missing = [k for k in TARGETS if k not in arrays] if isinstance(arrays, dict) \
                else list(TARGETS)
            if missing:
                raise RowError(f"{self.source}: {field} lacks {', '.join(missing)}")
            wrong = [k for k in TARGETS if np.shape(arrays[k]) != (n,)]
            if wrong:
                raise RowError(f"{self.source}: {field}[{wrong[0]!r}] has shape "
                               f"{np.shape(arrays[wrong[0]])}, not ({n},)")
        if (self.priors is None) != (self.statuses is None):
            raise RowError(f"{self.source}: a Geometric row has both priors and statuses")
        if self.statuses is not None and len(self.statuses) != n:
            raise RowError(f"{self.source}: {len(self.statuses)} statuses for {n} pairs")

    @property
    def num_pairs(self):
        return len(self.indices)


@dataclasses.dataclass(frozen=True, kw_only=True, eq=False)
class Rig:
    """One real rig of Table 2: its dataset file and its rows (name -> ``Row``)."""

    # the rig's name, its dataset file, the pairs in words and where they came from
    rig: str
    data: str
    data_description: str
    data_source: str | None
    # whether its pairs are rectified, the image width in px, the pairs scored
    rectified: bool
    width: int
    num_pairs: int
    rows: dict

    #: The fields a predictions file of the rig keeps in its ``context``.
    CONTEXT = ("rig", "data", "data_description", "rectified", "width", "data_source",
               "num_pairs")

    def __post_init__(self):
        wrong = [name for name, row in self.rows.items() if not isinstance(row, Row)]
        if wrong:
            raise RowError(f"rig {self.rig}: row {wrong[0]} is not a Row")

    def context(self):
        """The rig's facts (``CONTEXT``) as a dict, in that order."""
        return {name: getattr(self, name) for name in self.CONTEXT}
