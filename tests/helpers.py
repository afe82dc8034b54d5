"""What several test files share: the repository's folder, the small
fixture datasets and batches they build, the commands' main functions, the
arguments of the whole commands that conftest.py starts early, waiting on
what a process prints or writes, and writable copies of the session's
read-only files.

Tests import their helpers from here, never from one another or from
conftest.py (tests/test_structure.py checks it). Heavy imports (Keras's
models, OpenCV) stay inside the functions, so that conftest.py can import
this module before the backend is chosen.
"""

import csv
import os
import shutil
import stat
import sys

import numpy as np

#: The repository's root folder.
REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


# ---------------------------------------------------------------------------
# Fixture datasets (the storage format of cpl_keras.data.storage)
# ---------------------------------------------------------------------------
def fixture_labels(n, image_size, configs=4, seed=0):
    """Labels of ``n`` pairs that obey the camera equations (Eqs. 4a-5c)."""
    from cpl_keras import camera

    rng = np.random.default_rng(seed)
    config_id = np.arange(n) % configs
    fov = np.radians(rng.uniform(50, 150, configs))[config_id]
    focal = camera.focal_from_fov(fov, image_size)
    tx = rng.uniform(0.5, 5.0, configs)[config_id]
    labels = {
        "fx": focal, "fy": focal,
        "u0": np.full(n, image_size / 2), "v0": np.full(n, image_size / 2),
        "baseline": tx, "tx": tx,
        "ty": rng.uniform(-5, 5, configs)[config_id],
        "tz": rng.uniform(-0.4, 1.6, configs)[config_id],
        "pitch": np.radians(rng.uniform(-30, 30, configs))[config_id],
        "disparity": rng.uniform(1.0, 20.0, n),
        "disparity_released": rng.uniform(-15.0, 5.0, n),
        "u": rng.uniform(0, image_size, n), "v": rng.uniform(0, image_size, n),
    }
    params = {name: labels[name] for name in camera.PARAMETERS}
    labels["X"], labels["Y"], labels["Z"] = camera.image_to_world(**params, u=labels["u"], v=labels["v"])
    labels = {name: values.astype(np.float32) for name, values in labels.items()}
    labels["config_id"] = config_id.astype(np.int32)
    labels["town_id"] = (config_id % 2).astype(np.int32)
    labels["frame_index"] = np.arange(n, dtype=np.int32)
    return labels


def write_stereo_fixture(path, n=40, image_size=32, configs=4, seed=0, labels=None, drop=()):
    """A small dataset file: random images, labels from ``fixture_labels``."""
    from cpl_keras.data.writer import StereoWriter

    rng = np.random.default_rng(seed + 1)
    h, w = (image_size, image_size) if np.isscalar(image_size) else image_size
    labels = dict(labels or fixture_labels(n, w, configs, seed))
    for name in drop:
        labels.pop(name)
    left = rng.integers(0, 256, (n, h, w, 3), dtype=np.uint8)
    right = rng.integers(0, 256, (n, h, w, 3), dtype=np.uint8)
    with StereoWriter(path, n, (h, w), metadata={"protocol": "test"}) as writer:
        writer.write(0, left, right, labels)
    return str(path)


# ---------------------------------------------------------------------------
# A model batch
# ---------------------------------------------------------------------------
#: The image size (pixels, square) of ``batch``'s images and of the models
#: the model tests build for them.
SIZE = 32


def batch(n=4, seed=0):
    """Images and targets that obey the camera equations."""
    from cpl_keras import TARGETS, camera

    rng = np.random.default_rng(seed)
    x = {
        "left_image": rng.uniform(0, 255, (n, SIZE, SIZE, 3)).astype("float32"),
        "right_image": rng.uniform(0, 255, (n, SIZE, SIZE, 3)).astype("float32"),
    }
    p = {
        "fx": rng.uniform(20, 60, n), "fy": rng.uniform(20, 60, n),
        "u0": np.full(n, 16.0), "v0": np.full(n, 16.0), "baseline": rng.uniform(0.2, 2, n),
        "disparity": rng.uniform(1, 8, n), "tx": rng.normal(0, 1, n), "ty": rng.normal(0, 1, n),
        "tz": rng.normal(0, 0.3, n), "pitch": rng.uniform(-0.3, 0.3, n),
    }
    X, Y, Z = camera.image_to_world(**p, u=rng.uniform(0, SIZE, n), v=rng.uniform(0, SIZE, n))
    p.update(X=X, Y=Y, Z=Z)
    y = {name: np.asarray(p[name], "float32").reshape(n, 1) for name in TARGETS}
    return x, y


