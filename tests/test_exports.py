"""calibrate's exports (cpl_keras/exports.py): every one written whatever
the rig's notes, a failure one line with nothing left behind, and the three
formats in agreement, each read back by its consumer's rules."""

import dataclasses
import json
import os
import re
import warnings

import cv2
import numpy as np
import pytest

from helpers import REPO
from cpl_keras import exports
from cpl_keras.calibrate import Calibrator, CalibrationWarning
from cpl_keras.commands import calibrate as calibrate_command
from cpl_keras.errors import Error
from cpl_keras.stereo_camera import StereoCamera

#: A rig's notes as long as the OAK-D folder's with the demonstration run
#: (35 of them, 4,424 characters): over OpenCV's 4,095 for one string.
LONG_NOTES = tuple(f"pair_{k:02d}_left.png: a disparity of 9748 px is at or beyond the image "
                   "width (640 px): no point seen in both images can have it" for k in range(35))
#: OpenCV's chessboard rig as calibrate gives it with --baseline 0.0836: the
#: baseline head's 0.0836 m beside a translation of length 0.0798 m.
BOARD = dict(fx=542.34, fy=542.34, u0=328.33, v0=246.96, width=640, height=480,
             baseline=0.0836, pitch=0.00029, tx=-0.0010, ty=-0.0798, tz=0.0007)


@pytest.fixture(scope="module")
def pair(tiny_run, tmp_path_factory):
    root = tmp_path_factory.mktemp("exports")
    rng = np.random.default_rng(0)
    left = (rng.random((40, 64, 3)) * 255).astype(np.uint8)
    cv2.imwrite(str(root / "left.png"), left)
    cv2.imwrite(str(root / "right.png"), np.roll(left, -3, axis=1))
    return {"left": str(root / "left.png"), "right": str(root / "right.png"),
            "run": tiny_run["run"]}


@pytest.fixture(scope="module")
def record(pair):
    """The tiny run's calibration of a random pair (a cvgl model: its right
    camera in front of the left one)."""
    calibrator = Calibrator.from_run(pair["run"])
    return calibrator.calibrate(pair["left"], pair["right"], warn=lambda line: None)


def _strings(node):
    return [node.at(i).string() for i in range(node.size())]


def _pair_folder(folder, pairs=2):
    os.makedirs(folder)
    rng = np.random.default_rng(1)
    for k in range(pairs):
        left = (rng.random((40, 64, 3)) * 255).astype(np.uint8)
        cv2.imwrite(os.path.join(folder, f"{k}_left.png"), left)
        cv2.imwrite(os.path.join(folder, f"{k}_right.png"), np.roll(left, -2, axis=1))
    return str(folder)


def _with_notes(monkeypatch, **changes):
    """``Calibrator.calibrate_folder`` giving its record with ``changes``."""
    original = Calibrator.calibrate_folder

    def calibrate_folder(self, *args, **kwargs):
        return dataclasses.replace(original(self, *args, **kwargs), **changes)

    monkeypatch.setattr(Calibrator, "calibrate_folder", calibrate_folder)


# ---------------------------------------------------------------------------
# Item 1: written whatever the rig's notes; OpenCV's refusal one line
# ---------------------------------------------------------------------------
def test_a_rig_with_many_impossible_notes_is_written_each_note_readable(record, tmp_path):
    assert len("; ".join(LONG_NOTES)) > 4096
    noted = dataclasses.replace(record, impossible=LONG_NOTES)
    path = exports.write_opencv_yaml(str(tmp_path / "stereo.yml"), noted)
    fs = cv2.FileStorage(path, cv2.FILE_STORAGE_READ)
    assert fs.getNode("impossible").isSeq()
    assert _strings(fs.getNode("impossible")) == list(LONG_NOTES)
    np.testing.assert_allclose(fs.getNode("M1").mat(), record.camera.K, rtol=1e-12)
    fs.release()


