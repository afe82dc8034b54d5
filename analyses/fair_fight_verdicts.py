"""The fair fight's verdicts page (paper_results/fair-fight/protocol.md,
and its plateau amendment, protocol-plateau.md): ``<out>/<towers>/verdicts.md``
and ``.json`` from the published runs, written by ``python
analyses/fair_fight.py --towers T --verdicts`` (``--plateau`` for the
amendment's runs).

For each pair of arms (``fair_fight.PAIRS``) over the seeds both have
published, two at least: the protocol's rules (``protocol_verdict``), its
validation at equal epochs (``equal_epochs``; from one seed on), each arm's
test NMAE beside the Average row's (``beside_average``) and each run's
collapsed-head shares (``head_shares``). ``regenerate`` renders a committed
page again from its JSON.
"""

from __future__ import annotations

import dataclasses
import glob
import json
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from fair_fight import ARMS, NAMES, PAIRS, PLATEAU, PROTOCOL_SEEDS, sibling  # noqa: E402


def protocol_verdict(verdicts):
    """The protocol's verdict of a pair from its column verdicts: "A lower"
    (A decided lower somewhere, B nowhere), "B lower", "mixed" or "not
    decided"."""
    from cpl_keras.evaluation import verdicts as rules

    a = sum(v.verdict == rules.A_LOWER for v in verdicts)
    b = sum(v.verdict == rules.B_LOWER for v in verdicts)
    return {(True, False): "A lower", (False, True): "B lower",
            (True, True): "mixed"}.get((a > 0, b > 0), "not decided")


#: The epochs at which each pair of arms is compared on validation (every
#: run trains the same ``EPOCHS``).
EQUAL_EPOCHS = (10, 20, 30, 40, 50)


def equal_epochs(logs_a, logs_b, epochs=EQUAL_EPOCHS):
    """Validation at equal epochs of a pair of arms over the seeds both have
    (``logs_x``: ``{seed: log.csv path}``): at each of ``epochs`` that every
    run reached, the monitor and each column's validation NMAE, means over
    the seeds; and per seed, at how many epochs both ran A's monitor is
    lower."""
    from cpl_keras.camera import PARAMETERS

    curves = sibling("equal_epochs")  # (analyses/equal_epochs.py)

    seeds = sorted(set(logs_a) & set(logs_b))
    runs = {side: {s: curves.validation(logs[s]) for s in seeds}
            for side, logs in (("a", logs_a), ("b", logs_b))}
    reached = [e for e in epochs if all(e in run for side in runs.values()
                                        for run in side.values())]
    means = {side: {str(e): {k: sum(run[e][k] for run in side_runs.values()) / len(seeds)
                             for k in ("val_nmae",) + PARAMETERS}
                    for e in reached}
             for side, side_runs in runs.items()}
    ahead = {}
    for seed in seeds:
        a, b = runs["a"][seed], runs["b"][seed]
        common = sorted(set(a) & set(b))
        ahead[str(seed)] = {"epochs": len(common),
                            "a_lower": sum(a[e]["val_nmae"] < b[e]["val_nmae"] for e in common)}
    return {"seeds": seeds, "a": means["a"], "b": means["b"], "monitor_a_lower": ahead}


def head_shares(log_path, kept_epoch):
    """Per head, the share of the logged training pairs on which every
    first-layer unit was at or below zero (``dead_<head>``, train.py's
    ``--head-units``) at ``kept_epoch`` (the weights the predictions come
    from) and at the last epoch; None where the log has no such column."""
    from cpl_keras.camera import PARAMETERS
    from cpl_keras.runs import read_log

    rows = {int(row["epoch"]): row for row in read_log(log_path)}
    last = rows[max(rows)]
    kept = rows.get(kept_epoch, last)
    return {"kept": {h: kept.get(f"dead_{h}") for h in PARAMETERS},
            "last": {h: last.get(f"dead_{h}") for h in PARAMETERS}}


#: The folder suffix of the plateau amendment's runs (``inception-plateau``).
PLATEAU_SUFFIX = "-plateau"


def amendment(out, towers, records):
    """What the plateau amendment's page adds (None for the protocol's own
    folders): the amendment's page, the 50-epoch verdict of each pair (the
    same runs' first 50 epochs, ``<towers without -plateau>/verdicts.json``)
    and each run's starts from its record's ledger (``starts.json``)."""
    from cpl_keras import files

    if not towers.endswith(PLATEAU_SUFFIX):
        return None
    fifty = towers[:-len(PLATEAU_SUFFIX)]
    found = files.read_json(os.path.join(out, fifty, "verdicts.json"), default={"pairs": {}})
    starts = {}
    for key, record in sorted(records.items()):
        ledger = files.read_json(os.path.join(record, "starts.json"), default={"starts": []})
        starts[f"{key[0]}-s{key[1]}"] = {"starts": len(ledger["starts"]),
                                         "resumed": ledger.get("resumed", 0),
                                         "machines": len(ledger.get("machines", []))}
    return {"page": "protocol-plateau.md", "fifty_epochs_page": f"../{fifty}/verdicts.md",
            "fifty_epochs": {title: pair.get("verdict") for title, pair in found["pairs"].items()},
            "starts": starts}


