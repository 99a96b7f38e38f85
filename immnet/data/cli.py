"""``immnet data generate|merge|export|plot|adsb|subset|turns|scenes``: make, convert and look at 3D-LAST data sets;
real flights; multi-target scenes.

    immnet data generate --out data/train --n 100000 --seed 0 [--single-mode ct+] [--config configs/data/tiny.yaml] [--workers 2]
    immnet data generate --out data/train-1 --n 1000000 --seed 0 --shard 1/4      # shard 1 of 4 (one machine's part)
    immnet data generate --out data/polar --n 10000 --seed 0 --sigma-range 20,60 --sigma-azimuth 0.05,0.2 --sigma-elevation 0.05,0.3
    immnet data merge --out data/train data/train-0 data/train-1 data/train-2 data/train-3
    immnet data export --data data/train --out train.npz
    immnet data plot --data data/train --out trajectories.png [--n 400] [--seed 0]
    immnet data adsb --samples collections/quickstart --out data/real/quickstart [--T 200] [--dt 1] [--seed 0]
    immnet data subset --data data/real/quickstart/train --out data/real/train-half --flights 0.5 [--seed 0]
    immnet data subset --data data/real/quickstart-1s/test --out data/real/unseen --without data/real/other/{train,val}
    immnet data turns --data data/real/quickstart/val --out data/real/val-turns --turns 0.5 [--bank 10,30] [--seed 0]
    immnet data scenes --samples collections/quickstart collections/switzerland --out data/scenes --n 3 [--last 2]
"""

from __future__ import annotations

import argparse
from pathlib import Path

from immnet.labels import MODE_NAMES


def _generate(args) -> int:
    from immnet.data.spec import PLOT_PAIRS, DataSpec
    from immnet.data.storage import write_dataset

    spec = DataSpec()
    if args.config:
        from immnet.config import resolve_path

        spec = DataSpec.from_yaml(resolve_path(args.config))
    plots = {}
    for name, unit in PLOT_PAIRS.items():
        pair = getattr(args, name)
        if pair is not None:
            plots.update({f"{name}_min{unit}": pair[0], f"{name}_max{unit}": pair[1]})
    plots.update({k: getattr(args, k) for k in ("outliers", "outlier_scale") if getattr(args, k) is not None})
    if plots:
        spec = DataSpec.from_dict({**spec.to_dict(), **plots})
    out = write_dataset(args.out, args.n, args.seed, spec, single_mode=args.single_mode,
                        overwrite=args.overwrite, workers=args.workers, progress=not args.quiet,
                        shard=args.shard)
    if args.shard is None:
        print(f"wrote {args.n} trajectories (T={spec.T}, seed {args.seed}) to {out}")
    else:
        from immnet.data.storage import shard_rows

        a, b = shard_rows(args.n, *args.shard)
        print(f"wrote shard {args.shard[0]} of {args.shard[1]}: trajectories [{a}, {b}) of {args.n} "
              f"(T={spec.T}, seed {args.seed}) to {out}")
    return 0


def _shard(text: str) -> tuple[int, int]:
    """``"i/K"`` -> ``(i, K)``; the range is checked by ``write_dataset`` (with ``n`` known)."""
    i, sep, k = text.partition("/")
    try:
        if not sep:
            raise ValueError
        return int(i), int(k)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected INDEX/COUNT such as 0/4, got {text!r}") from None


def _merge(args) -> int:
    from immnet.data.shards import merge_shards

    out = merge_shards(args.out, args.shards, overwrite=args.overwrite, progress=not args.quiet)
    print(f"merged {len(args.shards)} shards into {out}")
    return 0


def _export(args) -> int:
    from immnet.data.storage import export_npz

    out = export_npz(args.data, args.out)
    print(f"wrote {out}")
    return 0


def _plot(args) -> int:
    from immnet.data.plot import plot_trajectories
    from immnet.data.storage import load_dataset

    td, _ = load_dataset(args.data)
    out = plot_trajectories(td, args.out, n=args.n, seed=args.seed)
    print(f"wrote {out}")
    return 0


def _floats(n: int, what: str):
    """An argparse type: ``n`` comma-separated numbers."""

    def parse(text: str) -> tuple[float, ...]:
        try:
            vals = tuple(float(v) for v in text.split(","))
        except ValueError:
            vals = ()
        if len(vals) != n:
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
        return vals

    return parse


