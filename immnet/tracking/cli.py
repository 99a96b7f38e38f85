"""``immnet track --input FILE --output FILE [--checkpoint CKPT]``: estimates for your own measurements.

The input is checked before anything is written, and never written: an ``--output`` that is the
input file (by any path, symlink or hard link) is refused. A measurement a sensor cannot report
(non-finite, or ``|z_a| > --max-position``) is a missed detection, counted on stderr. CSV rows are
tracked in segments (``immnet.tracking.segments``: a track with no detection for more than
``--max-coast`` seconds is dropped and restarts at its next detection). Beside the state and the mode
probabilities the output holds the state's covariance where the tracker keeps one (CSV: the position and
velocity entries ``immnet.data.csvio.COV_COLUMNS``; .npz: ``state_cov [N, T, 9, 9]``). See ``docs/tracking.md``.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

from immnet import keys
from immnet.checkpoints import BANK, DEFAULT_WEIGHTS, SHIPPED, TABLE, WEIGHTS, shipped
from immnet.data.validate import MAX_ABS_POSITION, check_limit, gate_measurements
from immnet.filters.registry import MULTI_TARGET_FILTER
from immnet.tracking import multi_cli
from immnet.tracking.segments import MAX_COAST, check_coast, split_rows, split_segments, track_rows, track_segments

DEFAULT_FILTER = MULTI_TARGET_FILTER
"""The multi-target tracker's per-track filter (``immnet.filters.registry``, read without torch for the help)."""


WEIGHTS_HELP = {BANK: TABLE["bank"]["summary"], **{name: entry["summary"] for name, entry in WEIGHTS.items()}}
"""What each name ``--weights`` takes tracks with (``immnet.checkpoints.SHIPPED`` and ``BANK``), for its help."""


