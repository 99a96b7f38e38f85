"""Where a multi-target tracker's GOSPA goes: its parts per scan split by cause, on a scene set's TRAINING scenes
(the split ``train`` unless told another), for choosing what to work on without looking at held-out scenes.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/mtt_breakdown.py --scenes data/scenes63 [--filter real-imm-5s] \\
        [--confirm 4,5] [--delete-after 3] [--no-cover] [--split train]

Each scan is scored as ``immnet.evaluation.gospa.gospa`` scores it (c = 200 m, p = 2, alpha = 2); the missed and false
parts (``c^2 / 2`` each) are then put under one cause each:

* a missed aircraft: ``new`` (never yet paired with a track in this scene; ``<4``: fewer than four of its plots so
  far, so no 4-of-5 track could be confirmed on it) or ``seen`` (paired before: its track was lost or has drifted),
  and ``off`` where a reported track lies within 1 km of it (beyond the cut-off, not missing) else ``none``;
* a false track: ``off`` (an aircraft within 1 km: a track drifted beyond the cut-off) or ``ghost`` (none within
  1 km), and ``outside`` where its position lies outside the radar's cover; ``off`` is also split by the track's
  age (scans since it was first reported, 5 for 5 or more) and range (20 km bins);
* the localisation part by direction: along the horizontal range, across it, and height; and its RMS per 25 km of
  range.

Every number is a mean per scan over all scans of the split's scenes (m^2), as the benchmark's parts are.
"""

from __future__ import annotations

import argparse
import collections
import sys
from pathlib import Path

import numpy as np

from immnet.data.scenes import load_split
from immnet.evaluation.gospa import gospa
from immnet.evaluation.scenes import cover, run_tracker

C = 200.0
DUMMY = C**2 / 2


def breakdown(scenes, filter: str, **settings) -> tuple[float, dict, dict]:
    """``(mean GOSPA, {cause: mean per scan}, {25 km range bin: localisation RMS})`` of the tracker over ``scenes``."""
    parts, per_range, gospas = collections.Counter(), collections.defaultdict(list), []
    for sc in scenes:
        run = run_tracker(sc, filter, **settings)
        seen_by = cover(sc.meta["spec"])
        n_plots, ever, born = collections.Counter(), set(), {}
        for k in range(len(sc)):
            a, b = sc.plot_offsets[k], sc.plot_offsets[k + 1]
            n_plots.update(int(s) for s in sc.plot_source[a:b] if s >= 0)
            tpos, tid = sc.truth(k)
            epos, eid = run["est_pos"][k], run["est_ids"][k]
            for i in eid.tolist():
                born.setdefault(i, k)
            g = gospa(tpos, epos, C, 2.0, 2.0)
            gospas.append(g["gospa"])
            asg = g["assignment"]
            for i, truth in enumerate(tid.tolist()):
                if asg[i] >= 0:
                    d = tpos[i] - epos[asg[i]]
                    u = tpos[i][:2] / np.linalg.norm(tpos[i][:2])
                    parts["localisation along range"] += (d[:2] @ u) ** 2
                    parts["localisation across range"] += (d[0] * u[1] - d[1] * u[0]) ** 2
                    parts["localisation height"] += d[2] ** 2
                    per_range[int(np.linalg.norm(tpos[i]) // 25000)].append(d @ d)
                    ever.add(truth)
                    continue
                near = np.linalg.norm(epos - tpos[i], axis=1).min(initial=np.inf)
                kind = "seen" if truth in ever else ("new <4 plots" if n_plots[truth] < 4 else "new")
                kind += " (the scene's first 3 scans)" if k < 3 and kind != "seen" else ""
                parts[f"missed {kind}, {'off' if near < 1000 else 'none'}"] += DUMMY
            used = set(asg[asg >= 0].tolist())
            for j in range(len(epos)):
                if j in used:
                    continue
                near = np.linalg.norm(tpos - epos[j], axis=1).min(initial=np.inf)
                outside = "" if seen_by.contains(epos[j]) else ", outside the cover"
                parts[f"false {'off' if near < 1000 else 'ghost'}{outside}"] += DUMMY
                if near < 1000:
                    parts[f"false off, age {min(k - born[int(eid[j])], 5)}"] += DUMMY
                    parts[f"false off, range {int(np.linalg.norm(epos[j]) // 20000) * 20} km+"] += DUMMY
    n = len(gospas)
    rms = {f"{b * 25}-{b * 25 + 25} km": float(np.sqrt(np.mean(v))) for b, v in sorted(per_range.items())}
    return float(np.mean(gospas)), {k: v / n for k, v in sorted(parts.items())}, rms


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", required=True, type=Path, help="a scene set of `immnet data scenes`")
    ap.add_argument("--split", default="train", help="the scenes' split (default train)")
    ap.add_argument("--filter", default=None, help="the per-track filter (default: the tracker's)")
    ap.add_argument("--confirm", default=None, help="M,N (default: the tracker's)")
    ap.add_argument("--delete-after", type=int, default=None)
    ap.add_argument("--no-cover", action="store_true", help="do not tell the tracker the radar's cover")
    a = ap.parse_args(argv)
    from immnet.filters.multi import DEFAULT_FILTER

    settings = {}
    if a.confirm:
        settings["confirm"] = tuple(int(v) for v in a.confirm.split(","))
    if a.delete_after is not None:
        settings["delete_after"] = a.delete_after
    if a.no_cover:
        settings["cover"] = None
    scenes = load_split(a.scenes, a.split)
    mean, parts, rms = breakdown(scenes, a.filter or DEFAULT_FILTER, **settings)
    print(f"{a.filter or DEFAULT_FILTER} {settings or ''} on {len(scenes)} {a.split} scenes: mean GOSPA {mean:.1f} m")
    for k, v in parts.items():
        print(f"  {k:52s} {v:9.0f}")
    for k, v in rms.items():
        print(f"  localisation RMS {k:35s} {v:9.0f} m")
    return 0


if __name__ == "__main__":
    sys.exit(main())
