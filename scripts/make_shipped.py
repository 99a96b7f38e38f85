"""Ship a fine-tuned IMMNet: export its run's best checkpoint into immnet/pretrained/immnet-NAME.ckpt, score it on
each of its test sets beside the model-based filters (and the clairvoyant bound on 3D-LAST) in one run per set, and
write immnet/pretrained/provenance-NAME.json and PROVENANCE-NAME.md. NAME is one of SHIPS: `real` (three runs of
recipes/real-singer-output.yaml, two with an overlay of configs/members/, their corrections joined: 1 s), `real-5s`
(the same of recipes/real-singer-5s-output.yaml: 4.5-5.5 s), `real-11s` (of recipes/real-singer-11s-output.yaml:
10-12 s), `real-4.5-12s` (the same of recipes/real-singer-4.5-12s-output.yaml: 4.5-12 s) or `general`
(recipes/general.yaml, 0.5-12 s); `bank`, the default tracker, exports nothing (its members are the shipped files) and
writes its provenance from its scores.

Run (after the run that trains it: `bash scripts/real.sh` or `bash scripts/general.sh`):
    .venv/bin/python scripts/make_shipped.py --name general [--commit C] [--wandb-runs ID,...] [--note TEXT]
`--rescore` exports nothing: it scores the shipped file again on its test sets with today's methods (another
shipped network replaced, a filter added) and rewrites its provenance, keeping what it says of the training (commit,
date, data, W&B runs, note) and recording when and at which commit it was scored.
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "immnet/pretrained"
REAL = "runs/real/data"


def real_filters(tag: str) -> list[str]:
    """A real-flight test set's baselines: the raw measurements, 3D-LAST's imm-ekf and the five filters tuned at the
    set's scans (``tag``: the configs' suffix, ``""`` at 1 s, ``"-5s"``, ``"-7s"``, ``"-11s"``)."""
    return ["measurements", "imm-ekf",
            *(f"{m}{tag}" for m in ("real-ca", "real-imm", "real-imm-axis", "real-imm-channel", "real-imm-singer"))]


REAL1, REAL5, REAL7, REAL11 = (real_filters(tag) for tag in ("", "-5s", "-7s", "-11s"))
LAST = ["measurements", "imm-tuned", "imm-ekf", "imm-ekf-guard-sticky", "clairvoyant"]
QUICKSTART = ("collections/quickstart's training flights (immnet data adsb --seed 0), split by flight; no test flight "
              "trained or tuned on")


def _runs(tag: str) -> dict:
    """The three runs whose corrections a shipped real-flight network averages: the recipe, and it with each overlay
    of configs/members/ (a second seed; turns flown into half its views); ``tag`` the recipe's and run directories'
    suffix (``""``, ``"-5s"``, ``"-11s"``, ``"-4.5-12s"``)."""
    recipe, members = f"recipes/real-singer{tag}-output.yaml", f"configs/members/real{tag}"
    return {"ckpt": [f"runs/real/output{tag}{run}/checkpoints/best.ckpt" for run in ("", "-seed1", "-turns")],
            "recipe": [recipe] + [f"{recipe} + {members}-{overlay}.yaml" for overlay in ("seed1", "turns")]}


def _corrections(tag: str, scans: str, train: str, tests: list[str], prior: str = "", reading: str = "",
                 tuned: str = "") -> dict:
    """A real-flight network of three runs of one recipe on one filter, their corrections averaged
    (docs/notebook/real-flights.md "Several corrections on one filter"): ``_runs(tag)``. ``tag``: the recipe's, run
    directories' and filter's suffix (``""``, ``"-5s"``, ``"-11s"``); ``scans``: the scans it was trained at, as the
    provenance says them; ``train``: its training data's scans and noise; ``tests``: the registry names scored beside
    its set's filters."""
    name, filt, data = f"real{tag}", f"real-imm-singer{tag}", f"{REAL}/quickstart{tag or '-1s'}"
    return {
        **_runs(tag),
        "init": ("each its untrained start (the output correction's last layer zero: the three-filter decoupled IMM "
                 f"{filt} with r estimated{prior}, exactly)"),
        "what": ("three output corrections (GRUs after the fusion that correct the reported position from the track's "
                 f"history{reading}), their corrections averaged, on the three-filter decoupled IMM tuned on real "
                 f"flights{tuned} ({filt}'s CV, CA and Singer filters per axis), each track's r estimated, each trained "
                 f"on real flights at {scans} (a fresh view of its flights each batch) as a run of its own, without a "
                 "range guard; only the corrections learned"),
        "data": {"train": f"{data}/train: {QUICKSTART}, {train}", "val": f"{data}/val"},
        "guard": "none",
        "tests": {f"quickstart{tag or '-1s'}": (f"{data}/test", tests + [f"immnet-{name}"])},
    }