class _HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Each option's default after its help where it has one; an option whose default is None (left out: its help
    says what happens then) shows none."""

    def _get_help_string(self, action):
        return action.help if action.default is None else super()._get_help_string(action)


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "track",
        help="track your own measurements (CSV track_id,t,x,y,z or .npz) with a trained IMMNet, or a radar's "
             "unlabelled plots (CSV t,range,azimuth,elevation or t,x,y,z) with the multi-target tracker",
        formatter_class=_HelpFormatter,
    )
    p.add_argument("--input", required=True, type=Path,
                   help="CSV (track_id,t,x,y,z, optional r_xx..r_zz; or a radar's plots track_id,t,range,azimuth,"
                        "elevation) or .npz with measurements [N,T,3]; a CSV without a track_id column (t,range,"
                        "azimuth,elevation or t,x,y,z, the rows of a scan sharing its t) is a radar's unlabelled "
                        "plots, tracked by the multi-target tracker (docs/multi-target.md)")
    p.add_argument("--output", required=True, type=Path, help="CSV or .npz (same kind as the input)")
    names = (DEFAULT_WEIGHTS, *(name for name in (BANK, *SHIPPED) if name != DEFAULT_WEIGHTS))
    p.add_argument("--weights", default=None, choices=sorted([*SHIPPED, BANK]),
                   help=f"shipped weights by name (default {DEFAULT_WEIGHTS}); "
                        + "; ".join(f"{name}: {WEIGHTS_HELP[name]}" for name in names)
                        + " (immnet/pretrained/PROVENANCE-*.md)")
    p.add_argument("--checkpoint", default=None, help="a Lightning checkpoint or exported weights of your own instead")
    p.add_argument("--method", default=None,
                   help="CSV: a method of immnet evaluate instead of the checkpoint's IMMNet; one that takes any "
                        "interval (e.g. imm-tuned) tracks each row as a scan at its own time (any spacing). Plots "
                        f"without track_id: the multi-target tracker's per-track filter, a model-based IMM or Kalman "
                        f"filter by name (default {DEFAULT_FILTER}, the joint IMM tuned on real flights at the scan "
                        f"interval) or a shipped network by its weights' name (e.g. radar-5s; GNN only)")
    p.add_argument("--max-position", type=float, default=MAX_ABS_POSITION,
                   help="largest |x|, |y|, |z| (m) a detection may have; beyond it, or non-finite, a measurement "
                        "is a missed detection (counted on stderr); 'inf' keeps every finite one")
    p.add_argument("--max-coast", type=float, default=None,
                   help=f"seconds a track may go without a detection before it is dropped; its next "
                        f"detection starts it again ('inf': never dropped; default {MAX_COAST:g})")
    p.add_argument(
        "--guard", default="checkpoint",
        help="range guard: 'checkpoint' (as trained: none in the general weights and in the bank's members, the default; "
             "the 3dlast weights: 3D-LAST's region, "
             "turns back beyond 33 km and within 4 km, and its speed envelope, 40-330 m/s), 'none' (data from another "
             "region), or "
             "'OUTER,INNER' in metres (another region, 3D-LAST's speed envelope)",
    )
    p.add_argument(
        "--r", type=float, default=None, metavar="METRES",
        help="the radar's measurement std (m, each axis), where it is known: the network's filter experts use it in "
             "place of each track's estimate from its measurements, and a --method told each track's r (the "
             "real-flight filters) reads it (docs/tracking.md, 'A radar that knows its accuracy')",
    )
    p.add_argument(
        "--robust", type=float, default=None, metavar="K",
        help="Huber's robust update of the network's (or the bank's) filter experts, k standard deviations (e.g. 3.5): "
             "an isolated plot beyond k pulls the track k deviations at most (plots with outliers; docs/radar.md, "
             "'Outliers'). A CSV of plots with covariances and a --method carry their own",
    )
    for option, unit, what in (("range", "METRES", "slant range (m)"), ("azimuth", "DEG", "azimuth (degrees)"),
                               ("elevation", "DEG", "elevation (degrees)")):
        p.add_argument(
            f"--sigma-{option}", type=float, default=None, metavar=unit,
            help=f"the radar's {what} std, for a CSV of plots (range,azimuth,elevation) without the columns "
                 f"sigma_range,sigma_azimuth,sigma_elevation: the three options together (docs/radar.md, 'Input')",
        )
    p.add_argument("--associator", default=None, choices=("gnn", "jpda"),
                   help="plots without track_id: how plots go to tracks, gnn (an optimal assignment, the default) "
                        "or jpda (each track updated by its gated plots, weighted by their association probabilities)")
    p.add_argument("--pd", type=float, default=None,
                   help="--associator jpda: the probability that an aircraft is detected at a scan (default 0.9)")
    p.add_argument("--clutter-density", type=float, default=None, metavar="PER_M3",
                   help="--associator jpda: false plots per m^3 (default 1e-12)")
    p.add_argument("--max-range", type=float, default=None, metavar="METRES",
                   help="plots without track_id: the radar's cover, the slant range it sees up to; a track that gets "
                        "no plot beyond it is deleted at that scan (default: no cover)")
    p.add_argument("--min-elevation", type=float, default=None, metavar="DEG",
                   help="with --max-range: the lowest elevation the radar sees (default 0)")
    p.add_argument("--figure", type=Path, default=None, metavar="FILE.png",
                   help="plots without track_id: draw the run as a radar display (plots, tracks with their ids, "
                        "range rings)")
    p.add_argument("--scene", type=Path, default=None, metavar="SCENE.npz",
                   help="with --figure: the scene file (immnet data scenes) the CSV was written from; its truth "
                        "marks the clutter")
    p.add_argument(
        "--adapt", action="store_true",
        help="adaptive process noise in the filter experts (immnet.imm.adaptive.AdaptiveNoise): for targets "
             "that fly rougher than the training data (docs/immnet.md, 'Adaptive process noise')",
    )
    p.set_defaults(func=run)


def _load_options(args) -> dict:
    """``--adapt``, ``--robust`` and ``--r`` as ``load_network``'s ``adapt``, ``robust`` and ``r``: the checkpoint's
    setting (``AS_CONFIGURED``) where not given; a clear error unless ``--r`` is a finite number > 0."""
    from immnet.tracking.tracker import AS_CONFIGURED

    multi_cli.check_positive(args.r, "--r is the radar's measurement std in metres, a finite number")
    robust = AS_CONFIGURED if args.robust is None else float(args.robust)
    r = AS_CONFIGURED if args.r is None else float(args.r)
    return {"adapt": True if args.adapt else AS_CONFIGURED, "robust": robust, "r": r}


def _bank(args, limit: float, options: dict):
    """``--weights bank``: the shipped bank as a method (``immnet.tracking.bank.BankMethod``), no range guard unless
    ``--guard`` gives one, ``--adapt``, ``--robust`` and ``--r`` (``options``) for every member."""
    from immnet.imm.guard import parse_guard
    from immnet.tracking.bank import BankMethod

    guard = None if args.guard == "checkpoint" else parse_guard(args.guard)
    method = BankMethod(guard=guard, return_cov=True, max_position=limit, **options)
    method.net.max_coast = check_coast(args.max_coast, method.net.dt)  # the rows' segments are cut at it already
    return method


def _tracker(args, weights: Path, limit: float, options: dict):
    """The ``Tracker`` of ``weights`` as the options load it: ``--guard``, ``--max-position``, ``--max-coast`` and
    ``options`` (``--adapt``, ``--robust``, ``--r``)."""
    from immnet.imm.guard import parse_guard
    from immnet.tracking.tracker import Tracker

    tracker = Tracker.from_checkpoint(weights, parse_guard(args.guard), max_position=limit, **options)
    tracker.max_coast = check_coast(args.max_coast, tracker.net.dt)
    return tracker


def _weights(args) -> Path | None:
    """The checkpoint ``immnet track`` loads: ``--checkpoint``, else the shipped ``--weights``; None for the bank
    (``--weights bank``, or neither option: the default)."""
    if args.checkpoint is not None and args.weights is not None:
        raise ValueError("give --weights (shipped weights by name) or --checkpoint (a file of your own), not both")
    if args.checkpoint is not None:
        return Path(args.checkpoint)
    name = args.weights or DEFAULT_WEIGHTS
    return None if name == BANK else shipped(name)


def _check_options(args) -> None:
    """A clear error for options that cannot go together: ``--method`` tracks without a network, so with
    ``--checkpoint``, ``--weights`` or ``--robust`` one of them would be ignored; and it tracks CSV rows, not an
    .npz."""
    multi_cli.check_positive(args.robust, "--robust is Huber's k, a finite number of standard deviations")
    if args.robust is not None and args.method is not None:
        raise ValueError("--robust sets the networks' update; a --method has its own (robust: in its YAML)")
    if args.input.suffix.lower() != ".csv" and _sigmas(args) is not None:
        raise ValueError(f"--sigma-range, --sigma-azimuth, --sigma-elevation are the stds of a CSV of plots "
                         f"(range,azimuth,elevation); {args.input} is not a CSV")
    if args.method is None:
        return
    for option, what in (("checkpoint", "a file of your own"), ("weights", "shipped weights by name")):
        if getattr(args, option) is not None:
            raise ValueError(f"give --method (a method of immnet evaluate) or --{option} ({what}), not both")
    if args.input.suffix.lower() != ".csv":
        raise ValueError(f"--method tracks a CSV input (each row a scan at its own time); {args.input} is not one: "
                         f"leave --method out to track it with the network")


def _sigmas(args):
    """The radar's stds the options give, ``(range, azimuth, elevation)``, or None where none is given."""
    got = (args.sigma_range, args.sigma_azimuth, args.sigma_elevation)
    return None if all(v is None for v in got) else got


