"""The plateau amendment's six runs as they stand
(paper_results/fair-fight/protocol-plateau.md): which have started, how far
each has trained, how long since its validation monitor last improved and
how fast it is still falling; a published run's test columns beside its
50-epoch record's.

    python analyses/plateau_progress.py          # writes inception-plateau/progress.{md,json}
    python analyses/plateau_progress.py --print  # the page on stdout, nothing written

A run's state comes from three places: its ledger of starts, committed
beside its record (``run_starts.py``); its run directory in ``--home``
(``~/cpl-runs``, outside the work tree: ``backup/state.json`` and
``log.csv``) while it trains; its published record once it has ended. The
page is a snapshot, dated, of what this machine holds: it decides nothing
(the verdicts page does, from the published runs). A run's status is one of
"not started", "training" (a live process claims it), "interrupted" (its
run directory waits for the same command), "lost" (a ledger with starts and
no run directory here) and "published". The slope is the least-squares
slope of the monitor over the last ``WINDOW`` logged epochs, times
``WINDOW``, over their mean: the change in 10 epochs as a share of the
monitor (negative: still falling).
"""

from __future__ import annotations

import datetime
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import fair_fight  # noqa: E402
import run_starts  # noqa: E402

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
OUT = os.path.join(REPO, "paper_results", "fair-fight")
#: The epochs of the slope's window.
WINDOW = 10
#: The monitor every run keeps its best epoch by (the default, val_nmae).
MONITOR = "val_nmae"


def slope(values):
    """The least-squares slope of ``values`` (one per epoch) times their
    count, over their mean; None below two values or at a zero mean."""
    n = len(values)
    if n < 2:
        return None
    mean_x, mean_y = (n - 1) / 2, sum(values) / n
    num = sum((i - mean_x) * (v - mean_y) for i, v in enumerate(values))
    den = sum((i - mean_x) ** 2 for i in range(n))
    return None if mean_y == 0 else num / den * n / mean_y


#: A log's columns that are the machine's (its clock and load), not the training's.
MACHINE_COLUMNS = ("wall_time_s", "load_average")


def repeats(rows, earlier):
    """``{"epochs", "of"}``: how many epochs from the first the log ``rows``
    repeats of the ``earlier`` log to the last digit (every column both
    have but the machine's), of the epochs both have; None without one."""
    if not rows or not earlier:
        return None
    both = min(len(rows), len(earlier))
    same = 0
    for row, old in zip(rows[:both], earlier[:both]):
        keys = (set(row) & set(old)) - set(MACHINE_COLUMNS)
        if any(row[k] != old[k] for k in keys):
            break
        same += 1
    return {"epochs": same, "of": both}


def run_progress(arm, seed, home, out):
    """One run's entry: its status, epochs, best monitor (1-based epoch),
    epochs since it, the slope, the monitor at the amendment's equal epochs,
    how much of the 50-epoch run of its arm and seed it repeats and its
    ledger's counts."""
    from cpl_keras import files
    from cpl_keras.runs import read_log
    from cpl_keras.training.state import read_state

    name = f"cvgl_{arm}-s{seed}"
    record = os.path.join(out, "inception-plateau", "runs", name)
    run_dir = os.path.join(home, fair_fight.PLATEAU["runs_dir"], "inception", f"{arm}-s{seed}")
    ledger = run_starts.read(record)
    entry = {"arm": arm, "seed": seed, **run_starts.summary(ledger["starts"])}
    entry["machines"] = len(entry["machines"])
    if os.path.isdir(record):
        config = files.read_json(os.path.join(record, "config.json"))
        log, status = os.path.join(record, "log.csv"), "published"
        epochs, best_epoch = config.get("epochs_run"), config.get("best_epoch")
        stopped, wait, best = config.get("stopped"), None, config.get("best_score")
    elif os.path.isdir(run_dir):
        state = read_state(run_dir)
        log = os.path.join(run_dir, "log.csv")
        status = "training" if fair_fight.claimed(run_dir) else "interrupted"
        epochs, stopped, wait, best = state.epoch, state.stopped, state.wait, state.best
        best_epoch = None if state.best_epoch is None else state.best_epoch + 1
    else:
        return dict(entry, status="lost" if ledger["starts"] else "not started")
    logged = read_log(log) if os.path.isfile(log) else []
    rows = {int(row["epoch"]): float(row[MONITOR]) for row in logged}
    last = [rows[e] for e in sorted(rows)[-WINDOW:]]
    fifty = os.path.join(out, "inception", "runs", name, "log.csv")
    if status == "published":
        entry["test"] = test_nmae(out, arm, seed)
    return dict(entry, repeats_fifty=repeats(logged, read_log(fifty) if os.path.isfile(fifty)
                                             else []),
                status=status, epochs=epochs, stopped=stopped, wait=wait,
                best_epoch=best_epoch, best=best,
                slope=slope(last) if len(last) == WINDOW else None,
                at=({str(e): rows[e] for e in fair_fight.PLATEAU["equal_epochs"] if e in rows}))


