"""Training over several processes (``cpl_keras.distributed``): the slices
each process reads, the group's checks, and two local processes of
``train.py --data-parallel`` against one process on one and on two devices,
a partner killed with -9, the group resumed, then each process stopped by SIGTERM."""

import contextlib
import functools
import json
import os
import signal
import socket
import subprocess
import sys
import time

import h5py
import numpy as np
import pytest

from cpl_keras import distributed, heartbeats
from cpl_keras.training.sequence import StereoSequence
from helpers import QUICK_XLA_FLAGS, REPO, read_log, train_py, wait_for

#: Every subprocess of these tests ends within this many seconds or fails.
TIMEOUT_S = 240
#: The runs compared: MTL-CPL-U, the small backbone, batch 4 on a 52-pair
#: fixture (32 training pairs, 4 validation pairs: every batch splits evenly
#: over two devices, so one device sees the same batches as two).
ARGS = ["--variant", "cpl-u", "--backbone", "small", "--batch-size", "4", "--quiet"]
#: Every train.py of these tests compiles at XLA's level 0 (its runs are
#: start-up and compilation, not training steps): on one device, on two and
#: in two processes alike.
XLA_FLAGS = QUICK_XLA_FLAGS


@pytest.fixture(scope="module")
def fixture52(tmp_path_factory):
    from helpers import write_stereo_fixture

    path = str(tmp_path_factory.mktemp("dist") / "stereo52.h5")
    write_stereo_fixture(path, n=52, image_size=32)
    return path


@pytest.fixture(scope="module")
def fixture60(tmp_path_factory):
    from helpers import write_stereo_fixture

    path = str(tmp_path_factory.mktemp("dist") / "stereo60.h5")
    write_stereo_fixture(path, n=60, image_size=32)
    return path


@contextlib.contextmanager
def _coordinator_port():
    """A port for a group's coordinator, held by this process for the block.

    Race-free, not retried: the port stays bound here (SO_REUSEADDR, never
    listening) until the coordinator has it, so that no other socket of the
    machine is given the number in between (a port bound and released at
    once, as before, could be taken by another process before process 0's
    coordination service bound it). Its gRPC server sets SO_REUSEADDR too,
    so it binds and listens beside this idle socket."""
    with socket.socket() as reserved:
        reserved.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        reserved.bind(("localhost", 0))
        yield reserved.getsockname()[1]


def _listening(port):
    """Whether a socket of this machine listens on TCP ``port`` (/proc/net)."""
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        if os.path.exists(table):
            with open(table) as f:
                for line in list(f)[1:]:
                    local, state = line.split()[1], line.split()[3]
                    if state == "0A" and int(local.rsplit(":", 1)[1], 16) == port:
                        return True
    return False


def _group_env(port, process_id, extra=None):
    return {"KERAS_DISTRIBUTION_JOB_ADDRESSES": f"localhost:{port}",
            "KERAS_DISTRIBUTION_NUM_PROCESSES": "2",
            "KERAS_DISTRIBUTION_PROCESS_ID": str(process_id),
            "CPL_KERAS_PEER_TIMEOUT_S": "5", **(extra or {})}


def _start_group(tmp, cache, data_paths, run_dir, epochs, extra=()):
    """Two train.py processes of one group; returns the Popen objects once
    process 0's coordination service listens (or a process has ended)."""
    processes = []
    with _coordinator_port() as port:
        for process_id, data in enumerate(data_paths):
            argv, environ = train_py(*ARGS, *extra, "--data", data, "--epochs", str(epochs),
                                     "--data-parallel", "--run-dir", run_dir, cache=cache,
                                     env=_group_env(port, process_id, {"XLA_FLAGS": XLA_FLAGS}))
            out = open(os.path.join(tmp, f"p{process_id}.{len(os.listdir(tmp))}.txt"), "w+")
            processes.append(subprocess.Popen(argv, env=environ, stdout=out,
                                              stderr=subprocess.STDOUT, text=True))
            processes[-1].log = out
        wait_for(lambda: _listening(port) or any(p.poll() is not None for p in processes),
                 TIMEOUT_S)
    return processes


