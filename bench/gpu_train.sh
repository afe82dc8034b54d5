#!/usr/bin/env bash
# Several train.py runs at once on a lent GPU machine, each published the
# moment it ends and packed for the trip back; or the same plan on this CPU
# at tiny scale (--dry-run).
#
#   bash bench/paper_gpu.sh --fetch-wheels                 # here, once: Keras, namex, optree into .whl/
#   bash bench/gpu_train.sh "$OUT" JOBS                    # there (device run, carry [".whl"])
#   bash bench/gpu_train.sh runs/gpu-dry JOBS --dry-run    # here: the same steps, tiny
#
# JOBS (bench/gpu_jobs/*.txt) names the dataset and the runs, one per line:
#   data cvgl 2000 0                   protocol, pairs, seed: rendered there on
#                                      every core under the name the presets give it
#   NAME train.py arguments ...        one run (--data and --run-dir are added)
# The runs train side by side on the one GPU (each process takes
# XLA_PYTHON_CLIENT_MEM_FRACTION of its memory, default 0.25). A run still
# training TRAIN_LIMIT seconds (default 440) after the start is sent SIGTERM
# and comes back unpublished (its log, config and curves only: weights never
# travel). A finished run is published at once (jobs.publish_run: its test
# predictions, log, curves, config and split), as a preset publishes it.
#
# What lands in OUT: runs.tar.gz (records/NAME: the published runs;
# unfinished/NAME: the small files of runs that did not finish; logs/NAME.out)
# and machine.txt (the machine, the dataset's fingerprint, each run's exit).
# Back here: tar xzf OUT/runs.tar.gz -C runs/gpu, then copy each
# records/NAME where its preset keeps its runs (paper_results/<preset>/runs/).
set -euo pipefail
cd "$(dirname "$0")/.."

out=${1:?usage: bash bench/gpu_train.sh OUT JOBS [--dry-run]}
jobs_file=${2:?usage: bash bench/gpu_train.sh OUT JOBS [--dry-run]}
mode=${3:-}
[ -f "$jobs_file" ] || { echo "gpu_train: no jobs file $jobs_file" >&2; exit 2; }
data_line=$(grep -m1 '^data ' "$jobs_file" || true)
[ "$(wc -w <<< "$data_line")" = 4 ] || {
    echo "gpu_train: $jobs_file: no line 'data PROTOCOL PAIRS SEED'" >&2; exit 2; }
grep -qvE '^(#|data |[[:space:]]*$)' "$jobs_file" || {
    echo "gpu_train: $jobs_file: no run (a line 'NAME train.py arguments')" >&2; exit 2; }
mkdir -p "$out"
start=$(date +%s)
work=$(mktemp -d)
mkdir -p "$work/data" "$work/runs" "$work/pack/records" "$work/pack/unfinished" "$work/pack/logs"
export KERAS_BACKEND=jax PYTHONUNBUFFERED=1
export XLA_PYTHON_CLIENT_MEM_FRACTION=${XLA_PYTHON_CLIENT_MEM_FRACTION:-0.25}
if [ -d .whl ] && [ "$mode" != "--dry-run" ]; then
    # A target of its own, so that bench/paper_gpu.sh may install beside it.
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
        --target /tmp/site-train .whl/*.whl
    export PYTHONPATH=/tmp/site-train${PYTHONPATH:+:$PYTHONPATH}
fi
python=python3
[ "$mode" = "--dry-run" ] && [ -x .venv/bin/python ] && python=.venv/bin/python
limit=${TRAIN_LIMIT:-440}
tiny=()
if [ "$mode" = "--dry-run" ]; then
    # The same steps at tiny scale on a CPU: the small towers, two epochs.
    tiny=(--backbone small --epochs 2)
    limit=${TRAIN_LIMIT:-600}
fi

read -r _ protocol pairs data_seed <<< "$data_line"
[ "$mode" = "--dry-run" ] && pairs=120
data="$work/data/${protocol}_${pairs}_112px_s${data_seed}_v3.0.h5"
{
    date -u
    echo "cores $(nproc)"
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv 2>/dev/null \
        || echo "no nvidia-smi"
    "$python" -c 'import jax, keras; print("jax", jax.__version__, jax.devices(), "keras", keras.__version__)'
    "$python" -m cpl_keras.data.generate --protocol "$protocol" --pairs "$pairs" \
        --seed "$data_seed" --out "$data" --no-progress
    # Compare with the same file here: equal labels make equal splits.
    "$python" - "$data" <<'EOF'
import hashlib, sys
import h5py
with h5py.File(sys.argv[1], "r") as f:
    for name in ("labels/fx", "labels/baseline", "labels/disparity", "left", "right"):
        print("sha256", name, hashlib.sha256(f[name][()].tobytes()).hexdigest()[:16])
EOF
    echo "dataset ready after $(( $(date +%s) - start )) s"
} 2>&1 | tee "$out/machine.txt"

deadline=$(( start + limit ))
pids=()
names=()
while read -r name args; do
    case "$name" in ''|'#'*|data) continue ;; esac
    names+=("$name")
    (
        set +e
        left=$(( deadline - $(date +%s) ))
        # shellcheck disable=SC2086  # the arguments are words of the jobs file
        timeout -s TERM -k 30 "$left" "$python" train.py $args "${tiny[@]}" --data "$data" \
            --run-dir "$work/runs/$name" > "$work/pack/logs/$name.out" 2>&1
        status=$?
        echo "$name: train.py exit $status after $(( $(date +%s) - start )) s"
        if [ "$status" = 0 ]; then
            "$python" -c 'import sys; from cpl_keras.reproduce.jobs import publish_run; publish_run(sys.argv[1], sys.argv[2], [])' \
                "$work/runs/$name" "$work/pack/records/$name" >> "$work/pack/logs/$name.out" 2>&1
            echo "$name: publish exit $? after $(( $(date +%s) - start )) s"
        else
            mkdir -p "$work/pack/unfinished/$name"
            for f in config.json log.csv curves.png train_stats.json backup/state.json; do
                [ -f "$work/runs/$name/$f" ] && cp "$work/runs/$name/$f" "$work/pack/unfinished/$name/"
            done
        fi
    ) >> "$out/machine.txt" 2>&1 &
    pids+=($!)
done < "$jobs_file"
echo "training ${names[*]}" | tee -a "$out/machine.txt"
for pid in "${pids[@]}"; do wait "$pid" || true; done
nvidia-smi --query-gpu=memory.used --format=csv 2>/dev/null >> "$out/machine.txt" || true
echo "done after $(( $(date +%s) - start )) s" | tee -a "$out/machine.txt"
tar czf "$out/runs.tar.gz" -C "$work/pack" records unfinished logs
tar tzf "$out/runs.tar.gz" | grep -v '/$' | sed 's/^/packed: /'
cat "$out/machine.txt"
rm -rf "$work"
