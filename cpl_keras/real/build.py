"""Build a real-data HDF5 file for Table 2.

Usage::

    python -m cpl_keras.real.build all --out-dir data/real [--kitti DIR] [--kitti-raw DIR]
                                       [--tsinghua DIR] [--cityscapes DIR]
    python -m cpl_keras.real.build chessboard --out data/real/chessboard.h5 [--root DIR] [--crops 20]
    python -m cpl_keras.real.build middlebury --out data/middlebury.h5 [--crops 500]
    python -m cpl_keras.real.build oakd --out data/oakd.h5 [--crops 20]
    python -m cpl_keras.real.build kitti --root DIR --out data/kitti.h5 [--layout stereo|raw] [--split training]
    python -m cpl_keras.real.build tsinghua --root DIR --out data/tdcb.h5 [--split test]
    python -m cpl_keras.real.build cityscapes --root DIR --out data/cityscapes.h5

``all`` builds every real set that needs no download (the chessboard rig,
Middlebury and the OAK-D rig) and each dataset whose root is given, one file per rig in
``--out-dir`` (existing files are kept; ``--force`` rebuilds them).

Options: ``--image-size`` (112), ``--seed`` (0), ``--crops`` (chessboard, oakd:
per pair, default 20; middlebury: total, default 500), ``--right {warp,released}``
and ``--labels {rig,vehicle}`` (Tsinghua-Daimler / Cityscapes only),
``--limit N`` (first N images, N >= 1). Bad input prints one line and exits
with status 2, as do crops that would not fit in memory or on disk (checked
before any work); the output file appears only when complete.
"""

from __future__ import annotations

import os

from cpl_keras import cli
from cpl_keras.real import chessboard, kitti, middlebury, oakd, tsinghua_cityscapes

SOURCES = ("all", "chessboard", "middlebury", "oakd", "kitti", "tsinghua", "cityscapes")
#: Default crops of the sets that draw crops (chessboard, oakd: per pair).
DEFAULT_CROPS = {"chessboard": 20, "middlebury": 500, "oakd": 20}
#: ``all``: (file stem, source, option holding the root, extra arguments).
#: The sets that ship with the package (no --root needed).
SHIPPED = ("chessboard", "middlebury", "oakd")
ALL_SETS = (
    ("chessboard", "chessboard", None, {}),
    ("middlebury", "middlebury", None, {}),
    ("oakd", "oakd", None, {}),
    ("kitti", "kitti", "kitti", {"layout": "stereo"}),
    ("kitti_raw", "kitti", "kitti_raw", {"layout": "raw"}),
    ("tsinghua", "tsinghua", "tsinghua", {}),
    ("cityscapes", "cityscapes", "cityscapes", {}),
)


PROG = "python -m cpl_keras.real.build"



def _check_out(path):
    """Writes nothing; missing folders are created just before the build."""
    cli.check_output_file(path)


def build_one(source, out, *, root=None, image_size=112, seed=0, crops=None, split=None,
              layout="stereo", right="warp", labels="rig", kitti_calib=None, limit=None,
              command=None, report=None):
    """Build the real set ``source`` into the HDF5 file ``out``; returns its
    path. The keywords are the command line's options (``--image-size``,
    ``--crops`` (None: ``DEFAULT_CROPS``), ...); ``root`` is required for the
    sets that do not ship with the package."""
    _check_out(out)
    crops = crops if crops is not None else DEFAULT_CROPS.get(source)
    if source not in SHIPPED and not (root and os.path.isdir(root)):
        raise ValueError(f"--root is required for {source}" if not root
                         else f"dataset root not found: {root}")
    cli.make_parent(out)
    if source == "middlebury":
        return middlebury.build_middlebury(out, crops=crops, image_size=image_size, seed=seed,
                                           command=command)
    if source == "oakd":
        return oakd.build_oakd(out, root=root or oakd.DATA_DIR, crops=crops,
                               image_size=image_size, seed=seed, command=command)
    if source == "chessboard":
        return chessboard.build_chessboard(out, root=root or chessboard.DATA_DIR, crops=crops,
                                           image_size=image_size, seed=seed, command=command,
                                           report=report)
    if source == "kitti":
        return kitti.build_kitti(root, out, layout=layout, split=split, image_size=image_size,
                                 limit=limit, calib_root=kitti_calib, command=command)
    return tsinghua_cityscapes.build_stereo_dataset(
        root, out, dataset=source, split=split, image_size=image_size, right=right,
        labels=labels, seed=seed, limit=limit, command=command)


def build_all(out_dir, *, roots=None, stems=None, crops_per_source=None, force=False,
              command=None, report=print, **options):
    """``all``: every set that ships with the package (``stems`` of them;
    None: all) and each one ``roots`` ({"kitti", "kitti_raw", "tsinghua",
    "cityscapes": root}) gives, as ``<out_dir>/<stem>.h5``; an existing file
    is kept unless ``force``. ``crops_per_source`` ({source: crops}) overrides
    the crops per source; ``options`` are ``build_one``'s keywords for every
    set."""
    if os.path.exists(out_dir) and not os.path.isdir(out_dir):
        raise ValueError(f"output directory is a file: {out_dir}")
    cli.check_output_file(os.path.join(out_dir, "x.h5"))
    os.makedirs(out_dir, exist_ok=True)
    roots = roots or {}
    paths = []
    for stem, source, option, extra in ALL_SETS:
        root = roots.get(option) if option else None
        if option and not root:
            continue
        if not option and stems is not None and stem not in stems:
            continue
        out = os.path.join(out_dir, f"{stem}.h5")
        if os.path.exists(out) and not force:
            report(f"{out}: exists, kept (--force rebuilds it)")
            paths.append(out)
            continue
        keywords = {**options, **extra}
        if crops_per_source and source in crops_per_source:
            keywords["crops"] = crops_per_source[source]
        paths.append(build_one(source, out, root=root, command=command, report=report,
                               **keywords))
        report(f"{out}: built ({stem})")
    return paths


#: The options of ``build_one`` the command line passes on.
OPTIONS = ("image_size", "seed", "crops", "split", "layout", "right", "labels", "kitti_calib",
           "limit")


if __name__ == "__main__":  # the command line: cpl_keras/commands/real_build.py
    import runpy

    runpy.run_module("cpl_keras.commands.real_build", run_name="__main__")
