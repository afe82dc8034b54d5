"""A calibration written for other tools: OpenCV's stereo YAML, ROS
``camera_info`` YAML and COLMAP's ``cameras.txt`` (``python -m
cpl_keras.calibrate ... --opencv-yaml FILE --ros-yaml DIR --colmap DIR``).

Each writer takes calibrate's record, a ``cpl_keras.calibration_records.Calibration``
(one pair) or ``RigCalibration`` (a rig: the medians over its pairs), and
describes its camera (a ``cpl_keras.stereo_camera.StereoCamera``) as
calibrate found it, in the input images' pixels: one pinhole camera model
``K = [[fx, 0, u0], [0, fy, v0], [0, 0, 1]]`` for both cameras (the model
predicts one; ``StereoCamera.K``), no distortion (the paper's model has
none), and the right camera's pose from ``pitch`` and ``(tx, ty, tz)``
(``StereoCamera.to_opencv_pose``; yaw and roll are not predicted: 0).

* OpenCV (``write_opencv_yaml``): ``cv2.FileStorage``'s own YAML, the keys of
  OpenCV's ``stereo_calib`` sample: ``M1, D1, M2, D2`` (intrinsics and
  distortion), ``R, T`` (``X_right = R X_left + T``, OpenCV axes, metres),
  and ``image_width``, ``image_height``.
* ROS (``write_ros_yaml``): ``left.yaml`` and ``right.yaml`` in the format of
  ROS's ``camera_calibration_parsers``, as for an unrectified pair:
  ``camera_matrix``, ``distortion_model: plumb_bob`` with zero
  coefficients, ``rectification_matrix`` identity and ``projection_matrix
  = [K | 0]`` for the left camera and ``K [R | T]`` for the right one.
* COLMAP (``write_colmap_cameras``): ``cameras.txt`` with the left and
  right cameras as PINHOLE models, ``cx, cy`` moved by half a pixel to
  COLMAP's pixel centres.
"""

from __future__ import annotations

import os

import numpy as np

from cpl_keras.files import atomic_path, new_folders, write_text


def write_opencv_yaml(path, calibration):
    """Write ``calibration`` as an OpenCV stereo YAML (atomically)."""
    with atomic_path(path) as tmp:
        _opencv_yaml(tmp, calibration, path)
    return path


def _opencv_yaml(tmp, calibration, path):
    """The OpenCV stereo YAML into the file ``tmp`` (``path``: its final
    name, for the one-line ``OSError`` of a failure: OpenCV raises its own
    error type, with a traceback's worth of text)."""
    import cv2

    K, (R, T) = calibration.camera.K, calibration.camera.to_opencv_pose()
    try:
        fs = cv2.FileStorage(tmp, cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_FORMAT_YAML)
    except cv2.error:
        raise OSError(f"cannot write {path}") from None
    if not fs.isOpened():
        raise OSError(f"cannot write {path}")
    try:
        fs.write("image_width", calibration.camera.width)
        fs.write("image_height", calibration.camera.height)
        for name, value in (("M1", K), ("D1", np.zeros((1, 5))), ("M2", K),
                            ("D2", np.zeros((1, 5))), ("R", R), ("T", T.reshape(3, 1))):
            fs.write(name, np.asarray(value, np.float64))
        fs.write("baseline_m", calibration.camera.baseline)
        fs.write("source", f"cpl_keras.calibrate, run {calibration.run}")
        if calibration.impossible:  # (read with the matrices: not a calibration to use)
            fs.write("impossible", "; ".join(calibration.impossible))
    finally:
        fs.release()


def write_all(calibration, *, json_text=None, json_out=None, opencv_yaml=None, ros_yaml=None,
              colmap=None):
    """Every requested export of ``calibration`` (the JSON ``json_text`` to
    ``json_out``, OpenCV's YAML, ROS's two files in ``ros_yaml``, COLMAP's
    cameras.txt in ``colmap``), all or none: each is written under a
    temporary name first, and all are renamed into place only once every one
    has been written; on a failure none is, and the folders made for them
    are removed again. Returns the paths written."""
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
        text = colmap_cameras(calibration)
        writers.append((os.path.join(colmap, "cameras.txt"), lambda tmp: _text(tmp, text)))
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


def ros_camera_info(calibration, side):
    """The text of one ROS ``camera_info`` YAML (``side``: left or right)."""
    K = calibration.camera.K
    if side == "left":
        P = np.hstack([K, np.zeros((3, 1))])
    else:
        R, T = calibration.camera.to_opencv_pose()
        P = K @ np.hstack([R, T.reshape(3, 1)])
    return (f"image_width: {calibration.camera.width}\n"
            f"image_height: {calibration.camera.height}\n"
            f"camera_name: {side}\n"
            + _matrix("camera_matrix", 3, 3, K)
            + "distortion_model: plumb_bob\n"
            + _matrix("distortion_coefficients", 1, 5, np.zeros(5))
            + _matrix("rectification_matrix", 3, 3, np.eye(3))
            + _matrix("projection_matrix", 3, 4, P))


def write_ros_yaml(directory, calibration):
    """Write ``left.yaml`` and ``right.yaml`` into ``directory`` (created if
    missing); returns their paths."""
    os.makedirs(directory, exist_ok=True)
    paths = []
    for side in ("left", "right"):
        path = os.path.join(directory, f"{side}.yaml")
        write_text(path, ros_camera_info(calibration, side))
        paths.append(path)
    return paths


#: COLMAP puts the centre of the top-left pixel at (0.5, 0.5); this project
#: (and OpenCV) at (0, 0).
COLMAP_PIXEL_OFFSET = 0.5


def colmap_cameras(calibration):
    """The text of COLMAP's ``cameras.txt``: cameras 1 (left) and 2 (right),
    model PINHOLE (``fx fy cx cy``, no distortion), in the input images'
    pixels with COLMAP's pixel centres (``cx = u0 + 0.5``)."""
    cam = calibration.camera
    params = " ".join(repr(float(v)) for v in (
        cam.fx, cam.fy, cam.u0 + COLMAP_PIXEL_OFFSET, cam.v0 + COLMAP_PIXEL_OFFSET))
    return ("# Camera list with one line of data per camera:\n"
            "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
            "# Number of cameras: 2\n"
            f"# cpl_keras.calibrate, run {calibration.run}: 1 = left, 2 = right\n"
            f"1 PINHOLE {cam.width} {cam.height} {params}\n"
            f"2 PINHOLE {cam.width} {cam.height} {params}\n")


def write_colmap_cameras(directory, calibration):
    """Write ``directory/cameras.txt`` (created if missing); returns its path."""
    os.makedirs(directory, exist_ok=True)
    path = os.path.join(directory, "cameras.txt")
    write_text(path, colmap_cameras(calibration))
    return path


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
