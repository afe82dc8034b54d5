"""Benchmark the dataset generator: prints pairs/s.

    python bench/bench_generate.py [--pairs 2000] [--protocol cvgl] [--image-size 112] [--workers W]

Writes a throw-away dataset into a temporary directory through the same
``generate_dataset`` the CLI uses (rendering, StereoBM, HDF5 compression and
writing included) and reports the end-to-end rate.
"""

import argparse
import os
import sys
import tempfile
import time

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from cpl_keras.data.generate import generate_dataset  # noqa: E402
from cpl_keras.data.protocols import PROTOCOLS  # noqa: E402


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=2000)
    parser.add_argument("--protocol", default="cvgl", choices=PROTOCOLS)
    parser.add_argument("--image-size", type=int, default=112)
    parser.add_argument("--workers", type=int, default=None)
    args = parser.parse_args()
    workers = args.workers or os.cpu_count()
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "bench.h5")
        start = time.perf_counter()
        generate_dataset(path, protocol=args.protocol, pairs=args.pairs,
                         image_size=args.image_size, workers=workers, progress=False)
        elapsed = time.perf_counter() - start
        size = os.path.getsize(path)
    rate = args.pairs / elapsed
    print(f"protocol={args.protocol} pairs={args.pairs} image_size={args.image_size} "
          f"workers={workers} cores={os.cpu_count()}: {elapsed:.1f} s, {rate:.1f} pairs/s, "
          f"{size / args.pairs / 1024:.1f} KiB/pair")


if __name__ == "__main__":
    main()
