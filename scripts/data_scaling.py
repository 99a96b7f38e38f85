"""How the real-flight network's accuracy grows with its training flights: the same recipe trained on nested
subsets of the training flights (``immnet data subset``: for one seed each smaller subset is part of every
larger one; another seed draws other flights), each scored on the validation and the test flights (and a
held-out set) in one run beside the model-based filters given. The filters stay as tuned on every training
flight (a handful of settings; the network's data is the variable).

    python scripts/data_scaling.py --data runs/real/data/quickstart-1s --flights 0.125,0.25,0.5,1 [--seeds 0,1] \\
        [--recipe recipes/real.yaml] [--out runs/real/scaling] [--baselines real-imm-axis] \\
        [--heldout runs/real/data/heldout-1s/test] [--skip-training] [--json F] [--markdown F] [--figure F.png]

``--data``: ``immnet data adsb``'s OUT (its train, val and test); ``--flights``: fractions (or counts) of the
training flights, ``1`` for all of them (trained once, whatever the seeds). Each run trains in
``OUT/seed<S>/<flights>/`` (all flights: ``OUT/all/``) with ``immnet fit --config RECIPE --config
<run>/overlay.yaml``, the overlay moving the run's directory and its training data, nothing else; a run whose
``checkpoints/best.ckpt`` exists is not trained again, and ``--skip-training`` trains none. Real flights carry
no range guard.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import yaml

from immnet.data.real import subset_flights, window_flights
from immnet.data.storage import load_dataset
from immnet.filters.methods import build_method
from immnet.evaluation.runner import evaluate, to_json
from immnet.imm.guard import parse_guard
from immnet.tracking.methods import IMMNetMethod


def overlay(recipe: dict, run: Path, train: Path) -> dict:
    """The recipe's settings that place a run: its directory, its checkpoint's directory, its training data."""
    callbacks = []
    for cb in recipe["trainer"].get("callbacks", []):
        cb = json.loads(json.dumps(cb))  # a copy
        if cb.get("class_path", "").endswith("ModelCheckpoint"):
            cb["init_args"]["dirpath"] = str(run / "checkpoints")
        callbacks.append(cb)
    return {"trainer": {"default_root_dir": str(run), "callbacks": callbacks}, "data": {"data": str(train)}}


def label(flights: float) -> str:
    """A run's directory name: ``all``, or the fraction or count as given."""
    return "all" if flights == 1 else f"{flights:g}"


def plan(data: Path, out: Path, fractions: list[float], seeds: list[int]) -> list[dict]:
    """Every run: its name, directory, training data and seed (all flights once, first)."""
    runs = []
    if 1 in fractions:
        runs.append({"name": "all", "run": out / "all", "train": data / "train", "seed": None, "fraction": 1.0})
    for seed in seeds:
        for f in fractions:
            if f != 1:
                run = out / f"seed{seed}" / label(f)
                runs.append({"name": f"{label(f)} (seed {seed})", "run": run, "train": run / "data", "seed": seed,
                             "fraction": f})
    return runs


def train(r: dict, recipe_path: Path, recipe: dict, data: Path) -> None:
    if r["seed"] is not None and not (r["train"] / "meta.json").exists():
        subset_flights(data / "train", r["train"], r["fraction"], seed=r["seed"], overwrite=True)
    if (r["run"] / "checkpoints" / "best.ckpt").exists():
        print(f"[data_scaling] {r['name']}: trained already ({r['run']})", flush=True)
        return
    r["run"].mkdir(parents=True, exist_ok=True)
    (r["run"] / "overlay.yaml").write_text(yaml.safe_dump(overlay(recipe, r["run"], r["train"]), sort_keys=False))
    cmd = [sys.executable, "-m", "immnet.cli", "fit", "--config", str(recipe_path), "--config",
           str(r["run"] / "overlay.yaml")]
    print(f"[data_scaling] {r['name']}: {' '.join(cmd)}", flush=True)
    subprocess.run(cmd, check=True)


