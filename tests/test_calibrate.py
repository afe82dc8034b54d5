"""python -m cpl_keras.calibrate on image files."""

import dataclasses
import json
import os
import subprocess
import sys

import cv2
import numpy as np
import pytest

from helpers import REPO, writable_copy
from cpl_keras import calibration, calibration_records, exports, runs
from cpl_keras.calibrate import Calibration, CalibrationError, Calibrator, RigCalibration
from cpl_keras.commands import calibrate as calibrate_command
from cpl_keras.camera import PARAMETERS, fov_from_focal
from cpl_keras.image_pairs import find_pairs
from cpl_keras.models.inference import predict_images
from cpl_keras.stereo_camera import Point, StereoCamera

SIZE = 32


@pytest.fixture(scope="module")
def setup(tiny_run, tmp_path_factory):
    root = tmp_path_factory.mktemp("calib")
    run = tiny_run["run"]
    rng = np.random.default_rng(0)
    left = (rng.random((40, 64, 3)) * 255).astype(np.uint8)        # W = 64, H = 40
    right = np.roll(left, -3, axis=1)
    cv2.imwrite(str(root / "left.png"), left)
    cv2.imwrite(str(root / "right.png"), right)
    cv2.imwrite(str(root / "small.png"), left[:20, :30])
    (root / "notes.png").write_text("not an image")
    return {"root": root, "run": str(run)}


@pytest.fixture(scope="module")
def calibrator(setup):
    """The tiny run's ``Calibrator``, its model loaded once for the module."""
    return Calibrator.from_run(setup["run"])


def test_calibrate_scales_back_to_input_pixels(setup, calibrator, tmp_path, capsys):
    root = setup["root"]
    out = tmp_path / "calib.json"
    assert calibrate_command.main([str(root / "left.png"), str(root / "right.png"), "--run",
                           setup["run"], "--json-out", str(out)]) == 0
    text = capsys.readouterr().out
    printed = json.loads(text)
    assert printed == json.load(open(out))
    # the Python API's record is what the command printed, to the byte
    record = calibrator.calibrate(str(root / "left.png"), str(root / "right.png"))
    assert isinstance(record, Calibration) and record.as_dict() == printed
    assert record.to_json() + "\n" == text == out.read_text()
    assert list(record.as_dict()) == list(printed) and "notes" not in printed
    assert record.parameters == printed["parameters"] and record.network_fy == printed["network_fy"]
    with pytest.raises(dataclasses.FrozenInstanceError):
        record.aspect = "model"
    record.as_dict()["parameters"]["fx"] = -1.0          # a copy: the record keeps its fx
    assert record.parameters["fx"] == printed["parameters"]["fx"]
    assert set(printed["parameters"]) == set(PARAMETERS)
    assert (printed["image_width"], printed["image_height"]) == (64, 40)
    # the same forward pass by hand, on the resized pair
    run = runs.load_run(setup["run"])
    model = runs.load_model(run)
    left = cv2.cvtColor(cv2.imread(str(root / "left.png")), cv2.COLOR_BGR2RGB)
    right = cv2.cvtColor(cv2.imread(str(root / "right.png")), cv2.COLOR_BGR2RGB)
    resize = lambda im: cv2.resize(im, (SIZE, SIZE), interpolation=cv2.INTER_AREA)[None]
    raw = predict_images(model, resize(left), resize(right))
    p = printed["parameters"]
    assert p["fx"] == pytest.approx(raw["fx"][0] * 64 / SIZE, rel=1e-4)
    # square pixels (the default): fy = fx on the input images; the network's
    # fy, scaled back by H / S, is kept beside it
    assert printed["aspect"] == "square" and p["fy"] == p["fx"]
    assert printed["network_fy"] == pytest.approx(raw["fy"][0] * 40 / SIZE, rel=1e-4)
    assert printed["spread"]["fy"] == printed["spread"]["fx"]
    assert p["u0"] == pytest.approx((raw["u0"][0] + 0.5) * 64 / SIZE - 0.5, rel=1e-4, abs=1e-4)
    assert p["v0"] == pytest.approx((raw["v0"][0] + 0.5) * 40 / SIZE - 0.5, rel=1e-4, abs=1e-4)
    assert p["baseline"] == pytest.approx(raw["baseline"][0], rel=1e-4, abs=1e-6)
    assert printed["fov_horizontal_deg"] == pytest.approx(
        np.degrees(fov_from_focal(p["fx"], 64)), rel=1e-6)
    assert printed["fov_vertical_deg"] == pytest.approx(
        np.degrees(fov_from_focal(p["fy"], 40)), rel=1e-6)
    # the network's fy with --aspect model
    assert calibrate_command.main([str(root / "left.png"), str(root / "right.png"), "--run",
                           setup["run"], "--aspect", "model"]) == 0
    model_fy = json.loads(capsys.readouterr().out)
    assert model_fy["aspect"] == "model"
    assert model_fy["parameters"]["fy"] == pytest.approx(raw["fy"][0] * 40 / SIZE, rel=1e-4)
    assert model_fy["parameters"]["fx"] == p["fx"]
    assert model_fy["fov_vertical_deg"] == pytest.approx(
        np.degrees(fov_from_focal(model_fy["parameters"]["fy"], 40)), rel=1e-6)