def _detection_cov(args, rows, method, label: str, who: str | None = None):
    """Each row's measurement covariance for ``method``'s batch (``keys.MEAS_COV``): the rows' own, or for a method
    that reads it from a CSV without any, ``--r`` squared on the diagonal; None where the method has no use for it
    and the rows give none. Said on stderr where the rows give one the method does not read. ``who``: the tracker as
    the refusals name it (default ``--method LABEL``)."""
    reads = keys.MEAS_COV in getattr(method, "needs", ())
    who = who or f"--method {label}"
    if rows.cov is not None:
        if reads:
            _one_noise(args, rows, who)
        else:
            print(f"{label} assumes its own measurement noise: each detection's covariance from the CSV is not used "
                  f"(docs/radar.md, 'Input')", file=sys.stderr)
        return rows.cov
    if not reads:
        return None
    if args.r is None:
        raise ValueError(f"{who} is told each detection's covariance, which this CSV does not hold: give "
                         f"the columns r_xx..r_zz, a radar's plots with their stds, or one std for all with --r METRES")
    return np.where(np.isnan(rows.z).any(-1)[:, None, None], np.nan, np.eye(3) * float(args.r) ** 2)


def _one_noise(args, rows, who: str) -> None:
    """A ValueError where ``--r`` is given for CSV rows that carry each detection's covariance: two noises for
    ``who``."""
    if args.r is not None:
        raise ValueError(f"--r and the CSV's {'plots' if rows.polar else 'covariance columns'} both give the "
                         f"measurement noise of {who}: give one of the two")


