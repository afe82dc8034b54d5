"""The authors' released CVGL data, read as released (numpy only).

Two layouts (``detect_layout``; ../docs/data.md "The paper's own data"):

``flat`` ("format used for experiments")
    One folder of 15 flat ``.npy`` files, one row per pair, rows shuffled
    once by the release before saving: ``li``, ``ri`` uint8
    ``(N, 112, 112, 3)`` in BGR order, and 13 float ``(N,)`` label files
    ``fx fy u0 v0 b d tx ty tz p x y z`` (the models' output order). The
    real sets use the same names with a suffix: ``r`` (Tsinghua-Daimler
    test split, images RGB) and ``r_cs`` (Cityscapes).
``episodes`` (raw CARLA episodes)
    ``Town*/<folder whose name contains "episode">/LeftRGB_<k>.png``,
    ``RightRGB_<k>.png`` (paired by the suffix after the first ``_``) and
    ``params.txt``, whose first five lines give the right camera's fov, x,
    y, z and pitch after a ``:`` (CARLA's conventions: degrees, y right,
    pitch up). Its labels are computed as the release computed them
    (``episode_labels``).

Every problem is a one-line ``ReleaseError`` naming the file; the release's
own quirks (negative disparities, pitch in degrees) are data, not errors.
Images are read a block at a time (``NpyRows``), never whole.
"""

from __future__ import annotations

import glob
import math
import os
import re

import numpy as np

from cpl_keras import camera
from cpl_keras.data import protocols
from cpl_keras.data.storage import DatasetError

#: The release's 13 label files, in the models' output order, and the
#: project's name of each.
LABEL_FILES = ("fx", "fy", "u0", "v0", "b", "d", "tx", "ty", "tz", "p", "x", "y", "z")
TARGET_OF_FILE = dict(zip(LABEL_FILES, camera.TARGETS))
IMAGE_FILES = ("li", "ri")
#: The suffixes of the release's sets: "" its CVGL data, "r" Tsinghua-Daimler,
#: "r_cs" Cityscapes.
SUFFIXES = ("", "r", "r_cs")
#: The release's image side (its frames are rendered and stored at 112 px).
IMAGE_SIZE = 112
#: The projection pixel of the release's X, Y, Z: (56, 56) on its CVGL data,
#: (5, 5) on its real sets.
RELEASE_PIXEL = {"": IMAGE_SIZE / 2, "r": 5.0, "r_cs": 5.0}
#: Whether a set's images are stored BGR (read with OpenCV) or RGB (PIL).
BGR = {"": True, "r": False, "r_cs": False}
#: The first five lines of an episode's params.txt, in order.
PARAMS = ("fov", "x", "y", "z", "pitch")


class ReleaseError(DatasetError):
    """The release's files are missing, malformed or not one of its layouts."""


def detect_layout(directory, suffix=""):
    """``"flat"`` or ``"episodes"``: which release layout ``directory`` holds
    (ReleaseError, one line, when neither)."""
    directory = os.fspath(directory)
    if not os.path.isdir(directory):
        raise ReleaseError(f"release folder not found: {directory}")
    if any(os.path.exists(os.path.join(directory, f"{name}{suffix}.npy"))
           for name in IMAGE_FILES + LABEL_FILES):
        return "flat"
    if _episode_folders(directory):
        if suffix:
            raise ReleaseError(f"{directory}: raw episodes are CVGL data; --suffix {suffix} is "
                               "for the real sets' flat .npy files")
        return "episodes"
    raise ReleaseError(
        f"{directory} is neither release layout: no li{suffix}.npy, ri{suffix}.npy and label "
        f"files, and no Town*/*episode*/ folders with LeftRGB_*.png and params.txt")


# ---------------------------------------------------------------------------
# The flat layout
# ---------------------------------------------------------------------------
class NpyRows:
    """The rows of a ``.npy`` file, read a block at a time (``rows[start:stop]``)
    without mapping or loading the file: its images never sit in memory,
    nor in the process's resident pages, beyond the block asked for."""

    def __init__(self, path):
        self.path = path
        with open(path, "rb") as f:
            version = np.lib.format.read_magic(f)
            header = (np.lib.format.read_array_header_1_0 if version == (1, 0) else
                      np.lib.format.read_array_header_2_0)
            self.shape, fortran, self.dtype = header(f)
            self.offset = f.tell()
        if fortran or self.dtype.hasobject:
            raise ValueError("not a C-ordered array of numbers")
        self.ndim = len(self.shape)
        self.row_items = int(np.prod(self.shape[1:], dtype=np.int64))
        if os.path.getsize(path) < self.offset + len(self) * self.row_items * self.dtype.itemsize:
            raise ValueError("the file is shorter than its header says")

    def __len__(self):
        return int(self.shape[0]) if self.shape else 0

    def __getitem__(self, rows):
        start, stop, _ = rows.indices(len(self))
        with open(self.path, "rb") as f:
            f.seek(self.offset + start * self.row_items * self.dtype.itemsize)
            block = np.fromfile(f, self.dtype, max(stop - start, 0) * self.row_items)
        return block.reshape((max(stop - start, 0),) + tuple(self.shape[1:]))


