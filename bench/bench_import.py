"""Benchmark the release importer: prints its peak memory and pairs/s.

    python bench/bench_import.py [--pairs 20000] [--dir DIR]

Writes a folder in the release's flat format (``li.npy``, ``ri.npy`` uint8
(N, 112, 112, 3), BGR, and the 13 label files; smooth images with noise, so
that compression works as on rendered frames, and the labels of 50 rigs) a
block at a time, then imports it with ``python -m cpl_keras.data.import_cvgl``
in a child process and reports the child's peak resident memory (its
``ru_maxrss``, which counts the resident set the child inherits when it is
started: this process writes the folder a small block at a time to stay
small), the wall time and pairs/s, the images' bytes in the folder and the
size of the file written. The importer reads the images a block at a time
and writes them in blocks, so its peak memory should not grow with
``--pairs``: run it at two sizes to see. ``--dir`` keeps the folder (a
second run reuses it); by default it is a temporary one.
"""

import os
import resource
import subprocess
import sys
import tempfile
import time

import numpy as np

from cpl_keras import cli  # noqa: E402
from cpl_keras.data.release_files import IMAGE_FILES, IMAGE_SIZE, LABEL_FILES  # noqa: E402

#: Pairs written at a time (few: this process must stay small, see above).
BLOCK = 100


def parse_args(argv=None):
    parser = cli.Parser(prog="bench/bench_import.py", description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=cli.positive_int, default=20000)
    parser.add_argument("--dir", help="keep the release folder here (reused when complete)")
    return parser.parse_args(argv)


def write_release(folder, n):
    """A flat release folder of ``n`` pairs (skipped when complete)."""
    done = os.path.join(folder, f"complete_{n}")
    if os.path.exists(done):
        return
    os.makedirs(folder, exist_ok=True)
    rng = np.random.default_rng(0)
    y, x = np.mgrid[0:IMAGE_SIZE, 0:IMAGE_SIZE]
    shape = (n, IMAGE_SIZE, IMAGE_SIZE, 3)
    for name in IMAGE_FILES:
        # (plain writes a block at a time: this process stays small, so the
        # importer's child does not start from a large inherited resident set)
        with open(os.path.join(folder, f"{name}.npy"), "wb") as f:
            np.lib.format.write_array_header_1_0(f, {"descr": "|u1", "fortran_order": False,
                                                     "shape": shape})
            for start in range(0, n, BLOCK):
                k = min(BLOCK, n - start)
                phase = rng.uniform(0, 6.3, (k, 1, 1, 3))
                base = 127 + 90 * np.sin(x[None, :, :, None] / 9.0 + phase) * np.cos(
                    y[None, :, :, None] / 13.0)
                f.write(np.clip(base + rng.normal(0, 6, base.shape), 0, 255)
                        .astype(np.uint8).tobytes())
    rig = rng.integers(0, 50, n)
    values = {name: rng.normal(0, 5, 50)[rig] for name in LABEL_FILES}
    values["fx"] = values["fy"] = rng.uniform(15, 120, 50)[rig]
    values["u0"] = values["v0"] = np.full(n, IMAGE_SIZE / 2)
    values["d"] = rng.normal(-11, 4, n)
    for name in LABEL_FILES:
        np.save(os.path.join(folder, f"{name}.npy"), values[name].astype(np.float64))
    with open(done, "w"):
        pass


def main(argv=None):
    args = parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.dir or os.path.join(tmp, "release")
        start = time.perf_counter()
        write_release(folder, args.pairs)
        print(f"release folder of {args.pairs} pairs ready in {time.perf_counter() - start:.1f} s "
              f"({2 * args.pairs * IMAGE_SIZE * IMAGE_SIZE * 3 / 1e9:.2f} GB of images)")
        out = os.path.join(tmp, "imported.h5")
        start = time.perf_counter()
        done = subprocess.run([sys.executable, "-m", "cpl_keras.data.import_cvgl", folder,
                               "--out", out, "--no-progress"], capture_output=True, text=True,
                              timeout=3600)
        elapsed = time.perf_counter() - start
        if done.returncode != 0:
            return cli.fail("bench/bench_import.py", f"import failed: {done.stderr.strip()}")
        peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
        size = os.path.getsize(out)
    print(f"import of {args.pairs} pairs: {elapsed:.1f} s wall, {args.pairs / elapsed:.0f} "
          f"pairs/s, peak memory {peak:.0f} MB (the child's maximum resident set), file "
          f"{size / 1e9:.2f} GB; load average {os.getloadavg()[0]:.1f}")
    return 0


if __name__ == "__main__":
    cli.run(main, "bench/bench_import.py")
