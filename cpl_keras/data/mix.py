"""Mix dataset files into one training file (library function and CLI).

Usage::

    python -m cpl_keras.data.mix --out data/recipe.h5 data/cameras.h5 \\
        data/real/middlebury.h5 data/real/oakd.h5

Rendered sets (``cpl_keras.data.generate``) and real sets
(``cpl_keras.real.build``: crops of real pairs whose labels the crop and
resize updated exactly) share one file layout, so a model can train on
rendered rigs and real rigs together. The mixed file:

* holds every pair of every source, in the order given (a source's pairs in
  their own order), so a source's pairs are a contiguous block;
* keeps the labels that every source has (the required ones always are);
* renumbers ``config_id`` and ``town_id`` so that no two sources share a rig
  configuration or a scene (the splits then never mistake two rigs of
  different sources for one): a source's values are replaced by their rank
  plus the number of values the sources before it used;
* adds ``source_index``, the position of the pair's source in ``sources``;
* records the sources in its metadata (``sources``: file, pairs, protocol,
  rig, source) and the real rigs among them (``rigs``), so that Table 2 can
  refuse to score a model on a rig it was trained on (leave one rig out).

Every source must have the same image size, and no file may be given
twice (by one path or another: a link, another spelling): its pairs would
be in the mix twice, and a split would put copies of one pair on both
sides. The output appears only when complete; bad input prints one line and
exits with status 2.
"""

from __future__ import annotations

import os

import numpy as np

from cpl_keras import cli
from cpl_keras.data.storage import INDEX_LABELS, DatasetError, StereoFile
from cpl_keras.data.writer import StereoWriter

PROG = "python -m cpl_keras.data.mix"
#: Pairs copied at a time.
BLOCK = 256
#: The mixed file's protocol (its metadata).
PROTOCOL = "mix"


def _renumbered(values, offset):
    """``values`` replaced by their rank among the distinct values, plus ``offset``."""
    distinct, rank = np.unique(values, return_inverse=True)
    return (rank + offset).astype(np.int32), len(distinct)


def _source_record(path, data):
    meta = data.metadata
    return {"file": os.path.basename(path), "pairs": data.num_pairs,
            "protocol": meta.get("protocol"), "rig": meta.get("rig"),
            "source": meta.get("source")}


def _common_labels(files):
    """The label names every source has, the integer ones among them."""
    names = set(files[0].labels)
    for f in files[1:]:
        names &= set(f.labels)
    missing = [name for name in INDEX_LABELS if name not in names]
    if missing:
        raise DatasetError(f"every source needs the label(s) {', '.join(missing)}; "
                           f"{', '.join(f.path for f in files if missing[0] not in f.labels)} "
                           f"lack(s) {missing[0]}")
    integer = {name for name in names if all(f.labels[name].dtype.kind in "iub" for f in files)}
    return sorted(names), integer


def _mixed_labels(files, names):
    """The labels of all sources, concatenated, with config_id and town_id
    renumbered per source and ``source_index`` added."""
    labels = {name: [] for name in names}
    labels["source_index"] = []
    offsets = {"config_id": 0, "town_id": 0}
    for k, f in enumerate(files):
        for name in names:
            values = f.labels[name]
            if name in offsets:
                values, used = _renumbered(values, offsets[name])
                offsets[name] += used
            labels[name].append(values)
        labels["source_index"].append(np.full(f.num_pairs, k, np.int32))
    return {name: np.concatenate(parts) for name, parts in labels.items()}


def _same_file(a, b):
    """Whether the paths ``a`` and ``b`` name one existing file."""
    try:
        return os.path.samefile(a, b)
    except OSError:  # (one is missing: StereoFile says so)
        return False


def _check_distinct(out, sources):
    """DatasetError when a file is among the sources twice, or is the output."""
    for i, path in enumerate(sources):
        if os.path.abspath(out) == os.path.abspath(path) or _same_file(out, path):
            raise DatasetError(f"the output {out} is also a source")
        for other in sources[:i]:
            if os.path.abspath(other) == os.path.abspath(path) or _same_file(other, path):
                named = f"{path} is" if path == other else f"{other} and {path} are one file,"
                raise DatasetError(f"{named} given twice: its pairs would be in the mix twice, "
                                   "and copies of one pair on both sides of a split")


def mix_datasets(out, sources, *, command=None):
    """Write the pairs of the dataset files ``sources`` (two or more) into
    ``out`` as one dataset; returns ``out``. DatasetError (one line) when a
    source is unreadable or the sources do not fit together."""
    sources = [os.fspath(s) for s in sources]
    if len(sources) < 2:
        raise DatasetError(f"give at least two dataset files to mix, got {len(sources)}")
    _check_distinct(os.fspath(out), sources)
    files = []
    try:
        for path in sources:
            files.append(StereoFile(path))
        shapes = {f.image_shape for f in files}
        if len(shapes) > 1:
            sizes = ", ".join(f"{os.path.basename(f.path)} {f.image_shape[1]}x{f.image_shape[0]}"
                              for f in files)
            raise DatasetError(f"the sources' images differ in size ({sizes}); build them at "
                               f"one --image-size")
        names, integer = _common_labels(files)
        labels = _mixed_labels(files, names)
        records = [_source_record(path, f) for path, f in zip(sources, files)]
        metadata = {"protocol": PROTOCOL, "generator": PROG, "sources": records,
                    "rigs": sorted({r["rig"] for r in records if r["rig"]}),
                    "pairs": int(sum(f.num_pairs for f in files)),
                    "image_size": files[0].image_shape[0], "command": command}
        height, width, _ = files[0].image_shape
        with StereoWriter(out, metadata["pairs"], (height, width), metadata=metadata,
                          int_labels=integer | {"source_index"}) as writer:
            start = 0
            for f in files:
                for first in range(0, f.num_pairs, BLOCK):
                    cli.check_interrupt()
                    index = np.arange(first, min(first + BLOCK, f.num_pairs))
                    left, right = f.read_pairs(index)
                    stop = start + len(index)
                    writer.write(start, left, right,
                                 {name: values[start:stop] for name, values in labels.items()})
                    start = stop
    finally:
        for f in files:
            f.close()
    return os.fspath(out)


def training_rigs(metadata):
    """The real rigs a dataset's pairs come from (its metadata): a mixed
    file's ``rigs``, a real set's own ``rig``, none for a rendered set."""
    if metadata.get("protocol") == PROTOCOL:
        return list(metadata.get("rigs") or [])
    return [metadata["rig"]] if metadata.get("rig") else []


if __name__ == "__main__":  # the command line: cpl_keras/commands/mix.py
    import runpy

    runpy.run_module("cpl_keras.commands.mix", run_name="__main__")