_pair = _floats(2, "LOW,HIGH (two numbers)")


def _splits(text: str) -> tuple[float, float, float]:
    if text == "all-test":
        return 0.0, 0.0, 1.0
    return _floats(3, "TRAIN,VAL,TEST fractions such as 0.7,0.15,0.15 (or all-test)")(text)


def _adsb(args) -> int:
    from immnet.data.real import PAIRS, RealSpec, make_adsb

    if args.splits is not None and args.splits_from is not None:
        raise ValueError("give --splits or --splits-from, not both: --splits-from takes the other set's partition")
    same = ("T", "dt", "dt_jitter", "p_miss", "max_range", "max_gap", "max_flights", "truth_gap",
            "max_position_interval", "outliers", "outlier_scale")  # the options named as RealSpec's fields
    spec = RealSpec(**{k: getattr(args, k) for k in same}, **{k: getattr(args, k) or () for k in PAIRS},
                    r_min=args.r[0], r_max=args.r[1], splits=args.splits or RealSpec.splits)
    meta = make_adsb(args.out, args.samples, spec, seed=args.seed, site=args.site, npz=args.npz,
                     overwrite=args.overwrite, progress=not args.quiet, skip_unreadable=args.skip_unreadable,
                     splits_from=args.splits_from)
    c = meta["counts"]
    wins = ", ".join(f"{k} {v}" for k, v in c["windows"].items() if v)
    print(f"wrote {args.out}: {c['flights_with_windows']} flights with windows ({wins}); {c['fresh_points']} fresh "
          f"points, {c['stale']} stale and {c['glitch']} glitch rows removed ({meta['seconds']:.1f} s)")
    if c.get("unsplit"):
        print(f"left out {c['unsplit']} flight(s) with windows that {meta['splits_from']} does not split")
    if c["sparse"]:
        print(f"left out {c['sparse']} flight(s) whose fresh positions lie more than {spec.max_position_interval:g} s "
              f"apart (median)")
    if meta["skipped"]:
        print(f"skipped {len(meta['skipped'])} unreadable sample(s): {', '.join(s['name'] for s in meta['skipped'])}")
    return 0


def _subset(args) -> int:
    from immnet.data.real import subset_flights

    meta = subset_flights(args.data, args.out, args.flights, seed=args.seed, overwrite=args.overwrite,
                          without=args.without)
    s = meta["subset"]
    out = f" ({s['without']['flights']} left out as flights of --without)" if "without" in s else ""
    print(f"wrote {args.out}: {s['flights']} of {s['of_flights']} flights{out}, {s['windows']} of {s['of_windows']} "
          f"windows (seed {s['seed']})")
    return 0


def _turns(args) -> int:
    from immnet.data.real import turned_flights

    meta = turned_flights(args.data, args.out, args.turns, seed=args.seed, bank=args.bank, segment=args.segment,
                          overwrite=args.overwrite)
    t = meta["turns"]
    print(f"wrote {args.out}: {meta['n']} windows, turns added to a share {t['turns']:g} of them (bank "
          f"{t['bank'][0]:g}-{t['bank'][1]:g} deg, segments {t['segment'][0]:g}-{t['segment'][1]:g} s, "
          f"seed {t['seed']})")
    return 0


def _flights(text: str) -> float:
    return _floats(1, "a count such as 40 or a fraction such as 0.25")(text)[0]


def _scenes(args) -> int:
    from immnet.data.scenes import SceneSpec, make_scenes

    same = ("duration", "dt", "dt_jitter", "pd", "clutter", "sigma_range", "max_range", "max_elevation", "truth_gap",
            "crossing_pairs", "close_pairs")  # the options named as SceneSpec's fields
    spec = SceneSpec(**{k: getattr(args, k) for k in same}, sigma_azimuth_deg=args.sigma_azimuth,
                     sigma_elevation_deg=args.sigma_elevation, min_targets=args.targets_in_cover[0],
                     max_targets=args.targets_in_cover[1], targets=args.last_targets)
    index = make_scenes(args.out, args.samples, n=args.n, spec=spec, seed=args.seed, site=args.site, last=args.last,
                        last_split=args.last_split, write_csv=args.csv, overwrite=args.overwrite, progress=not args.quiet)
    per = {}
    for e in index["scenes"]:
        per.setdefault(e["split"], []).append(e["name"])
    print(f"wrote {args.out}: " + "; ".join(f"{k} {len(v)} ({', '.join(v)})" for k, v in sorted(per.items()))
          + f" ({index['seconds']:.1f} s)")
    return 0


