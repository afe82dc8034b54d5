"""Faults that a command must survive in one line, exit status 2 and no
file left behind under a final name that is not whole: a full disk (the
file size limit, ``RLIMIT_FSIZE``, gives every write beyond it EFBIG, as a
full disk gives ENOSPC; where the tests run as root, a small tmpfs gives
ENOSPC itself), and a refused command, which writes nothing."""

import errno
import os
import resource
import shutil
import signal
import subprocess
import sys
import uuid

import pytest

from helpers import REPO, writable_copy, write_stereo_fixture


def _limited(limit):
    """A ``preexec_fn``: writes beyond ``limit`` bytes fail with EFBIG (the
    signal that would otherwise kill the process at the limit ignored)."""
    def set_limit():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    return set_limit


def _command(args, preexec_fn=None, timeout=300):
    return subprocess.run([sys.executable, *args], cwd=REPO, text=True, capture_output=True,
                          env=dict(os.environ, KERAS_BACKEND="jax"), preexec_fn=preexec_fn,
                          timeout=timeout)


def _files(folder):
    return sorted(os.path.relpath(os.path.join(root, name), folder)
                  for root, _, names in os.walk(folder) for name in names)


def _tmpfs(tmp_path, options):
    """A tmpfs mounted with ``options`` (root only; skipped elsewhere),
    unmounted afterwards."""
    folder = tmp_path / f"disk-{uuid.uuid4().hex[:8]}"
    folder.mkdir()
    if os.geteuid() != 0 or not shutil.which("mount"):
        pytest.skip("mounting a tmpfs needs root")
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(folder)],
                          capture_output=True, text=True, timeout=60)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.strip()}")
    try:
        yield folder
    finally:
        subprocess.run(["umount", str(folder)], capture_output=True, timeout=60)


@pytest.fixture
def small_disk(tmp_path):
    """A 4 MiB tmpfs."""
    yield from _tmpfs(tmp_path, "size=4m")


@pytest.fixture
def read_only_disk(tmp_path):
    """A read-only tmpfs (root's writes fail there too, unlike a folder's mode)."""
    yield from _tmpfs(tmp_path, "ro,size=1m")


def _fill(folder):
    """Write into ``folder`` until its device is full."""
    with open(folder / "filler", "wb") as f:
        try:
            while True:
                f.write(b"\0" * 65536)
                f.flush()
        except OSError:
            pass


def test_an_atomic_write_flushes_the_file_then_the_rename(tmp_path, monkeypatch):
    """``files.write_text`` (``atomic_path``, ``commit``): fsync of the
    temporary file, the rename, then fsync of the folder (the rename itself
    on disk); a folder that cannot be fsync'd (OSError) is let be."""
    from cpl_keras import files

    synced, fsync = [], os.fsync

    def recording_fsync(fd):
        synced.append((os.readlink(f"/proc/self/fd/{fd}"), os.path.exists(tmp_path / "a.txt")))
        fsync(fd)

    monkeypatch.setattr(os, "fsync", recording_fsync)
    files.write_text(tmp_path / "a.txt", "text\n")
    assert synced == [(str(tmp_path / ".a.partial.txt"), False), (str(tmp_path), True)]
    assert (tmp_path / "a.txt").read_text() == "text\n"

    def refusing_fsync(fd):
        if os.path.isdir(os.readlink(f"/proc/self/fd/{fd}")):
            raise OSError(22, "Invalid argument")
        fsync(fd)

    monkeypatch.setattr(os, "fsync", refusing_fsync)
    files.write_text(tmp_path / "a.txt", "again\n")
    assert (tmp_path / "a.txt").read_text() == "again\n"
    assert sorted(os.listdir(tmp_path)) == ["a.txt"]