def write_verdicts(towers, out, data, command, resamples=2000, epochs=EQUAL_EPOCHS):
    """``<out>/<towers>/verdicts.md`` and ``.json`` (``towers``: the folder,
    ``inception-plateau`` for the amendment's runs): each pair of arms over
    the seeds published for both, by the protocol's rules, validation at
    equal ``epochs``. Returns the md path."""
    from cpl_keras import files, runs
    from cpl_keras.baselines.average import load_statistics
    from cpl_keras.evaluation import verdicts as rules
    from cpl_keras.evaluation.forward_pass import paired_outputs

    page = sibling("verdicts")  # (analyses/verdicts.py: the same tables as every folder's)

    folder = os.path.join(out, towers)
    rows, configs, logs, statistics, records = {}, {}, {}, {}, {}
    for record in sorted(glob.glob(os.path.join(folder, "runs", "cvgl_*-s*"))):
        if not os.path.isdir(record):
            continue
        arm, seed = os.path.basename(record)[len("cvgl_"):].rsplit("-s", 1)
        raw, config = paired_outputs(record, data)
        rows.setdefault(arm, {})[int(seed)] = raw
        statistics[(arm, int(seed))] = load_statistics(os.path.join(record, runs.STATS))
        configs[(arm, int(seed))] = config
        logs.setdefault(arm, {})[int(seed)] = os.path.join(record, "log.csv")
        records[(arm, int(seed))] = record
    plateau = amendment(out, towers, records)
    result = {"command": command, "rules": page.RULES, "protocol_seeds": PROTOCOL_SEEDS,
              "runs": [{"arm": arm, "seed": seed, "epochs_run": config.epochs_run,
                        "best_epoch": config.best_epoch, "wall_time_s": config.wall_time_s,
                        "dead_heads": head_shares(logs[arm][seed], config.best_epoch)}
                       for (arm, seed), config in sorted(configs.items())],
              "pairs": {}}
    if plateau:  # (its arms alone; how each run ended, and its starts)
        result["amendment"] = plateau
        for run in result["runs"]:
            run["stopped"] = configs[(run["arm"], run["seed"])].stopped
    for a, b in PAIRS:
        if plateau and not {a, b} <= set(PLATEAU["arms"]):
            continue
        seeds = sorted(set(rows.get(a, {})) & set(rows.get(b, {})))
        title = f"{NAMES[a]} vs {NAMES[b]}"
        if len(seeds) < 2:
            result["pairs"][title] = {"a": NAMES[a], "b": NAMES[b], "seeds": seeds}
            if seeds:
                result["pairs"][title]["equal_epochs"] = equal_epochs(
                    logs[a], logs[b], epochs)
            continue
        found = rules.compare({s: rows[a][s] for s in seeds}, {s: rows[b][s] for s in seeds},
                              resamples=resamples, bootstrap_seed=0)
        result["pairs"][title] = {"a": NAMES[a], "b": NAMES[b], "seeds": seeds,
                                  "verdict": protocol_verdict(found),
                                  "columns": page.summary(found),
                                  "detail": [dataclasses.asdict(v) for v in found],
                                  "equal_epochs": equal_epochs(logs[a], logs[b], epochs)}
    result["beside_average"] = beside_average(rows, statistics)
    result = json.loads(json.dumps(result))
    path = os.path.join(folder, "verdicts.md")
    files.write_text(path, verdicts_markdown(towers, result))
    files.write_json(os.path.join(folder, "verdicts.json"), result)
    return path


