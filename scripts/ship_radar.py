"""Ship a radar network (scripts/radar_range.sh): export its run's best checkpoint into
immnet/pretrained/immnet-NAME.ckpt, write its checksum into the weights table (immnet/pretrained/weights.json, whose
row for NAME must exist) and its provenance, provenance-NAME.json and PROVENANCE-NAME.md, with the validation scores
it was chosen on (RUN/val-*.json, `immnet evaluate` on validation splits only; the test splits' tables are
docs/radar.md's). NAME: radar-5s or radar-11s.

Run (after scripts/radar_range.sh):  .venv/bin/python scripts/ship_radar.py --name radar-5s [--run runs/radar-range]
"""

from __future__ import annotations

import argparse
import datetime
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "immnet/pretrained"
DATA = "runs/radar-range/data"
BANDS = {"radar-5s": ("4.5-5.5 s", [4.5, 5.5], "5"), "radar-11s": ("10-12 s", [10.0, 12.0], "11")}
RADARS = ("range std U[10, 80] m, azimuth and elevation stds U[0.03, 0.3] deg, drawn per window, each flight's radar "
          "5-150 km from it, 5 % missed")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--name", required=True, choices=sorted(BANDS))
    p.add_argument("--run", default="runs/radar-range", help="scripts/radar_range.sh's folder (default %(default)s)")
    p.add_argument("--commit", default="HEAD", help="the commit the weights were trained at (default: HEAD)")
    p.add_argument("--note", default="", help="how the training departed from the recipe, if it did")
    a = p.parse_args(argv)
    scans, span, s = BANDS[a.name]
    run = ROOT / a.run
    registry = f"immnet-{a.name}"
    trained = run / a.name / "checkpoints/best.ckpt"
    if not trained.is_file():
        p.error(f"{trained} does not exist: run scripts/radar_range.sh first")
    commit = subprocess.run(["git", "rev-parse", "--verify", f"{a.commit}^{{commit}}"], cwd=ROOT, capture_output=True,
                            text=True).stdout.strip()
    if not commit:
        p.error(f"--commit {a.commit!r} is not a commit of this repository")
    validation = {}
    for path in sorted(run.glob(f"val-*.json")):
        d = json.loads(path.read_text())
        if registry in d["methods"]:
            validation[path.stem[len("val-"):]] = {"data": str(Path(d["data"]).relative_to(ROOT)) if Path(d["data"]).is_absolute() else d["data"],
                                                   "n": d["n_trajectories"],
                                                   "metrics": {m: v["rmse"] for m, v in d["methods"].items()}}
    if not validation:
        p.error(f"no validation scores of {registry} in {run}/val-*.json: run scripts/radar_range.sh first")
    from immnet.checkpoints import CHECKSUM_KEY, load_checkpoint, record_shipped
    from immnet.training.export import export_weights

    ckpt = load_checkpoint(trained)
    out = export_weights(trained, OUT / f"{registry}.ckpt")
    record_shipped(a.name)
    checksum = load_checkpoint(out)[CHECKSUM_KEY]
    sets = ["clean", "out5", "out10", "out20"]
    prov = {
        "file": f"immnet/pretrained/{registry}.ckpt",
        "weights_sha256": checksum,
        "recipe": f"recipes/{a.name}.yaml",
        "init": (f"its untrained start (the output correction's last layer zero: radar-imm-robust-{s}s, the joint IMM "
                 "told each plot's covariance with Huber's update and its re-acquisition, exactly)"),
        "made_by": f".venv/bin/python scripts/ship_radar.py --name {a.name}",
        "date": datetime.date.today().isoformat(),
        "commit": commit,
        "global_step": ckpt.get("global_step"),
        "data": {"train": [f"{DATA}/r{s}-{x}/train" for x in sets], "val": [f"{DATA}/r{s}-{x}/val" for x in sets],
                 "what": (f"collections/quickstart's training flights (immnet data adsb --splits 0.7,0.15,0.15 --seed "
                          f"0; no validation or test flight trained on) at {scans} scans, seen by radars of {RADARS}; "
                          "clean, and 1 % outliers at 5x, 3 % at 10x, 5 % at 20x (scripts/radar_range.sh)")},
        "guard": None,
        "scan_interval": None,
        "interval_range": span,
        "settings": None,
        "wandb": None,
        "note": a.note,
        "validation": validation,
    }
    (OUT / f"provenance-{a.name}.json").write_text(json.dumps(prov, indent=2, allow_nan=False) + "\n")
    rows = []
    for set_name, v in validation.items():
        m = {k: r["avg"] for k, r in v["metrics"].items()}
        best = min(m[f"radar-imm-{s}s"], m[f"radar-imm-robust-{s}s"])
        rows.append(f"| `{v['data']}` | {v['n']} | {m[f'radar-imm-{s}s']:.2f} | {m[f'radar-imm-robust-{s}s']:.2f} | "
                    f"{m[registry]:.2f} | {m[registry] / best:.3f} |")
    lines = [f"# Shipped IMMNet weights: {a.name}\n",
             f"`{registry}.ckpt` ({out.stat().st_size / 2**20:.2f} MB, `weights_sha256` {checksum}): an output "
             f"correction (one GRU layer of 64) reading the innovation whitened by each plot's covariance, on "
             f"radar-imm-robust-{s}s as IMMNet's step (its filter experts told each plot's covariance, `r: detection`, "
             f"Huber's update, its re-acquisition: immnet.imm.reacquire, and its start's prior on the vertical speed, as "
             f"the recipe sets them), only the correction learned; for a "
             f"surveillance radar's plots at {scans} "
             f"scans, told each plot's covariance (the data's `meas_cov`; docs/radar.md). Trained by "
             f"`{prov['recipe']}` from {prov['init']} at commit `{commit[:10]}` ({prov['date']}), "
             f"{prov['global_step']} steps, chosen on the validation splits below; exported by `{prov['made_by']}`. "
             f"Registry name `{registry}`; it takes scan intervals {span[0]:g}-{span[1]:g} s. No range guard.\n",
             f"Training data: {prov['data']['what']}: " + ", ".join(prov["data"]["train"]) + ".\n",
             "W&B: no run id recorded for this training (`wandb: null`).\n",
             *([f"Note: {a.note}.\n"] if a.note else []),
             "Validation splits (what it was chosen and shipped on; Average RMSE, m, each set one `immnet evaluate` "
             "run; the ratio to the better filter told each plot's covariance). The test splits' tables are "
             "docs/radar.md's.\n",
             f"| validation set | windows | radar-imm-{s}s | radar-imm-robust-{s}s | {registry} | ratio |\n"
             "|:---|---:|---:|---:|---:|---:|\n" + "\n".join(rows) + "\n"]
    (OUT / f"PROVENANCE-{a.name}.md").write_text("\n".join(lines))
    print(f"wrote {out}, provenance-{a.name}.json and PROVENANCE-{a.name}.md", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