def _wait(process, timeout=TIMEOUT_S):
    try:
        status = process.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        process.kill()
        raise AssertionError(f"a process of the group ran past {timeout} s") from None
    process.log.seek(0)
    return status, process.log.read()


def _lines(text):
    """The output without the Gloo library's own connection notices."""
    return [line for line in text.splitlines() if line and not line.startswith("[Gloo]")]


def _weights(run_dir):
    arrays = []
    with h5py.File(os.path.join(run_dir, "best.weights.h5")) as f:
        f.visititems(lambda name, item: arrays.append((name, item[...]))
                     if isinstance(item, h5py.Dataset) else None)
    return arrays


# ---------------------------------------------------------------------------
# The slices, and the group from the environment
# ---------------------------------------------------------------------------
def test_each_process_reads_a_disjoint_equal_part_of_every_global_batch(fixture52):
    rng = np.random.default_rng(0)
    for _ in range(200):
        processes = int(rng.integers(1, 5))
        batch = rng.permutation(1000)[:processes * int(rng.integers(1, 9))]
        parts = [distributed.local_part(batch, p, processes) for p in range(processes)]
        assert all(len(part) == len(batch) // processes for part in parts)
        np.testing.assert_array_equal(np.concatenate(parts), batch)  # disjoint, whole, in order
    with pytest.raises(ValueError, match="does not split"):
        distributed.local_part(np.arange(5), 0, 2)

    # the sequences of the two processes of a group: equal step counts, and
    # their batches together the one-process batch, epoch after epoch
    train = np.arange(0, 50, 1)[::-1][:38]
    whole = StereoSequence(fixture52, train, batch_size=4, shuffle=True, seed=3, multiple_of=2)
    parts = [StereoSequence(fixture52, train, batch_size=4, shuffle=True, seed=3, multiple_of=2,
                            part=functools.partial(distributed.local_part, process_id=p,
                                                   num_processes=2)) for p in range(2)]
    assert len(parts[0]) == len(parts[1]) == len(whole)
    for epoch in (0, 1, 5):
        for sequence in [whole] + parts:
            sequence.set_epoch(epoch)
        for index in range(len(whole)):
            x, y = whole[index]
            pieces = [part[index] for part in parts]
            np.testing.assert_array_equal(
                np.concatenate([p[0]["left_image"] for p in pieces]), x["left_image"])
            np.testing.assert_array_equal(np.concatenate([p[1]["fx"] for p in pieces]), y["fx"])
            np.testing.assert_array_equal(parts[1].batch_targets(index)["fx"], y["fx"])
    with pytest.raises(ValueError, match="does not split"):
        StereoSequence(fixture52, train, batch_size=3,
                       part=functools.partial(distributed.local_part, process_id=0,
                                              num_processes=2))


def test_group_from_environment():
    assert distributed.group_from_environment({}) is None
    group = distributed.group_from_environment(_group_env(1234, 1))
    assert group == distributed.ProcessGroup("localhost:1234", 2, 1) and not group.chief
    bad = [({"KERAS_DISTRIBUTION_NUM_PROCESSES": "2"}, "needs all three"),
           ({**_group_env(1, 2)}, "is not a process of"),
           ({**_group_env(1, 0), "KERAS_DISTRIBUTION_JOB_ADDRESSES": "nohost"}, "host:port"),
           ({**_group_env(1, 0), "KERAS_DISTRIBUTION_NUM_PROCESSES": "two"}, "integers")]
    for environ, message in bad:
        with pytest.raises(distributed.DistributedError, match=message):
            distributed.group_from_environment(environ)


# ---------------------------------------------------------------------------
# The trainer's seam: one process, or a group
# ---------------------------------------------------------------------------
def test_one_process_writes_everything_and_waits_for_nobody():
    from cpl_keras.training.processes import SingleProcess

    calls = []
    one = SingleProcess()
    assert one.writes and one.count == 1
    batch = np.arange(6)
    assert one.part(batch) is batch and one.global_batch(batch) is batch
    assert one.write("what", lambda a, b: calls.append((a, b)) or a + b, 1, 2) == 3
    assert calls == [(1, 2)]
    assert one.decide("stop", "early stopping") == "early stopping"
    one.agree("the run", lambda: calls.append("fingerprint"))  # (not computed)
    assert calls == [(1, 2)]
    with one.alone(), pytest.raises(RuntimeError, match="as it was"), one.failures():
        raise RuntimeError("as it was")


def test_a_group_writes_on_process_0_and_every_process_waits(monkeypatch):
    from cpl_keras.training.processes import Group, join_processes
    from cpl_keras.training.planning import TrainingError

    calls = []
    monkeypatch.setattr(distributed, "barrier", lambda what: calls.append(("barrier", what)))
    monkeypatch.setattr(distributed, "broadcast", lambda what, value: f"process 0's {what}")
    monkeypatch.setattr(distributed, "check_same", lambda what, values: calls.append(values))
    write = lambda: calls.append("written") or "config"  # noqa: E731
    other = Group(distributed.ProcessGroup("localhost:1", 2, 1))
    assert not other.writes and other.count == 2
    np.testing.assert_array_equal(other.part(np.arange(6)), [3, 4, 5])
    assert other.write("run directory ready", write) is None
    assert calls == [("barrier", "run directory ready")]
    chief = Group(distributed.ProcessGroup("localhost:1", 2, 0))
    assert chief.writes and chief.count == 2
    np.testing.assert_array_equal(chief.part(np.arange(6)), [0, 1, 2])
    assert chief.write("run finished", write) == "config"
    assert calls[1:] == ["written", ("barrier", "run finished")]
    assert other.decide("stop", None) == "process 0's stop"
    other.agree("the run", dict, {"epochs": 2})
    assert calls[-1] == {"epochs": 2}

    # a collective that fails becomes one line; the package's errors pass as they are
    monkeypatch.setenv("CPL_KERAS_PEER_TIMEOUT_S", "0")
    monkeypatch.setattr(heartbeats, "BEAT_S", 0.01)
    with pytest.raises(distributed.DistributedError, match="^the process group failed: reset$"):
        with other.failures():
            raise RuntimeError("reset\nstack")
    with pytest.raises(TrainingError, match="^bad file$"), other.failures():
        raise TrainingError("bad file")

    # no KERAS_DISTRIBUTION_* variables: one process; set, they need data parallelism
    for name in distributed.ENVIRONMENT:
        monkeypatch.delenv(name, raising=False)
    assert join_processes(data_parallel=False).count == 1
    for name, value in _group_env(1, 0).items():
        monkeypatch.setenv(name, value)
    with pytest.raises(TrainingError, match="needs --data-parallel"):
        join_processes(data_parallel=False)


#: A group of one process, joined for real: the coordination service's
#: key-value store and barrier (a private JAX handle), the text of a missing
#: key, Keras's shared seed, and ``alone`` through the public distribution API.
GROUP_OF_ONE = """
import json, sys
import keras
from keras.src.utils import rng_utils
from cpl_keras import distributed, heartbeats
from cpl_keras.training.processes import join_processes
processes = join_processes(data_parallel=True)
out = dict(writes=processes.writes, part=processes.part([0, 1]), count=processes.count,
           written=processes.write("w", lambda a: a + 1, 1),
           decided=processes.decide("stop", "early stopping"),
           gathered=distributed.gather("g", {"a": 1}),
           missing=heartbeats._try_get(distributed._state["client"], "cpl_keras/none"),
           seed=rng_utils.get_random_seed() is not None)
processes.agree("the run", dict, {"a": 1})
keras.distribution.set_distribution(keras.distribution.DataParallel())
with processes.alone():
    out["alone"] = keras.distribution.distribution() is None
out["after"] = type(keras.distribution.distribution()).__name__
print(json.dumps(out))
"""


def test_a_group_of_one_process_joins_agrees_writes_and_saves_alone():
    with _coordinator_port() as port:
        environ = {**os.environ, "KERAS_BACKEND": "jax", **_group_env(port, 0),
                   "KERAS_DISTRIBUTION_NUM_PROCESSES": "1"}
        result = subprocess.run([sys.executable, "-c", GROUP_OF_ONE], env=environ,
                                capture_output=True, text=True, timeout=TIMEOUT_S, cwd=REPO)
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout.splitlines()[-1]) == {
        "writes": True, "part": [0, 1], "count": 1, "written": 2, "decided": "early stopping",
        "gathered": [{"a": 1}], "missing": None, "seed": True, "alone": True,
        "after": "DataParallel"}


