"""A calibration written for other tools: OpenCV's stereo YAML, ROS
``camera_info`` YAML and COLMAP's ``cameras.txt`` and ``rig_config.json``
(``python -m cpl_keras.calibrate ... --opencv-yaml FILE --ros-yaml DIR
--colmap DIR``).

Each writer takes calibrate's record, a ``cpl_keras.calibration_records.Calibration``
(one pair) or ``RigCalibration`` (a rig: the medians over its pairs), and
describes its camera (a ``cpl_keras.stereo_camera.StereoCamera``) as
calibrate found it, in the input images' pixels: one pinhole camera model
``K = [[fx, 0, u0], [0, fy, v0], [0, 0, 1]]`` for both cameras (the model
predicts one; ``StereoCamera.K``), no distortion (the paper's model has
none), and the right camera's pose from ``pitch`` and ``(tx, ty, tz)``
(``StereoCamera.to_opencv_pose``; yaw and roll are not predicted: 0). The
three agree (``exported_rig``, one rule for all): the translation is the
direction of ``(tx, ty, tz)`` at the length of the baseline (the network's
baseline head, or the known ``--baseline``, where the two differ), and a
rig whose baseline is more than ``SIDE_BY_SIDE_MAX_DEG`` from the left
camera's x axis (a model trained on cvgl labels puts it along the optical
axis) is not a side-by-side pair, which each export says (``note``).

* OpenCV (``write_opencv_yaml``): ``cv2.FileStorage``'s own YAML, the keys of
  OpenCV's ``stereo_calib`` sample: ``M1, D1, M2, D2`` (intrinsics and
  distortion), ``R, T`` (``X_right = R X_left + T``, OpenCV axes, metres),
  and ``image_width``, ``image_height``, ``baseline_m`` (``|T|``),
  ``side_by_side`` (1 or 0), ``notes`` and ``impossible`` (lists of
  strings, only where there is something to say: OpenCV writes no string of
  4,096 characters or more).
* ROS (``write_ros_yaml``): ``left.yaml`` and ``right.yaml`` in the format of
  ROS's ``camera_calibration_parsers``: ``camera_matrix`` K,
  ``distortion_model: plumb_bob`` with zero coefficients, and for a
  side-by-side pair the rectified pair ROS's stereo nodes read:
  ``rectification_matrix`` each camera's rotation into the common rectified
  frame (Bouguet's, as ``cv2.stereoRectify``), ``projection_matrix`` ``[K |
  0]`` (left) and ``[K | (Tx, 0, 0)]`` with ``Tx = -fx * B`` (right; B the
  baseline, negative for a right camera on the left). ROS has no stereo
  pair of any other layout: such a rig's cameras are written each alone
  (identity rectification, ``[K | 0]``), the note a comment at the top.
* COLMAP (``write_colmap_cameras``): ``cameras.txt`` with the left and
  right cameras as PINHOLE models, ``cx, cy`` moved by half a pixel to
  COLMAP's pixel centres, and ``rig_config.json`` for COLMAP's
  ``rig_configurator`` (3.12 and later; images in ``left/`` and ``right/``):
  the left camera the reference sensor, the right one's
  ``cam_from_rig_rotation`` (quaternion w, x, y, z) and
  ``cam_from_rig_translation``, which are OpenCV's R and T.

A file that cannot be written as asked is an ``ExportError`` (a
``cpl_keras.errors.Error``), one line, and none of the files is left.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re

import numpy as np

from cpl_keras.errors import Error, one_line
from cpl_keras.files import atomic_path, new_folders

#: A side-by-side pair: its baseline at most this far (degrees) from the
#: left camera's x axis, to the right or (a swapped pair) to the left.
SIDE_BY_SIDE_MAX_DEG = 30.0


class ExportError(Error):
    """An export that cannot be written as asked, said in one line."""


@dataclasses.dataclass(frozen=True)
class ExportedRig:
    """The pair as every export writes it: OpenCV's ``R, T``
    (``X_right = R X_left + T``), ``T`` at the baseline's length."""

    R: np.ndarray          #: the right camera's rotation (OpenCV axes)
    T: np.ndarray          #: the translation (m), its length the baseline
    baseline: float        #: ``|T|`` (m)
    side_by_side: bool     #: the baseline within SIDE_BY_SIDE_MAX_DEG of the x axis
    note: str | None       #: one line where the rig is not side by side


