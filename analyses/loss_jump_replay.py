"""One epoch of a run replayed step by step: which pairs and which predicted
values make its training loss jump (the fair fight's MTL-CPL-A InceptionV3
seed 1, epoch 21: a mean loss of 448.0 after 14.3).

    python analyses/loss_jump_replay.py --run-dir '~/cpl-runs/replay/cpl-a-s1' \\
        --data '~/cpl-runs/data/cvgl_2000_112px_s0_v3.0.h5' \\
        --log paper_results/fair-fight/inception/runs/cvgl_cpl-a-s1/log.csv

``RUN`` is the run trained again by its published command and stopped
(SIGTERM) once the epoch before the replayed one was checkpointed
(``backup/state.json``: that epoch; its checkpoint holds the weights and the
optimizer's state). The replay:

1. checks that the run repeats the published ``--log`` to the last digit
   over every epoch it has (every logged value but the wall time and the
   load; training is deterministic on one machine kind), and refuses (one
   line) a run that does not;
2. loads the checkpoint into the run's model, compiled as ``train.py`` does,
   and serves the next epoch's batches in the order ``train.py`` would
   (``StereoSequence``: the order depends only on the seed and the epoch);
3. for each batch: the model's outputs on each pair in training mode with
   the weights of that step (a stateless call: nothing is updated), then
   the training step itself (``train_on_batch``: the same compiled step as
   ``fit``), whose loss is the batch's;
4. writes ``--out`` (``.md`` and ``.json``): the epoch's loss replayed
   against the log's, the batches with the largest losses, and the pairs
   with the largest errors of the projected point X, with their predicted
   disparity, fy, fx and baseline against the truth and the graph's floors.

The figures are the replay's; what they say of the jump is the page's
reading of them.
"""

from __future__ import annotations

import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import numpy as np  # noqa: E402

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
OUT = os.path.join(REPO, "paper_results", "fair-fight", "loss-jump-replay")
#: The predicted values shown beside each pair's point error.
SHOWN = ("disparity", "fy", "fx", "baseline", "pitch", "X", "Y", "Z")
#: How many batches and pairs the page lists.
TOP = 10
#: A predicted disparity within this share above the graph's floor is "at the floor".
FLOOR_MARGIN = 0.01


def _error(message):
    from cpl_keras.training_options import TrainingError

    return TrainingError(message)


def check_repeats(run_dir, log_path):
    """The run's training state (``state.epoch``: the epochs it has
    completed), after checking that its log repeats the published log over
    all of them (TrainingError, one line)."""
    from cpl_keras.runs import read_log
    from cpl_keras.training.state import read_state

    import plateau_progress  # (analyses/plateau_progress.py: ``repeats``)

    state = read_state(run_dir)
    epoch = state.epoch
    if epoch < 1 or state.checkpoint is None:
        raise _error(f"{run_dir}: no checkpoint to replay from (train it first, and stop it "
                     "after the epoch before the one to replay)")
    rows = read_log(os.path.join(run_dir, "log.csv"))[:epoch]
    found = plateau_progress.repeats(rows, read_log(log_path))
    if found is None or found["epochs"] < epoch:
        same = 0 if found is None else found["epochs"]
        raise _error(f"{run_dir} repeats {log_path} over {same} of its {epoch} epochs: not the "
                     "published run (another machine kind or code?), so its next epoch is no "
                     "replay")
    return state


