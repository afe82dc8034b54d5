"""Faults that a command must survive in one line, exit status 2 and no
file left behind under a final name that is not whole: a full disk (the
file size limit, ``RLIMIT_FSIZE``, gives every write beyond it EFBIG, as a
full disk gives ENOSPC; where the tests run as root, a small tmpfs gives
ENOSPC itself), and a refused command, which writes nothing."""

import os
import resource
import shutil
import signal
import subprocess
import sys
import uuid

import pytest

from helpers import REPO, write_stereo_fixture


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


@pytest.fixture
def small_disk(tmp_path):
    """A 4 MiB tmpfs (root only; skipped elsewhere), unmounted afterwards."""
    folder = tmp_path / f"disk-{uuid.uuid4().hex[:8]}"
    folder.mkdir()
    if os.geteuid() != 0 or not shutil.which("mount"):
        pytest.skip("mounting a tmpfs needs root")
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=4m", "tmpfs", str(folder)],
                          capture_output=True, text=True, timeout=60)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.strip()}")
    try:
        yield folder
    finally:
        subprocess.run(["umount", str(folder)], capture_output=True, timeout=60)


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
