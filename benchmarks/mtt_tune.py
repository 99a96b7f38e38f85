"""Tune our multi-target tracker's few settings on TRAINING scenes only (split ``train`` of a scene set), by the mean
GOSPA over every scan of those scenes: the per-track filter (the model-based IMMs and Kalman filters tuned on real
flights), M-of-N confirmation, ``delete_after`` and the gate probability (docs/notebook/multi-target.md).

    immnet data scenes --samples collections/quickstart collections/switzerland --out data/scenes63 --n 5
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/mtt_tune.py --scenes data/scenes63 [--out results/mtt_tune.json]

It never reads a ``test`` scene. It writes OUT (every grid point's GOSPA, parts, id switches, and the choice) and
prints the grid sorted by GOSPA.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from pathlib import Path

from immnet.data.scenes import load_index, load_scene
from immnet.evaluation.scenes import evaluate_scenes

FILTERS = ("real-imm-singer", "real-imm-singer-5s", "real-imm-5s", "real-imm-axis-5s", "real-ca-5s")
CONFIRM = ((2, 3), (3, 4), (3, 5), (4, 5))
DELETE_AFTER = (2, 3, 4)
GATE = (0.99, 0.999, 0.9999)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", required=True, type=Path, help="a scene set of `immnet data scenes`")
    ap.add_argument("--tune-scenes", type=int, default=5, help="training scenes to tune on (default 5)")
    ap.add_argument("--filters", default=",".join(FILTERS), help="per-track filters to try (comma-separated)")
    ap.add_argument("--out", type=Path, default=Path("results/mtt_tune.json"))
    a = ap.parse_args(argv)
    index = load_index(a.scenes)
    train = [load_scene(a.scenes / e["file"]) for e in index["scenes"] if e["split"] == "train"][: a.tune_scenes]
    if not train:
        ap.error(f"{a.scenes}: no training scenes (split train) to tune on")
    filters = [f.strip() for f in a.filters.split(",") if f.strip()]
    grid = []
    for f, (m, n), d, g in itertools.product(filters, CONFIRM, DELETE_AFTER, GATE):
        settings = {"confirm": (m, n), "delete_after": d, "gate": g}
        r = evaluate_scenes(train, [f], told=False, raw=False, settings=settings)[f]["mean"]
        row = {"filter": f, "confirm": [m, n], "delete_after": d, "gate": g,
               **{k: r[k] for k in ("gospa", "localisation", "missed", "false", "id_switches", "fragmentations",
                                    "continuity")}}
        grid.append(row)
        print(f"{f} confirm {m}/{n} delete_after {d} gate {g}: GOSPA {r['gospa']:.2f} m, "
              f"id switches {r['id_switches']}", file=sys.stderr, flush=True)
    best = min(grid, key=lambda r: r["gospa"])
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps({"scenes": [s.name for s in train], "grid": grid, "chosen": best}, indent=1) + "\n")
    for r in sorted(grid, key=lambda r: r["gospa"])[:15]:
        print(f"{r['filter']:20s} {r['confirm'][0]}/{r['confirm'][1]} {r['delete_after']} {r['gate']:<7g} "
              f"{r['gospa']:.2f} {r['id_switches']}")
    print(f"chosen: {best}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