def load_for_replay(run_dir, data, state):
    """``(model, sequence, config)``: the run's model compiled as train.py
    compiles it, its last checkpoint (``state``'s) loaded (weights and
    optimizer), and its training batches in the order of the next epoch."""
    from cpl_keras import models, runs
    from cpl_keras.data.storage import StereoFile
    from cpl_keras.datasets import load_split, targets_from_labels
    from cpl_keras.training.checkpointing import load_checkpoint
    from cpl_keras.training.sequence import StereoSequence

    config = runs.read_run_config(run_dir)
    training = config.training
    if training.target_scaling == "std" or training.data_parallel:
        raise _error(f"{run_dir}: the replay serves runs without target scaling or data "
                     "parallelism")
    model = models.build_from_config(config.variant, config.build, read_backbone_weights=False)
    models.compile_model(model, training)
    load_checkpoint(model, run_dir, state.checkpoint)
    with StereoFile(data) as f:
        targets = targets_from_labels(f.labels, as_released=config.model.as_released)
    split = load_split(os.path.join(run_dir, runs.SPLIT))
    sequence = StereoSequence(data, split["train"], targets=targets,
                              batch_size=config.device_batch_size, shuffle=True,
                              seed=training.seed, augment=training.augment)
    sequence.set_epoch(state.epoch)
    return model, sequence, config


def replay_epoch(model, sequence):
    """Each batch's training loss (the step's own) and each pair's outputs
    with the weights of its step: ``{"batches": [...], "pairs": {...}}``."""
    batches, pairs = [], {"index": [], "batch": [], "pred": {}, "truth": {}}
    for number in range(len(sequence)):
        x, y = sequence[number]
        trainable = [v.value for v in model.trainable_variables]
        frozen = [v.value for v in model.non_trainable_variables]
        outputs, _ = model.stateless_call(trainable, frozen, x, training=True)
        if not isinstance(outputs, dict):
            outputs = dict(zip(model.output_names, outputs))
        logs = model.train_on_batch(x, y, return_dict=True)
        indices = [int(i) for i in sequence.batch_indices(number)]
        batches.append({"batch": number, "pairs": len(indices),
                        **{k: float(v) for k, v in logs.items()}})
        pairs["index"] += indices
        pairs["batch"] += [number] * len(indices)
        for name, value in outputs.items():
            pairs["pred"].setdefault(name, []).extend(np.asarray(value).reshape(-1).tolist())
            pairs["truth"].setdefault(name, []).extend(np.asarray(y[name]).reshape(-1).tolist())
    return {"batches": batches, "pairs": pairs}


def summarise(replayed, epoch, log_rows, floors, smallest):
    """The page's figures: the epoch's loss replayed (sample-weighted mean
    of the steps' losses) against the log's, the batches by loss, the pairs
    by X's error with their predicted values, and how the pairs of a large
    X error stand to the graph's floors and the smallest training labels
    (``smallest``: parameter -> its smallest training value)."""
    batches, pairs = replayed["batches"], replayed["pairs"]
    weights = np.array([b["pairs"] for b in batches], np.float64)
    losses = np.array([b["loss"] for b in batches], np.float64)
    pred = {k: np.asarray(v, np.float64) for k, v in pairs["pred"].items()}
    truth = {k: np.asarray(v, np.float64) for k, v in pairs["truth"].items()}
    error = np.abs(pred["X"] - truth["X"])
    order = np.argsort(-error)
    large = error > 10 * np.median(error)
    by_loss = sorted(batches, key=lambda b: -b["loss"])[:TOP]
    floor = float(floors.get("disparity", 0.0))
    at_floor = pred["disparity"] <= floor * (1 + FLOOR_MARGIN)
    batch_of = np.asarray(pairs["batch"])
    floored = sorted({int(b) for b in batch_of[at_floor]})
    elsewhere = ~np.isin(batch_of, floored)
    logged = {int(row["epoch"]): row for row in log_rows}
    return {
        "epoch": epoch, "log_loss": logged[epoch]["loss"],
        "log_loss_before": logged[epoch - 1]["loss"] if epoch > 1 else None,
        "replay_loss": float(np.sum(weights * losses) / np.sum(weights)),
        "log_X_mae": logged[epoch].get("X_mae", logged[epoch].get("X_loss")),
        "replay_X_mae": float(np.mean(error)),
        "batches": len(batches),
        "loss_share_top_batches": float(np.sum([b["loss"] * b["pairs"] for b in by_loss])
                                        / np.sum(weights * losses)),
        "top_batches": [{k: b[k] for k in ("batch", "pairs", "loss") if k in b}
                        | {"X": b.get("X_mae", b.get("X_loss")),
                           "at_floor": int(np.sum(at_floor[batch_of == b["batch"]]))}
                        for b in by_loss],
        "at_floor": int(at_floor.sum()), "at_floor_batches": floored,
        "at_floor_true": [float(truth["disparity"][at_floor].min()),
                          float(truth["disparity"][at_floor].max())] if at_floor.any() else None,
        "at_floor_batches_loss_share": float(sum(b["loss"] * b["pairs"] for b in batches
                                                 if b["batch"] in floored)
                                             / np.sum(weights * losses)),
        "other_batches_max_loss": max((b["loss"] for b in batches if b["batch"] not in floored),
                                      default=None),
        "smallest_disparity_elsewhere": float(pred["disparity"][elsewhere].min())
        if elsewhere.any() else None,
        "pairs": len(error), "median_X_error": float(np.median(error)),
        "large": int(large.sum()),
        "X_error_share_large": float(error[large].sum() / error.sum()),
        "floors": dict(floors), "smallest_training": dict(smallest),
        "large_below_smallest": {name: int(np.sum(pred[name][large] < smallest[name]))
                                 for name in smallest},
        "large_below_truth_half": {name: int(np.sum(pred[name][large] < truth[name][large] / 2))
                                   for name in smallest},
        "top_pairs": [{"pair": pairs["index"][i], "batch": pairs["batch"][i],
                       "X_error": float(error[i]),
                       **{name: [float(pred[name][i]), float(truth[name][i])]
                          for name in SHOWN if name in pred}}
                      for i in order[:TOP]],
    }