def test_nmae(out, arm, seed):
    """A published run's NMAE per column on its seed's test pairs, at its
    kept epoch, beside the 50-epoch record of the same arm and seed on the
    same pairs (``{"plateau": {...}, "fifty": {...}}``; "fifty" is None
    without that record). The truths come from ``fair_fight_rows``."""
    import fair_fight_rows

    from cpl_keras import files, metrics
    from cpl_keras.camera import PARAMETERS

    def columns(towers):
        (raw,) = fair_fight_rows.rows(os.path.join(out, towers, "runs"), arm, [seed]).values()
        return {p: metrics.nmae(raw["truth"][p], raw["pred"][p]) for p in PARAMETERS}

    found = {"plateau": columns("inception-plateau"), "fifty": None}
    fifty = os.path.join(out, "inception", "runs", f"cvgl_{arm}-s{seed}")
    if os.path.isdir(fifty):
        found.update(fifty=columns("inception"), fifty_best_epoch=files.read_json(
            os.path.join(fifty, "config.json"))["best_epoch"])
    return found


def progress(home, out):
    """Every run of the amendment, in its command's order, with the date."""
    now = datetime.datetime.now(datetime.timezone.utc)
    return {"as_of": now.strftime("%Y-%m-%d %H:%M"),
            "patience": fair_fight.PLATEAU["patience"], "epoch_cap": fair_fight.PLATEAU["epochs"],
            "window": WINDOW, "monitor": MONITOR,
            "runs": [run_progress(arm, seed, home, out) for seed in fair_fight.PROTOCOL_SEEDS
                     for arm in fair_fight.PLATEAU["arms"]]}


def _number(value, digits=3, percent=False):
    if value is None:
        return "-"
    return f"{100 * value:+.0f} %" if percent else f"{value:.{digits}f}"


def _repeats(found):
    return "-" if found is None else f"{found['epochs']} of {found['of']}"