def _ints2(text: str) -> tuple[int, int]:
    lo, hi = _pair(text)
    if lo != int(lo) or hi != int(hi):
        raise argparse.ArgumentTypeError(f"expected MIN,MAX (two whole numbers), got {text!r}")
    return int(lo), int(hi)


def _writes(parser, func, progress: str | None = "no progress lines") -> None:
    """A writing subcommand's last options: ``--overwrite`` (its output directory), ``--quiet`` (where it says
    ``progress``), and its function."""
    parser.add_argument("--overwrite", action="store_true", help="replace a non-empty output directory")
    if progress:
        parser.add_argument("--quiet", action="store_true", help=progress)
    parser.set_defaults(func=func)


def _sigma_options(parser, where: str, per: str, instead: str) -> None:
    """``--sigma-range``, ``--sigma-azimuth``, ``--sigma-elevation``: a radar's plots (``where`` it stands), each a
    noise std drawn per ``per``; ``instead``: what the three replace."""
    for option, unit, what in (("range", "m", "slant range"), ("azimuth", "degrees", "azimuth"),
                               ("elevation", "degrees", "elevation")):
        parser.add_argument(f"--sigma-{option}", type=_floats(2, "LOW,HIGH such as 20,60"), default=None,
                            metavar="LOW,HIGH", help=f"a radar's plots{' ' + where if where else ''}: the {what} noise "
                                                     f"std per {per}, U[LOW, HIGH] ({unit}); the three --sigma-* "
                                                     f"together, {instead}")


