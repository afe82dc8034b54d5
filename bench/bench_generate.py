"""Benchmark the dataset generator: prints pairs/s.

    python bench/bench_generate.py [--pairs 2000] [--protocol cvgl] [--image-size 112] [--workers W]

Writes a throw-away dataset into a temporary directory through the same
``generate_dataset`` the CLI uses (rendering, StereoBM, HDF5 compression and
writing included) and reports the end-to-end wall-clock rate. Because other
programs may share the cores, it also reports the CPU time the generator used
(this process and its workers) and the load average, and the rate that CPU
time corresponds to on the machine's cores if they were all free.
"""

import os
import resource
import tempfile
import time


from cpl_keras import cli  # noqa: E402
from cpl_keras.data.generate import generate_dataset  # noqa: E402
from cpl_keras.data.protocols import PROTOCOLS  # noqa: E402


def parse_args(argv=None):
    parser = cli.Parser(prog="bench/bench_generate.py", description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=cli.positive_int, default=2000)
    parser.add_argument("--protocol", default="cvgl", choices=PROTOCOLS)
    parser.add_argument("--image-size", type=cli.positive_int, default=112)
    parser.add_argument("--workers", type=cli.worker_count, default=None)
    return parser.parse_args(argv)


def main(argv=None):
    args = parse_args(argv)
    workers = args.workers or os.cpu_count()
    def cpu_seconds():
        total = 0.0
        for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN):
            usage = resource.getrusage(who)
            total += usage.ru_utime + usage.ru_stime
        return total

    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "bench.h5")
        cpu_start = cpu_seconds()
        start = time.perf_counter()
        generate_dataset(path, protocol=args.protocol, pairs=args.pairs,
                         image_size=args.image_size, workers=workers, progress=False)
        elapsed = time.perf_counter() - start
        cpu = cpu_seconds() - cpu_start
        size = os.path.getsize(path)
    rate = args.pairs / elapsed
    cores = os.cpu_count()
    print(f"protocol={args.protocol} pairs={args.pairs} image_size={args.image_size} "
          f"workers={workers} cores={cores}: {elapsed:.1f} s wall, {rate:.1f} pairs/s, "
          f"{size / args.pairs / 1024:.1f} KiB/pair")
    print(f"cpu time {cpu:.1f} s = {args.pairs / cpu:.1f} pairs per cpu-second "
          f"(~{cores * args.pairs / cpu:.0f} pairs/s on {cores} free cores); "
          f"load average {load_before:.1f} before, {os.getloadavg()[0]:.1f} after")


if __name__ == "__main__":
    cli.run(main, 'bench/bench_generate.py')