def test_train_py_group_arguments_fail_in_one_line(fixture52, tmp_path):
    cases = [(["--coordinator", "localhost:1"], "go together"),
             (["--coordinator", "localhost:1", "--num-processes", "2", "--process-id", "0"],
              "--data-parallel"),
             (["--coordinator", "localhost:1", "--num-processes", "2", "--process-id", "2",
               "--data-parallel"], "is not a process of")]
    for extra, message in cases:
        argv, environ = train_py(*ARGS, "--data", fixture52, "--run-dir",
                                 str(tmp_path / "run"), *extra, cache=None)
        result = subprocess.run(argv, env=environ, capture_output=True, text=True,
                                timeout=TIMEOUT_S)
        assert result.returncode == 2, result.stderr
        assert len(result.stderr.strip().splitlines()) == 1 and message in result.stderr
        assert not os.path.exists(tmp_path / "run")


# ---------------------------------------------------------------------------
# Two processes against one
# ---------------------------------------------------------------------------
@pytest.fixture(scope="module")
def compared_runs(fixture52, tmp_path_factory):
    """The same 2-epoch run on 1 device, on 2 forced devices of one process,
    and in 2 local processes of one device each: their run directories."""
    root = tmp_path_factory.mktemp("compared")
    cache = None  # (the session's)
    runs = {name: str(root / name) for name in ("one", "two_devices", "two_processes")}
    for name, extra, env in (("one", [], {"XLA_FLAGS": XLA_FLAGS}),
                             ("two_devices", ["--data-parallel"], {"XLA_FLAGS": XLA_FLAGS +
                              " --xla_force_host_platform_device_count=2"})):
        argv, environ = train_py(*ARGS, "--data", fixture52, "--epochs", "2", *extra,
                                 "--run-dir", runs[name], cache=cache, env=env)
        result = subprocess.run(argv, env=environ, capture_output=True, text=True,
                                timeout=TIMEOUT_S)
        assert result.returncode == 0, result.stderr
    logs = root / "logs"
    logs.mkdir()
    group = _start_group(str(logs), cache, [fixture52, fixture52], runs["two_processes"], 2)
    outputs = [_wait(process) for process in group]
    for status, text in outputs:
        assert status == 0, text
    return runs, outputs