# ---------------------------------------------------------------------------
# The commands' main functions
# ---------------------------------------------------------------------------
def load_script(relative_path, name=None):
    """The repository's script ``relative_path`` (e.g. ``analyses/paired_runs.py``)
    imported as a module, its ``__main__`` block not run."""
    import importlib.util

    name = name or os.path.splitext(os.path.basename(relative_path))[0]
    spec = importlib.util.spec_from_file_location(name, os.path.join(REPO, relative_path))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


# ---------------------------------------------------------------------------
def main_functions():
    """``{command: its main function}`` for the package's commands and the
    repository's train.py and evaluate.py."""
    from cpl_keras.commands import (
        calibrate, chessboard, generate, graph, import_cvgl, learning_curves, mix, real_build,
        reproduce,
    )

    mains = {"reproduce": reproduce.main, "data.generate": generate.main, "data.mix": mix.main,
             "data.import_cvgl": import_cvgl.main,
             "calibrate": calibrate.main, "graph": graph.main, "real.build": real_build.main,
             "learning_curves": learning_curves.main, "real.chessboard": chessboard.main}
    for script in ("train.py", "evaluate.py"):
        mains[script] = load_script(script, script[:-3] + "_cli").main
    return mains


# ---------------------------------------------------------------------------
# A KITTI stereo folder (tests/fixtures/kitti)
# ---------------------------------------------------------------------------
KITTI_FIXTURES = os.path.join(os.path.dirname(os.path.abspath(__file__)), "fixtures", "kitti")
KITTI_CAM_TO_CAM = os.path.join(KITTI_FIXTURES, "calib_cam_to_cam.txt")
KITTI_OBJECT = os.path.join(KITTI_FIXTURES, "calib_object_000000.txt")
#: The size of KITTI's images (and of ``kitti_image``'s).
KITTI_WIDTH, KITTI_HEIGHT = 1242, 375


def kitti_image(seed):
    """A KITTI-sized image (``KITTI_HEIGHT`` x ``KITTI_WIDTH`` x 3, uint8)."""
    # smooth texture: quick to write, compresses well
    y, x = np.mgrid[0:KITTI_HEIGHT, 0:KITTI_WIDTH]
    base = (127 + 100 * np.sin(x / (7.0 + seed)) * np.cos(y / 11.0)).astype(np.uint8)
    return np.stack([base, base[:, ::-1],
                     base.T[:KITTI_HEIGHT, :KITTI_WIDTH] if False else base], -1)


def kitti_stereo_root(root, calib="cam_to_cam", disparity=12.5):
    """A KITTI stereo folder under ``root`` (a ``pathlib.Path``): frames
    000000_10 and 000000_11, a ground-truth disparity of ``disparity`` in a
    block of frame _10 only, and the calibration in KITTI's ``cam_to_cam``
    or object (``calib``) format. Returns ``root``."""
    import cv2

    base = root / "training"
    for folder in ("image_2", "image_3", "disp_occ_0", "calib_cam_to_cam", "calib"):
        (base / folder).mkdir(parents=True, exist_ok=True)
    for name in ("000000_10", "000000_11"):
        cv2.imwrite(str(base / "image_2" / f"{name}.png"), kitti_image(0))
        cv2.imwrite(str(base / "image_3" / f"{name}.png"), kitti_image(1))
    raw = np.zeros((KITTI_HEIGHT, KITTI_WIDTH), np.uint16)
    raw[200:300, 100:400] = int(disparity * 256)        # valid block left of centre
    cv2.imwrite(str(base / "disp_occ_0" / "000000_10.png"), raw)
    if calib == "cam_to_cam":
        shutil.copy(KITTI_CAM_TO_CAM, base / "calib_cam_to_cam" / "000000.txt")
    else:
        shutil.copy(KITTI_OBJECT, base / "calib" / "000000.txt")
    return root