def _report_cov_unused(rows, what: str) -> None:
    if rows.cov is not None:
        print(f"{what} estimates each track's measurement noise from its measurements: each detection's covariance "
              f"from the CSV is not used (a --method that reads it does: docs/radar.md, 'Input')", file=sys.stderr)


def check_paths(source: Path, target: Path) -> None:
    """A clear error unless ``source`` exists, ``target``'s folder does and a file can be written there, both are
    .csv or both .npz, and ``target`` is not ``source`` (compared as files: symlinks and hard links included)."""
    suffix_in, suffix_out = source.suffix.lower(), target.suffix.lower()
    if suffix_in not in (".csv", ".npz") or suffix_out != suffix_in:
        raise ValueError(f"--input and --output must both be .csv or both .npz (got {source.name}, {target.name})")
    if not source.is_file():
        raise FileNotFoundError(f"input not found: {source}")
    if target.is_dir():
        raise ValueError(f"--output {target} is a folder; name the file to write")
    multi_cli.check_output(target, "--output")
    if target.resolve() == source.resolve() or (target.exists() and os.path.samefile(source, target)):
        raise FileExistsError(f"--output {target} is the input file {source}: refusing to overwrite the input")


def _report_gated(n_gated: int, limit: float, where: str = "") -> None:
    if n_gated:
        print(f"gated {n_gated} measurement(s) a sensor cannot report (non-finite, or |x|, |y| or |z| > {limit:g} m)"
              f"{where}: tracked as missed detections", file=sys.stderr)


def _advise(weights: Path, intervals) -> None:
    """The provenance's notes for the data's scan intervals: where the weights were measured behind a filter there,
    and where other shipped weights, trained for those scans, were measured ahead of them (``immnet.tracking.advice``)."""
    from immnet.tracking.advice import interval_note, load_provenance, weights_note

    provenance = load_provenance(weights)
    _say(interval_note(provenance, intervals), weights_note(weights, provenance, intervals))


def _advise_bank(intervals) -> None:
    """The bank's note: where the general network's provenance has it behind its filter at the data's median scan
    interval, with what another member trained for those scans measured (``immnet.tracking.advice.bank_note``)."""
    from immnet.tracking.advice import bank_note

    _say(bank_note(intervals))


def _say(*notes) -> None:
    """Each of ``notes`` that there is (not None, not empty) on stderr."""
    for note in notes:
        if note:
            print(note, file=sys.stderr)


def _report_no_cov(why: str) -> None:
    print(f"no covariance: {why}; the cov_* columns are empty (an .npz output has no state_cov)", file=sys.stderr)


def _track_rows_with_method(args, rows, limit: float, method=None, label: str | None = None,
                            name: str | None = None, who: str | None = None) -> int:
    """CSV rows tracked by ``--method`` (or the registry method ``name``, or ``method``, built; ``who``: the tracker as
    the refusals name it): each row one scan at its own time (``segments.split_rows``); for a network trained over a
    range of intervals, a gap longer than the range is cut into missed scans inside it (``track_rows(max_interval=...)``).
    A method told each detection's covariance (``keys.MEAS_COV`` in its ``needs``) is given the rows'."""
    from immnet.filters.methods import build_method, gives_cov

    name = name or args.method
    if method is None:
        has_cov = gives_cov(name)
        method, label = build_method(name, return_cov=has_cov), name
        why = f"{name} keeps no covariance of its state"
        if keys.R in getattr(method, "needs", ()) and args.r is None:
            raise ValueError(f"--method {name} is told each track's measurement std, which a CSV does not hold: "
                             f"give the radar's with --r METRES")
        meas_cov = _detection_cov(args, rows, method, label, who)
    else:
        has_cov, why = method.net.has_cov, method.net.no_cov_reason()
        if keys.MEAS_COV in getattr(method, "needs", ()):
            meas_cov = _detection_cov(args, rows, method, label, f"the network {label}")
        else:
            meas_cov = None
            _report_cov_unused(rows, label)
    span = getattr(getattr(method, "net", None), "interval_range", None)
    z, n_gated = gate_measurements(rows.z, limit)
    if meas_cov is not None:  # a gated detection is a missed one: no covariance
        meas_cov = np.where(np.isnan(z).any(-1)[:, None, None], np.nan, meas_cov)
    segs, offset = split_rows(rows.ids, rows.t, z, args.max_coast)
    # a segment of one row padded at an interval the method takes (the bank, without a range, keeps 1 s: its members
    # choose by it)
    pad = 1.0 if span is None else (float(span[0]) + float(span[1])) / 2
    state, probs, cov = track_rows(method, segs, offset, return_cov=True,
                                   max_interval=None if span is None else span[1], r=args.r, meas_cov=meas_cov,
                                   one_row_interval=pad)
    return _write_rows(args, rows, z, n_gated, limit, len(segs.span), (state, probs, cov if has_cov else None), why,
                       f" with {label}")