def test_what_opencv_refuses_is_one_line_and_leaves_nothing(record, tmp_path):
    """A string OpenCV's writer cannot take (a run's name past its 4,095
    characters) is the package's one-line ``Error``, not ``cv2.error``; no
    export is written and a file already there stays as it was."""
    odd = dataclasses.replace(record, run="r" * 5000)
    (tmp_path / "stereo.yml").write_text("old\n")
    with pytest.raises(Error) as caught:
        exports.write_all(odd, opencv_yaml=str(tmp_path / "stereo.yml"),
                          ros_yaml=str(tmp_path / "ros"), colmap=str(tmp_path / "colmap"))
    message = str(caught.value)
    assert isinstance(caught.value, exports.ExportError) and "\n" not in message
    assert message.startswith(f"cannot write {tmp_path / 'stereo.yml'}: ") and "too long" in message
    assert sorted(os.listdir(tmp_path)) == ["stereo.yml"]
    assert (tmp_path / "stereo.yml").read_text() == "old\n"


def test_calibrate_folder_writes_every_export_of_a_rig_with_many_notes(pair, tmp_path, capsys,
                                                                        monkeypatch):
    """The issue's command (``--folder`` with ``--opencv-yaml``) on a rig
    whose notes run past OpenCV's limit: exit 0, every export written, the
    notes a list in the YAML as in the JSON."""
    _with_notes(monkeypatch, impossible=LONG_NOTES)
    folder = _pair_folder(tmp_path / "rig")
    out = {"opencv": tmp_path / "stereo.yml", "ros": tmp_path / "ros",
           "colmap": tmp_path / "colmap"}
    assert calibrate_command.main(["--folder", folder, "--run", pair["run"], "--opencv-yaml",
                                   str(out["opencv"]), "--ros-yaml", str(out["ros"]),
                                   "--colmap", str(out["colmap"])]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["rig"]["impossible"] == list(LONG_NOTES)
    fs = cv2.FileStorage(str(out["opencv"]), cv2.FILE_STORAGE_READ)
    assert _strings(fs.getNode("impossible")) == list(LONG_NOTES)
    fs.release()
    assert sorted(os.listdir(out["ros"])) == ["left.yaml", "right.yaml"]
    assert sorted(os.listdir(out["colmap"])) == ["cameras.txt", "rig_config.json"]


def test_the_documented_snippet_filled_in_writes_the_rig_and_catches_what_the_api_raises(
        pair, tmp_path, capsys, monkeypatch):
    """docs/calibrate.md's Python example filled in (the run, a pair, a rig
    folder): with the rig's notes past OpenCV's limit it writes the YAML;
    with an export OpenCV refuses, its ``except`` says so in one line."""
    with open(os.path.join(REPO, "docs", "calibrate.md")) as f:
        [snippet] = re.findall(r"```python\n(.*?)```", f.read(), re.S)
    filled = snippet.replace('"runs/cpl-a-paper-s0"', repr(pair["run"]))
    assert filled != snippet and '"runs/stereo.yml"' in filled
    monkeypatch.chdir(tmp_path)
    os.mkdir("runs")   # (as in the repository's root after train.py)
    for side in ("left", "right"):
        os.link(pair[side], tmp_path / f"{side}.png")
    _pair_folder(tmp_path / "cpl_keras" / "real" / "oakd_stereo")
    code = compile(filled, "docs/calibrate.md", "exec")

    _with_notes(monkeypatch, impossible=LONG_NOTES)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", CalibrationWarning)
        exec(code, {})
    assert "cannot calibrate" not in capsys.readouterr().out
    fs = cv2.FileStorage("runs/stereo.yml", cv2.FILE_STORAGE_READ)
    assert _strings(fs.getNode("impossible")) == list(LONG_NOTES)
    fs.release()

    os.remove("runs/stereo.yml")
    _with_notes(monkeypatch, run="r" * 5000)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", CalibrationWarning)
        exec(code, {})
    printed = capsys.readouterr().out.strip().splitlines()
    assert printed[-1].startswith("cannot calibrate: cannot write runs/stereo.yml: "), printed
    assert os.listdir("runs") == []


# ---------------------------------------------------------------------------
# Item 2: the three exports agree, read by their consumers' rules
# ---------------------------------------------------------------------------
def _opencv_reads(path):
    """K and the signed baseline as OpenCV's stereo YAML gives them: the
    right camera's centre -R^T T, its length and its side (x: right)."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    K, K2 = fs.getNode("M1").mat(), fs.getNode("M2").mat()
    R, T = fs.getNode("R").mat(), fs.getNode("T").mat().reshape(3)
    baseline_m = fs.getNode("baseline_m").real()
    fs.release()
    np.testing.assert_array_equal(K, K2)
    centre = -R.T @ T
    assert baseline_m == pytest.approx(np.linalg.norm(T), rel=1e-12)
    return K, np.sign(centre[0]) * np.linalg.norm(T), R


def _ros_reads(folder):
    """K and the signed baseline as a ROS stereo consumer reads the pair's
    camera_info (stereo_image_proc): K from camera_matrix, the baseline
    from the right camera's P, Tx = P[0, 3] = -fx' B."""
    read = {}
    for side in ("left", "right"):
        fs = cv2.FileStorage(str(folder / f"{side}.yaml"), cv2.FILE_STORAGE_READ)
        read[side] = {name: np.array([fs.getNode(name).getNode("data").at(i).real()
                                      for i in range(fs.getNode(name).getNode("data").size())])
                      for name in ("camera_matrix", "rectification_matrix", "projection_matrix")}
        fs.release()
    K = read["left"]["camera_matrix"].reshape(3, 3)
    np.testing.assert_array_equal(K, read["right"]["camera_matrix"].reshape(3, 3))
    P_left = read["left"]["projection_matrix"].reshape(3, 4)
    P_right = read["right"]["projection_matrix"].reshape(3, 4)
    assert P_left[0, 3] == 0 and P_right[1, 3] == 0 and P_right[2, 3] == 0
    R1, R2 = (read[side]["rectification_matrix"].reshape(3, 3) for side in ("left", "right"))
    for R in (R1, R2):   # each rectification a rotation
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)
    return K, -P_right[0, 3] / P_right[0, 0], R1, R2


def _colmap_reads(folder):
    """K from cameras.txt's PINHOLE (fx, fy, cx, cy; pixel centres at +0.5)
    and the signed baseline from rig_config.json's right camera
    (cam_from_rig: X_cam = R X_rig + t, the quaternion w, x, y, z)."""
    cameras = exports.read_colmap_cameras(folder / "cameras.txt")
    assert [cameras[i][0] for i in (1, 2)] == ["PINHOLE", "PINHOLE"]
    fx, fy, cx, cy = cameras[1][3]
    assert cameras[2][3] == cameras[1][3]
    K = np.array([[fx, 0, cx - 0.5], [0, fy, cy - 0.5], [0, 0, 1]])
    [rig] = json.loads((folder / "rig_config.json").read_text())
    reference, right = rig["cameras"]
    assert reference["ref_sensor"] is True and "ref_sensor" not in right
    assert (reference["image_prefix"], right["image_prefix"]) == ("left/", "right/")
    w, x, y, z = right["cam_from_rig_rotation"]
    R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                  [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                  [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    t = np.array(right["cam_from_rig_translation"])
    return K, np.sign((-R.T @ t)[0]) * np.linalg.norm(t), R


@pytest.mark.parametrize("side, ty, pitch", [
    ("right of the left one", BOARD["ty"], BOARD["pitch"]),
    ("left of it (a swapped pair)", -BOARD["ty"], BOARD["pitch"]),
    ("right, turned down by 3 degrees", BOARD["ty"], 0.05)])
def test_the_three_exports_agree_on_k_and_the_baselines_length_and_sign(record, tmp_path, side,
                                                                       ty, pitch):
    """One calibration written for OpenCV, ROS and COLMAP and read back by
    each consumer's rules: one K, and a baseline of the rig's length
    (0.0836 m, not |t| = 0.0798 m nor ROS's K [R | T] reading of 0.056 m),
    positive with the right camera on the right, negative when swapped;
    ROS's rectification turns both cameras to one orientation with the
    baseline along x."""
    camera = StereoCamera(**dict(BOARD, ty=ty, pitch=pitch))
    calibration = dataclasses.replace(record, camera=camera)
    opencv, ros, colmap = tmp_path / "stereo.yml", tmp_path / "ros", tmp_path / "colmap"
    exports.write_all(calibration, opencv_yaml=str(opencv), ros_yaml=str(ros),
                      colmap=str(colmap))
    expected = BOARD["baseline"] * (1.0 if ty < 0 else -1.0)
    K_cv, b_cv, R_cv = _opencv_reads(opencv)
    K_ros, b_ros, R1, R2 = _ros_reads(ros)
    K_colmap, b_colmap, R_colmap = _colmap_reads(colmap)
    for K in (K_cv, K_ros, K_colmap):
        np.testing.assert_allclose(K, camera.K, rtol=1e-12, atol=1e-12)
    assert [b_cv, b_ros, b_colmap] == pytest.approx([expected] * 3, rel=1e-9)
    np.testing.assert_allclose(R_colmap, R_cv, atol=1e-12)
    fs = cv2.FileStorage(str(opencv), cv2.FILE_STORAGE_READ)
    T_cv = fs.getNode("T").mat().reshape(3)
    fs.release()
    np.testing.assert_allclose(R2 @ R_cv @ R1.T, np.eye(3), atol=1e-12)   # one orientation
    np.testing.assert_allclose(R2 @ T_cv, [-expected, 0.0, 0.0], atol=1e-12)  # along x
    assert exports.exported_rig(calibration).side_by_side
    fs = cv2.FileStorage(str(opencv), cv2.FILE_STORAGE_READ)
    assert fs.getNode("side_by_side").real() == 1 and fs.getNode("notes").empty()
    fs.release()


def test_a_rig_that_is_not_side_by_side_says_so_in_every_export_and_on_the_command_line(
        pair, record, tmp_path, capsys):
    """A model trained on cvgl labels (the baseline along the optical axis)
    puts the right camera in front of the left one: one warning line, the
    OpenCV YAML's side_by_side 0 with the note, ROS's pair without a stereo
    Tx (each camera alone), COLMAP's files with the note; the exported
    translation still has the known baseline's length."""
    t = np.array([record.camera.tx, record.camera.ty, record.camera.tz])
    assert abs(t[1]) < 0.5 * np.linalg.norm(t)   # (the tiny cvgl run's rig: not side by side)
    opencv, ros, colmap = tmp_path / "stereo.yml", tmp_path / "ros", tmp_path / "colmap"
    assert calibrate_command.main([pair["left"], pair["right"], "--run", pair["run"],
                                   "--baseline", "0.0836", "--opencv-yaml", str(opencv),
                                   "--ros-yaml", str(ros), "--colmap", str(colmap)]) == 0
    err = capsys.readouterr().err
    [line] = [line for line in err.splitlines() if "side-by-side" in line]
    assert line.startswith("python -m cpl_keras.calibrate: warning: not a side-by-side stereo "
                           "pair: the right camera's centre is ")
    assert "in front of the left one's" in line
    fs = cv2.FileStorage(str(opencv), cv2.FILE_STORAGE_READ)
    assert fs.getNode("side_by_side").real() == 0
    [note] = _strings(fs.getNode("notes"))
    assert note.startswith("not a side-by-side stereo pair: ") and note in line
    assert np.linalg.norm(fs.getNode("T").mat()) == pytest.approx(0.0836, rel=1e-12)
    assert fs.getNode("baseline_m").real() == pytest.approx(0.0836, rel=1e-12)
    fs.release()
    K = None
    for name in ("left", "right"):
        text = (ros / f"{name}.yaml").read_text()
        assert f"# {note}" in text
        fs = cv2.FileStorage(str(ros / f"{name}.yaml"), cv2.FILE_STORAGE_READ)
        data = fs.getNode("projection_matrix").getNode("data")
        P = np.array([data.at(i).real() for i in range(data.size())]).reshape(3, 4)
        data = fs.getNode("camera_matrix").getNode("data")
        K = np.array([data.at(i).real() for i in range(data.size())]).reshape(3, 3)
        fs.release()
        np.testing.assert_array_equal(P, np.hstack([K, np.zeros((3, 1))]))  # (no stereo Tx)
    assert f"# {note}" in (colmap / "cameras.txt").read_text()
    _, b_colmap, _ = _colmap_reads(colmap)
    assert abs(b_colmap) == pytest.approx(0.0836, rel=1e-12)
