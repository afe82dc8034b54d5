"""Calibrate a stereo pair of image files with a trained run.

    python -m cpl_keras.calibrate LEFT.png RIGHT.png --run RUN_DIR [--json-out FILE]
        [--opencv-yaml FILE] [--ros-yaml DIR] [--colmap DIR]
        [--baseline METRES] [--focal PX|exif]
    python -m cpl_keras.calibrate --folder DIR --run RUN_DIR [...]

Prints JSON with the 10 camera parameters, the point X, Y, Z and the
horizontal and vertical fields of view, in the input images' own pixel
units (``cpl_keras.calibration``, whose ``Calibrator`` this command is a
thin layer over, says how they are scaled back from the model's input).

Bad input (unreadable or non-image files, images of different sizes or
smaller than the model's input, identical left and right images, a run
directory without weights) prints one line and exits with status 2; no
output file is written then. A grey image, and predictions outside the range
of the run's training labels (train_stats.json), are warned about on stderr,
one line each. The JSON says what the run was trained on (``training``: its
protocol, split and training label ranges, in the model's input units), the
spread of each value over crops of the pair (``spread``: its standard
deviation over the whole image and 8 crops, ``spread_method`` says so), what
rests on the pair rather than on a scene scale and which values are scale
priors (``from_the_pair``, ``scale_priors``), what every field means (``fields``), and whether the run
is the demonstration model (then also warned about). One line on stderr,
and ``real_camera_record`` in the JSON, give the run's record on real
cameras (``cpl_keras.real_record``): the real rigs it was scored on without
having seen them, with its median relative fx error beside the Average
row's, or that it was never validated on one.

Known values replace the network's guesses (``cpl_keras.priors``):
``--baseline METRES`` scales the metric quantities, ``--focal PX`` (or
``exif``: a JPEG's 35 mm equivalent) sets fx, fy and the depth through
them; ``priors`` and ``from_prior`` in the JSON say which values came from
them.

``--aspect square`` (the default) takes the pixels as square, as real
cameras' are: fy = fx in the input image's pixels, the network's own fy
kept as ``network_fy``. The network sees the pair squashed to a square, so
its fy must guess the image's aspect ratio from content, and on real rigs it
did worse than fx (docs/real-data.md, "Models for real cameras");
``--aspect model`` reports the network's fy.

``--folder DIR`` calibrates every pair of one rig (``find_pairs``) and
prints ``{"rig": ..., "pairs": [...]}``: the rig's parameters are the
medians over the pairs (the disparity, which belongs to each pair's scene,
is left out), ``spread_over_pairs`` their standard deviations; the YAML
exports describe the rig.
"""

from __future__ import annotations

from cpl_keras.calibration import (
    Calibration, CalibrationError, CalibrationWarning, Calibrator, RigCalibration,
)

__all__ = ["Calibration", "CalibrationError", "CalibrationWarning", "Calibrator", "RigCalibration"]


if __name__ == "__main__":  # the command line: cpl_keras/commands/calibrate.py
    import runpy

    runpy.run_module("cpl_keras.commands.calibrate", run_name="__main__")