def _write_rows(args, rows, z, n_gated: int, limit: float, n_segments: int, out: tuple, why: str, by: str = "") -> int:
    """The CSV output of ``rows`` from their estimates ``out`` (state, mode probabilities, covariance: None, and ``why``
    on stderr, where the tracker keeps none), then on stderr the gated detections (``z`` as tracked: the CSV lines
    whose measurement it made a missed detection, the first five) and what was tracked (``by``: with which tracker)."""
    from immnet.data.csvio import write_tracks_csv
    from immnet.tracking.networks import listed

    write_tracks_csv(args.output, rows, *out)
    if out[2] is None:
        _report_no_cov(why)
    gated = np.flatnonzero(np.isnan(z).all(-1) & ~np.isnan(rows.z).all(-1))
    _report_gated(n_gated, limit, " on line(s) " + listed([rows.lines[i] for i in gated]) if len(gated) else "")
    print(f"tracked {len(set(rows.ids))} tracks ({n_segments} segments), {len(rows)} rows{by} -> {args.output}",
          file=sys.stderr)
    return 0


def _refuse_bank_options(args, what: str, name: str, them: str) -> None:
    """``--adapt`` and ``--guard`` refused where input with each detection's covariance (``what`` it is) goes to the
    default ``name`` for it, which has neither: one line naming the option and saying how to track ``them`` with the
    bank."""
    for option, given in (("--adapt", args.adapt), ("--guard", args.guard not in ("checkpoint", "none"))):
        if given:
            raise ValueError(f"{option} is the bank's and the shipped networks' option; {what} tracked by {name} by "
                             f"default, which has none: give --weights bank to track {them} with the bank")


def _track_plots(args, rows, limit: float) -> int:
    """The default for CSV rows that carry each detection's covariance (a radar's plots, or ``r_xx..r_zz``): the
    registry method ``immnet.tracking.advice.radar_default`` picks for their scan intervals (the shipped radar network
    of their band, told each plot's covariance, else the model-based filter told it), named on stderr."""
    from immnet.tracking.advice import radar_default, track_intervals

    name, line = radar_default(track_intervals(rows.ids, rows.t))
    _refuse_bank_options(args, "these rows carry each detection's covariance and are", name, "them")
    who = f"{name} (the default for rows with covariances)"
    _one_noise(args, rows, who)
    print(line, file=sys.stderr)
    return _track_rows_with_method(args, rows, limit, name=name, who=who)