def _cell(value, digits=3):
    if value is None:
        return "-"
    return f"{value:,.{digits}f}" if abs(value) < 1e4 else f"{value:,.0f}"


def markdown(found, command):
    """The page, from ``summarise``'s figures."""
    from cpl_keras import files

    floors = ", ".join(f"{k} {v:g}" for k, v in found["floors"].items())
    smallest = ", ".join(f"{k} {v:.3g}" for k, v in found["smallest_training"].items())
    lines = [files.generated_line(command), "",
             f"# Epoch {found['epoch']} replayed step by step", "",
             f"The run trained again by its published command repeats the published log to "
             f"the last digit over epochs 1-{found['epoch'] - 1}; epoch {found['epoch']} is "
             "replayed from its checkpoint one training step at a time, each pair's outputs "
             "read in training mode with the weights of its step.", "",
             "| | published log | replay |", "|---|---|---|",
             f"| epoch {found['epoch']}'s mean training loss | {_cell(found['log_loss'])} | "
             f"{_cell(found['replay_loss'])} |",
             f"| epoch {found['epoch']}'s X MAE | {_cell(found['log_X_mae'])} | "
             f"{_cell(found['replay_X_mae'])} |", "",
             f"The epoch before had a mean loss of {_cell(found['log_loss_before'])}. Its "
             f"{TOP} largest of {found['batches']} batch losses carry "
             f"{found['loss_share_top_batches']:.2f} of the epoch's loss:", "",
             "| batch | pairs | loss | X MAE | disparities at the floor |", "|---|---|---|---|---|"]
    lines += [f"| {b['batch']} | {b['pairs']} | {_cell(b['loss'])} | {_cell(b['X'])} | "
              f"{b['at_floor']} |" for b in found["top_batches"]]
    batches = ", ".join(map(str, found["at_floor_batches"])) or "none"
    truths = found["at_floor_true"]
    lines += ["", f"{found['at_floor']} pairs had their disparity predicted at the graph's "
              f"floor ({found['floors'].get('disparity', 0):g} px, within "
              f"{FLOOR_MARGIN:.0%}), in batches {batches}"
              + (f", against true disparities of {_cell(truths[0])}-{_cell(truths[1])} px"
                 if truths else "")
              + f"; those batches carry {found['at_floor_batches_loss_share']:.3f} of the "
              f"epoch's loss, and no other batch's loss exceeds "
              f"{_cell(found['other_batches_max_loss'])}. In every other batch the smallest "
              f"predicted disparity was {_cell(found['smallest_disparity_elsewhere'])} px."]
    lines += ["", f"Of the epoch's {found['pairs']} pairs, {found['large']} have an error of X "
              f"above ten times the median ({_cell(found['median_X_error'])} m); they carry "
              f"{found['X_error_share_large']:.2f} of the epoch's summed X error. Of them, "
              "predicted below the smallest training value: "
              + ", ".join(f"{k} {v}" for k, v in found["large_below_smallest"].items())
              + "; predicted below half their own truth: "
              + ", ".join(f"{k} {v}" for k, v in found["large_below_truth_half"].items())
              + f". The graph's floors: {floors}; the smallest training values: {smallest}.",
              "", f"The {TOP} pairs with the largest X error (predicted / true):", "",
              "| pair | batch | X error (m) | " + " | ".join(SHOWN) + " |",
              "|---|---|---|" + "---|" * len(SHOWN)]
    for p in found["top_pairs"]:
        lines.append(f"| {p['pair']} | {p['batch']} | {_cell(p['X_error'], 1)} | "
                     + " | ".join(f"{_cell(p[n][0])} / {_cell(p[n][1])}" if n in p else "-"
                                  for n in SHOWN) + " |")
    return "\n".join(lines) + "\n"