def beside_average(rows, statistics):
    """Each arm's test NMAE per column, the mean over its seeds, beside the
    Average row's over the seeds published and over the arm's seeds (each
    parameter predicted as its training split's mean: the seed's
    ``train_stats.json``, scored on the same test pairs). ``rows``: ``{arm: {seed: raw}}`` (``paired_outputs``);
    ``statistics``: ``{(arm, seed): train_stats}``; the arms of one seed
    share a split, so their training means must agree."""
    import numpy as np

    from cpl_keras import metrics
    from cpl_keras.baselines.average import average_predictions
    from cpl_keras.camera import PARAMETERS

    seed_stats, truths = {}, {}
    for (arm, seed), stats in sorted(statistics.items()):
        found = seed_stats.setdefault(seed, stats)["mean"]
        if any(abs(found[p] - stats["mean"][p]) > 1e-9 * max(1.0, abs(found[p]))
               for p in PARAMETERS):
            raise ValueError(f"seed {seed}: the training means of {arm} differ from another "
                             "arm's (the arms of a seed must share one split)")
        truths.setdefault(seed, rows[arm][seed]["truth"])

    def level(nmaes):
        columns = {p: float(np.mean([n[p] for n in nmaes])) for p in PARAMETERS}
        return {"sum": sum(columns.values()), **columns}

    def nmaes(pred_of, seeds):
        return [{p: metrics.nmae(truths[s][p], pred_of(s, p)) for p in PARAMETERS}
                for s in seeds]

    def average(seeds):
        predictions = {s: average_predictions(seed_stats[s], len(truths[s]["fx"]))
                       for s in seeds}
        return level(nmaes(lambda s, p: predictions[s][p], seeds))

    arms = {arm: {"seeds": sorted(rows[arm]),
                  "nmae": level(nmaes(lambda s, p, arm=arm: rows[arm][s]["pred"][p],
                                      sorted(rows[arm]))),
                  "average_nmae": average(sorted(rows[arm]))}  # (over the arm's seeds)
            for arm in ARMS if arm in rows}
    return {"arms": arms, "average": {"seeds": sorted(truths), "nmae": average(sorted(truths))}}


#: An NMAE at or below this is the Average row being exact (a constant column).
EXACT = 1e-12


def average_markdown(found):
    """Markdown lines: ``beside_average``'s table, each arm's row and its
    ratio to the Average row's."""
    from cpl_keras.camera import PARAMETERS

    keys = ("sum",) + PARAMETERS
    average = found["average"]["nmae"]
    exact = [p for p in PARAMETERS if average[p] <= EXACT]

    def seeds(x):
        return ", ".join(map(str, x["seeds"]))

    def ratio(row, p):  # (against the Average row over the arm's own seeds)
        below = row["average_nmae"][p]
        return "-" if below <= EXACT else f"{row['nmae'][p] / below:.2f}"

    lines = ["## Test NMAE beside the Average row", "",
             "For context, not a rule of the protocol: each arm's test NMAE, the mean over "
             "its seeds, and the Average row's: each parameter predicted as the training "
             "split's mean (each seed's `train_stats.json`), scored on the same test pairs. "
             "The rows \"/ Average\" divide an arm's NMAE by the Average row's over the arm's "
             "seeds"
             + (f" (\"-\" where the Average row is exact: {', '.join(exact)}, constant "
                "in the labels)" if exact else "") + ".", "",
             "| row | seeds | " + " | ".join(keys) + " |",
             "|---|---|" + "---|" * len(keys)]
    arms = found["arms"]
    for arm, row in arms.items():
        lines.append(f"| {NAMES[arm]} | {seeds(row)} | "
                     + " | ".join(f"{row['nmae'][k]:.3f}" for k in keys) + " |")
    lines.append(f"| Average (training mean) | {seeds(found['average'])} | "
                 + " | ".join(f"{average[k]:.3f}" for k in keys) + " |")
    for arm, row in arms.items():
        lines.append(f"| {NAMES[arm]} / Average | | "
                     + " | ".join(ratio(row, k) for k in keys) + " |")
    return lines + [""]


def verdicts_markdown(towers, result):
    """verdicts.md from verdicts.json's content ``result``."""
    from cpl_keras import files

    page = sibling("verdicts")  # (analyses/verdicts.py: the same tables as every folder's)

    plateau = result.get("amendment")
    if plateau:
        md = [files.generated_line(result["command"]),
              "# Fair fight, InceptionV3 to a plateau: verdicts", "",
              f"The protocol's rules ([../protocol.md](../protocol.md)) at the plateau "
              f"([../{plateau['page']}](../{plateau['page']})): each run trained until its "
              "validation monitor had not improved for 20 epochs (at most 200), the kept "
              "epoch its best. A column is decided where the seed-spread rule and the paired "
              "bootstrap (every seed) agree; the pair's verdict is A lower (A decided lower "
              "somewhere, B nowhere), B lower, mixed or not decided.", ""]
    else:
        md = [files.generated_line(result["command"]),
              f"# Fair fight, {towers} towers: verdicts", "",
              "The protocol's rules ([../protocol.md](../protocol.md)): a column is decided "
              "where the seed-spread rule and the paired bootstrap (every seed) agree; the "
              "pair's verdict is A lower (A decided lower somewhere, B nowhere), B lower, "
              "mixed or not decided.", ""]
    md += runs_markdown(result["runs"], plateau)
    for title, pair in result["pairs"].items():
        if "detail" not in pair:
            md += [f"### {title}", "", f"Not yet: seeds published for both: {pair['seeds']}.",
                   ""]
        else:
            md += page.pair_markdown(pair["a"], pair["b"],
                                     [page.verdict_from_json(c) for c in pair["detail"]])
            seeds = ", ".join(map(str, pair["seeds"]))
            protocol = result["protocol_seeds"]
            if pair["seeds"] == protocol:
                md += [f"**The protocol's verdict: {pair['verdict']}** (A = {pair['a']}, "
                       f"seeds {seeds}).", ""]
            else:  # (the rules are the protocol's, the seeds not all in yet)
                md += [f"**So far: {pair['verdict']}** (A = {pair['a']}, seeds {seeds} of "
                       f"the protocol's {', '.join(map(str, protocol))}: not the "
                       "protocol's verdict until every seed is published).", ""]
            if plateau and plateau["fifty_epochs"].get(title):
                md += [f"At 50 epochs (the same runs' first 50, "
                       f"[{plateau['fifty_epochs_page']}]({plateau['fifty_epochs_page']})): "
                       f"{plateau['fifty_epochs'][title]}.", ""]
        if "equal_epochs" in pair:
            md += equal_epochs_markdown(pair["equal_epochs"])
    if "beside_average" in result:
        md += average_markdown(result["beside_average"])
    md += heads_markdown(result["runs"])
    return "\n".join(md)