def test_the_record_holds_a_camera_and_writes_the_constant_prose_once(setup, calibrator):
    """A ``Calibration`` holds typed values (its ``StereoCamera``, the
    disparity, the ``Point``); what is the same for every pair (what each
    field means, units, how the spread is measured, the notes) is written by
    ``as_dict``, not carried by each record."""
    root = setup["root"]
    record = calibrator.calibrate(str(root / "left.png"), str(root / "right.png"))
    cam = record.camera
    assert isinstance(cam, StereoCamera) and isinstance(record.point, Point)
    assert (cam.width, cam.height, record.image_width, record.image_height) == (64, 40, 64, 40)
    assert (cam.yaw, cam.roll) == (0.0, 0.0)                       # not predicted
    printed = record.as_dict()
    assert printed["parameters"] == {name: cam.to_labels(disparity=record.disparity)[name]
                                     for name in PARAMETERS}
    assert printed["point"] == record.point.as_dict()
    assert printed["fov_horizontal_deg"] == cam.fov_deg[0] == record.fov_horizontal_deg
    names = {field.name for field in dataclasses.fields(Calibration)}
    assert not names & {"fields", "units", "spread_method", "aspect_note", "scale_priors",
                        "notes", "from_the_pair", "parameters", "from_prior"}
    assert printed["fields"] == calibration_records.FIELDS
    assert printed["aspect_note"] == calibration_records.ASPECT_NOTES["square"]
    assert printed["spread_method"] == calibration_records.SPREAD_METHOD.format(
        record.windows, record.windows - 1)
    assert printed["from_the_pair"]["baseline_over_depth"] == record.disparity / cam.fx
    # the exporters' K and pose are the camera's
    assert f"data: [{', '.join(repr(float(v)) for v in cam.K.reshape(-1))}]" in \
        exports.ros_camera_info(record, "left")


def _fails(args, capsys, match, out=None):
    assert calibrate_command.main(args) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("python -m cpl_keras.calibrate: error:") and "\n" not in err and match in err, err
    if out is not None:
        assert not os.path.exists(out) and not os.path.exists(str(out) + ".partial")


def test_bad_inputs(setup, tmp_path, capsys):
    root, run = setup["root"], setup["run"]
    out = tmp_path / "c.json"
    left, right = str(root / "left.png"), str(root / "right.png")
    _fails([str(root / "notes.png"), right, "--run", run, "--json-out", str(out)], capsys,
           "as an image", out)
    _fails([left, str(root / "missing.png"), "--run", run, "--json-out", str(out)], capsys,
           "not found", out)
    _fails([left, str(root / "small.png"), "--run", run, "--json-out", str(out)], capsys,
           "differ in size", out)
    no_weights = tmp_path / "no_weights"
    writable_copy(run, no_weights)
    os.remove(no_weights / "model.keras")
    _fails([left, right, "--run", str(no_weights), "--json-out", str(out)], capsys,
           "weights", out)
    _fails([left, right, "--run", str(tmp_path / "nothing")], capsys, "not found")