# ---------------------------------------------------------------------------
# The authors' release, in its exact formats, from the project's own renderer
# ---------------------------------------------------------------------------
#: The row order of ``release_flat``: the release shuffled its rows once
#: before saving them (here a fixed permutation, so a test can follow rows).
def release_order(n):
    return np.random.default_rng(7).permutation(n)


def release_flat(rendered, directory, suffix=""):
    """The pairs of the rendered cvgl file ``rendered`` in the release's flat
    layout (``cpl_keras.data.release_files.write_flat``: BGR images, the
    release's labels, pitch in degrees, StereoBM's mean disparity, the
    vehicle-frame differences, X, Y, Z of its formula at (56, 56)), rows in
    ``release_order``. ``suffix`` "r" writes them as the real sets' files
    (RGB, pitch in radians, X, Y, Z at (5, 5), intrinsics 10x as at full
    resolution), as data only. Returns ``directory``."""
    from cpl_keras import camera
    from cpl_keras.data.release_files import release_labels, write_flat
    from cpl_keras.data.storage import StereoFile
    from cpl_keras.datasets import targets_from_labels

    with StereoFile(rendered) as f:
        order = release_order(f.num_pairs)
        left, right = f.read_pairs(order)
        labels = {k: np.asarray(v)[order] for k, v in f.labels.items()}
    released = release_labels(targets_from_labels(labels, as_released=True))
    if suffix:
        for name in ("fx", "fy", "u0", "v0"):
            released[name] = released[name] * 10
        released["p"] = np.radians(released["p"])
        params = {camera.TARGETS[i]: released[k] for i, k in enumerate(("fx", "fy", "u0", "v0",
                  "b", "d", "tx", "ty", "tz", "p"))}
        released["x"], released["y"], released["z"] = camera.image_to_world(**params, u=5.0,
                                                                            v=5.0)
    return write_flat(directory, left, right, released, suffix)


def release_episodes(rendered, root):
    """The pairs of the rendered cvgl file ``rendered`` as the release's raw
    episodes: ``Town<k>/episode_<c>/LeftRGB_<i>.png``, ``RightRGB_<i>.png``
    (written by OpenCV, so BGR on disk as CARLA's) and ``params.txt`` with
    the right camera's CARLA fov, x, y, z, pitch. Returns ``root``."""
    import cv2

    from cpl_keras.data.storage import StereoFile

    with StereoFile(rendered) as f:
        configs = f.metadata["configurations"]
        config_id, frame = f.labels["config_id"], f.labels["frame_index"]
        for i in range(f.num_pairs):
            cfg = configs[int(config_id[i])]
            folder = os.path.join(root, f"Town{cfg['town_id'] + 1}",
                                  f"episode_{int(config_id[i]):04d}")
            if not os.path.isdir(folder):
                os.makedirs(folder)
                carla = cfg["carla"]
                with open(os.path.join(folder, "params.txt"), "w") as out:
                    out.write("".join(f"{name}: {carla[key]!r}\n" for name, key in (
                        ("fov", "fov_deg"), ("x", "x"), ("y", "y"), ("z", "z"),
                        ("pitch", "pitch_deg"))) + "yaw: 0.0\n")
            left, right = f.read_pairs([i])
            cv2.imwrite(os.path.join(folder, f"LeftRGB_{int(frame[i])}.png"), left[0][..., ::-1])
            cv2.imwrite(os.path.join(folder, f"RightRGB_{int(frame[i])}.png"),
                        right[0][..., ::-1])
    return root