PRIOR = " from a prior of 20 m"  # the r estimate's prior at the training flights' mean r (U[5, 35] m)
READING = ", reading each scan's interval"
SHIPS = {
    # each chosen on its validation flights over each run alone and each pair (docs/real.md)
    "real": {**_corrections("", "1 s scans", "1 s scans, r ~ U[1, 7] m", REAL1 + ["immnet", "immnet-general"]),
             "scan_interval": 1.0},
    # no covariance consistency (docs/immnet.md): of none, 0.005, 0.01, 0.02 and 0.05 its weight, none gives the mean
    # position NEES nearest 3 on the validation flights (docs/real.md, "Calibration")
    "real-5s": {**_corrections("-5s", "those scans", "U[4.5, 5.5] s scans, r ~ U[5, 35] m",
                               REAL5 + ["imm-ekf-general", "immnet-general"], PRIOR, READING, " at 4.5-5.5 s"),
                "interval_range": [4.5, 5.5]},
    # real-5s's form at an en-route radar's scans (docs/real.md "Results (10-12 s scans, r 5-35 m)")
    "real-11s": {**_corrections("-11s", "those scans", "U[10, 12] s scans, r ~ U[5, 35] m",
                                REAL11 + ["imm-ekf-general", "immnet-general"], PRIOR, READING, " at 10-12 s"),
                 "interval_range": [10.0, 12.0]},
    # one network for every interval from 4.5 to 12 s, three runs as real-5s's (docs/real.md "Between the trained
    # intervals"), chosen on the three validation sets together
    "real-4.5-12s": {
        **_runs("-4.5-12s"),
        "init": ("each its untrained start (the output correction's last layer zero: the three-filter decoupled IMM of "
                 f"real-imm-singer-11s's settings with r estimated{PRIOR}, exactly)"),
        "what": ("three output corrections (GRUs after the fusion that correct the reported position from the track's "
                 f"history{READING}), their corrections averaged, on the three-filter decoupled IMM tuned on real "
                 "flights at 4.5-5.5, 6-8 and 10-12 s together (real-imm-singer-11s's settings: its CV, CA and Singer "
                 "filters per axis), each track's r estimated, each trained on real flights at those three kinds of "
                 "scans (a fresh view of its flights each batch) as a run of its own, without a range guard; only the "
                 "corrections learned"),
        "data": {"train": [f"{REAL}/quickstart-{s}/train: {QUICKSTART}, {scans} s scans, r ~ U[5, 35] m"
                           for s, scans in (("5s", "U[4.5, 5.5]"), ("7s", "U[6, 8]"), ("11s", "U[10, 12]"))],
                 "val": [f"{REAL}/quickstart-{s}/val" for s in ("5s", "7s", "11s")]},
        "interval_range": [4.5, 12.0],
        "guard": "none",
        "tests": {
            "quickstart-7s": (f"{REAL}/quickstart-7s/test", REAL7 + ["imm-ekf-general", "immnet-general",
                                                                     "immnet-real-4.5-12s"]),
            "quickstart-5s": (f"{REAL}/quickstart-5s/test", REAL5 + ["imm-ekf-general", "immnet-general", "immnet-real-5s",
                                                                     "immnet-real-4.5-12s"]),
            "quickstart-11s": (f"{REAL}/quickstart-11s/test", REAL11 + ["imm-ekf-general", "immnet-general",
                                                                       "immnet-real-11s", "immnet-real-4.5-12s"]),
        },
    },
    "general": {
        "ckpt": "runs/general/fit/checkpoints/best.ckpt",
        "recipe": "recipes/general.yaml",
        "init": "immnet/pretrained/immnet.ckpt (3D-LAST), widened to read each scan's interval (a zero column)",
        "what": ("one network for any scan interval from 0.5 to 12 s, on real flights and 3D-LAST, without a range "
                 "guard: the 3D-LAST weights fine-tuned on a mixture"),
        "data": {"train": ["runs/general/data/3dlast: 3D-LAST at U[0.5, 12] s scans, 1,500 trajectories of 200 scans, "
                           "seed 61 (95 % of it; 5 % validation)",
                           f"{REAL}/quickstart-1s/train: {QUICKSTART}, 1 s scans, r ~ U[1, 7] m",
                           f"{REAL}/quickstart-5s/train: the same flights at U[4.5, 5.5] s scans (one partition for "
                           "both intervals; docs/data.md \"One partition per region\"), r ~ U[5, 35] m",
                           "runs/general/data/3dlast-1s: 3D-LAST at 1 s scans, 500 trajectories of 400 scans, seed 63 "
                           "(95 % of it)"],
                 "val": [f"{REAL}/quickstart-1s/val", f"{REAL}/quickstart-5s/val"]},
        "interval_range": [0.5, 12.0],
        "guard": "none",
        # what it reports: its covariance scaled by a running mean of its NIS / 3, the weight chosen on the validation
        # flights and fresh 3D-LAST (docs/immnet.md, "Covariance consistency"); its estimates are the trained network's
        "settings": {"cov_consistency": 0.05},
        "tests": {
            # beside each set's filters, imm-ekf-general: IMMNet with nothing learned tuned on the same mixture
            "quickstart-1s": (f"{REAL}/quickstart-1s/test", REAL1 + ["imm-ekf-general", "immnet", "immnet-real",
                                                                     "immnet-general"]),
            "quickstart-5s": (f"{REAL}/quickstart-5s/test", REAL5 + ["imm-ekf-general", "immnet-general",
                                                                     "immnet-real-5s"]),
            "3dlast-1s": ("runs/general/data/test-1s", LAST + ["imm-ekf-general", "immnet", "immnet-general"]),
            "3dlast-4.5-5.5s": ("runs/general/data/test-4.5-5.5s", LAST + ["imm-ekf-general", "immnet-general"]),
            "3dlast-0.5-12s": ("runs/general/data/test-0.5-12s", LAST + ["imm-ekf-general", "immnet-general"]),
        },
        # by scan interval beside its filter: what `immnet track` reads to advise on a user's scans
        # (immnet.tracking.advice)
        "interval_bins": {"data": "runs/general/data/test-0.5-12s", "filter": "imm-ekf-general",
                          "edges": [0.5, 2, 4, 6, 8, 10, 12]},
    },
    "bank": {
        # no weights of its own: the shipped networks above (and 3dlast) as they are, scored together as the default;
        # its members and how it weighs them are the table's (immnet/pretrained/weights.json, "bank")
        "bank": True,
        "what": ("The default tracker: the shipped networks general, real, real-5s, real-11s, real-4.5-12s and 3dlast "
                 "(without its range guard) "
                 "run side by side, each on the tracks whose scan intervals it was trained for and weighed per track by "
                 "the likelihood of the track's measurements under its predictions of the track as it reports it, each "
                 "scan's to the power 0.5 (immnet.tracking.bank, docs/tracking.md \"A bank of networks\"); nothing "
                 "trained for it"),
        "interval_range": [0.5, 12.0],
        "tests": {
            "quickstart-1s": (f"{REAL}/quickstart-1s/test", REAL1 + ["immnet", "immnet-real", "immnet-general",
                                                                     "immnet-bank"]),
            "quickstart-5s": (f"{REAL}/quickstart-5s/test", REAL5 + ["immnet-real-5s", "immnet-general", "immnet-bank"]),
            "quickstart-7s": (f"{REAL}/quickstart-7s/test", REAL7 + ["immnet-real-4.5-12s", "immnet-general",
                                                                     "immnet-bank"]),
            "quickstart-11s": (f"{REAL}/quickstart-11s/test", REAL11 + ["immnet-real-11s", "immnet-general",
                                                                       "immnet-bank"]),
            "3dlast-1s": ("runs/general/data/test-1s", LAST + ["immnet", "immnet-general", "immnet-bank"]),
            "3dlast-4.5-5.5s": ("runs/general/data/test-4.5-5.5s", LAST + ["immnet-general", "immnet-bank"]),
            "3dlast-0.5-12s": ("runs/general/data/test-0.5-12s", LAST + ["immnet-general", "immnet-bank"]),
            "3dlast-10-12s": ("runs/general/data/test-10-12s", LAST + ["immnet-general", "immnet-bank"]),
        },
    },
}