def test_a_failed_atomic_write_names_its_file_and_leaves_no_folder(small_disk):
    """A full disk in the middle of writing several files (``atomic_path``;
    ENOSPC names no file): one line naming the file being written; none of
    the files, and none of the folders made for them (``new_folders``)."""
    from cpl_keras import files

    small, large = small_disk / "out" / "sub" / "a.txt", small_disk / "out" / "sub" / "b.txt"
    with pytest.raises(OSError) as caught:
        with files.new_folders(small, large), files.atomic_path(small, large) as (a, b):
            with open(a, "w") as f:
                f.write("small\n")
            with open(b, "wb") as f:
                f.write(b"\0" * (8 << 20))
    assert str(caught.value) == f"cannot write {large}: no space left on the device"
    assert caught.value.errno == errno.ENOSPC
    assert files.write_failed(large, caught.value) == str(caught.value)
    assert _files(small_disk) == [] and os.listdir(small_disk) == []


def test_evaluate_and_calibrate_refuse_a_full_disk_before_the_work(small_disk):
    """A full output disk is found before anything is evaluated or
    calibrated (the run and the data need not even exist): one line naming
    the folder, exit 2, no folder made. Both found it only once all the work
    was done, in a line that named no file ([Errno 28]), and evaluate.py
    left its empty output folder."""
    _fill(small_disk)
    out = small_disk / "tables" / "new"
    done = _command(["evaluate.py", "--table", "1", "--runs", "no-such-run", "--out", str(out)])
    assert done.returncode == 2, done.stderr
    [line] = done.stderr.splitlines()
    assert line.startswith(f"evaluate.py: error: no space left on the device of {small_disk}: ")
    done = _command(["-m", "cpl_keras.calibrate", "l.png", "r.png", "--run", "no-such-run",
                     "--ros-yaml", str(out)])
    assert done.returncode == 2, done.stderr
    assert done.stderr.splitlines() == [
        line.replace("evaluate.py", "python -m cpl_keras.calibrate")], done.stderr
    assert _files(small_disk) == ["filler"] and os.listdir(small_disk) == ["filler"]


def test_evaluate_and_calibrate_refuse_a_read_only_folder_before_the_work(read_only_disk):
    for args, prog in ((["evaluate.py", "--run", "no-such-run", "--data", "no.h5", "--out",
                         str(read_only_disk / "out")], "evaluate.py"),
                       (["-m", "cpl_keras.calibrate", "l.png", "r.png", "--run", "no-such-run",
                         "--json-out", str(read_only_disk / "c.json")],
                        "python -m cpl_keras.calibrate")):
        done = _command(args)
        assert done.returncode == 2, done.stderr
        what = "directory" if prog == "evaluate.py" else "output directory"
        assert done.stderr.splitlines() == [
            f"{prog}: error: {what} is not writable: {read_only_disk}"], done.stderr


def test_generation_beyond_the_file_size_limit_is_one_line_and_no_file(tmp_path):
    out = tmp_path / "g.h5"
    done = _command(["-m", "cpl_keras.data.generate", "--pairs", "300", "--image-size", "48",
                     "--workers", "1", "--no-progress", "--out", str(out)],
                    preexec_fn=_limited(400_000))
    assert done.returncode == 2, done.stderr
    assert done.stderr.splitlines() == [
        f"python -m cpl_keras.data.generate: error: cannot write {out}: "
        "the file is larger than this system allows"], done.stderr
    assert _files(tmp_path) == []


def test_generation_into_a_full_disk_is_one_line_and_no_file(small_disk):
    out = small_disk / "g.h5"
    done = _command(["-m", "cpl_keras.data.generate", "--pairs", "400", "--image-size", "64",
                     "--workers", "2", "--no-progress", "--out", str(out)])
    assert done.returncode == 2, done.stderr
    assert done.stderr.splitlines() == [
        f"python -m cpl_keras.data.generate: error: cannot write {out}: "
        "no space left on the device"], done.stderr
    assert _files(small_disk) == []


@pytest.mark.slow
def test_training_beyond_the_file_size_limit_leaves_no_partial_checkpoint(tmp_path, stereo40):
    """The first checkpoint (the small backbone's weights and optimizer
    state, about 17 MB) cannot be written: one line, exit 2, no weights
    file and no temporary file in the run directory."""
    run_dir = tmp_path / "run"
    done = _command(["train.py", "--variant", "baseline", "--backbone", "small", "--data",
                     stereo40, "--epochs", "2", "--batch-size", "5", "--quiet", "--run-dir",
                     str(run_dir)], preexec_fn=_limited(8_000_000))
    assert done.returncode == 2, done.stderr
    lines = done.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"train.py: error: cannot write {run_dir}"), \
        done.stderr
    assert lines[0].endswith("the file is larger than this system allows"), done.stderr
    left = _files(run_dir)
    assert not [name for name in left if name.endswith(".h5") or "partial" in name], left