def _load(directory, name, rows=False):
    """The release's file ``name`` in ``directory``: whole (a label), or as
    ``NpyRows`` (``rows``: the images); ReleaseError naming it otherwise."""
    path = os.path.join(directory, name)
    if not os.path.isfile(path):
        raise ReleaseError(f"{directory}: missing {name}")
    try:
        return NpyRows(path) if rows else np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as error:
        first = (str(error).strip().splitlines() or [type(error).__name__])[0]
        raise ReleaseError(f"cannot read {path} ({first})") from None


def _check_extra(directory, suffix):
    """ReleaseError for a ``.npy`` file that is none of the release's."""
    known = {f"{name}{s}.npy" for name in IMAGE_FILES + LABEL_FILES for s in SUFFIXES}
    extra = sorted(os.path.basename(p) for p in glob.glob(os.path.join(directory, "*.npy"))
                   if os.path.basename(p) not in known)
    if extra:
        raise ReleaseError(f"{directory}: unexpected file {extra[0]} (the release's files are "
                           f"{', '.join(n + suffix for n in IMAGE_FILES + LABEL_FILES)}, .npy)")


def read_flat(directory, suffix=""):
    """``(left, right, labels)`` of the flat layout: the two image arrays
    read a block at a time (``NpyRows``; uint8 ``(N, 112, 112, 3)``, as
    stored: BGR or RGB) and
    the 13 label files as float64 arrays keyed by file name, every one
    checked (ReleaseError naming the file)."""
    directory = os.fspath(directory)
    _check_extra(directory, suffix)
    left, right = (_load(directory, f"{name}{suffix}.npy", rows=True) for name in IMAGE_FILES)
    for name, images in zip(IMAGE_FILES, (left, right)):
        if images.dtype != np.uint8 or images.ndim != 4 or images.shape[1:] != (
                IMAGE_SIZE, IMAGE_SIZE, 3):
            raise ReleaseError(f"{name}{suffix}.npy must be uint8 (N, {IMAGE_SIZE}, "
                               f"{IMAGE_SIZE}, 3), got {images.dtype} {images.shape}")
    n = len(left)
    if n == 0:
        raise ReleaseError(f"{directory}: li{suffix}.npy holds no pairs")
    if len(right) != n:
        raise ReleaseError(f"ri{suffix}.npy has {len(right)} rows, li{suffix}.npy {n}")
    labels = {}
    for name in LABEL_FILES:
        file = f"{name}{suffix}.npy"
        values = _load(directory, file)
        if values.dtype.kind != "f" or values.shape != (n,):
            raise ReleaseError(f"{file} must be float ({n},) like li{suffix}.npy, "
                               f"got {values.dtype} {values.shape}")
        values = np.asarray(values, np.float64)
        bad = int(np.sum(~np.isfinite(values)))
        if bad:
            raise ReleaseError(f"{file} has {bad} non-finite values")
        labels[name] = values
    return left, right, labels


# ---------------------------------------------------------------------------
# The raw episodes
# ---------------------------------------------------------------------------
def _episode_folders(root):
    return sorted(p for p in glob.glob(os.path.join(root, "Town*", "*"))
                  if os.path.isdir(p) and "episode" in os.path.basename(p))


def _key(path):
    """The suffix after the first ``_`` of a frame's file name, and its
    numeric sort key."""
    suffix = os.path.splitext(os.path.basename(path))[0].split("_", 1)[1]
    digits = re.findall(r"\d+", suffix)
    return suffix, (int(digits[0]) if digits else -1, suffix)


def read_params(path):
    """The right camera's ``{fov, x, y, z, pitch}`` from an episode's
    params.txt (CARLA's conventions; lines after the fifth ignored)."""
    try:
        with open(path) as f:
            lines = f.read().splitlines()
    except OSError as error:
        raise ReleaseError(f"cannot read {path} ({error.strerror or error})") from None
    if len(lines) < len(PARAMS):
        raise ReleaseError(f"{path} has {len(lines)} lines; its first five give "
                           f"{', '.join(PARAMS)}")
    values = {}
    for name, line in zip(PARAMS, lines):
        try:
            value = float(line.split(":", 1)[1])
        except (IndexError, ValueError):
            raise ReleaseError(f"{path}: line {PARAMS.index(name) + 1} gives no {name} "
                               f"after ':' ({line.strip()!r})") from None
        if not math.isfinite(value):
            raise ReleaseError(f"{path}: {name} is not finite")
        values[name] = value
    if not 0 < values["fov"] < 180:
        raise ReleaseError(f"{path}: fov {values['fov']} is not in (0, 180) degrees")
    return values