def claims(rows: dict, name: str) -> dict:
    """What the tests hold the file to on one test set, rounded up to 0.01: its ratio to the clairvoyant bound
    where the set has one (3D-LAST), else to the best model-based filter there."""
    avg = {n: r["rmse"]["avg"] for n, r in rows.items()}
    if "clairvoyant" in avg:
        return {"ratio_to_clairvoyant": math.ceil(100 * avg[name] / avg["clairvoyant"]) / 100}
    best = min((n for n in avg if n.startswith(("real-", "imm-"))), key=avg.get)
    return {"ratio_to_best_model_based": math.ceil(100 * avg[name] / avg[best]) / 100, "best_model_based": best}


def score(ship: dict, registry: str) -> tuple[dict, list[str]]:
    """Each of ``ship``'s test sets scored in one run of its methods (real flights without a range guard): the
    provenance's ``tests`` (data, n, metrics, claims) and a Markdown table per set."""
    from immnet.data.storage import load_dataset
    from immnet.filters.methods import build_method
    from immnet.evaluation.runner import evaluate, to_json
    from immnet.evaluation.table import format_markdown, format_table
    from immnet.imm.guard import parse_guard

    tests, tables = {}, []
    for set_name, (path, names) in ship["tests"].items():
        data, _ = load_dataset(ROOT / path)
        guard = parse_guard(ship.get("guard", "none")) if set_name.startswith("quickstart") else parse_guard("checkpoint")
        methods = {n: build_method(n, guard=guard) for n in names}  # registry: the file just written
        print(f"{set_name}: {data.batch_size[0]} windows", file=sys.stderr)
        rows = to_json(evaluate(methods, data, progress=True))
        print(format_table(rows))
        tests[set_name] = {"data": path, "n": data.batch_size[0], "metrics": {n: r["rmse"] for n, r in rows.items()},
                           "claims": claims(rows, registry)}
        tables.append(f"**{set_name}** (`{path}`, {data.batch_size[0]} windows):\n\n{format_markdown(rows)}\n")
    return tests, tables