def test_a_refused_resume_leaves_the_run_directory_unchanged(tmp_path, stereo40, monkeypatch):
    """A run directory whose data has changed since (another split) is
    refused before anything in it is written: every byte stays."""
    from cpl_keras.training import train
    from cpl_keras.training.planning import TrainingError
    from helpers import interrupt_after_epoch

    run_dir, data = tmp_path / "run", str(tmp_path / "data.h5")
    shutil.copyfile(stereo40, data)
    interrupt_after_epoch(monkeypatch, 1)
    with pytest.raises(KeyboardInterrupt):
        train(data, variant="baseline", run_dir=str(run_dir), backbone="small", epochs=2,
              batch_size=5, verbose=0)
    monkeypatch.undo()
    before = {name: (run_dir / name).read_bytes() for name in _files(run_dir)}
    os.remove(data)
    write_stereo_fixture(data, n=48, image_size=32)  # (the same file, made again larger)
    with pytest.raises(TrainingError, match="differs from this run's split"):
        train(data, variant="baseline", run_dir=str(run_dir), backbone="small", epochs=2,
              batch_size=5, verbose=0)
    assert {name: (run_dir / name).read_bytes() for name in _files(run_dir)} == before


# ---------------------------------------------------------------------------
# Damaged run files: named, with the way out, and never reported as finished
# ---------------------------------------------------------------------------
def _interrupted_run(tmp_path, data, monkeypatch):
    """A run of 2 epochs interrupted after its first: ``(run_dir, train)``."""
    from cpl_keras.training import train
    from helpers import interrupt_after_epoch

    run_dir = tmp_path / "run"
    settings = dict(variant="baseline", run_dir=str(run_dir), backbone="small", epochs=2,
                    batch_size=5, verbose=0)
    interrupt_after_epoch(monkeypatch, 1)
    with pytest.raises(KeyboardInterrupt):
        train(data, **settings)
    monkeypatch.undo()
    return run_dir, lambda: train(data, **settings)


def test_a_damaged_split_or_checkpoint_is_named_with_the_way_out(tmp_path, stereo40,
                                                                  monkeypatch):
    from cpl_keras.training import TrainingError

    run_dir, resume = _interrupted_run(tmp_path, stereo40, monkeypatch)
    split = run_dir / "split.npz"
    good = split.read_bytes()
    split.write_bytes(good[: len(good) // 2])
    with pytest.raises(TrainingError, match=f"cannot read the split {split} .*delete it") as e:
        resume()
    assert "\n" not in str(e.value)
    split.write_bytes(good)
    checkpoints = sorted((run_dir / "backup").glob("*.weights.h5"))
    assert checkpoints
    data = checkpoints[-1].read_bytes()
    checkpoints[-1].write_bytes(data[: len(data) // 3])
    with pytest.raises(TrainingError, match=f"cannot resume from the checkpoint "
                       f"{checkpoints[-1]} .*delete {run_dir / 'backup'} to start") as e:
        resume()
    assert "\n" not in str(e.value)


def test_a_finished_run_with_a_damaged_model_is_not_reported_finished(tmp_path, tiny_run):
    from cpl_keras.training import TrainingError, train

    run_dir = tmp_path / "run"
    writable_copy(tiny_run["run"], run_dir)
    settings = dict(variant="baseline", run_dir=str(run_dir), epochs=1, batch_size=8,
                    backbone="small", verbose=0, return_model=False)
    assert train(tiny_run["data"], **settings).finished_before  # (whole: finished)
    for name in ("model.keras", "best.weights.h5"):
        path = run_dir / name
        whole = path.read_bytes()
        path.write_bytes(whole[: len(whole) // 2])
        with pytest.raises(TrainingError, match=f"finished run's {path} is damaged .*delete "
                           "the run directory"):
            train(tiny_run["data"], **settings)
        path.write_bytes(whole)