def register(subparsers) -> None:
    data = subparsers.add_parser("data", help="generate, merge, export and plot 3D-LAST data sets; real ADS-B flights",
                                 description=__doc__.splitlines()[0])
    sub = data.add_subparsers(dest="data_command", required=True, metavar="ACTION")

    g = sub.add_parser("generate", help="generate a 3D-LAST data set directory (memmapped TensorDict)")
    g.add_argument("--out", required=True, type=Path, help="output directory (must be absent or empty)")
    g.add_argument("--n", required=True, type=int, help="number of trajectories")
    g.add_argument("--seed", required=True, type=int)
    g.add_argument("--single-mode", choices=MODE_NAMES, default=None,
                   help="one-segment trajectories of this mode (stage-1 data)")
    g.add_argument("--config", default=None, help="YAML of DataSpec fields to override (e.g. configs/data/tiny.yaml)")
    _sigma_options(g, "from the origin", "trajectory", "in place of r N(0, I3), writing meas_cov")
    g.add_argument("--outliers", type=float, default=None,
                   help="with the plots: share of the detections whose noise is --outlier-scale times larger "
                        "(default 0)")
    g.add_argument("--outlier-scale", type=float, default=None, help="an outlier's noise factor (default 10)")
    g.add_argument("--workers", type=int, default=1, help="processes to shard generation over (same bytes)")
    g.add_argument("--shard", type=_shard, default=None, metavar="I/K",
                   help="write only shard I of K (whole blocks; for several machines), joined by `immnet data merge`")
    _writes(g, _generate, "no progress bar")

    m = sub.add_parser("merge", help="join the K shards of one data set (generate --shard I/K) into one directory")
    m.add_argument("--out", required=True, type=Path, help="output directory (must be absent or empty)")
    m.add_argument("shards", nargs="+", type=Path, metavar="SHARD_DIR", help="every shard directory, any order")
    _writes(m, _merge, "no progress bar")

    e = sub.add_parser("export", help="write a data set as one .npz interchange file")
    e.add_argument("--data", required=True, type=Path, help="data set directory or .npz")
    e.add_argument("--out", required=True, type=Path, help="output .npz")
    e.set_defaults(func=_export)

    p = sub.add_parser("plot", help="3D plot of randomly sampled trajectories, colored by mode")
    p.add_argument("--data", required=True, type=Path, help="data set directory or .npz")
    p.add_argument("--out", required=True, type=Path, help="output .png")
    p.add_argument("--n", type=int, default=400, help="trajectories to draw (default 400)")
    p.add_argument("--seed", type=int, default=0, help="seed of the random sample")
    p.set_defaults(func=_plot)

    a = sub.add_parser("adsb", help="real ADS-B flights seen by a simulated radar, split by flight (docs/data.md)")
    a.add_argument("--samples", required=True, nargs="+", metavar="SAMPLE",
                   help="sample names of traffic's data/samples (e.g. collections/quickstart), or files of state "
                        "vectors: JSON as traffic's samples, or CSV with a header (traffic's field names or "
                        "OpenSky's: time, icao24, lat, lon, baroaltitude in metres, lastposupdate)")
    a.add_argument("--out", required=True, type=Path, help="output directory: OUT/train, OUT/val, OUT/test")
    a.add_argument("--T", type=int, default=200, help="scans per window (default 200)")
    a.add_argument("--dt", type=float, default=1.0, help="scan interval, or its mean with --dt-jitter (s, default 1)")
    a.add_argument("--dt-jitter", type=float, default=0.0, help="intervals U[dt - j, dt + j] (s, default 0)")
    a.add_argument("--p-miss", type=float, default=0.0, help="missed-detection probability (default 0)")
    a.add_argument("--r", type=_floats(2, "RMIN,RMAX such as 1,7"), default=(1.0, 7.0), metavar="RMIN,RMAX",
                   help="measurement noise std per window, U[RMIN, RMAX] (m, default 1,7)")
    _sigma_options(a, "", "window", "in place of --r (default: 3D-LAST's noise r N(0, I3))")
    a.add_argument("--outliers", type=float, default=0.0,
                   help="share of the detections whose noise is --outlier-scale times larger (default 0)")
    a.add_argument("--outlier-scale", type=float, default=10.0, help="an outlier's noise factor (default 10)")
    a.add_argument("--range-km", type=_floats(2, "LOW,HIGH such as 10,150"), default=None, metavar="LOW,HIGH",
                   help="a radar per flight, U[LOW, HIGH] km from the flight's median position, seeing slant ranges "
                        "in [LOW, HIGH] km (default: --site or each sample's median)")
    a.add_argument("--seed", type=int, default=0)
    a.add_argument("--splits", type=_splits, default=None, metavar="TRAIN,VAL,TEST",
                   help="fractions of flights (default 0.7,0.15,0.15), or all-test")
    a.add_argument("--splits-from", type=Path, default=None, metavar="SET",
                   help="take the partition of the flights of SET (a set of the same samples, its OUT or one split) "
                        "instead of --splits: one partition for every scan interval of a region")
    a.add_argument("--site", type=_floats(3, "LAT,LON,H such as 48.9,2.5,0"), default=None, metavar="LAT,LON,H",
                   help="radar site for every sample (degrees, degrees, m; default: each sample's own radar at the "
                        "median position of its flights, height 0)")
    a.add_argument("--max-range", type=float, default=200_000.0, help="radar coverage, slant range (m, default 200000)")
    a.add_argument("--max-gap", type=float, default=600.0, help="a longer gap starts a new flight (s, default 600)")
    a.add_argument("--truth-gap", type=float, default=5.0,
                   help="a scan has truth only between fresh positions at most this far apart (s, default 5; "
                        "samples of state vectors every 10 s need more)")
    a.add_argument("--max-position-interval", type=float, default=0.0, metavar="S",
                   help="leave out flights whose fresh positions lie more than S s apart at the median (counted as "
                        "'sparse'; default 0: none): at faster scans their truth between positions is interpolation")
    a.add_argument("--max-flights", type=int, default=0, help="only the first N flights by id (default 0: all)")
    a.add_argument("--npz", action="store_true", help="also write OUT/<split>.npz")
    a.add_argument("--skip-unreadable", action="store_true",
                   help="skip a sample that is not readable state vectors (listed in meta.json) instead of stopping")
    _writes(a, _adsb)

    s = sub.add_parser("subset", help="the windows of some of a real-flight set's flights (a data-scaling curve)")
    s.add_argument("--data", required=True, type=Path, help="a split of `immnet data adsb` (e.g. OUT/train)")
    s.add_argument("--out", required=True, type=Path, help="output directory (must be absent or empty)")
    s.add_argument("--flights", type=_flights, metavar="N|FRACTION",
                   help="flights to keep: a count (40) or a fraction below 1 (0.25); with one seed a smaller subset "
                        "is part of every larger one (default: every flight left by --without)")
    s.add_argument("--without", nargs="+", type=Path, default=[], metavar="SPLIT_DIR",
                   help="leave out the flights these splits of real-flight sets name (e.g. the training and "
                        "validation splits of a set of the same samples at another scan interval)")
    s.add_argument("--seed", type=int, default=0, help="seed of the flights' permutation (default 0)")
    _writes(s, _subset, None)

    t = sub.add_parser("turns", help="a real-flight set's windows with turns added to some (patterns, orbits)")
    t.add_argument("--data", required=True, type=Path, help="a split of `immnet data adsb` (e.g. OUT/val)")
    t.add_argument("--out", required=True, type=Path, help="output directory (must be absent or empty)")
    t.add_argument("--turns", required=True, type=float, help="share of the windows given added turns, in [0, 1]")
    t.add_argument("--bank", type=_pair, default=(10.0, 30.0), metavar="LOW,HIGH",
                   help="bank angle of an added coordinated turn, degrees (default 10,30)")
    t.add_argument("--segment", type=_pair, default=(20.0, 120.0), metavar="LOW,HIGH",
                   help="seconds of each straight or turning segment (default 20,120)")
    t.add_argument("--seed", type=int, default=0, help="seed of the turns and the new noise (default 0)")
    _writes(t, _turns, None)

    sc = sub.add_parser("scenes", help="multi-target scenes: several aircraft, one radar, missed detections and "
                                       "clutter (docs/data.md)")
    sc.add_argument("--samples", nargs="*", default=[], metavar="SAMPLE",
                    help="ADS-B samples (names or files); scenes of collections/quickstart are for training and "
                         "tuning (OUT/train), of any other sample for evaluation only (OUT/test)")
    sc.add_argument("--out", required=True, type=Path, help="output directory: OUT/scenes.json, OUT/<split>/NAME.npz")
    sc.add_argument("--n", type=int, default=3, help="scenes per sample (default 3)")
    sc.add_argument("--last", type=int, default=0, help="3D-LAST scenes to add (default 0)")
    sc.add_argument("--last-split", choices=("train", "test"), default="test", help="split of the 3D-LAST scenes")
    sc.add_argument("--seed", type=int, default=0)
    sc.add_argument("--duration", type=float, default=300.0, help="seconds per scene (default 300)")
    sc.add_argument("--dt", type=float, default=5.0, help="scan interval, or its mean with --dt-jitter (s, default 5)")
    sc.add_argument("--dt-jitter", type=float, default=0.5, help="intervals U[dt - j, dt + j] (s, default 0.5)")
    sc.add_argument("--pd", type=float, default=0.9, help="detection probability (default 0.9)")
    sc.add_argument("--clutter", type=float, default=10.0, help="mean clutter plots per scan (Poisson, default 10)")
    sc.add_argument("--sigma-range", type=float, default=30.0, help="range noise std (m, default 30)")
    sc.add_argument("--sigma-azimuth", type=float, default=0.15, help="azimuth noise std (degrees, default 0.15)")
    sc.add_argument("--sigma-elevation", type=float, default=0.15, help="elevation noise std (degrees, default 0.15)")
    sc.add_argument("--max-range", type=float, default=60_000.0, help="radar cover, slant range (m, default 60000)")
    sc.add_argument("--max-elevation", type=float, default=30.0,
                    help="top of the clutter's cover (degrees, default 30)")
    sc.add_argument("--targets-in-cover", type=_ints2, default=(5, 14), metavar="MIN,MAX",
                    help="aircraft in cover at every scan of an ADS-B scene (default 5,14)")
    sc.add_argument("--truth-gap", type=float, default=30.0,
                    help="an aircraft has truth at a scan only between fresh positions at most this far apart "
                         "(s, default 30)")
    sc.add_argument("--site", type=_floats(3, "LAT,LON,H such as 48.9,2.5,0"), default=None, metavar="LAT,LON,H",
                    help="radar site for every sample (default: each sample's median position, height 0)")
    sc.add_argument("--last-targets", type=int, default=8, help="targets per 3D-LAST scene (default 8)")
    sc.add_argument("--crossing-pairs", type=int, default=2, help="crossing pairs per 3D-LAST scene (default 2)")
    sc.add_argument("--close-pairs", type=int, default=2, help="close pairs per 3D-LAST scene (default 2)")
    sc.add_argument("--csv", action="store_true", help="also write each scene's plots as NAME.csv "
                                                      "(t,range,azimuth,elevation)")
    _writes(sc, _scenes)