TESTS_HEADING = ("Test sets (never trained or tuned on), position RMSE in metres, each set one run (real flights "
                 "without a range guard)")


def claims_line(tests: dict) -> str:
    """A provenance's last paragraph: each test set's claims, which the tests check."""
    return ("Claims checked by the tests (`tests/test_real_flights.py`, `tests/test_pretrained.py`): "
            + "; ".join(f"{s}: " + ", ".join(f"{k} {v}" for k, v in t["claims"].items()) for s, t in tests.items()) + ".\n")


def ship_bank(name: str, ship: dict, commit: str) -> int:
    """The bank's provenance: its members' files and checksums, its tests and claims; nothing exported (it has no
    weights of its own)."""
    from immnet.checkpoints import BANK_MEMBERS, BANK_SETTINGS, CHECKSUM_KEY, SHIPPED, load_checkpoint, shipped
    from immnet.tracking.advice import registry_name

    registry = registry_name(name)
    members = {m: {"file": f"immnet/pretrained/{SHIPPED[m]}", "weights_sha256": load_checkpoint(shipped(m))[CHECKSUM_KEY]}
               for m in BANK_MEMBERS}
    tests, tables = score(ship, registry)
    weighing = dict(BANK_SETTINGS)
    prov = {"members": members, "weighing": weighing,
            "made_by": f".venv/bin/python scripts/make_shipped.py --name {name}",
            "date": datetime.date.today().isoformat(), "commit": commit, "guard": None,
            "interval_range": ship["interval_range"], "tests": tests}
    (OUT / f"provenance-{name}.json").write_text(json.dumps(prov, indent=2, allow_nan=False) + "\n")
    rows = "\n".join(f"| `{m}` | `{v['file']}` | {v['weights_sha256']} |" for m, v in members.items())
    lines = [f"# Shipped tracker: {name} (the default)\n",
             f"{ship['what']}. Registry name `{registry}`; it takes scan intervals {ship['interval_range'][0]:g}-"
             f"{ship['interval_range'][1]:g} s. Scored at commit `{commit[:10]}` ({prov['date']}) by "
             f"`{prov['made_by']}`.\n",
             f"Members, as shipped (each with its own provenance), weighed by the `{weighing['likelihood']}` likelihood "
             f"to the power {weighing['temper']:g}:\n\n| member | file | weights_sha256 |\n|:---|:---|:---|\n"
             f"{rows}\n",
             TESTS_HEADING + ":\n", *tables,
             claims_line(tests)]
    (OUT / f"PROVENANCE-{name}.md").write_text("\n".join(lines))
    print(f"wrote provenance-{name}.json and PROVENANCE-{name}.md", file=sys.stderr)
    return 0