def exported_rig(calibration):
    """The ``ExportedRig`` of ``calibration``'s camera: the direction of
    ``(tx, ty, tz)`` at the length of its ``baseline`` (kept at ``|t|``
    where the baseline is not a positive number)."""
    camera = calibration.camera
    R, T = camera.to_opencv_pose()
    length, baseline = float(np.linalg.norm(T)), camera.baseline
    if length > 0 and math.isfinite(length) and math.isfinite(baseline) and baseline > 0:
        T = T * (baseline / length)
    size = float(np.linalg.norm(T))
    centre = -R.T @ T                      # the right camera's centre: x right, y down, z forward
    angle = math.degrees(math.acos(min(1.0, abs(centre[0]) / size))) if size > 0 else 90.0
    side_by_side = size > 0 and angle <= SIDE_BY_SIDE_MAX_DEG
    return ExportedRig(R=R, T=T, baseline=size, side_by_side=side_by_side,
                       note=None if side_by_side else _layout_note(centre, angle))


def _layout_note(centre, angle):
    """The one line that says a rig is not side by side, and where its
    right camera is."""
    right, down, forward = (float(v) for v in centre)
    if not (right or down or forward):
        where = "the left one's (no baseline)"
    else:
        where = (f"{abs(forward):.3g} m {'in front of' if forward >= 0 else 'behind'} the left "
                 f"one's, {abs(right):.3g} m to its {'right' if right >= 0 else 'left'} and "
                 f"{abs(down):.3g} m {'below' if down >= 0 else 'above'} it")
    hint = ("; a model trained on cvgl labels puts it along the optical axis"
            if forward and abs(forward) >= max(abs(right), abs(down)) else "")
    return (f"not a side-by-side stereo pair: the right camera's centre is {where} (its "
            f"baseline {angle:.0f} deg from the left camera's x axis, a side-by-side pair's within "
            f"{SIDE_BY_SIDE_MAX_DEG:g}{hint}); the exports hold it as found, ROS's camera_info "
            "(side-by-side pairs only) each camera alone, with no stereo Tx")


def write_opencv_yaml(path, calibration):
    """Write ``calibration`` as an OpenCV stereo YAML (atomically; a missing
    folder is made); returns ``path``."""
    return write_all(calibration, opencv_yaml=path)[0]


def _cv_message(error):
    """The words of a ``cv2.error`` (its text is a source line's worth)."""
    text = one_line(error)
    found = re.search(r"error: \([^)]*\) (.*?)(?: in function .*)?$", text)
    return found.group(1) if found else text


def _opencv_yaml(tmp, calibration, path):
    """The OpenCV stereo YAML into the file ``tmp`` (``path``: its final
    name, for the one-line error of a failure: OpenCV raises its own error
    type, with a traceback's worth of text)."""
    import cv2

    K, rig = calibration.camera.K, exported_rig(calibration)
    try:
        fs = cv2.FileStorage(tmp, cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_FORMAT_YAML)
    except cv2.error as error:
        raise OSError(f"cannot write {path}: {_cv_message(error)}") from None
    if not fs.isOpened():
        raise OSError(f"cannot write {path}")
    try:
        fs.write("image_width", calibration.camera.width)
        fs.write("image_height", calibration.camera.height)
        for name, value in (("M1", K), ("D1", np.zeros((1, 5))), ("M2", K),
                            ("D2", np.zeros((1, 5))), ("R", rig.R), ("T", rig.T.reshape(3, 1))):
            fs.write(name, np.asarray(value, np.float64))
        fs.write("baseline_m", rig.baseline)
        fs.write("side_by_side", int(rig.side_by_side))
        fs.write("source", f"cpl_keras.calibrate, run {calibration.run}")
        # (read with the matrices; one string each: OpenCV writes none of 4,096 characters)
        for key, lines in (("notes", [rig.note] if rig.note else []),
                           ("impossible", calibration.impossible)):
            if lines:
                fs.startWriteStruct(key, cv2.FileNode_SEQ)
                for line in lines:
                    fs.write("", line)
                fs.endWriteStruct()
    except cv2.error as error:
        raise ExportError(f"cannot write {path}: OpenCV's YAML writer refused it "
                          f"({_cv_message(error)})") from None
    finally:
        fs.release()