@pytest.mark.slow
def test_two_processes_train_one_model_as_one_process_does(compared_runs):
    runs, outputs = compared_runs
    config = json.load(open(os.path.join(runs["two_processes"], "config.json")))
    assert (config["num_devices"], config["num_processes"], config["status"]) == (2, 2, "finished")
    reference = read_log(runs["one"])
    for name in ("two_devices", "two_processes"):
        rows = read_log(runs[name])
        assert len(rows) == len(reference) == 2
        for row, expected in zip(rows, reference):
            for key in ("loss", "val_loss", "val_nmae"):
                assert float(row[key]) == pytest.approx(float(expected[key]), rel=1e-5, abs=1e-6)
        for (name_a, a), (name_b, b) in zip(_weights(runs[name]), _weights(runs["one"])):
            assert name_a == name_b
            np.testing.assert_allclose(a, b, atol=1e-5, rtol=1e-5)
    # each process said the same last line; the run directory was written once
    assert _lines(outputs[0][1])[-1] == _lines(outputs[1][1])[-1]
    assert os.path.isfile(os.path.join(runs["two_processes"], "model.keras"))


def test_processes_with_unequal_steps_stop_before_training(fixture52, fixture60, tmp_path):
    group = _start_group(str(tmp_path), None, [fixture52, fixture60],
                         str(tmp_path / "run"), 2)
    for status, text in (_wait(process) for process in group):
        assert status == 2, text
        lines = _lines(text)
        assert len(lines) == 1 and "training steps per epoch is 8 on process 0, 10 on " \
                                   "process 1" in lines[0], text
    assert not os.path.exists(tmp_path / "run" / "log.csv")


