"""The records calibrate gives, and the JSON they write: ``Calibration``
(one pair calibrated by a run) and ``RigCalibration`` (the pairs of one rig
and the rig from them), made by ``cpl_keras.calibration.Calibrator``.

Each holds typed values: its ``camera`` (a
``cpl_keras.stereo_camera.StereoCamera``: fx, fy, u0, v0 and the images'
size, the baseline, the pose), a pair's ``disparity`` and ``point`` (a
``Point``), the spread, the known values (a ``cpl_keras.priors.Priors``).
What is the same for every record, the prose of the JSON (what each field
means, the units, how the spread is measured, the notes), is written once,
here, by ``as_dict``; ``to_json`` is the text ``python -m
cpl_keras.calibrate`` prints, and ``cpl_keras.exports`` writes the records
for OpenCV, ROS and COLMAP.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math

from cpl_keras import priors as known
from cpl_keras.camera import PARAMETERS, UNITS
from cpl_keras.stereo_camera import Point, StereoCamera

#: Test-time crops for the spread: how many, and their side as a share of the image.
TTA_CROPS = 8
TTA_FRACTION = (0.8, 0.95)
#: What each printed field means, with its unit.
FIELDS = {
    "fx": "focal length along u (px of the input images)",
    "fy": "focal length along v (px)",
    "u0": "principal point u (px; pixel centres at integers)",
    "v0": "principal point v (px)",
    "baseline": "distance between the camera centres (m; a scale prior, see scale_priors)",
    "disparity": "disparity of the projection pixel (px; Eq. 4a: fx * baseline / xCam)",
    "tx": "right camera's position along the left camera's forward axis (m; scale prior)",
    "ty": "right camera's position along the left camera's left axis (m; scale prior)",
    "tz": "right camera's position along the left camera's up axis (m; scale prior)",
    "pitch": "right camera's pitch relative to the left one (rad; positive: down)",
    "X": "the projection pixel's point, forward (m, left camera frame; scale prior)",
    "Y": "the point, to the left (m; scale prior)",
    "Z": "the point, up (m; scale prior)",
}
#: What the JSON says of the quantities a pair does not fix.
SCALE_PRIORS = ("baseline", "tx", "ty", "tz", "X", "Y", "Z")
SCALE_NOTE = ("what does not rest on the scene scale seen in training: disparity_px is the "
              "network's estimate from the pair, not a measurement of its matches (the pair's "
              "matches could fix it, in pixels of the input images; it scales with the "
              "images' size: not scale-free); baseline / depth = disparity / fx is unitless, but for "
              "a rectified or nearly rectified rig (parallel optical axes) the matches carry "
              "nothing of fx, fy, u0, v0 (its fundamental matrix does not depend on them), so "
              "fx, and through it baseline / depth, come from how scenes looked in training; "
              "the metres of baseline, tx, ty, tz and X, Y, Z come from the scene scale seen "
              "in training (scale_priors)")
ASPECT_NOTES = {
    "square": "square pixels: fy = fx (px of the input images); network_fy is the network's "
              "own fy, which guesses the aspect ratio of the squashed image from content",
    "model": "fy is the network's fy head (the pair squashed to the model's square input)",
}
SPREAD_METHOD = ("each value's sample standard deviation (n - 1 in the denominator), in its "
                 "own unit, over {} predictions: the whole image and {} crops of "
                 f"{int(100 * TTA_FRACTION[0])}-{int(100 * TTA_FRACTION[1])} % of each side at "
                 "seeded positions, each crop's prediction mapped back to the full image's "
                 "pixels, with any known value in place (a known focal length's fx: 0); how far "
                 "the estimate moves with the framing, not its error (a confident wrong value "
                 "has a small spread)")
RELEASED_NOTE = ("run trained as released: pitch converted from degrees; disparity is the "
                 "release's StereoBM mean label, not a pixel disparity")
#: The rig's parameters (the disparity belongs to each pair's scene).
RIG_PARAMETERS = tuple(name for name in PARAMETERS if name != "disparity")
RIG_METHOD = ("median over the pairs; spread_over_pairs: standard deviation over the pairs "
              "(n - 1 in the denominator)")



class _Record:
    """``to_json`` of the records below (each writes its ``as_dict``)."""

    def to_json(self):
        """The JSON text ``python -m cpl_keras.calibrate`` prints."""
        return json.dumps(self.as_dict(), indent=2, allow_nan=False)

    @property
    def image_width(self):
        """W of the input images (px)."""
        return self.camera.width

    @property
    def image_height(self):
        """H of the input images (px)."""
        return self.camera.height

    @property
    def pitch_deg(self):
        """The pitch in degrees."""
        return math.degrees(self.camera.pitch)

    @property
    def fov_horizontal_deg(self):
        """The horizontal field of view from fx and W (degrees)."""
        return self.camera.fov_deg[0]

    @property
    def fov_vertical_deg(self):
        """The vertical field of view from fy and H (degrees)."""
        return self.camera.fov_deg[1]

    @property
    def from_prior(self):
        """The outputs that came from, or through, a known value."""
        return known.from_prior(self.priors)


@dataclasses.dataclass(frozen=True, kw_only=True)
class Calibration(_Record):
    """One pair calibrated by a run, in the input images' pixels. What is
    the same for every pair (what each field means, the units, how the
    spread is measured, the notes) is written by ``as_dict``."""

    left: str                 #: the left image file (absolute path)
    right: str                #: the right image file
    model_input: tuple        #: (S_h, S_w), the model's input the pair was resized to
    run: str                  #: the run directory
    variant: str              #: the run's model variant
    camera: StereoCamera      #: fx, fy, u0, v0 (px), the images' size, baseline, pose
    disparity: float          #: the projection pixel's disparity (px; Eq. 4a)
    point: Point              #: the projection pixel's point (m, left camera frame)
    spread: dict              #: each value's standard deviation over crops of the pair
    windows: int              #: how many predictions the spread is over
    demonstration_model: bool  #: the run is the demonstration model
    aspect: str               #: "square" (fy = fx) or "model" (the network's fy)
    network_fy: float         #: the network's own fy (px)
    training: dict            #: the run's protocol, split and training label ranges
    real_camera_record: dict  #: the run's record on real cameras (``real_record``)
    priors: known.Priors      #: the known values given (a focal length from EXIF read)
    baseline_factor: float | None = None  #: known baseline / the network's (None: none known)
    impossible: tuple = ()    #: what no pair can show (``impossible_geometry``)

    @property
    def parameters(self):
        """fx, fy, u0, v0, baseline, disparity, tx, ty, tz, pitch (a new dict)."""
        labels = self.camera.to_labels(disparity=self.disparity)
        return {name: labels[name] for name in PARAMETERS}

    def as_dict(self):
        """The record as calibrate's JSON-ready dict (a copy: changing it
        leaves the record as it is)."""
        out = {"left": self.left, "right": self.right, "image_width": self.image_width,
               "image_height": self.image_height, "model_input": list(self.model_input),
               "run": self.run, "variant": self.variant, "parameters": self.parameters,
               "point": self.point.as_dict(), "pitch_deg": self.pitch_deg,
               "fov_horizontal_deg": self.fov_horizontal_deg,
               "fov_vertical_deg": self.fov_vertical_deg,
               "units": {name: UNITS[name] for name in PARAMETERS}, "spread": dict(self.spread),
               "spread_method": SPREAD_METHOD.format(self.windows, self.windows - 1),
               "from_the_pair": {"disparity_px": self.disparity,
                                 "baseline_over_depth": self.disparity / self.camera.fx,
                                 "note": SCALE_NOTE},
               "scale_priors": list(SCALE_PRIORS), "fields": dict(FIELDS),
               "demonstration_model": self.demonstration_model, "aspect": self.aspect,
               "network_fy": self.network_fy, "aspect_note": ASPECT_NOTES[self.aspect],
               "training": copy.deepcopy(self.training)}
        if self.training["as_released"]:
            out["notes"] = [RELEASED_NOTE]
        out.update(real_camera_record=copy.deepcopy(self.real_camera_record),
                   priors=known.describe(self.priors, factor=self.baseline_factor),
                   from_prior=self.from_prior)
        if self.impossible:
            out["impossible"] = list(self.impossible)
        return out


@dataclasses.dataclass(frozen=True, kw_only=True)
class RigCalibration(_Record):
    """The pairs of one rig calibrated by a run, and the rig from them;
    ``as_dict()`` is ``{"rig": ..., "pairs": [...]}``."""

    folder: str               #: the folder of pairs (absolute path)
    run: str                  #: the run directory
    variant: str              #: the run's model variant
    camera: StereoCamera      #: each of RIG_PARAMETERS the median over the pairs; their size
    spread_over_pairs: dict   #: their standard deviation over the pairs
    demonstration_model: bool  #: the run is the demonstration model
    aspect: str               #: "square" or "model"
    real_camera_record: dict  #: the run's record on real cameras
    priors: known.Priors      #: the known values given (the first pair's)
    pairs: tuple = ()         #: each pair's ``Calibration``
    impossible: tuple = ()    #: what no pair can show: the rig's medians', then each pair's

    @property
    def num_pairs(self):
        """How many pairs the folder holds."""
        return len(self.pairs)

    @property
    def parameters(self):
        """Each of RIG_PARAMETERS, the median over the pairs (a new dict)."""
        return {name: getattr(self.camera, name) for name in RIG_PARAMETERS}

    def as_dict(self):
        rig = {"folder": self.folder, "num_pairs": self.num_pairs, "run": self.run,
               "variant": self.variant, "image_width": self.image_width,
               "image_height": self.image_height, "parameters": self.parameters,
               "spread_over_pairs": dict(self.spread_over_pairs), "method": RIG_METHOD,
               "pitch_deg": self.pitch_deg, "fov_horizontal_deg": self.fov_horizontal_deg,
               "fov_vertical_deg": self.fov_vertical_deg,
               "units": {name: UNITS[name] for name in RIG_PARAMETERS},
               "scale_priors": [n for n in SCALE_PRIORS if n in RIG_PARAMETERS],
               "demonstration_model": self.demonstration_model, "aspect": self.aspect,
               "aspect_note": ASPECT_NOTES[self.aspect],
               "real_camera_record": copy.deepcopy(self.real_camera_record),
               "priors": known.describe(self.priors), "from_prior": self.from_prior}
        if self.impossible:
            rig["impossible"] = list(self.impossible)
        return {"rig": rig, "pairs": [pair.as_dict() for pair in self.pairs]}
