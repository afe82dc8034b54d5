"""What a user already knows about their rig, put in place of the network's
guess: a known baseline and a known focal length (``python -m
cpl_keras.calibrate ... --baseline METRES --focal PX|exif``).

A pair's matches fix the disparity in pixels, but neither the focal length
of a rectified rig nor the scale of the scene (``calibration_records.SCALE_NOTE``):
those the network can only guess from how scenes looked in training, and on
real cameras that guess has been poor (paper_results/real-cameras). Where
the user knows them, they replace it:

* ``Priors.focal_px``: fx is the known focal length (input image pixels) and
  fy likewise (square pixels; with ``--aspect model`` the network's aspect
  ratio fy / fx is kept). The point's depth follows it through Eq. 4a
  (``xCam = fx * baseline / disparity``), so X, Y, Z are recomputed from the
  same projection pixel (u, v) with the camera equations (Eqs. 4b-5c), as is
  baseline / depth = disparity / fx and the fields of view.
* ``Priors.baseline_m``: every metric quantity (baseline, tx, ty, tz, X, Y,
  Z) is scaled by ``baseline_m / baseline``; pitch, the intrinsics and the
  disparity are not in metres and stay.

``exif_focal_px(path, width, height)`` reads a JPEG's 35 mm equivalent focal
length (EXIF ``FocalLengthIn35mmFilm``) and converts it to pixels over the
image diagonal (a 35 mm frame's diagonal is 43.27 mm, the definition of the
equivalent in CIPA DC-008), when the file has it.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from cpl_keras import camera
from cpl_keras.errors import Error
from cpl_keras.images import pillow_limit

#: The quantities in metres: a known baseline rescales them all.
METRIC = ("baseline", "tx", "ty", "tz", "X", "Y", "Z")
#: The quantities a known focal length sets or moves (the point's depth
#: through Eq. 4a, and what is derived from fx downstream).
FOCAL_DEPENDENT = ("fx", "fy", "X", "Y", "Z")
#: The diagonal of a 36 x 24 mm frame.
FULL_FRAME_DIAGONAL_MM = math.hypot(36.0, 24.0)
#: The largest known focal length taken, pixels: a field of view of 0.34 deg
#: across a 6,000 px wide image, beyond any lens (an 800 mm lens on such a
#: full-frame sensor is 133,000 px); a larger one is a slip (units, a typo).
MAX_FOCAL_PX = 1e6
#: EXIF's Exif IFD pointer and its FocalLengthIn35mmFilm tag.
EXIF_IFD, FOCAL_35MM = 0x8769, 0xA405


class PriorError(Error):
    """A known value that cannot be used (one line)."""


@dataclasses.dataclass(frozen=True)
class Priors:
    """What the user knows, each None when not known."""

    # the rig's baseline, metres
    baseline_m: float | None = None
    # the focal length, pixels of the input images (--focal PX, or from EXIF)
    focal_px: float | None = None
    # where focal_px came from, for the output ("--focal", "EXIF ...")
    focal_source: str | None = None

    def __post_init__(self):
        for name in ("baseline_m", "focal_px"):
            value = getattr(self, name)
            if value is not None and not (isinstance(value, (int, float)) and
                                          math.isfinite(value) and value > 0):
                raise PriorError(f"a known {name.replace('_', ' ')} must be a positive number, "
                                 f"got {value!r}")
        if self.focal_px is not None and self.focal_px > MAX_FOCAL_PX:
            raise PriorError(f"a known focal length must be at most {MAX_FOCAL_PX:,.0f} px, got "
                             f"{self.focal_px:g} px")

    def __bool__(self):
        return self.baseline_m is not None or self.focal_px is not None


def exif_focal_px(path, width, height):
    """The 35 mm equivalent focal length of the image file ``path`` in
    pixels of its ``width`` x ``height`` (over the diagonal), and the line
    that says where it came from. PriorError when the file has no such tag."""
    try:
        with pillow_limit() as Image, Image.open(path) as image:
            exif = image.getexif()
            focal = exif.get_ifd(EXIF_IFD).get(FOCAL_35MM) or exif.get(FOCAL_35MM)
    except OSError as error:
        raise PriorError(f"cannot read the EXIF of {path}: {error}") from None
    if not focal or float(focal) <= 0:
        raise PriorError(f"{path} has no 35 mm equivalent focal length in its EXIF "
                         "(FocalLengthIn35mmFilm); give --focal PX")
    pixels = float(focal) * math.hypot(width, height) / FULL_FRAME_DIAGONAL_MM
    return pixels, f"EXIF FocalLengthIn35mmFilm {float(focal):g} mm over the image diagonal"


def apply(values, priors, aspect="square"):
    """``values`` (one window's parameters and point, input image pixels)
    with the known focal length and baseline in place (a new dict)."""
    out = dict(values)
    if priors.focal_px is not None:
        out = _with_focal(out, priors.focal_px, aspect)
    if priors.baseline_m is not None:
        if not (math.isfinite(out["baseline"]) and out["baseline"] > 0):
            raise PriorError(f"the network's baseline {out['baseline']:.4g} m cannot be "
                             "rescaled to the known one")
        factor = priors.baseline_m / out["baseline"]
        for name in METRIC:
            out[name] = out[name] * factor
    return out


def _with_focal(values, focal, aspect):
    """fx (and fy) set to ``focal``; X, Y, Z from the same projection pixel."""
    p = {name: np.float64(values[name]) for name in camera.TARGETS}
    u, v, _ = camera.world_to_image(p["X"], p["Y"], p["Z"], p["fx"], p["fy"], p["u0"], p["v0"],
                                    p["baseline"], p["pitch"], p["tx"], p["ty"], p["tz"])
    fy = focal if aspect == "square" else focal * float(p["fy"] / p["fx"])
    X, Y, Z = camera.image_to_world(focal, fy, p["u0"], p["v0"], p["baseline"], p["disparity"],
                                    p["pitch"], p["tx"], p["ty"], p["tz"], u, v)
    return dict(values, fx=float(focal), fy=float(fy), X=float(X), Y=float(Y), Z=float(Z))


def describe(priors, factor=None):
    """The output's ``priors`` field: each known value, where it came from,
    and the outputs it set or moved."""
    said = {}
    if priors.focal_px is not None:
        said["focal_px"] = {"value": priors.focal_px, "source": priors.focal_source or "--focal",
                            "outputs": list(FOCAL_DEPENDENT) + [
                                "from_the_pair.baseline_over_depth", "fov_horizontal_deg",
                                "fov_vertical_deg"]}
    if priors.baseline_m is not None:
        said["baseline_m"] = {"value": priors.baseline_m, "source": "--baseline",
                              "outputs": list(METRIC)}
        if factor is not None:
            said["baseline_m"]["scale_factor"] = factor
    return said


def from_prior(priors):
    """The names of the outputs that came from, or through, a known value."""
    names = []
    if priors.focal_px is not None:
        names += FOCAL_DEPENDENT
    if priors.baseline_m is not None:
        names += [n for n in METRIC if n not in names]
    return names