def test_cli_exit_status_without_traceback(setup):
    root = setup["root"]
    result = subprocess.run(
        [sys.executable, "-m", "cpl_keras.calibrate", str(root / "notes.png"),
         str(root / "right.png"), "--run", setup["run"]],
        capture_output=True, text=True, timeout=120,
        cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    assert result.returncode == 2
    assert result.stderr.strip().count("\n") == 0 and "Traceback" not in result.stderr


def _one_line_2(capsys, status, needle):
    err = capsys.readouterr().err.strip()
    assert status == 2 and "\n" not in err and needle in err, err


def test_refuses_images_smaller_than_the_model_input(setup, tmp_path, capsys):
    small = cv2.imread(str(setup["root"] / "small.png"))
    cv2.imwrite(str(tmp_path / "r.png"), np.roll(small, -2, axis=1))
    out = tmp_path / "c.json"
    status = calibrate_command.main([str(setup["root"] / "small.png"), str(tmp_path / "r.png"),
                             "--run", setup["run"], "--json-out", str(out)])
    _one_line_2(capsys, status, "smaller than the model's input 32x32")
    assert not out.exists()


def test_refuses_identical_left_and_right(setup, capsys):
    left = str(setup["root"] / "left.png")
    _one_line_2(capsys, calibrate_command.main([left, left, "--run", setup["run"]]), "identical")


def test_warns_about_grey_images_and_says_what_the_run_was_trained_on(setup, tmp_path, capsys):
    grey = cv2.cvtColor(cv2.imread(str(setup["root"] / "left.png")), cv2.COLOR_BGR2GRAY)
    cv2.imwrite(str(tmp_path / "l.png"), grey)
    cv2.imwrite(str(tmp_path / "r.png"), np.roll(grey, -3, axis=1))
    assert calibrate_command.main([str(tmp_path / "l.png"), str(tmp_path / "r.png"),
                           "--run", setup["run"]]) == 0
    captured = capsys.readouterr()
    grey_lines = [line for line in captured.err.splitlines() if "is grey" in line]
    assert len(grey_lines) == 2, captured.err
    training = json.loads(captured.out)["training"]
    assert training["protocol"] == "cvgl" and training["split"] == "paper"
    with open(os.path.join(setup["run"], "train_stats.json")) as f:
        stats = json.load(f)
    assert training["label_ranges"]["fx"] == [stats["min"]["fx"], stats["max"]["fx"]]


def test_warns_about_a_pair_turned_by_exif_or_given_swapped(calibrator, tmp_path):
    """The shipped OAK-D desk pair as given: no doubt; its left file saved
    with EXIF orientation 3 (the reader turns it upside down, as a viewer
    shows it): the turn named with both files' orientations; the two files
    given the other way round: "looks swapped". (Both were calibrated
    without a word.)"""
    from PIL import Image

    from cpl_keras.real import oakd

    left, right = (os.path.join(oakd.DATA_DIR, f"desk_{side}.png") for side in ("left", "right"))
    exif = Image.Exif()
    exif[0x0112] = 3
    turned = tmp_path / "desk_left.png"
    Image.open(left).save(turned, exif=exif.tobytes())
    said = {}
    for case, pair in (("given", (left, right)), ("turned", (str(turned), right)),
                       ("swapped", (right, left))):
        said[case] = []
        calibrator.calibrate(*pair, warn=said[case].append)
        said[case] = [line for line in said[case]
                      if "is turned by" in line or "looks swapped" in line]
    assert said["given"] == []
    assert len(said["turned"]) == 1 and said["turned"][0].startswith(
        "warning: the left image is turned by about 180 degrees against the right one (their "
        "EXIF orientations applied: the left file's 3, turned 180 degrees, the right file's 1, "
        "upright)"), said
    assert len(said["swapped"]) == 1 and said["swapped"][0].startswith(
        "warning: the pair looks swapped: in "), said
    assert said["swapped"][0].endswith("give the left camera's image first")


def test_warns_about_predictions_outside_the_training_labels(setup, tmp_path, capsys):
    run = tmp_path / "run"
    writable_copy(setup["run"], run)
    with open(run / "train_stats.json") as f:
        stats = json.load(f)
    stats["min"]["fx"], stats["max"]["fx"] = 1e6, 1e6 + 1   # no prediction can be in there
    with open(run / "train_stats.json", "w") as f:
        json.dump(stats, f)
    root = setup["root"]
    assert calibrate_command.main([str(root / "left.png"), str(root / "right.png"),
                           "--run", str(run)]) == 0
    lines = [line for line in capsys.readouterr().err.splitlines() if "outside" in line]
    assert len(lines) == 1 and "fx" in lines[0] and "1e+06" in lines[0], lines


def test_pose_conversion_to_opencv_inverts_the_rig_pose():
    from cpl_keras.frames import rotation_matrix
    from cpl_keras.frames import opencv_pose_to_rig, rig_to_opencv_pose

    R_lr, t = rotation_matrix(0.2, 0.05, -0.03), np.array([0.3, -0.12, 0.04])
    R, T = rig_to_opencv_pose(R_lr, t)
    back_R, back_t = opencv_pose_to_rig(R, T)
    np.testing.assert_allclose(back_R, R_lr, atol=1e-12)
    np.testing.assert_allclose(back_t, t, atol=1e-12)
    # a right camera 0.3 m to the right (project y left: ty < 0), no rotation:
    # OpenCV's T = -R C = (-0.3, 0, 0) (x right)
    R, T = rig_to_opencv_pose(np.eye(3), [0.0, -0.3, 0.0])
    np.testing.assert_allclose(R, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(T, [-0.3, 0.0, 0.0], atol=1e-12)


def test_exports_opencv_and_ros_yaml_that_opencv_reads_back(setup, calibrator, tmp_path,
                                                            capsys):
    """--opencv-yaml and --ros-yaml: cv2.FileStorage reads both back; K holds
    the printed intrinsics, R is the pitch's rotation in OpenCV's axes, T the
    translation at the baseline's length; the tiny cvgl run's rig is not
    side by side, so ROS's files hold each camera alone, [K | 0] (the
    agreement of a side-by-side pair's exports: tests/test_exports.py)."""
    root = setup["root"]
    opencv, ros = tmp_path / "stereo.yml", tmp_path / "ros"
    assert calibrate_command.main([str(root / "left.png"), str(root / "right.png"), "--run",
                           setup["run"], "--opencv-yaml", str(opencv), "--ros-yaml",
                           str(ros)]) == 0
    p = json.loads(capsys.readouterr().out)["parameters"]
    # the exporters take the API's record and write the command's files, to the byte
    record = calibrator.calibrate(str(root / "left.png"), str(root / "right.png"))
    assert open(exports.write_opencv_yaml(str(tmp_path / "api.yml"), record), "rb").read() \
        == opencv.read_bytes()
    for side, path in zip(("left", "right"), exports.write_ros_yaml(str(tmp_path / "api"),
                                                                    record)):
        assert open(path).read() == (ros / f"{side}.yaml").read_text()
    K = np.array([[p["fx"], 0, p["u0"]], [0, p["fy"], p["v0"]], [0, 0, 1]])
    fs = cv2.FileStorage(str(opencv), cv2.FILE_STORAGE_READ)
    assert fs.isOpened() and fs.getNode("image_width").real() == 64
    np.testing.assert_allclose(fs.getNode("M1").mat(), K, rtol=1e-12)
    np.testing.assert_allclose(fs.getNode("M2").mat(), K, rtol=1e-12)
    assert not fs.getNode("D1").mat().any()
    R, T = fs.getNode("R").mat(), fs.getNode("T").mat().reshape(3)
    fs.release()
    c, s = np.cos(p["pitch"]), np.sin(p["pitch"])
    # By hand: a pitch p tilts the right camera's optical axis down, to
    # (0, sin p, cos p) in the left camera's OpenCV axes (y down). R maps left
    # to right coordinates, so R^T (0, 0, 1), R's third row, is that axis: a
    # rotation about x, R = [[1, 0, 0], [0, c, -s], [0, s, c]].
    np.testing.assert_allclose(R, [[1, 0, 0], [0, c, -s], [0, s, c]], atol=1e-12)
    # T = -R * (right camera centre in OpenCV axes: x = -ty, y = -tz, z = tx),
    # at the length of the baseline
    centre = np.array([-p["ty"], -p["tz"], p["tx"]])
    np.testing.assert_allclose(T, -R @ centre * p["baseline"] / np.linalg.norm(centre),
                               atol=1e-12)
    for side in ("left", "right"):
        fs = cv2.FileStorage(str(ros / f"{side}.yaml"), cv2.FILE_STORAGE_READ)
        node = fs.getNode("projection_matrix").getNode("data")
        P = np.array([node.at(i).real() for i in range(node.size())]).reshape(3, 4)
        node = fs.getNode("camera_matrix").getNode("data")
        np.testing.assert_allclose(
            np.array([node.at(i).real() for i in range(node.size())]).reshape(3, 3), K)
        assert fs.getNode("distortion_model").string() == "plumb_bob"
        assert fs.getNode("camera_name").string() == side
        np.testing.assert_allclose(P, np.hstack([K, np.zeros((3, 1))]), rtol=1e-9, atol=1e-9)
        fs.release()


def test_from_window_maps_a_crop_prediction_back_by_hand():
    values = {"fx": 10.0, "fy": 12.0, "u0": 15.5, "v0": 7.0, "baseline": 0.3, "disparity": 4.0,
              "tx": 0.01, "ty": -0.3, "tz": 0.02, "pitch": 0.05, "X": 5.0, "Y": 1.0, "Z": -0.5}
    out = calibration.from_window(values, (20, 6, 50, 40), (32, 32), (64, 40))
    assert out["fx"] == pytest.approx(10 * 50 / 32) and out["fy"] == pytest.approx(12 * 40 / 32)
    assert out["u0"] == pytest.approx((15.5 + 0.5) * 50 / 32 - 0.5 + 20)
    assert out["v0"] == pytest.approx((7.0 + 0.5) * 40 / 32 - 0.5 + 6)
    assert out["disparity"] == pytest.approx(4 * 50 / 32) and out["baseline"] == 0.3
    # metres and radians stay; the dict keeps its names and order
    assert list(out) == list(values)
    assert all(out[name] == values[name] for name in ("tx", "ty", "tz", "pitch", "X", "Y", "Z"))
    windows = calibration.crop_windows(64, 40)
    assert windows[0] == (0, 0, 64, 40) and len(windows) == 1 + calibration.TTA_CROPS
    assert all(x + w <= 64 and y + h <= 40 and 0.75 * 64 < w < 64 for x, y, w, h in windows[1:])


def test_spread_scale_priors_fields_and_the_demonstration_notice(setup, tmp_path, capsys):
    """The JSON gives a spread per parameter (crops of the pair), the
    quantities that rest on the pair beside the scale priors, a meaning for every
    field; a demonstration run is announced as such on stderr."""
    root = setup["root"]
    args = [str(root / "left.png"), str(root / "right.png"), "--run"]
    assert calibrate_command.main(args + [setup["run"]]) == 0
    captured = capsys.readouterr()
    result = json.loads(captured.out)
    assert set(result["spread"]) == set(PARAMETERS) | {"X", "Y", "Z"}
    assert all(np.isfinite(v) and v >= 0 for v in result["spread"].values())
    assert result["spread"]["fx"] > 0           # the crops do move the estimate
    p = result["parameters"]
    assert result["from_the_pair"]["baseline_over_depth"] == \
        pytest.approx(p["disparity"] / p["fx"])
    assert result["from_the_pair"]["disparity_px"] == p["disparity"]
    assert "in pixels" in result["from_the_pair"]["note"]
    assert result["spread_method"].startswith("each value's sample standard deviation")
    assert f"over {1 + calibration.TTA_CROPS} predictions" in result["spread_method"]
    assert set(result["scale_priors"]) == {"baseline", "tx", "ty", "tz", "X", "Y", "Z"}
    assert set(result["fields"]) == set(PARAMETERS) | {"X", "Y", "Z"}
    assert result["demonstration_model"] is False and "demonstration" not in captured.err
    demo = tmp_path / "demo-run"
    writable_copy(setup["run"], demo)
    config = json.loads((demo / "config.json").read_text())
    config["data"] = "/cache/demo-cvgl-800-112px-s0-v3.0.h5"
    (demo / "config.json").write_text(json.dumps(config))
    assert calibrate_command.main(args + [str(demo)]) == 0
    captured = capsys.readouterr()
    assert json.loads(captured.out)["demonstration_model"] is True
    assert "demonstration model" in captured.err


def test_find_pairs_of_the_shipped_rigs_and_of_left_right_folders(tmp_path):
    from cpl_keras.real import chessboard, oakd

    board = find_pairs(chessboard.DATA_DIR)
    assert len(board) == 13 and all(
        os.path.basename(r) == os.path.basename(l).replace("left", "right") for l, r in board)
    assert len(find_pairs(oakd.DATA_DIR)) == 12
    for side in ("left", "right"):
        (tmp_path / side).mkdir()
        for name in ("a.png", "b.png"):
            (tmp_path / side / name).write_bytes(b"")
    assert [os.path.basename(l) for l, _ in find_pairs(str(tmp_path))] == \
        ["a.png", "b.png"]
    (tmp_path / "left" / "c.png").write_bytes(b"")
    with pytest.raises(CalibrationError, match="c.png has no right image"):
        find_pairs(str(tmp_path))
    with pytest.raises(CalibrationError, match="no stereo pairs"):
        find_pairs(str(tmp_path / "left"))


def test_a_folder_of_pairs_is_one_rig_of_medians_with_their_spread(setup, calibrator, tmp_path,
                                                                   capsys):
    """--folder: each pair calibrated as on its own, the rig's parameters the
    medians over the pairs (worked out here from the printed pairs), their
    spread the standard deviation; the YAML holds the rig's intrinsics; a
    warning given for every pair is said once."""
    rng = np.random.default_rng(1)
    folder = tmp_path / "rig"
    folder.mkdir()
    for k in range(3):
        left = (rng.random((40, 64, 3)) * 255).astype(np.uint8)
        cv2.imwrite(str(folder / f"{k}_left.png"), left)
        cv2.imwrite(str(folder / f"{k}_right.png"), np.roll(left, -2 - k, axis=1))
    opencv = tmp_path / "rig.yml"
    assert calibrate_command.main(["--folder", str(folder), "--run", setup["run"],
                           "--opencv-yaml", str(opencv)]) == 0
    captured = capsys.readouterr()
    printed = json.loads(captured.out)
    pairs, rig = printed["pairs"], printed["rig"]
    assert [os.path.basename(p["left"]) for p in pairs] == [f"{k}_left.png" for k in range(3)]
    one = calibrator.calibrate(str(folder / "1_left.png"), str(folder / "1_right.png"))
    assert pairs[1]["parameters"] == one.parameters
    assert rig["num_pairs"] == 3 and "disparity" not in rig["parameters"]
    # the Python API: the same JSON, a record of records, the medians of its pairs
    record = calibrator.calibrate_folder(str(folder))
    assert isinstance(record, RigCalibration) and record.as_dict() == printed
    assert record.to_json() + "\n" == captured.out
    assert [pair.parameters for pair in record.pairs] == [p["parameters"] for p in pairs]
    for name in calibration.RIG_PARAMETERS:
        assert record.parameters[name] == float(np.median([p.parameters[name]
                                                           for p in record.pairs]))
    assert (tmp_path / "rig.yml").read_bytes() == \
        open(exports.write_opencv_yaml(str(tmp_path / "api.yml"), record), "rb").read()
    for name in calibration.RIG_PARAMETERS:
        values = sorted(p["parameters"][name] for p in pairs)
        assert rig["parameters"][name] == values[1]
        mean = sum(values) / 3
        assert rig["spread_over_pairs"][name] == pytest.approx(
            (sum((v - mean) ** 2 for v in values) / 2) ** 0.5)
    assert rig["fov_horizontal_deg"] == pytest.approx(
        float(np.degrees(fov_from_focal(rig["parameters"]["fx"], 64))))
    fs = cv2.FileStorage(str(opencv), cv2.FILE_STORAGE_READ)
    M1 = fs.getNode("M1").mat()
    fs.release()
    assert M1[0, 0] == pytest.approx(rig["parameters"]["fx"])
    lines = captured.err.splitlines()
    assert len(lines) == len(set(lines))
    # what no pair can show reaches the rig's record, its JSON and its YAML,
    # and the Python API warns of it without a ``warn`` of its own
    from_pairs = [f"{os.path.basename(p.left)}: {line}" for p in record.pairs
                  for line in p.impossible]
    assert from_pairs and list(record.impossible[-len(from_pairs):]) == from_pairs
    assert rig["impossible"] == list(record.impossible)
    fs = cv2.FileStorage(str(opencv), cv2.FILE_STORAGE_READ)
    node = fs.getNode("impossible")
    assert [node.at(i).string() for i in range(node.size())] == list(record.impossible)
    fs.release()
    with pytest.warns(calibration.CalibrationWarning, match="impossible for any pair"):
        calibrator.calibrate(str(folder / "1_left.png"), str(folder / "1_right.png"))


def test_folder_and_pair_arguments_are_one_or_the_other(setup, tmp_path, capsys):
    root = setup["root"]
    for argv in (["--folder", str(root), str(root / "left.png"), str(root / "right.png")],
                 [str(root / "left.png")], []):
        with pytest.raises(SystemExit) as exit_:
            calibrate_command.main(argv + ["--run", setup["run"]])
        assert exit_.value.code == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 or err[-1].startswith(calibrate_command.PROG)
    out = tmp_path / "never.json"
    assert calibrate_command.main(["--folder", str(tmp_path), "--run", setup["run"],
                           "--json-out", str(out)]) == 2
    assert "no stereo pairs" in capsys.readouterr().err and not out.exists()


@pytest.mark.parametrize("focal, message", [
    ("1e30", "at most 1,000,000 px"), ("1000001", "at most 1,000,000 px"),
    ("inf", "positive number"), ("nan", "positive number"), ("0", "positive number")])
def test_a_known_focal_length_must_be_finite_and_plausible(tmp_path, capsys, focal, message):
    """--focal is a positive number of pixels up to priors.MAX_FOCAL_PX (a
    field of view of 0.34 deg across 6,000 px): one line, exit 2, before
    any run or image is read; the Python API's Priors likewise."""
    from cpl_keras import priors as known

    with pytest.raises(SystemExit) as exit_:
        calibrate_command.main(["a.png", "b.png", "--run", str(tmp_path), "--focal", focal])
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith(f"{calibrate_command.PROG}: error: argument --focal: ") and \
        message in err[-1], err
    assert calibrate_command.focal_argument("1e6") == (1e6, "--focal")
    with pytest.raises(known.PriorError, match="at most 1,000,000 px"):
        known.Priors(focal_px=2e6)


@pytest.mark.parametrize("rig, pair", [("chessboard", "01"), ("oakd", "desk")])
def test_a_shipped_real_pair_calibrates_with_spreads_warnings_and_both_exports(
        setup, rig, pair, tmp_path, capsys):
    """A real pair as a user gives it (the shipped chessboard 640 x 480 and
    OAK-D pairs, grey): the grey warning, spreads for every value, fy = fx
    (square pixels) with the network's fy beside it, and the two YAML files
    OpenCV reads back with the printed intrinsics."""
    from cpl_keras.real import chessboard, oakd

    folder = {"chessboard": chessboard.DATA_DIR, "oakd": oakd.DATA_DIR}[rig]
    left, right = next((l, r) for l, r in find_pairs(folder)
                       if pair in os.path.basename(l))
    opencv, ros = tmp_path / "stereo.yml", tmp_path / "ros"
    assert calibrate_command.main([left, right, "--run", setup["run"], "--opencv-yaml", str(opencv),
                           "--ros-yaml", str(ros)]) == 0
    captured = capsys.readouterr()
    result = json.loads(captured.out)
    assert (result["image_width"], result["image_height"]) == (640, 480)
    assert "is grey" in captured.err
    p = result["parameters"]
    assert p["fy"] == p["fx"] and np.isfinite(result["network_fy"])
    assert all(np.isfinite(v) and v >= 0 for v in result["spread"].values())
    fs = cv2.FileStorage(str(opencv), cv2.FILE_STORAGE_READ)
    np.testing.assert_allclose(fs.getNode("M1").mat(),
                               [[p["fx"], 0, p["u0"]], [0, p["fy"], p["v0"]], [0, 0, 1]])
    assert fs.getNode("image_height").real() == 480
    fs.release()
    for side in ("left", "right"):
        fs = cv2.FileStorage(str(ros / f"{side}.yaml"), cv2.FILE_STORAGE_READ)
        assert fs.isOpened() and fs.getNode("image_width").real() == 640
        fs.release()


# ---------------------------------------------------------------------------
# What calibrate knows of real cameras, known priors, COLMAP
# ---------------------------------------------------------------------------
def _pair_args(setup):
    root = setup["root"]
    return [str(root / "left.png"), str(root / "right.png"), "--run", setup["run"]]


def test_the_real_camera_record_is_said_in_one_line_and_in_the_json(setup, tmp_path, capsys):
    """A run never scored on a real camera says so (a warning line and
    ``real_camera_record``); with a record in its run directory
    (``real_record.write_record``) the line gives each held-out rig's
    relative fx error beside the Average row's."""
    from cpl_keras import real_record
    from cpl_keras.evaluation import Table2

    assert calibrate_command.main(_pair_args(setup)) == 0
    captured = capsys.readouterr()
    record = json.loads(captured.out)["real_camera_record"]
    assert record["validated"] is False and record["rigs"] == {}
    lines = [line for line in captured.err.splitlines() if "real-camera record" in line]
    assert len(lines) == 1 and "never validated on a real camera" in lines[0]
    assert lines[0].startswith(f"{calibrate_command.PROG}: warning: ")

    run = tmp_path / "run"
    writable_copy(setup["run"], run)
    row = "MTL-Baseline"
    rows = {row: {"num_pairs": 5, "field": {"relative_fx_median": 0.58,
                                            "hfov_error_deg_median": 12.5}},
            "Average": {"num_pairs": 5, "field": {"relative_fx_median": 0.30,
                                                  "hfov_error_deg_median": 8.0}}}
    common = dict(data="middlebury.h5", data_description="5 pairs", data_source="middlebury",
                  num_pairs=5, image_width=32, runs=[str(run)], paper={},
                  paper_convention="nmae")
    table = Table2(**common, rows=rows, rigs={"middlebury": Table2(**common, rows=rows,
                                                                  rectified=True)},
                   fov_points={})
    real_record.write_record(str(run), table, command="test")
    args = _pair_args(setup)
    args[args.index("--run") + 1] = str(run)
    assert calibrate_command.main(args) == 0
    captured = capsys.readouterr()
    record = json.loads(captured.out)["real_camera_record"]
    assert record["validated"] is True
    assert record["rigs"]["middlebury"] == {"pairs": 5, "relative_fx_error": 0.58,
                                            "average_relative_fx_error": 0.30,
                                            "hfov_error_deg": 12.5}
    line = next(line for line in captured.err.splitlines() if "real-camera record" in line)
    assert "middlebury 0.58 (Average 0.30)" in line and "warning" in line
    assert "no better than the Average row on 1 of 1" in line


def test_a_known_baseline_scales_the_metric_values_and_says_so(setup, capsys):
    assert calibrate_command.main(_pair_args(setup)) == 0
    plain = json.loads(capsys.readouterr().out)
    assert calibrate_command.main(_pair_args(setup) + ["--baseline", "0.12"]) == 0
    known = json.loads(capsys.readouterr().out)
    factor = 0.12 / plain["parameters"]["baseline"]
    assert known["parameters"]["baseline"] == pytest.approx(0.12, rel=1e-9)
    for name in ("tx", "ty", "tz"):
        assert known["parameters"][name] == pytest.approx(
            plain["parameters"][name] * factor, rel=1e-6, abs=1e-12)
    for name in ("X", "Y", "Z"):
        assert known["point"][name] == pytest.approx(plain["point"][name] * factor, rel=1e-6,
                                                     abs=1e-12)
    for name in ("fx", "fy", "u0", "v0", "disparity", "pitch"):
        assert known["parameters"][name] == pytest.approx(plain["parameters"][name], rel=1e-9)
    assert known["priors"]["baseline_m"]["value"] == 0.12
    assert known["priors"]["baseline_m"]["scale_factor"] == pytest.approx(factor)
    assert set(known["from_prior"]) == {"baseline", "tx", "ty", "tz", "X", "Y", "Z"}
    assert plain["priors"] == {} and plain["from_prior"] == []


def test_a_known_focal_sets_fx_fy_and_moves_the_depth_by_eq_4a(setup, capsys):
    """The same projection pixel (u, v) and disparity with the known fx: the
    depth is xCam = fx b / d (Eq. 4a) with it; u0, v0, b, d, pitch and t
    stay as the network gave them."""
    from cpl_keras import camera

    assert calibrate_command.main(_pair_args(setup)) == 0
    plain = json.loads(capsys.readouterr().out)
    assert calibrate_command.main(_pair_args(setup) + ["--focal", "50"]) == 0
    known = json.loads(capsys.readouterr().out)
    p, q = plain["parameters"], known["parameters"]
    assert (q["fx"], q["fy"]) == (50.0, 50.0)
    for name in ("u0", "v0", "baseline", "disparity", "pitch", "tx", "ty", "tz"):
        assert q[name] == pytest.approx(p[name], rel=1e-9)

    def pixel_and_depth(result):
        r = dict(result["parameters"], **result["point"])
        u, v, _ = camera.world_to_image(r["X"], r["Y"], r["Z"], r["fx"], r["fy"], r["u0"],
                                        r["v0"], r["baseline"], r["pitch"], r["tx"], r["ty"],
                                        r["tz"])
        xcam = camera.world_to_camera(r["X"], r["Y"], r["Z"], r["pitch"], r["tx"], r["ty"],
                                      r["tz"])[0]
        return float(u), float(v), float(xcam)

    u, v, _ = pixel_and_depth(plain)
    u_known, v_known, xcam_known = pixel_and_depth(known)
    assert (u_known, v_known) == pytest.approx((u, v), rel=1e-5, abs=1e-5)
    assert xcam_known == pytest.approx(50.0 * p["baseline"] / p["disparity"], rel=1e-5)
    assert known["fov_horizontal_deg"] == pytest.approx(np.degrees(fov_from_focal(50.0, 64)))
    assert known["from_the_pair"]["baseline_over_depth"] == pytest.approx(p["disparity"] / 50.0)
    assert known["priors"]["focal_px"]["source"] == "--focal"
    assert set(known["from_prior"]) == {"fx", "fy", "X", "Y", "Z"}
    assert known["spread"]["fx"] == 0.0


def test_focal_from_a_jpegs_exif_35mm_equivalent(setup, tmp_path, capsys):
    from PIL import Image

    root = tmp_path
    rgb = cv2.cvtColor(cv2.imread(str(setup["root"] / "left.png")), cv2.COLOR_BGR2RGB)
    rgb_right = cv2.cvtColor(cv2.imread(str(setup["root"] / "right.png")), cv2.COLOR_BGR2RGB)
    exif = Image.Exif()
    exif.get_ifd(0x8769)[0xA405] = 28                    # FocalLengthIn35mmFilm, mm
    Image.fromarray(rgb).save(root / "left.jpg", exif=exif, quality=95)
    Image.fromarray(rgb_right).save(root / "right.jpg", quality=95)
    args = [str(root / "left.jpg"), str(root / "right.jpg"), "--run", setup["run"]]
    assert calibrate_command.main(args + ["--focal", "exif"]) == 0
    known = json.loads(capsys.readouterr().out)
    expected = 28 * np.hypot(64, 40) / np.hypot(36, 24)
    assert known["parameters"]["fx"] == pytest.approx(expected, rel=1e-9)
    assert "EXIF FocalLengthIn35mmFilm 28 mm" in known["priors"]["focal_px"]["source"]
    # a JPEG without the tag: one line, exit 2, nothing printed on stdout
    status = calibrate_command.main([str(root / "right.jpg"), str(root / "left.jpg"), "--run",
                             setup["run"], "--focal", "exif"])
    captured = capsys.readouterr()
    assert status == 2 and captured.out == ""
    assert captured.err.strip().endswith("has no 35 mm equivalent focal length in its EXIF "
                                         "(FocalLengthIn35mmFilm); give --focal PX")


def test_colmap_cameras_txt_reads_back(setup, calibrator, tmp_path, capsys):
    out = tmp_path / "colmap"
    assert calibrate_command.main(_pair_args(setup) + ["--colmap", str(out)]) == 0
    result = json.loads(capsys.readouterr().out)
    record = calibrator.calibrate(*_pair_args(setup)[:2])
    assert exports.colmap_cameras(record) == (out / "cameras.txt").read_text()
    cameras = exports.read_colmap_cameras(out / "cameras.txt")
    p = result["parameters"]
    expected = (p["fx"], p["fy"], p["u0"] + 0.5, p["v0"] + 0.5)
    assert sorted(cameras) == [1, 2]
    for camera_id in (1, 2):
        model, width, height, params = cameras[camera_id]
        assert (model, width, height) == ("PINHOLE", 64, 40)
        assert params == pytest.approx(expected, rel=1e-12)
    # a file where the folder should be: one line, exit 2
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert calibrate_command.main(_pair_args(setup) + ["--colmap", str(blocker)]) == 2
    assert "--colmap is a file, not a directory" in capsys.readouterr().err


def test_bad_arguments_to_the_python_api_are_one_line_calibration_errors(setup, calibrator,
                                                                          tmp_path):
    """Checked before any image is read or any pair searched for; a missing
    image and a run directory that is not one likewise, as one line."""
    from cpl_keras import priors as known
    from cpl_keras.errors import Error

    left, right = _pair_args(setup)[:2]
    cases = [(lambda: calibrator.calibrate(left, right, aspect="wide"), "unknown aspect 'wide'"),
             (lambda: calibrator.calibrate(left, right, priors={"baseline_m": 0.1}),
              "priors must be a cpl_keras.priors.Priors, not dict"),
             (lambda: calibrator.calibrate_folder(str(tmp_path / "none"), aspect="fisheye"),
              "unknown aspect 'fisheye'"),
             (lambda: calibrator.calibrate(left, str(tmp_path / "missing.png")), "not found")]
    for call, message in cases:
        with pytest.raises(CalibrationError) as error:
            call()
        assert message in str(error.value) and "\n" not in str(error.value), error.value
    with pytest.raises(Error) as error:
        Calibrator.from_run(str(tmp_path / "nothing"))
    assert "not found" in str(error.value) and "\n" not in str(error.value)
    # known values go through as on the command line
    known_focal = calibrator.calibrate(left, right, priors=known.Priors(focal_px=50.0))
    assert known_focal.parameters["fx"] == 50.0 and known_focal.from_prior


def test_exports_are_all_or_nothing(setup, tmp_path, capsys):
    """An export that cannot be written (its folder would be under a file)
    stops calibrate in one line, exit 2, before the work (``check_outputs``),
    with none of the others written and no folder made for them; the same
    exports that can be written all appear."""
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    (tmp_path / "out").mkdir()
    outputs = ["--json-out", str(tmp_path / "out" / "calib.json"),
               "--opencv-yaml", str(tmp_path / "out" / "stereo.yml"),
               "--ros-yaml", str(tmp_path / "ros")]
    assert calibrate_command.main(_pair_args(setup) + outputs
                          + ["--colmap", str(blocker / "colmap")]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if ": error: " in line]
    assert err == [f"python -m cpl_keras.calibrate: error: cannot create the output directory "
                   f"{blocker / 'colmap'}: {blocker} is a file"]
    assert sorted(os.listdir(tmp_path)) == ["a-file", "out"] and not os.listdir(tmp_path / "out")
    assert calibrate_command.main(_pair_args(setup) + outputs
                          + ["--colmap", str(tmp_path / "colmap")]) == 0
    capsys.readouterr()
    assert sorted(os.listdir(tmp_path / "out")) == ["calib.json", "stereo.yml"]
    assert sorted(os.listdir(tmp_path / "ros")) == ["left.yaml", "right.yaml"]
    assert sorted(os.listdir(tmp_path / "colmap")) == ["cameras.txt", "rig_config.json"]


def test_a_truncated_image_is_refused_in_one_line(setup, tmp_path, capsys):
    """A left image cut to half its bytes (OpenCV would fill the rest with
    grey and go on): one line naming it, exit 2, no JSON written."""
    data = (setup["root"] / "left.png").read_bytes()
    cut = tmp_path / "cut.png"
    cut.write_bytes(data[:len(data) // 2])
    out = tmp_path / "calib.json"
    assert calibrate_command.main([str(cut), str(setup["root"] / "right.png"), "--run", setup["run"],
                           "--json-out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{cut} is truncated or corrupt" in err[0], err
    assert not out.exists()


def test_impossible_geometry_is_named_whatever_the_training():
    """A disparity at or beyond the image width (the demonstration model's
    9,748 px on OpenCV's 640 px chessboard pair), a focal length with no
    field of view, a depth nearer than the baseline and a baseline wider
    than any rig (its 117.5 m) are impossible for any pair; a disparity
    inside the image and under fx is not."""
    from cpl_keras.calibration import impossible_geometry
    from cpl_keras.stereo_camera import StereoCamera

    board = StereoCamera(fx=530.0, fy=530.0, u0=319.5, v0=239.5, width=640, height=480,
                         baseline=0.08, pitch=0.0, tx=0.0, ty=-0.08, tz=0.0)
    assert impossible_geometry(board, 120.0) == []
    wide, near = impossible_geometry(board, 9748.0)
    assert "9748 px is at or beyond the image width (640 px)" in wide
    assert "depth fx b / d = 0.00435 m is nearer than the baseline (0.08 m)" in near
    assert impossible_geometry(board, 600.0) == [    # inside the image, but over fx
        "the projection pixel's depth fx b / d = 0.0707 m is nearer than the baseline "
        "(0.08 m): a disparity of 600 px is over fx (530 px)"]
    assert len(impossible_geometry(dataclasses.replace(board, fx=0.0), 640.0)) == 2
    # the demonstration model's answer on that pair: 117.5 m of baseline as well
    demo = dataclasses.replace(board, baseline=117.5)
    lines = impossible_geometry(demo, 9748.0)
    assert len(lines) == 3 and lines[-1] == ("a baseline of 117.5 m is wider than any "
                                             "handheld or vehicle stereo rig (over 5 m)")
    # known values that make an impossible camera are named alike (--focal 1e-30
    # gave a 180-degree field of view, --baseline 1e-30 passed without a word)
    assert impossible_geometry(dataclasses.replace(board, fx=1e-30), 120.0) == [
        "a focal length of 1e-30 px (under 1 px) gives no field of view between 0 and 180 "
        "degrees"]
    assert impossible_geometry(dataclasses.replace(board, baseline=1e-30), 120.0) == [
        "a baseline of 1e-30 m is narrower than any stereo rig (under 1 mm)"]


def test_the_documented_python_snippet_runs_as_printed_and_catches_a_missing_run(tmp_path):
    """docs/calibrate.md's Python example, run as printed in a folder
    without the run it names: the package's one error class catches the
    run directory's error (a ``RunError``), one line, no traceback."""
    import re

    with open(os.path.join(REPO, "docs", "calibrate.md")) as f:
        [snippet] = re.findall(r"```python\n(.*?)```", f.read(), re.S)
    done = subprocess.run([sys.executable, "-c", snippet], cwd=tmp_path, text=True,
                          capture_output=True, timeout=120,
                          env=dict(os.environ, PYTHONPATH=REPO, KERAS_BACKEND="jax"))
    assert done.returncode == 0 and "Traceback" not in done.stderr, done.stderr
    lines = done.stdout.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("cannot calibrate: "), done.stdout
    assert "runs/cpl-a-paper-s0" in lines[0]


def test_the_readme_python_example_runs_as_printed_on_a_run(tiny_run):
    """README's front-door example, with the tiny run in place of the
    demonstration run the first command makes: it calibrates the shipped
    chessboard pair and prints the parameters, K and the field of view."""
    import re

    with open(os.path.join(REPO, "README.md")) as f:
        text = f.read()
    start = text.index("## From Python")
    [snippet] = re.findall(r"```python\n(.*?)```", text[start:text.index("\n## ", start + 1)],
                           re.S)
    assert len(snippet.strip().splitlines()) <= 12
    assert text[:start].count("\n") < 60  # (within the README's first 60 lines)
    snippet = snippet.replace('"runs/demo-cpl-a-paper-s0"', repr(tiny_run["run"]))
    done = subprocess.run([sys.executable, "-c", snippet], cwd=REPO, text=True,
                          capture_output=True, timeout=300,
                          env=dict(os.environ, KERAS_BACKEND="jax"))
    assert done.returncode == 0, done.stderr[-3000:]
    assert "'fx':" in done.stdout and "pitch" in done.stdout