def run(args) -> int:
    from immnet.data.csvio import csv_header, read_tracks_csv

    _check_options(args)
    check_paths(args.input, args.output)
    header = csv_header(args.input) if args.input.suffix.lower() == ".csv" else None
    # CSV rows that name their track (a track_id column; an empty file too, which its reader refuses), or an .npz: else
    # a radar's unlabelled plots, for the multi-target tracker
    labelled = header is None or "track_id" in header
    multi_cli.check_options(args, labelled)
    limit = check_limit(args.max_position)
    options = _load_options(args)
    if not labelled:
        if args.robust is not None:
            raise ValueError("--robust is for tracks with a track_id; the multi-target tracker's filter is a --method "
                             "(e.g. radar-imm-robust-5s)")
        return multi_cli.track_plots(args, limit, _sigmas(args))
    if args.max_coast is None:
        args.max_coast = MAX_COAST
    if args.input.suffix.lower() == ".csv":
        from immnet.tracking.advice import track_intervals

        rows = read_tracks_csv(args.input, _sigmas(args))
        if args.method is not None:
            return _track_rows_with_method(args, rows, limit)
        if rows.cov is not None and args.weights is None and args.checkpoint is None:
            if args.robust is not None:
                raise ValueError("--robust: the default for rows with covariances carries Huber's update already "
                                 "(k 2.5, the radar networks'); give --weights or --checkpoint to set a network's")
            return _track_plots(args, rows, limit)
        weights = _weights(args)
        if weights is None:  # the bank: each row a scan at its own time, as for a network trained over a range
            code = _track_rows_with_method(args, rows, limit, _bank(args, limit, options), "the bank")
            _advise_bank(track_intervals(rows.ids, rows.t))
            return code
        tracker = _tracker(args, weights, limit, options)  # its max_coast: the rows' segments are cut at it already
        if tracker.net.start.told_r:
            raise ValueError(f"{weights}: this network's filter experts are told each track's measurement std, which a "
                             f"CSV does not hold: give the radar's with --r METRES")
        if tracker.net.interval_range is not None:  # any interval in its range: each row a scan at its own time
            from immnet.tracking.methods import IMMNetMethod

            method = IMMNetMethod.from_tracker(tracker, name="the checkpoint", return_cov=tracker.net.has_cov)
            code = _track_rows_with_method(args, rows, limit, method, str(weights))
            _advise(weights, track_intervals(rows.ids, rows.t))
            return code
        _report_cov_unused(rows, str(weights))
        z, n_gated = gate_measurements(rows.z, limit)
        segs = split_segments(rows.ids, rows.t, z, tracker.net.dt, args.max_coast, rows.lines, rows.times)
        state, probs, *cov = track_segments(tracker, segs, return_cov=tracker.net.has_cov)
        return _write_rows(args, rows, z, n_gated, limit, len(segs.span), (state, probs, cov[0] if cov else None),
                           tracker.net.no_cov_reason())
    from immnet.data.storage import load_dataset
    from immnet.tracking.tracker import check_dt

    data, meta = load_dataset(args.input)
    told = keys.MEAS_COV in data.keys()
    if told and args.weights is None and args.checkpoint is None:
        return _npz_plots(args, data, meta, limit)
    weights = _weights(args)
    if weights is None:
        _report_npz_cov_unused(data, "the bank", args.r)
        return _npz_with_bank(args, data, meta, _bank(args, limit, options).net, limit)
    tracker = _tracker(args, weights, limit, options)
    if tracker.net.start.told_cov and not told:
        raise ValueError(f"{weights}: this network is told each detection's covariance, which {args.input} does not "
                         f"hold: give the .npz its {keys.MEAS_COV!r} [N, T, 3, 3] (immnet data adsb --sigma-* writes "
                         f"it), or one std for all with --r METRES")
    if not tracker.net.start.told_cov:
        _report_npz_cov_unused(data, str(weights), args.r)
    from immnet.data.times import scan_intervals

    intervals = scan_intervals(data) if "t" in data.keys() else data["dt"]
    if tracker.net.interval_range is None:  # one interval; a range's, gaps cut, Tracker.track checks
        check_dt(tracker.net, intervals, "the checkpoint")
    has_cov = tracker.net.has_cov
    # each scan at its own interval (a network trained over a range runs F(dt), Q(dt) per scan; a gap longer than
    # the range coasted at intervals inside it), each track's r where the network's filter experts are told it
    out = tracker.track(data["measurements"], intervals=tracker.net.intervals_for(data), return_cov=has_cov,
                        r=tracker.net.told_r(data), meas_cov=tracker.net.told_cov(data))
    _write_npz(args, data, meta, {"state": out["state"].numpy(), "mode_probs": out["mode_probs"].numpy()},
               {"state_cov": out["state_cov"].numpy()} if has_cov else {}, tracker.n_gated, limit,
               why=None if has_cov else tracker.net.no_cov_reason())
    if tracker.net.interval_range is not None:
        _advise(weights, np.asarray(intervals, dtype=np.float64).ravel())
    return 0