def markdown(found, command):
    """The page: the runs' table, then the monitor at equal epochs."""
    from cpl_keras import files

    published = sum(r["status"] == "published" for r in found["runs"])
    started = sum(r["status"] != "not started" for r in found["runs"])
    lines = [files.generated_line(command), "",
             "# The plateau amendment's runs as they stand", "",
             f"As of {found['as_of']} UTC: {started} of {len(found['runs'])} runs started, "
             f"{published} published. From the ledgers of starts, the run directories in "
             "`~/cpl-runs/` and the published records, as this machine held them; it "
             "decides nothing (the verdicts page does, once the runs are published). "
             f"A run ends when its validation monitor (`{found['monitor']}`) has not "
             f"improved for {found['patience']} epochs, or at {found['epoch_cap']} epochs. "
             f"Slope: the least-squares change of the monitor over the last {found['window']} "
             "epochs, as a share of its mean (negative: still falling).", "",
             "The 50-epoch run: how many of its epochs, from the first, the run repeats "
             "to the last digit (every logged value but the wall time and the load); "
             "training is deterministic, so a run to a plateau that repeats all 50 is the "
             "50-epoch run trained on.", "",
             "| run | seed | status | epochs | best monitor (epoch) | epochs since best "
             "| slope per 10 epochs | the 50-epoch run | starts (resumed) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in found["runs"]:
        name = fair_fight.NAMES[r["arm"]]
        if "epochs" not in r:
            lines.append(f"| {name} | {r['seed']} | {r['status']} | - | - | - | - | - | "
                         f"{r['starts']} ({r['resumed']}) |")
            continue
        status = r["status"] + (f" ({r['stopped']})" if r.get("stopped") else "")
        # A run that has not finished its first epoch has no best and no wait yet.
        scored = r["best_epoch"] is not None
        since = (f"{r['wait']} of {found['patience']}" if scored and r["wait"] is not None
                 else "-")
        best = f"{_number(r['best'])} ({r['best_epoch']})" if scored else "-"
        lines.append(f"| {name} | {r['seed']} | {status} | {r['epochs']} | "
                     f"{best} | {since} | "
                     f"{_number(r['slope'], percent=True)} | {_repeats(r['repeats_fifty'])} | "
                     f"{r['starts']} ({r['resumed']}) |")
    reached = sorted({int(e) for r in found["runs"] for e in r.get("at", {})})
    if reached:
        lines += ["", f"The monitor (`{found['monitor']}`) at equal epochs:", "",
                  "| run | seed | " + " | ".join(map(str, reached)) + " |",
                  "|---|---|" + "---|" * len(reached)]
        lines += [f"| {fair_fight.NAMES[r['arm']]} | {r['seed']} | "
                  + " | ".join(_number(r["at"].get(str(e))) for e in reached) + " |"
                  for r in found["runs"] if r.get("at")]
    tested = [r for r in found["runs"] if r.get("test")]
    if tested:
        columns = list(tested[0]["test"]["plateau"])
        lines += ["", "The published runs on their seed's test pairs (NMAE per column), the "
                  "kept model of the run to a plateau above the 50-epoch record of the same "
                  "arm and seed; one run says nothing of the arms' comparison, which is "
                  "the verdicts page's:", "",
                  "| run | seed | trained | " + " | ".join(columns) + " |",
                  "|---|---|---|" + "---|" * len(columns)]
        for r in tested:
            for label, key in ((f"to a plateau (best epoch {r['best_epoch']})", "plateau"),
                               (f"50 epochs (best epoch {r['test'].get('fifty_best_epoch')})",
                                "fifty")):
                if r["test"][key] is not None:
                    lines.append(f"| {fair_fight.NAMES[r['arm']]} | {r['seed']} | {label} | "
                                 + " | ".join(_number(r["test"][key][c]) for c in columns)
                                 + " |")
    return "\n".join(lines) + "\n"


def regenerate(page_path):
    """The committed page, again from its JSON twin (the run directories it
    was read from are on the machine that trains them)."""
    from cpl_keras import files

    command, found = files.page_source(page_path)
    return markdown(found, command)


def main(argv=None):
    from cpl_keras import cli, files

    parser = cli.Parser(prog="analyses/plateau_progress.py",
                        description=__doc__.split("\n\n")[0])
    parser.add_argument("--home", default=fair_fight.PLATEAU["home"],
                        help="where the runs train (default ~/cpl-runs)")
    parser.add_argument("--out", default=OUT, help="the fair fight's folder of records")
    parser.add_argument("--print", action="store_true", help="print the page, write nothing")
    args = parser.parse_args(argv)
    found = progress(os.path.expanduser(args.home), args.out)
    page = markdown(found, cli.command_line("analyses/plateau_progress.py", argv))
    if args.print:
        print(page, end="")
        return 0
    folder = os.path.join(args.out, "inception-plateau")
    files.write_page(os.path.join(folder, "progress.md"), page, found)
    print(os.path.join(folder, "progress.md"))
    return 0


if __name__ == "__main__":
    from cpl_keras import cli

    cli.run(main, "analyses/plateau_progress.py")
