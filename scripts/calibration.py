"""Are the trackers' covariances honest? Coverage of the 95 % (and every other) position ellipsoid.

Runs each method that gives its state's covariance (built with ``return_cov=True``) on a data set and writes
a JSON of its coverages (``immnet.evaluation.calibration.track_coverage``) and the calibration figure
(``immnet.evaluation.figures.plot_calibration``: coverage against confidence level, the diagonal calibrated):

    python scripts/calibration.py --generate 300 --T 200 --seed 99 --methods immnet,imm-ekf,imm-tuned,imm-accurate \
        --figure docs/figures/calibration_3dlast.png --json docs/figures/calibration_3dlast.json
    python scripts/calibration.py --data DATA --split test --methods immnet,imm-ekf --figure calib.png

Scans from ``--from-scan`` on are scored (past the track start), where the truth is and the track has started.

``--consistency CKPT=W1,W2,...`` adds the IMMNet of ``CKPT`` (a checkpoint or shipped weights) as it is and with each
covariance-consistency weight (``IMMNet(cov_consistency=W)``: what it reports, not what it estimates; docs/immnet.md),
the rows a weight is chosen from on validation data (docs/real.md, "Calibration").
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _rounded(value, digits: int = 4):
    """Floats to ``digits`` decimals, throughout (a readable JSON)."""
    if isinstance(value, dict):
        return {k: _rounded(v, digits) for k, v in value.items()}
    return round(value, digits) if isinstance(value, float) else value


def _with_consistency(ckpt: str, weight: float | None, name: str):
    """The IMMNet of ``ckpt`` as a method that gives its covariance, with ``cov_consistency`` ``weight`` (None: as
    the file has it): the weights exported with that setting, as ``scripts/make_shipped.py`` ships them."""
    import tempfile

    from immnet.tracking.methods import IMMNetMethod
    from immnet.training.export import export_weights

    if weight is None:
        return IMMNetMethod(ckpt, name, return_cov=True)
    with tempfile.TemporaryDirectory() as tmp:
        return IMMNetMethod(str(export_weights(ckpt, Path(tmp) / "net.ckpt", {"cov_consistency": weight})), name,
                            return_cov=True)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--data", help="a data set directory or .npz (with states, the truth)")
    src.add_argument("--generate", type=int, metavar="N", help="generate N 3D-LAST trajectories")
    p.add_argument("--seed", type=int, default=99, help="the generator's seed (with --generate)")
    p.add_argument("--T", type=int, default=200, help="scans per generated trajectory (with --generate; default 200)")
    p.add_argument("--split", choices=("test", "all"), default="test", help="with --data, as immnet evaluate's")
    p.add_argument("--limit", type=int, help="only the first N trajectories of the split")
    p.add_argument("--methods", default="immnet,imm-ekf,imm-tuned", help="comma-separated method names")
    p.add_argument("--from-scan", type=int, default=20, help="the first scan scored (default 20)")
    p.add_argument("--consistency", metavar="CKPT=W1,W2,...",
                   help="also the IMMNet of CKPT as it is and with each covariance-consistency weight W")
    p.add_argument("--figure", type=Path, help="write the calibration figure (PNG) here")
    p.add_argument("--json", type=Path, help="write the coverages as JSON here")
    args = p.parse_args(argv)

    from immnet.evaluation.calibration import CURVE_LEVELS, LEVELS, track_coverage
    from immnet.filters.methods import build_method, gives_cov

    if args.generate is not None:
        from immnet.data.generate import generate
        from immnet.data.spec import DataSpec

        data = generate(args.generate, seed=args.seed, spec=DataSpec(T=args.T))
        source = f"3D-LAST, {args.generate} trajectories x {args.T} scans, seed {args.seed}"
    else:
        from immnet.evaluation.cli import load_split

        data, _ = load_split(args.data, args.split, args.limit)
        source = f"{args.data} ({args.split})"
    if args.limit is not None:
        data = data[: args.limit]
    names = [n.strip() for n in args.methods.split(",") if n.strip()]
    without = [n for n in names if not gives_cov(n)]
    if without:
        p.error(f"no covariance from {', '.join(without)} (their constructors take no return_cov)")
    methods = {name: (lambda name=name: build_method(name, return_cov=True)) for name in names}
    if args.consistency:
        ckpt, _, weights = args.consistency.partition("=")
        try:
            weights = [float(w) for w in weights.split(",") if w.strip()]
        except ValueError:
            p.error(f"--consistency wants CKPT=W1,W2,... (weights in (0, 1]), got {args.consistency!r}")
        for w in (None, *weights):
            label = Path(ckpt).stem + ("" if w is None else f", consistency {w:g}")
            methods[label] = lambda ckpt=ckpt, w=w, label=label: _with_consistency(ckpt, w, label)
    levels = tuple(sorted(set(CURVE_LEVELS) | set(LEVELS)))
    results = {}
    for name, build in methods.items():
        start = time.perf_counter()
        scores = track_coverage(build(), data, args.from_scan, levels)
        results[name] = scores
        split = (f"; {scores['post_switch'][0.95]:.3f} after a switch, {scores['steady'][0.95]:.3f} elsewhere"
                 if "post_switch" in scores else "")
        print(f"{name}: 95 % ellipsoid holds the truth at {scores['coverage'][0.95]:.3f} of {scores['scans']} scans{split}, "
              f"mean NEES {scores['nees_mean']:.2f} (3 calibrated) [{time.perf_counter() - start:.0f} s]", file=sys.stderr)
    report = {"data": source, "trajectories": int(data.batch_size[0]), "from_scan": args.from_scan, "methods": results}
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(_rounded(report), indent=1) + "\n")
    if args.figure:
        from immnet.evaluation.figures import plot_calibration

        args.figure.parent.mkdir(parents=True, exist_ok=True)
        title = f"Position ellipsoid coverage\n{source}; scans {args.from_scan}+"
        plot_calibration({n: r["coverage"] for n, r in results.items()}, args.figure, title=title)
    return 0


if __name__ == "__main__":
    sys.exit(main())