def interval_bins(spec: dict, registry: str) -> dict:
    """The network and its filter scored by scan interval on ``spec["data"]`` (``runner.evaluate_by_interval``):
    the provenance's ``interval_bins`` (``immnet.tracking.advice``)."""
    from immnet.data.storage import load_dataset
    from immnet.filters.methods import build_method
    from immnet.evaluation.runner import evaluate_by_interval

    td, _ = load_dataset(ROOT / spec["data"])
    print(f"{spec['data']} by interval: {registry}, {spec['filter']}", file=sys.stderr)
    methods = {name: build_method(name) for name in (registry, spec["filter"])}
    # full precision, as the test sets' metrics: the markdown table rounds once (a value rounded to 4 places here and
    # to 3 there could come out one unit off, 4.24551 -> 4.2455 -> 4.245)
    rmse = {name: row for name, row in evaluate_by_interval(methods, td, spec["edges"]) if name in methods}
    return {"data": spec["data"], "edges": spec["edges"], "network": registry, "filter": spec["filter"], "rmse": rmse}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--name", required=True, choices=sorted(SHIPS))
    p.add_argument("--checkpoint", default=None, help="the run's checkpoint (default: where its recipe writes it); "
                   "runs whose corrections are joined, comma-separated")
    p.add_argument("--commit", default="HEAD", help="the commit the weights were trained at (default: HEAD)")
    p.add_argument("--wandb-runs", default="", help="the W&B run ids of the training, comma-separated")
    p.add_argument("--note", default="", help="how the training departed from the recipe, if it did")
    p.add_argument("--rescore", action="store_true",
                   help="export nothing: score the shipped file again and rewrite its provenance, its training's "
                        "commit, date, W&B runs and note kept (--commit, --wandb-runs, --note and --checkpoint "
                        "refused)")
    a = p.parse_args(argv)
    if a.rescore and (a.checkpoint or a.commit != "HEAD" or a.wandb_runs or a.note):
        p.error("--rescore keeps the shipped provenance's training record: give no --checkpoint, --commit, "
                "--wandb-runs or --note")
    from immnet.tracking.advice import registry_name

    ship, registry = SHIPS[a.name], registry_name(a.name)
    commit = subprocess.run(["git", "rev-parse", "--verify", f"{a.commit}^{{commit}}"], cwd=ROOT, capture_output=True,
                            text=True).stdout.strip()
    if not commit:
        p.error(f"--commit {a.commit!r} is not a commit of this repository")
    if ship.get("bank"):  # the bank: nothing trained or exported, so nothing to keep; scoring is all it does
        if a.checkpoint or a.commit != "HEAD" or a.wandb_runs or a.note:
            p.error(f"{a.name} trains nothing: give no --checkpoint, --commit, --wandb-runs or --note")
        return ship_bank(a.name, ship, commit)
    old = OUT / f"provenance-{a.name}.json"
    if a.rescore and not old.is_file():
        p.error(f"--rescore: {old} does not exist (nothing shipped as {a.name!r} to score again)")
    from immnet.checkpoints import CHECKSUM_KEY, load_checkpoint
    from immnet.training.export import export_weights, join_corrections

    if a.rescore:
        out, kept = OUT / f"{registry}.ckpt", json.loads(old.read_text())
        if load_checkpoint(out)[CHECKSUM_KEY] != kept["weights_sha256"]:
            p.error(f"--rescore: {out}'s weights are not the ones {old.name} describes (weights_sha256 differs)")
    else:
        trained = a.checkpoint.split(",") if a.checkpoint else ship["ckpt"]
        trained = trained if isinstance(trained, list) else [trained]
        if len(trained) > 1:  # runs on one filter: their corrections joined
            if ship.get("settings"):
                p.error(f"{a.name}: settings at export are not taken by a join of runs")
            out = join_corrections([ROOT / r for r in trained], OUT / f"{registry}.ckpt")
        else:
            out = export_weights(ROOT / trained[0], OUT / f"{registry}.ckpt", ship.get("settings"))
        from immnet.checkpoints import record_shipped

        record_shipped(a.name)  # the weights table names the new file's weights
    tests, tables = score(ship, registry)
    bins = interval_bins(ship["interval_bins"], registry) if "interval_bins" in ship else None
    if bins:
        head = " | ".join(f"{lo:g}-{hi:g} s" for lo, hi in zip(bins["edges"][:-1], bins["edges"][1:]))
        body = "\n".join(f"| {n} | " + " | ".join("-" if v is None else f"{v:.3f}" for v in row) + " |"
                         for n, row in bins["rmse"].items())
        tables.append(f"**By scan interval** (`{bins['data']}`, each bin's pooled RMSE, the mean over x, y, z; "
                      f"`immnet track` notes where the network is behind `{bins['filter']}` at the data's median "
                      f"interval):\n\n| method | {head} |\n|:---|{'---:|' * (len(bins['edges']) - 1)}\n{body}\n")
    runs = [r.strip() for r in a.wandb_runs.split(",") if r.strip()]
    prov = {
        "file": f"immnet/pretrained/{registry}.ckpt",
        "weights_sha256": load_checkpoint(out)[CHECKSUM_KEY],
        "recipe": ship["recipe"],
        "init": ship["init"],
        "made_by": f".venv/bin/python scripts/make_shipped.py --name {a.name}",
        "date": datetime.date.today().isoformat(),
        "commit": commit,
        "data": ship["data"],
        "guard": None,
        "scan_interval": ship.get("scan_interval"),
        "interval_range": ship.get("interval_range"),
        "settings": ship.get("settings"),
        "wandb": {"project": "immnet", "runs": runs} if runs else None,
        "note": a.note,
    }
    if a.rescore:  # the training's record as exported (SHIPS may describe a newer training by now); today's scores
        prov = {k: v for k, v in kept.items() if k not in ("tests", "interval_bins", "scored")}
    runs, note = (prov.get("wandb") or {}).get("runs", []), prov.get("note", "")
    prov["tests"] = tests
    if bins:
        prov["interval_bins"] = bins
    if a.rescore:
        at = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
        prov["scored"] = {"date": datetime.date.today().isoformat(), "commit": at,
                          "by": f".venv/bin/python scripts/make_shipped.py --name {a.name} --rescore"}
    (OUT / f"provenance-{a.name}.json").write_text(json.dumps(prov, indent=2, allow_nan=False) + "\n")
    span = (f"scan intervals {prov['interval_range'][0]:g}-{prov['interval_range'][1]:g} s" if prov.get("interval_range")
            else f"{prov['scan_interval']:g} s scans only (a fixed-interval network)")
    recipes = ("; ".join(f"`{r}`" for r in prov["recipe"]) + " (one run each, joined)"
               if isinstance(prov["recipe"], list) else f"`{prov['recipe']}`")
    lines = [f"# Shipped IMMNet weights: {a.name}\n",
             f"`{registry}.ckpt` ({out.stat().st_size / 2**20:.1f} MB, `weights_sha256` {prov['weights_sha256']}): "
             f"{ship['what']}. Trained by {recipes} from {prov['init']} at commit `{prov['commit'][:10]}` "
             f"({prov['date']}), "
             f"exported and scored by `{prov['made_by']}`. Registry name `{registry}`; it takes {span}.\n",
             "Training data: " + "; ".join(prov["data"]["train"] if isinstance(prov["data"]["train"], list)
                                           else [prov["data"]["train"]]) + ".\n",
             (f"W&B runs (offline; `wandb sync`, docs/wandb.md): {', '.join(runs)}.\n" if runs else
              "W&B: no run id recorded for this training (`wandb: null`).\n"),
             *([f"Set at export (what it reports, not what it estimates): "
                f"{', '.join(f'{k} {v}' for k, v in prov['settings'].items())} (docs/immnet.md).\n"]
               if prov.get("settings") else []),
             *([f"Note: {note}.\n"] if note else []),
             TESTS_HEADING
             + (f", scored again at commit `{prov['scored']['commit'][:10]}` ({prov['scored']['date']}) by "
                f"`{prov['scored']['by']}`" if a.rescore else "") + ":\n", *tables,
             claims_line(tests)]
    (OUT / f"PROVENANCE-{a.name}.md").write_text("\n".join(lines))
    print(f"wrote {out}, provenance-{a.name}.json and PROVENANCE-{a.name}.md", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
