#!/usr/bin/env bash
# The `paper-gpu` reproduction preset on a lent GPU machine, packed for the
# trip back; or the same plan on this CPU at tiny scale (--dry-run).
#
#   bash bench/paper_gpu.sh --fetch-wheels      # here, once: the wheels the GPU machine
#                                               # lacks (Keras, namex, optree) into .whl/
#                                               # (git-ignored by .gitignore)
#   bash bench/paper_gpu.sh "$OUT"              # there (device run, carry [".whl"])
#   bash bench/paper_gpu.sh runs/dry --dry-run  # here: every step of the plan, tiny
#
# The plan (cpl_keras/reproduce/presets.py, PRESETS["paper-gpu"]): 20,000 cvgl pairs
# rendered on every CPU core of the machine, the real sets, MTL-CPL-A then
# MTL-Baseline with the paper's InceptionV3 towers (112 px, batch 16), each
# to early stopping or to 150 s of training, whichever comes first; each run
# is published the moment it ends. The reproduction is sent Ctrl-C at
# REPRODUCE_LIMIT seconds (default 480) so that whatever finished is packed
# before the machine's ten-minute limit.
#
# What lands in OUT (the device returns at most 8 files): paper-gpu.tar.gz
# (paper_results/paper-gpu: REPORT.md, the tables, every finished run's log,
# curves, config, split and predictions; no weights), reproduce.log and
# machine.txt. Back here:
#   tar xzf OUT/paper-gpu.tar.gz -C paper_results/
#   python -m cpl_keras.reproduce --from-predictions paper_results/paper-gpu
set -euo pipefail
cd "$(dirname "$0")/.."

if [ "${1:-}" = "--fetch-wheels" ]; then
    keras=$(python3 -c 'from importlib.metadata import version; print(version("keras"))')
    python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 \
        --implementation cp --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 \
        --platform manylinux2014_x86_64 -d .whl "keras==$keras" namex optree
    ls -l .whl
    exit 0
fi

out=${1:?usage: bash bench/paper_gpu.sh OUT [--dry-run] | --fetch-wheels}
mode=${2:-}
mkdir -p "$out"
# the reproduction's folders under OUT, so that an interrupted one is resumed
# by the same command (its own resume line names them) and removed once packed
work="$out/in-progress"
mkdir -p "$work"
export KERAS_BACKEND=jax PYTHONUNBUFFERED=1
if [ -d .whl ] && [ "$mode" != "--dry-run" ]; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
        --target /tmp/site .whl/*.whl
    export PYTHONPATH=/tmp/site${PYTHONPATH:+:$PYTHONPATH}
fi
{
    date -u
    nproc
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv 2>/dev/null \
        || echo "no nvidia-smi"
    python3 -c 'import jax, keras; print("jax", jax.__version__, jax.devices(), "keras", keras.__version__)'
} > "$out/machine.txt" 2>&1
cat "$out/machine.txt"

args=(--preset paper-gpu --out "$work/paper-gpu" --data-dir "$work/data" --runs-dir "$work/runs")
limit=${REPRODUCE_LIMIT:-480}
if [ "$mode" = "--dry-run" ]; then
    # The same plan at tiny scale on a CPU: InceptionV3 at its smallest input,
    # a budget short enough that the first epoch spends it.
    args+=(--allow-cpu --pairs 120 --image-size 75 --crops 24 --chessboard-crops 1
           --geometric-max 10 --run-budget 1 --workers 2)
    limit=${REPRODUCE_LIMIT:-1500}
fi
start=$(date +%s)
# --foreground: the reproduction stays in the terminal's process group, so a
# Ctrl-C reaches it (it stops with one line and exit 130, and what finished
# is still packed below); tee -i outlives the Ctrl-C to log that line.
set +e
timeout --foreground -s INT -k 30 "$limit" python3 -m cpl_keras.reproduce "${args[@]}" 2>&1 \
    | tee -i "$out/reproduce.log"
status=${PIPESTATUS[0]}
set -e
echo "reproduce: exit $status after $(( $(date +%s) - start )) s" | tee -a "$out/machine.txt"
if [ -n "$(find "$work/paper-gpu" -type f -print -quit 2>/dev/null)" ]; then
    tar czf "$out/paper-gpu.tar.gz" -C "$work" paper-gpu
    tar tzf "$out/paper-gpu.tar.gz" | sed 's/^/packed: /'
else
    echo "packed nothing: the reproduction wrote no results yet"
fi
if [ "$status" = 130 ] || [ "$status" = 143 ]; then
    # (interrupted: the same command goes on from what $work holds)
    echo "interrupted; to resume, run the same command again: bash bench/paper_gpu.sh $out $mode"
else
    rm -rf "$work"
fi
exit "$status"