def runs_markdown(runs, plateau=None):
    """Markdown lines: the runs, their epochs and training time; at the
    plateau also why each ended and its starts (resumed)."""
    if not plateau:
        lines = ["| run | seed | epochs (kept) | training time (s) |", "|---|---|---|---|"]
        lines += [f"| {NAMES[r['arm']]} | {r['seed']} | {r['epochs_run']} ({r['best_epoch']}) "
                  f"| {r['wall_time_s']:,.0f} |" for r in runs]
        return lines + [""]
    lines = ["| run | seed | epochs (kept) | ended | starts (resumed) | training time (s) |",
             "|---|---|---|---|---|---|"]
    for r in runs:
        starts = plateau["starts"].get(f"{r['arm']}-s{r['seed']}", {})
        lines.append(f"| {NAMES[r['arm']]} | {r['seed']} | {r['epochs_run']} "
                     f"({r['best_epoch']}) | {r.get('stopped') or 'at the epoch cap'} | "
                     f"{starts.get('starts', 0)} ({starts.get('resumed', 0)}) | "
                     f"{r['wall_time_s']:,.0f} |")
    return lines + [""]


def equal_epochs_markdown(found):
    """Markdown lines: a pair's validation at equal epochs (``equal_epochs``)."""
    curves = sibling("equal_epochs")  # (analyses/equal_epochs.py)

    seeds = ", ".join(map(str, found["seeds"]))
    table = curves.comparison({int(e): v for e, v in found["a"].items()},
                              {int(e): v for e, v in found["b"].items()},
                              sorted(int(e) for e in found["a"]))
    ahead = "; ".join(f"seed {seed}: {n['a_lower']} of {n['epochs']}"
                      for seed, n in found["monitor_a_lower"].items())
    over = f"means over seeds {seeds}" if len(found["seeds"]) > 1 else f"seed {seeds}"
    return [f"Validation at equal epochs ({over}; val_nmae is the monitor, the sum of the "
            "ten NMAEs; for context, not a rule of the protocol):", ""] + table + [
            "", f"Epochs at which A's monitor is lower than B's: {ahead}.", ""]


def heads_markdown(runs):
    """Markdown lines: each run's collapsed-head shares (``head_shares``)."""
    from cpl_keras.camera import PARAMETERS

    def cell(kept, last):
        if kept is None:
            return "-"
        return f"{kept:.2f}" + ("" if last == kept else f" ({last:.2f})")

    lines = ["## Collapsed heads", "",
             "Per run and head, the share of train.py's 64 logged training pairs on which "
             "every first-layer unit of the head is at or below zero (`dead_<head>`, "
             "`--head-units`), at the kept epoch, whose weights made the predictions (in "
             "brackets at the last epoch, where it differs). A ReLU head puts out one value "
             "on such a pair; the recipe's leaky heads still pass their slope's share of the "
             "gradient.", "",
             "| run | seed | kept | " + " | ".join(PARAMETERS) + " |",
             "|---|---|---|" + "---|" * len(PARAMETERS)]
    for run in runs:
        shares = run.get("dead_heads", {"kept": {}, "last": {}})
        lines.append(f"| {NAMES[run['arm']]} | {run['seed']} | {run['best_epoch']} | "
                     + " | ".join(cell(shares["kept"].get(h), shares["last"].get(h))
                                  for h in PARAMETERS) + " |")
    return lines + [""]


def regenerate(page_path):
    """The committed ``<towers>/verdicts.md`` from verdicts.json beside it."""
    from cpl_keras import files

    folder = os.path.dirname(os.path.abspath(page_path))
    return verdicts_markdown(os.path.basename(folder),
                             files.read_json(os.path.join(folder, "verdicts.json")))