def _npz_with_bank(args, data, meta, bank, limit: float) -> int:
    """An .npz tracked by the bank: each scan at its own interval; ``member_probs [N, T, K]`` beside the state, the
    mode probabilities and the covariance (``member_names`` their order)."""
    from immnet.data.times import scan_intervals

    intervals = scan_intervals(data)
    out = bank.track(data["measurements"], intervals=intervals, return_cov=True)
    _write_npz(args, data, meta, {"state": out["state"].numpy(), "mode_probs": out["mode_probs"].numpy(),
                                  "state_cov": out["state_cov"].numpy(),
                                  "member_probs": out[keys.MEMBER_PROBS].numpy(),
                                  "member_names": np.array(bank.names)}, {}, bank.n_gated, limit,
               f" with the bank ({', '.join(bank.names)})")
    _advise_bank(intervals.numpy()[:, 1:].ravel())
    return 0


def _write_npz(args, data, meta, arrays: dict, tail: dict, n_gated: int, limit: float, by: str = "",
               why: str | None = None) -> int:
    """The .npz output, written whole or not at all: ``arrays``, the data's ``dt`` (``meta``) and scan times ``t``
    where it has them, then ``tail``; then on stderr why it holds no covariance (``why``, where the tracker keeps
    none), the gated measurements and what was tracked (``by``: with which tracker)."""
    from immnet.data.scratch import publishing

    with publishing(args.output, suffix=".npz") as tmp:
        times = {"t": np.asarray(data["t"], dtype=np.float64)} if "t" in data.keys() else {}
        np.savez(tmp, **arrays, dt=np.float64(meta["dt"]), **times, **tail)
    if why is not None:
        _report_no_cov(why)
    _report_gated(n_gated, limit)
    print(f"tracked {len(arrays['state'])} tracks{by} -> {args.output}", file=sys.stderr)
    return 0


def _report_npz_cov_unused(data, what: str, r: float | None = None) -> None:
    if keys.MEAS_COV in data.keys():
        how = f"is given --r {r:g}" if r is not None else "estimates each track's measurement noise from its measurements"
        print(f"{what} {how}: the .npz's "
              f"{keys.MEAS_COV!r} is not used (docs/radar.md, 'Input')", file=sys.stderr)


def _npz_plots(args, data, meta, limit: float) -> int:
    """The default for an .npz holding each detection's covariance (``meas_cov``): the registry method
    ``immnet.tracking.advice.radar_default`` picks for its scan intervals (``t``, else ``dt``), as for CSV rows with
    covariances, told ``meas_cov``; each window tracked as ``immnet evaluate`` tracks it (a network's coasting limit
    ``--max-coast``; a model-based filter has none). Written as the other .npz outputs, the tracker named on stderr."""
    from immnet.data.times import scan_intervals
    from immnet.filters.methods import build_method, gives_cov
    from immnet.tracking.advice import radar_default
    from tensordict import TensorDict

    name, line = radar_default(scan_intervals(data).numpy()[:, 1:].ravel())
    line = (line.replace("the rows carry", "the .npz carries").replace("their median", "its median")
            .replace("--method or --weights bank", "--weights or --checkpoint"))
    _refuse_bank_options(args, f"this .npz carries each detection's covariance ({keys.MEAS_COV!r}) and is", name, "it")
    if args.r is not None:
        raise ValueError(f"--r and the .npz's {keys.MEAS_COV!r} both give the measurement noise of {name} (the "
                         f"default for an .npz with {keys.MEAS_COV!r}): give one of the two")
    has_cov = gives_cov(name)
    method = build_method(name, return_cov=has_cov)
    tracker = getattr(method, "tracker", None)
    if tracker is not None:
        tracker.max_coast = check_coast(args.max_coast, tracker.net.dt)
    print(line, file=sys.stderr)
    z, n_gated = gate_measurements(data[keys.MEASUREMENTS], limit)
    batch = TensorDict({**dict(data.items()), keys.MEASUREMENTS: z}, batch_size=data.batch_size)
    out = method.track(batch)
    probs = {"mode_probs": out[keys.MODE_PROBS].numpy()} if keys.MODE_PROBS in out.keys() else {}
    return _write_npz(args, data, meta, {"state": out[keys.STATE].numpy(), **probs},
                      {"state_cov": out[keys.STATE_COV].numpy()} if has_cov else {}, n_gated, limit, f" with {name}")