def figure(rows: list[dict], sets: list[str], path: Path, what: str = "quickstart-1s") -> None:
    """Each network's ratio to the best filter against its training flights, one panel line per set."""
    from immnet.evaluation.figures import save_figure  # matplotlib on its Agg backend

    import matplotlib.pyplot as plt
    import numpy as np

    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    for k, name in enumerate(sets):
        x = np.array([r["flights"] for r in rows])
        y = np.array([r["sets"][name]["ratio"] for r in rows])
        ax.scatter(x, y, s=18, color=f"C{k}", alpha=0.6)
        xs = sorted(set(x.tolist()))
        ax.plot(xs, [y[x == v].mean() for v in xs], color=f"C{k}", label=name)
    ax.axhline(1.0, color="0.4", lw=0.8, ls="--")
    ax.axhline(0.9, color="C3", lw=0.8, ls=":", label="target 0.90x")
    ax.set_xscale("log", base=2)
    ticks = sorted({r["flights"] for r in rows})
    ax.set_xticks(ticks, [str(v) for v in ticks])
    ax.minorticks_off()
    ax.set_xlabel(f"training flights ({what})")
    ax.set_ylabel("RMSE / best model-based filter")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    save_figure(fig, path, dpi=120)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True, type=Path, help="immnet data adsb's OUT (train, val, test)")
    p.add_argument("--flights", default="0.125,0.25,0.5,1", help="fractions (or counts) of the training flights")
    p.add_argument("--seeds", default="0", help="seeds of the flights' permutation (immnet data subset)")
    p.add_argument("--recipe", type=Path, default=Path("recipes/real.yaml"))
    p.add_argument("--out", type=Path, default=Path("runs/real/scaling"))
    p.add_argument("--baselines", default="real-imm-axis", help="comma-separated registry methods to score beside")
    p.add_argument("--heldout", type=Path, help="one more set to score on (samples never trained on)")
    p.add_argument("--skip-training", action="store_true", help="score the runs already in OUT")
    p.add_argument("--json", type=Path)
    p.add_argument("--markdown", type=Path)
    p.add_argument("--figure", type=Path, help="the ratio to the best filter against the training flights (.png)")
    args = p.parse_args(argv)
    recipe = yaml.safe_load(args.recipe.read_text())
    runs = plan(args.data, args.out, [float(f) for f in args.flights.split(",")],
                [int(s) for s in args.seeds.split(",")])
    for r in runs:
        if not args.skip_training:
            train(r, args.recipe, recipe, args.data)
        meta = load_dataset(r["train"])[1]
        try:
            r["flights"], r["windows"] = len(set(window_flights(meta, meta["n"], r["train"]))), meta["n"]
        except ValueError as err:
            raise SystemExit(str(err)) from None
    guard = parse_guard("none")
    sets = {"validation": args.data / "val", "test": args.data / "test"}
    if args.heldout:
        sets["held out"] = args.heldout
    baselines = [name for name in args.baselines.split(",") if name]
    best = {}
    for name, path in sets.items():
        data, _ = load_dataset(path)
        methods = {b: build_method(b, guard=guard) for b in baselines}
        for r in runs:
            methods[r["name"]] = IMMNetMethod(str(r["run"] / "checkpoints" / "best.ckpt"), r["name"], guard=guard)
        rmse = {m: row["rmse"]["avg"] for m, row in to_json(evaluate(methods, data, progress=True)).items()}
        best[name] = min(rmse[b] for b in baselines)
        for r in runs:
            r.setdefault("sets", {})[name] = {"rmse_avg": rmse[r["name"]], "ratio": rmse[r["name"]] / best[name]}
    rows = sorted(runs, key=lambda r: (r["flights"], r["seed"] or 0))
    head = " | ".join(f"{name} [m] | ratio" for name in sets)
    lines = [f"| training flights (windows), subset seed | {head} |", "|:---" + "|---:|---:" * len(sets) + "|"]
    for r in rows:
        cells = " | ".join(f"{r['sets'][s]['rmse_avg']:.3f} | {r['sets'][s]['ratio']:.3f}x" for s in sets)
        seed = "" if r["seed"] is None else f", seed {r['seed']}"
        lines.append(f"| {r['flights']} ({r['windows']}){seed} | {cells} |")
    cells = " | ".join(f"{best[s]:.3f} | 1.000x" for s in sets)
    lines.append(f"| best of {', '.join(baselines)} (tuned on every training flight) | {cells} |")
    text = "\n".join(lines)
    print(text)
    if args.markdown:
        args.markdown.write_text(text + "\n")
    if args.json:
        keep = ("name", "seed", "fraction", "flights", "windows", "sets")
        out = {"best_baseline": best, "runs": [{k: r[k] for k in keep} for r in rows]}
        args.json.write_text(json.dumps(out, indent=2, allow_nan=False) + "\n")
    if args.figure:
        figure(rows, list(sets), args.figure, args.data.name)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
