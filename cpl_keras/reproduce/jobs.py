"""Stage 2 of the reproduction: training every run of the settings, one at
a time or several in processes of their own, each published the moment it
ends (and restored from its published record on another machine)."""

from __future__ import annotations

import os

from cpl_keras import evaluation, published, runs, training
from cpl_keras.reproduce.plan import run_jobs
from cpl_keras.reproduce.presets import PROG, log, towers_weights
from cpl_keras.training import parallel, planning

# ---------------------------------------------------------------------------
# Stage 2: training
# ---------------------------------------------------------------------------
def training_arguments(config, run_dir, job):
    """The keyword arguments of ``training.train`` for ``job`` (a ``Job``) of
    ``config`` (the ``Settings``)."""
    return dict(
        variant=job.variant, run_dir=run_dir, epochs=config.epochs,
        batch_size=config.batch_size, backbone=config.backbone, split=job.split,
        as_released=job.released, seed=job.seed, patience=config.patience,
        time_budget_s=config.run_budget_s, disparity_ceiling=config.disparity_ceiling,
        bn_statistics=config.bn_statistics, monitor=config.monitor,
        weight_ema=config.weight_ema, backbone_weights=towers_weights(config, job.variant),
    )


def train_all(config, paths, runs_dir, seed, jobs=1, out_dir=None, train=True):
    """Stage 2: every run of ``config`` (the ``Settings``); returns ``{table key: {seed: [run dirs]}}``.
    ``jobs`` > 1 trains that many runs at a time, each in its own process
    (``train_parallel``); the runs are the same either way. With ``train``
    False nothing is trained: the runs not finished yet are left out.

    With ``out_dir``, each run is published the moment it ends
    (``publish_run``: its stored predictions, log, curves, config and split
    in ``out_dir/runs/<key>_<name>/``, no weights), and a run whose
    published record is there but whose run directory is not (another
    machine, a later rerun) is restored from it instead of trained again.
    """
    trained, pending = {}, []
    for job in run_jobs(config, seed):
        key, protocol, name = job.key, job.protocol, job.name
        run_dir = os.path.join(runs_dir, key, name)
        plan = training_arguments(config, run_dir, job)
        record = published_record(out_dir, key, name) if out_dir else None
        finished = getattr(runs.read_run_config(run_dir), "status", None) == "finished"
        if not finished and record and published.is_published(record) and \
                not (os.path.isdir(run_dir) and os.listdir(run_dir)):
            published.restore_run_dir(record, run_dir, paths[protocol])
            log(f"{key}/{name}: restored from its published record {record} (no weights)")
            finished = True
        # Refuses (TrainingError) a run directory that holds a run of other
        # settings, so a run made at another scale is never reused.
        planning.plan_run(paths[protocol], **plan)
        if not (finished or train):
            continue
        trained.setdefault(key, {}).setdefault(job.seed, []).append(run_dir)
        if finished:
            log(f"{key}/{name}: finished run found, reused")
            if record and not published.is_published(record):
                publish_run(run_dir, record, _real_paths(key, paths))
            continue
        pending.append((f"{key}/{name}", paths[protocol], plan,
                        (record, _real_paths(key, paths)) if record else None))
    if jobs > 1 and len(pending) > 1:
        publish = {label: record for label, _, _, record in pending}

        def on_finished(label, plan):
            if publish[label]:
                publish_run(plan["run_dir"], *publish[label])

        parallel.train_parallel([(label, data, plan) for label, data, plan, _ in pending],
                                jobs, on_finished=on_finished, log=log, prog=PROG)
        return trained
    for label, data, plan, publish in pending:
        log(f"training {label} ({config.backbone}, up to {config.epochs} epochs)")
        summary = training.train(data, verbose=2, **plan)
        log(training.summary_line(summary))
        if summary.config.best_epoch is None:
            raise training.TrainingError(f"{plan['run_dir']}: no epoch completed "
                                         f"({summary.config.stopped})")
        if publish:
            publish_run(plan["run_dir"], *publish)
    return trained


def published_record(out_dir, key, name):
    """Where run ``name`` of table ``key`` is published: ``out_dir/runs/<key>_<name>``."""
    return os.path.join(out_dir, "runs", f"{key}_{name}")


def _real_paths(key, paths):
    """The real sets a run of table ``key`` is evaluated on (Table 2: the cvgl runs)."""
    return list(paths.get("real") or []) if key == "cvgl" else []


def publish_run(run_dir, record, real_paths):
    """Publish a finished run at once: its outputs on its test split and on
    ``real_paths`` stored in the run directory (``evaluation.store_predictions``),
    then its published part copied to ``record`` (``published.publish_run_dir``)
    and its log and curves beside it (``published.publish_files``)."""
    evaluation.store_predictions(run_dir, real_paths)
    published.publish_run_dir(run_dir, record)
    published.publish_files(run_dir, os.path.dirname(record), os.path.basename(record))
    log(f"published {record}")