# ---------------------------------------------------------------------------
# Faults
# ---------------------------------------------------------------------------
def _when_logged(run_dir, rows, processes, timeout=TIMEOUT_S):
    """Wait until log.csv has ``rows`` epochs (while the processes run)."""
    deadline = time.monotonic() + timeout
    path = os.path.join(run_dir, "log.csv")
    while time.monotonic() < deadline:
        if os.path.exists(path) and len(read_log(run_dir)) >= rows:
            return
        assert all(p.poll() is None for p in processes), "the group ended too soon"
        time.sleep(0.05)
    raise AssertionError(f"no {rows} epochs logged within {timeout} s")


@pytest.mark.slow
def test_a_killed_or_stopped_partner_ends_the_group_and_the_same_command_resumes(
        fixture52, tmp_path):
    run_dir, cache, epochs = str(tmp_path / "run"), None, 12
    slow = ["--patience", "100"]  # (every epoch, so that there is time to stop it)

    # kill -9 of process 1: process 0 ends with one line, never waits forever
    group = _start_group(str(tmp_path), cache, [fixture52] * 2, run_dir, epochs, slow)
    _when_logged(run_dir, 1, group)
    group[1].kill()
    status0, text0 = _wait(group[0], 120)
    assert status0 == heartbeats.PARTNER_FAILED, text0
    assert "process 1 of 2 gave no sign of life" in _lines(text0)[-1]
    killed_at = len(read_log(run_dir))

    # the same command resumes the group after the last epoch; SIGTERM to
    # process 1, then (resumed again) to process 0, ends both within seconds,
    # each with one line and 130 (process 0, whose coordination service the
    # other needs, leaves last: a partner left without it was aborted, -6)
    for stopped in (1, 0):
        group = _start_group(str(tmp_path), cache, [fixture52] * 2, run_dir, epochs, slow)
        _when_logged(run_dir, killed_at + 1, group)
        group[stopped].send_signal(signal.SIGTERM)
        start = time.monotonic()
        (status0, text0), (status1, text1) = _wait(group[0], 60), _wait(group[1], 60)
        assert time.monotonic() - start < 30  # (seconds, not the heartbeats' timeout)
        assert (status0, status1) == (130, 130), (text0, text1)
        texts = {0: text0, 1: text1}
        assert "interrupted; to resume, run the same command again" in \
            _lines(texts[stopped])[-1], texts[stopped]
        assert f"process {stopped} interrupted" in _lines(texts[1 - stopped])[-1], texts
        assert f"Resuming {run_dir} after epoch {killed_at}" in text0
        rows = read_log(run_dir)
        assert len(rows) > killed_at
        assert [int(r["epoch"]) for r in rows] == list(range(1, len(rows) + 1))
        killed_at = len(rows)


def test_prediction_refuses_to_run_inside_a_group_of_several_processes(monkeypatch):
    from cpl_keras.models.inference import predict_images

    images = np.zeros((2, 32, 32, 3), np.uint8)
    monkeypatch.setitem(distributed._state, "group",
                        distributed.ProcessGroup("localhost:1", 2, 0))
    with pytest.raises(distributed.DistributedError, match="prediction runs in one process"):
        predict_images(None, images, images)
    monkeypatch.setitem(distributed._state, "group", distributed.ProcessGroup("localhost:1", 1, 0))
    with pytest.raises(AttributeError):  # (one process: on to the model, here None)
        predict_images(None, images, images)