def regenerate(page_path):
    """The committed page, again from its JSON twin."""
    from cpl_keras import files

    command, found = files.page_source(page_path)
    return markdown(found, command)


def main(argv=None):
    from cpl_keras import cli, files
    from cpl_keras.runs import read_log

    parser = cli.Parser(prog="analyses/loss_jump_replay.py",
                        description=__doc__.split("\n\n")[0])
    parser.add_argument("--run-dir", required=True, type=cli.path,
                        help="the run trained again and stopped after the epoch before")
    parser.add_argument("--data", required=True, type=cli.path, help="its dataset file")
    parser.add_argument("--log", required=True, type=cli.path, help="the published log.csv")
    parser.add_argument("--out", default=OUT, help="the page's path, without .md")
    args = parser.parse_args(argv)
    for name in ("run_dir", "data", "log"):  # ('~/cpl-runs/...': the page names no machine's)
        setattr(args, name, os.path.expanduser(getattr(args, name)))
    state = check_repeats(args.run_dir, args.log)
    model, sequence, config = load_for_replay(args.run_dir, args.data, state)
    try:
        replayed = replay_epoch(model, sequence)
    finally:
        sequence.close()
    train = sequence.indices
    smallest = {name: float(np.min(sequence.targets[name][train]))
                for name in ("disparity", "fy") if name in sequence.targets}
    found = summarise(replayed, state.epoch + 1, read_log(args.log),
                      config.model.floors or {}, smallest)
    command = cli.command_line("analyses/loss_jump_replay.py", argv)
    files.write_page(args.out + ".md", markdown(found, command), found)
    with files.atomic_path(args.out + "-pairs.npz") as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, index=np.asarray(replayed["pairs"]["index"], np.int64),
                                batch=np.asarray(replayed["pairs"]["batch"], np.int32),
                                **{f"pred_{k}": np.asarray(v, np.float32)
                                   for k, v in replayed["pairs"]["pred"].items()},
                                **{f"true_{k}": np.asarray(v, np.float32)
                                   for k, v in replayed["pairs"]["truth"].items()})
    print(args.out + ".md")
    return 0


if __name__ == "__main__":
    from cpl_keras import cli

    cli.run(main, "analyses/loss_jump_replay.py")