def write_all(calibration, *, json_text=None, json_out=None, opencv_yaml=None, ros_yaml=None,
              colmap=None):
    """Every requested export of ``calibration`` (the JSON ``json_text`` to
    ``json_out``, OpenCV's YAML, ROS's two files in ``ros_yaml``, COLMAP's
    cameras.txt and rig_config.json in ``colmap``), all or none: each is
    written under a temporary name first, and all are renamed into place
    only once every one has been written; on a failure none is, and the
    folders made for them are removed again. Returns the paths written."""
    writers = []
    if json_out:
        writers.append((json_out, lambda tmp: _text(tmp, json_text + "\n")))
    if opencv_yaml:
        writers.append((opencv_yaml, lambda tmp: _opencv_yaml(tmp, calibration, opencv_yaml)))
    for side in ("left", "right") if ros_yaml else ():
        text = ros_camera_info(calibration, side)
        writers.append((os.path.join(ros_yaml, f"{side}.yaml"),
                        lambda tmp, text=text: _text(tmp, text)))
    if colmap:
        for name, text in (("cameras.txt", colmap_cameras(calibration)),
                           ("rig_config.json", colmap_rig_config(calibration))):
            writers.append((os.path.join(colmap, name), lambda tmp, text=text: _text(tmp, text)))
    if not writers:
        return []
    paths = [path for path, _ in writers]
    with new_folders(*paths), atomic_path(*paths) as tmps:
        for (_, write), tmp in zip(writers, tmps if len(writers) > 1 else [tmps]):
            write(tmp)
    return paths


def _text(path, text):
    with open(path, "w") as f:
        f.write(text)


def _matrix(name, rows, cols, values):
    data = ", ".join(repr(float(v)) for v in np.asarray(values, np.float64).reshape(-1))
    return f"{name}:\n  rows: {rows}\n  cols: {cols}\n  data: [{data}]\n"


def _rectification(rig):
    """ROS's rectified pair of a side-by-side rig (Bouguet's rectification,
    as ``cv2.stereoRectify``'s): each camera turned by half the relative
    rotation, then both about one axis until the baseline lies along x.
    Returns ``R1, R2`` (left and right camera into the rectified frame) and
    the right camera's x in it, ``(R2 T)[0]`` (-B for a right camera on the
    right)."""
    from scipy.spatial.transform import Rotation

    half = Rotation.from_rotvec(-0.5 * Rotation.from_matrix(rig.R).as_rotvec()).as_matrix()
    t = half @ rig.T
    axis = np.array([1.0 if t[0] >= 0 else -1.0, 0.0, 0.0])
    turn_axis = np.cross(t, axis)
    size = float(np.linalg.norm(turn_axis))
    turn = np.eye(3)
    if size > 0:
        angle = math.acos(min(1.0, abs(t[0]) / float(np.linalg.norm(t))))
        turn = Rotation.from_rotvec(turn_axis / size * angle).as_matrix()
    R1, R2 = turn @ half.T, turn @ half
    return R1, R2, float((R2 @ rig.T)[0])


def ros_camera_info(calibration, side):
    """The text of one ROS ``camera_info`` YAML (``side``: left or right):
    for a side-by-side pair, the rectified pair (``Tx = -fx * B`` in the
    right camera's P); for another rig, each camera alone, with the note."""
    K, rig = calibration.camera.K, exported_rig(calibration)
    rectification, P = np.eye(3), np.hstack([K, np.zeros((3, 1))])
    if rig.side_by_side:
        R1, R2, x = _rectification(rig)
        rectification = R1 if side == "left" else R2
        if side == "right":
            P[0, 3] = K[0, 0] * x
    return (("" if rig.side_by_side else f"# {rig.note}\n")
            + f"image_width: {calibration.camera.width}\n"
            f"image_height: {calibration.camera.height}\n"
            f"camera_name: {side}\n"
            + _matrix("camera_matrix", 3, 3, K)
            + "distortion_model: plumb_bob\n"
            + _matrix("distortion_coefficients", 1, 5, np.zeros(5))
            + _matrix("rectification_matrix", 3, 3, rectification)
            + _matrix("projection_matrix", 3, 4, P))