def tsinghua_root(root, names=("a_000001", "a_000002"), shape=(48, 96), d=8.0,
                  camera=None, split="test", city="tsinghuaDaimlerDataset"):
    """A Tsinghua-Daimler Cyclist Benchmark folder under ``root`` (a
    ``pathlib.Path``) in that dataset's layout (``leftImg8bit``,
    ``disparity``, ``camera`` JSON), random images, a disparity of ``d``
    with an invalid strip. Returns the camera dict."""
    import json

    import cv2

    rng = np.random.default_rng(0)
    camera = camera or {
        "extrinsic": {"baseline": 0.3, "pitch": 0.04, "roll": 0.01, "x": 1.7, "y": 0.1,
                      "yaw": -0.02, "z": 1.2},
        "intrinsic": {"fx": 120.0, "fy": 125.0, "u0": 47.0, "v0": 23.0},
    }
    for name in names:
        for folder in ("leftImg8bit", "disparity", "camera"):
            os.makedirs(root / folder / split / city, exist_ok=True)
        image = (rng.random(shape + (3,)) * 255).astype(np.uint8)
        cv2.imwrite(str(root / "leftImg8bit" / split / city / f"{name}_leftImg8bit.png"), image)
        raw = np.full(shape, int(d * 256 + 1), np.uint16)
        raw[:, :4] = 0                                    # invalid strip
        cv2.imwrite(str(root / "disparity" / split / city / f"{name}_disparity.png"), raw)
        with open(root / "camera" / split / city / f"{name}_camera.json", "w") as f:
            json.dump(camera, f)
    return camera


# ---------------------------------------------------------------------------
# Whole commands (conftest.py's EARLY commands and the tests that rerun them)
# ---------------------------------------------------------------------------
#: The suite's quick reproduction is ``--quick`` on fewer pairs than the
#: preset's 150 of each protocol: 52 cvgl pairs (paper split: 32 training, 4
#: validation, 16 test) and 64 random ones (held-out rigs: 32, 8, 24), so that
#: every training set is whole batches of 16 and each run compiles one
#: training step, not one more for a short last batch. Every stage, run,
#: table and file of the reproduction is there as at the preset's size.
QUICK_PAIRS = 52
QUICK_SIZE = ["--pairs", str(QUICK_PAIRS), "--random-pairs", "64"]


def quick_reproduction_args(root):
    """``python -m cpl_keras.reproduce``'s arguments for the quick reproduction into ``root``
    (``QUICK_SIZE``): one run at a time, its default (at this scale faster
    than two at a time, and with less work:
    paper_results/notes/pipeline-and-suite.md; ``--jobs`` has tests of its
    own)."""
    return ["--quick", *QUICK_SIZE, "--out", os.path.join(root, "out"),
            "--data-dir", os.path.join(root, "data"), "--runs-dir", os.path.join(root, "runs")]


#: XLA's optimisation level for the commands whose runs are compilation, not
#: training steps (the quick reproduction's nine one-epoch runs, the process
#: groups' two-epoch runs): at level 0 the quick reproduction took 0.69 of its
#: CPU time (145 s -> 100 s of user CPU, beside a training run;
#: paper_results/notes/pipeline-and-suite.md). The suite as a whole keeps
#: XLA's defaults (no saving there: the same page).
QUICK_XLA_FLAGS = "--xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true"

#: train.py's arguments for the run that the kill-and-resume tests compare with.
RESUME_ARGS = ["--variant", "baseline", "--backbone", "small", "--epochs", "4",
               "--batch-size", "5", "--patience", "10", "--quiet"]