def find_episodes(root):
    """Every frame of the raw episodes, in order (towns, episodes, frames by
    number): a list of ``(town, episode, config_id, frame, left_png,
    right_png, params)``."""
    frames = []
    for config_id, folder in enumerate(_episode_folders(root)):
        params = read_params(os.path.join(folder, "params.txt"))
        lefts = {_key(p)[0]: p for p in glob.glob(os.path.join(folder, "LeftRGB_*.png"))}
        rights = {_key(p)[0]: p for p in glob.glob(os.path.join(folder, "RightRGB_*.png"))}
        for key in sorted(set(lefts) ^ set(rights)):
            have, lack = ("LeftRGB", "RightRGB") if key in lefts else ("RightRGB", "LeftRGB")
            raise ReleaseError(f"{folder}: {have}_{key}.png has no {lack}_{key}.png")
        if not lefts:
            raise ReleaseError(f"{folder}: no LeftRGB_*.png frames")
        town = os.path.basename(os.path.dirname(folder))
        for frame, key in enumerate(sorted(lefts, key=lambda k: _key("x_" + k)[1])):
            frames.append((town, os.path.basename(folder), config_id, frame, lefts[key],
                           rights[key], params))
    return frames


def read_frame_rgb(path):
    """One episode frame as RGB uint8 (112, 112, 3) (ReleaseError otherwise)."""
    import cv2

    image = cv2.imread(os.fspath(path), cv2.IMREAD_COLOR)
    if image is None:
        raise ReleaseError(f"cannot read image {path}")
    if image.shape != (IMAGE_SIZE, IMAGE_SIZE, 3):
        raise ReleaseError(f"{path} is {image.shape[1]}x{image.shape[0]}; the release's frames "
                           f"are {IMAGE_SIZE}x{IMAGE_SIZE}")
    return image[..., ::-1]


def episode_labels(params, disparity):
    """The release's 13 labels of a frame (keyed by file name) from its
    episode's ``params`` and its StereoBM mean ``disparity``: fx = fy from
    the fov, u0 = v0 = 56, the right-minus-left differences against the
    fixed left camera, b = tx, pitch in degrees, and X, Y, Z of the camera
    equations at pixel (56, 56) with those values (the degrees fed to sin
    and cos as radians, as released)."""
    focal = float(camera.focal_from_fov(math.radians(params["fov"]), IMAGE_SIZE))
    diff = protocols.cvgl_released(params["x"], params["y"], params["z"], params["pitch"])
    labels = {"fx": focal, "fy": focal, "u0": IMAGE_SIZE / 2, "v0": IMAGE_SIZE / 2,
              "b": diff["baseline"], "d": float(disparity), "tx": diff["tx"],
              "ty": diff["ty"], "tz": diff["tz"], "p": diff["pitch"]}
    pixel = RELEASE_PIXEL[""]
    x, y, z = camera.image_to_world(
        labels["fx"], labels["fy"], labels["u0"], labels["v0"], labels["b"], labels["d"],
        labels["p"], labels["tx"], labels["ty"], labels["tz"], pixel, pixel)
    labels.update(x=float(x), y=float(y), z=float(z))
    return labels


# ---------------------------------------------------------------------------
# Writing the flat layout
# ---------------------------------------------------------------------------
def release_labels(targets):
    """The release's 13 label files (name -> float64 array) from the 13
    targets as the release defined them (``datasets.targets_from_labels(...,
    as_released=True)``)."""
    return {file: np.asarray(targets[name], np.float64) for file, name in TARGET_OF_FILE.items()}


def write_flat(directory, left, right, labels, suffix=""):
    """Pairs in the release's flat layout: ``left``, ``right`` RGB uint8
    ``(N, 112, 112, 3)`` (written BGR for the CVGL set, as the release
    stored them) and ``labels`` keyed by file name (``release_labels``), to
    ``directory`` (made if missing): a rendered dataset in the format the
    authors' notebooks read, and the tests' fixtures."""
    os.makedirs(directory, exist_ok=True)
    for name, images in zip(IMAGE_FILES, (left, right)):
        images = np.asarray(images, np.uint8)
        np.save(os.path.join(directory, f"{name}{suffix}.npy"),
                images[..., ::-1] if BGR[suffix] else images)
    for name in LABEL_FILES:
        np.save(os.path.join(directory, f"{name}{suffix}.npy"), np.asarray(labels[name],
                                                                              np.float64))
    return directory