def write_ros_yaml(directory, calibration):
    """Write ``left.yaml`` and ``right.yaml`` into ``directory`` (created if
    missing; both or neither); returns their paths."""
    return write_all(calibration, ros_yaml=directory)


#: COLMAP puts the centre of the top-left pixel at (0.5, 0.5); this project
#: (and OpenCV) at (0, 0).
COLMAP_PIXEL_OFFSET = 0.5


def _colmap_params(camera):
    """PINHOLE's ``fx fy cx cy`` with COLMAP's pixel centres."""
    return [float(v) for v in (camera.fx, camera.fy, camera.u0 + COLMAP_PIXEL_OFFSET,
                               camera.v0 + COLMAP_PIXEL_OFFSET)]


def colmap_cameras(calibration):
    """The text of COLMAP's ``cameras.txt``: cameras 1 (left) and 2 (right),
    model PINHOLE (``fx fy cx cy``, no distortion), in the input images'
    pixels with COLMAP's pixel centres (``cx = u0 + 0.5``); a rig that is
    not side by side says so in a comment."""
    cam, note = calibration.camera, exported_rig(calibration).note
    params = " ".join(repr(v) for v in _colmap_params(cam))
    return ("# Camera list with one line of data per camera:\n"
            "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
            "# Number of cameras: 2\n"
            f"# cpl_keras.calibrate, run {calibration.run}: 1 = left, 2 = right; the pair's "
            "pose in rig_config.json\n"
            + (f"# {note}\n" if note else "")
            + f"1 PINHOLE {cam.width} {cam.height} {params}\n"
            f"2 PINHOLE {cam.width} {cam.height} {params}\n")


def _quaternion_wxyz(R):
    """The unit quaternion ``[w, x, y, z]`` (w >= 0) of the rotation ``R``."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(R).as_quat()
    sign = -1.0 if w < 0 else 1.0
    return [sign * float(v) for v in (w, x, y, z)]


def colmap_rig_config(calibration):
    """The text of COLMAP's ``rig_config.json`` (``colmap rig_configurator
    --rig_config_path``): one rig, the left camera (images ``left/...``) its
    reference sensor, the right one (``right/...``) at
    ``cam_from_rig_rotation`` (w, x, y, z) and ``cam_from_rig_translation``
    (``X_right = R X_left + T``: OpenCV's R and T), both PINHOLE."""
    rig, params = exported_rig(calibration), _colmap_params(calibration.camera)
    cameras = [{"image_prefix": "left/", "ref_sensor": True,
                "camera_model_name": "PINHOLE", "camera_params": params},
               {"image_prefix": "right/", "cam_from_rig_rotation": _quaternion_wxyz(rig.R),
                "cam_from_rig_translation": [float(v) for v in rig.T],
                "camera_model_name": "PINHOLE", "camera_params": params}]
    try:
        return json.dumps([{"cameras": cameras}], indent=2, allow_nan=False) + "\n"
    except ValueError:
        raise ExportError("cannot write COLMAP's rig_config.json: the camera holds a value "
                          "that is not a finite number") from None


def write_colmap_cameras(directory, calibration):
    """Write ``directory/cameras.txt`` and ``directory/rig_config.json``
    (created if missing; both or neither); returns their paths."""
    return write_all(calibration, colmap=directory)


def read_colmap_cameras(path):
    """COLMAP's ``cameras.txt`` as ``{camera_id: (model, width, height,
    params)}`` (what COLMAP's own ``read_cameras_text`` reads)."""
    cameras = {}
    with open(path) as f:
        for line in f:
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            fields = line.split()
            cameras[int(fields[0])] = (fields[1], int(fields[2]), int(fields[3]),
                                       tuple(float(v) for v in fields[4:]))
    return cameras