def train_py(*args, cache=None, env=None):
    """``(argv, environment)`` of train.py with ``args``; its XLA compile
    cache the session's (conftest.py), or ``cache`` (every program kept)."""
    environment = dict(os.environ, KERAS_BACKEND="jax", **(env or {}))
    if cache is not None:
        environment["JAX_COMPILATION_CACHE_DIR"] = cache
        environment["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
    return [sys.executable, os.path.join(REPO, "train.py"), *args], environment


#: The shared variant runs' settings (conftest's ``variant_run``): 40 pairs
#: -> 25 train, 3 val, 12 test; batches of 5 keep one shape (one
#: compilation); 2 epochs.
VARIANT_RUN = dict(backbone="small", epochs=2, batch_size=5, seed=1, verbose=0)


def interrupt_after_epoch(monkeypatch, epoch):
    """Make training raise KeyboardInterrupt right after epoch ``epoch``'s
    commit (1-based), as a kill at that moment would leave the run;
    ``monkeypatch.undo()`` ends it."""
    from cpl_keras.training import checkpointing

    original = checkpointing.RunState.on_epoch_end

    def interrupted(self, index, logs=None):
        original(self, index, logs)
        if index == epoch - 1:
            raise KeyboardInterrupt

    monkeypatch.setattr(checkpointing.RunState, "on_epoch_end", interrupted)


def assert_refuses_a_bare_log(script, tmp_path, capsys, message):
    """An analyses script given a run whose log.csv lacks its columns: one
    line naming ``message`` on stderr, exit 2, and no page written."""
    bare = tmp_path / "bare"
    bare.mkdir()
    (bare / "log.csv").write_text("epoch,loss\n1,1.0\n")
    capsys.readouterr()
    assert script.main(["--run", f"B={bare}", "--out", str(tmp_path / "bare.md")]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1
    assert not (tmp_path / "bare.md").exists()


# ---------------------------------------------------------------------------
# Waiting on a process that trains
# ---------------------------------------------------------------------------
def wait_for(condition, timeout=120):
    """Poll ``condition()`` (a file it reads may not be there yet: an
    ``OSError``, ``ValueError`` or ``KeyError`` counts as False) until it is
    true or ``timeout`` seconds have passed; returns whether it came true."""
    import time

    deadline = time.time() + timeout
    while time.time() < deadline:
        try:
            if condition():
                return True
        except (OSError, ValueError, KeyError):
            pass
        time.sleep(0.02)
    return False


def wait_for_output(stream, needle, timeout=120):
    """``wait_for`` a process to print ``needle``: read its pipe ``stream``
    (its stdout or stderr, unbuffered, as the text comes) until what was read
    holds ``needle``, the stream ends or ``timeout`` seconds have passed.
    Returns the text read (the caller checks for ``needle``); the rest stays
    in the pipe for ``communicate``."""
    import select

    seen = bytearray()

    def printed():
        if select.select([stream], [], [], 0)[0]:
            chunk = os.read(stream.fileno(), 65536)
            if not chunk:
                return True  # (the stream ended)
            seen.extend(chunk)
        return needle.encode() in seen

    wait_for(printed, timeout)
    return seen.decode(errors="replace")


def read_log(run_dir):
    """A run directory's log.csv: a dict of strings per epoch."""
    with open(os.path.join(run_dir, "log.csv")) as f:
        return list(csv.DictReader(f))


def epochs_done(run_dir):
    """The epochs a run directory's resume state says are committed."""
    import json

    with open(os.path.join(run_dir, "backup", "state.json")) as f:
        return json.load(f)["epoch"]


# ---------------------------------------------------------------------------
# The session's shared files (conftest.py), read only
# ---------------------------------------------------------------------------
def set_writable(path, writable):
    """Give ``path`` (a file, or a folder and everything in it; links left
    alone) back its owner's write permission, or take write permission from
    everyone (a file 0o644 becomes 0o444, a folder 0o755 0o555)."""
    paths = [path]
    if os.path.isdir(path) and not os.path.islink(path):
        for folder, folders, names in os.walk(path):
            paths += [os.path.join(folder, name) for name in folders + names]
    for name in paths:
        if not os.path.islink(name):
            mode = os.stat(name).st_mode
            os.chmod(name, (mode | stat.S_IWUSR) if writable else (mode & ~0o222))


def writable_copy(source, destination):
    """A copy of a session fixture's file or folder (which conftest.py makes
    read only, and ``shutil``'s copies keep read only) that the test may
    change: times kept, write permission given back. Returns its path."""
    if os.path.isdir(source):
        shutil.copytree(source, destination)
    else:
        shutil.copy2(source, destination)
    set_writable(destination, True)
    return str(destination)
