"""The scored tables as typed records.

``Table1`` is the paper's Table 1 (synthetic data), or one run's scores
(``evaluate_run``: ``table`` None); ``Table2`` is Table 2, pooled over the
real rigs, with a ``Table2`` of each rig in ``rigs``. Both are what
``cpl_keras.evaluation`` returns and ``cpl_keras.report`` renders;
``to_json()`` is the table's JSON file (its keys in this order; an optional
field left at None is not written), and ``table_from_json`` reads one back.

A row of ``rows`` maps row name -> its scores (a JSON-ready dict:
``source``, ``as_released``, ``num_pairs``, ``targets`` -> name -> metric ->
value, ``fov_within_deg``; Geometric also ``priors`` and ``failures``;
Table 2 also ``field``, and ``degenerate``; over several seeds also
``seeds``, ``spread`` and ``per_seed``).
"""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass(frozen=True, kw_only=True)
class _Table:
    """What both tables hold; ``ORDER`` is the JSON's key order."""

    # the paper's table number (1 or 2; None for one run's scores)
    table: int | None
    # the dataset file(s) the rows are scored on, in words, and where they came from
    data: str
    data_description: str
    data_source: str | None
    # pairs scored (pooled: over the rigs; over several seeds: summed), image width in px
    num_pairs: int
    image_width: int
    # the run directories of the network rows
    runs: list
    # row name -> its scores (the module doc)
    rows: dict
    # the paper's own table (row -> column -> value; none for a rig), its NMAE convention
    paper: dict
    paper_convention: str | None
    # over several seeds: the seeds, and what the spread of a cell is
    seeds: list | None = None
    spread: str | None = None

    ORDER = ()
    #: Fields written only when set.
    OPTIONAL = ()

    def to_json(self):
        """The table's JSON (a dict, keys in the file's order)."""
        return {name: getattr(self, name) for name in self.ORDER
                if name not in self.OPTIONAL or getattr(self, name) is not None}


@dataclasses.dataclass(frozen=True, kw_only=True)
class Table1(_Table):
    """Table 1 scored: every row on the runs' common test pairs (or one
    run's scores, ``table`` None)."""

    # the dataset's generator settings (source, protocol, seed, image size, ...)
    data_metadata: dict | None = None

    ORDER = ("table", "data", "data_description", "data_source", "data_metadata", "num_pairs",
             "image_width", "runs", "rows", "paper", "paper_convention", "seeds", "spread")
    OPTIONAL = ("data_metadata", "seeds", "spread")


@dataclasses.dataclass(frozen=True, kw_only=True)
class Table2(_Table):
    """Table 2 scored: pooled over the real rigs (``rigs``: one ``Table2``
    per rig, ``fov_points``), or one rig (``rectified`` set)."""

    table: int = 2
    # one rig: whether its pairs are rectified (no rotation to measure)
    rectified: bool | None = None
    # pooled: rig name -> its Table2, and rig -> row -> true and predicted FOVs (deg)
    rigs: dict | None = None
    fov_points: dict | None = None
    # pooled, where the rows' pairs differ (a Geometric row on fewer pairs): the
    # same rows, each column on the pairs every row has it on
    shared: Table2 | None = None

    ORDER = ("table", "data", "data_description", "data_source", "num_pairs", "image_width",
             "runs", "rows", "paper", "paper_convention", "rectified", "rigs", "shared",
             "fov_points", "seeds", "spread")
    OPTIONAL = ("rectified", "rigs", "shared", "fov_points", "seeds", "spread")

    @property
    def pooled(self):
        """Whether this is the table pooled over the rigs (not one rig's)."""
        return self.rigs is not None

    def to_json(self):
        """The table's JSON (a dict, keys in the file's order; each rig's too)."""
        out = super().to_json()
        if self.rigs is not None:
            out["rigs"] = {name: rig.to_json() for name, rig in self.rigs.items()}
        if self.shared is not None:
            out["shared"] = self.shared.to_json()
        return out


def table_from_json(data):
    """The record of a table's JSON (``to_json``'s dict, or a written file's,
    whose ``command`` is dropped): a ``Table2`` when ``table`` is 2."""
    data = {k: v for k, v in data.items() if k != "command"}
    if data.get("table") != 2:
        return Table1(**data)
    if data.get("rigs") is not None:
        data["rigs"] = {name: table_from_json(rig) for name, rig in data["rigs"].items()}
    if data.get("shared") is not None:
        data["shared"] = table_from_json(data["shared"])
    return Table2(**data)
