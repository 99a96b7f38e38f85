"""``immnet track`` for unlabelled plots: a CSV without a ``track_id`` column (``t,range,azimuth,elevation`` or
``t,x,y,z``, ``immnet.data.csvio.read_plots_csv``) goes to the multi-target tracker
(``immnet.filters.multi.MultiTargetTracker``), scan by scan. The output has one row per confirmed track per scan,
from its confirmation to its deletion (``immnet.data.csvio.PLOT_OUT_COLUMNS``), written through a temporary file
and moved into place only when complete; ``--figure`` draws the run as a radar display. See docs/multi-target.md.
"""

from __future__ import annotations

import csv
import sys
from pathlib import Path

import numpy as np

LONG = 1000
"""Scans from which a run says on stderr where it is (``immnet.progress``)."""

MULTI_OPTIONS = ("associator", "pd", "clutter_density", "max_range", "min_elevation", "figure", "scene")
"""The options of the multi-target tracker alone (None where not given)."""
SINGLE_OPTIONS = {
    "weights": "its per-track filter is named by --method NAME (a model-based method, or a shipped network such as "
               "radar-5s)",
    "checkpoint": "its per-track filter is named by --method NAME (a model-based method, or a shipped network such as "
                  "radar-5s), not a checkpoint file",
    "adapt": "its filters keep the method's own process noise",
    "max_coast": "a confirmed track is deleted after missed scans in a row (once they span its min_coast seconds), "
                 "not after a time alone",
}
"""The options of the tracker of labelled tracks alone, and why the multi-target tracker has no use for them
(``--guard`` too: it has no range guard)."""


def check_positive(value, what: str) -> None:
    """A ValueError ``{what} > 0; got {value}`` unless an option's ``value`` (None: not given) is a finite number > 0
    (``what``: the option and what it is, e.g. ``--r is the radar's measurement std in metres, a finite number``)."""
    if value is not None and not (np.isfinite(value) and value > 0):
        raise ValueError(f"{what} > 0; got {value:g}")


def check_output(path: Path, option: str) -> None:
    """A clear error, before any work, unless the folder of ``option``'s ``path`` exists and a file can be written
    there (``immnet.data.scratch.check_writable``: a read-only folder refused now, not after the tracking)."""
    if not path.parent.is_dir():
        raise FileNotFoundError(f"the folder of {option} does not exist: {path.parent}")
    from immnet.data.scratch import check_writable

    check_writable(path)


def _option(name: str) -> str:
    return "--" + name.replace("_", "-")


def check_options(args, labelled: bool) -> None:
    """A clear error for an option of the other path: the multi-target tracker's options for tracks that name their
    ids (or an .npz), and the options of the tracker of labelled tracks for unlabelled plots; for plots, ``--pd`` and
    ``--clutter-density`` without ``--associator jpda``, ``--min-elevation`` without ``--max-range``, ``--scene``
    without ``--figure``, and the values."""
    if labelled:
        for name in MULTI_OPTIONS:
            if getattr(args, name) is not None:
                what = (f"{args.input} has a track_id column" if args.input.suffix.lower() == ".csv"
                        else f"{args.input} is not a CSV")
                raise ValueError(f"{_option(name)} is the multi-target tracker's, for a CSV of plots without a "
                                 f"track_id column; {what}")
        return
    for name, why in SINGLE_OPTIONS.items():
        if getattr(args, name) not in (None, False):
            raise ValueError(f"{_option(name)} does not apply to plots without a track_id column (the multi-target "
                             f"tracker): {why}")
    if args.guard != "checkpoint":
        raise ValueError("--guard does not apply to plots without a track_id column (the multi-target tracker): it "
                         "has no range guard")
    if (args.associator or "gnn") == "gnn":
        for name in ("pd", "clutter_density"):
            if getattr(args, name) is not None:
                raise ValueError(f"{_option(name)} is JPDA's (--associator jpda): GNN does not use it")
    if args.pd is not None and not 0.0 < args.pd <= 1.0:
        raise ValueError(f"--pd is the probability that an aircraft is detected, in (0, 1]; got {args.pd:g}")
    check_positive(args.clutter_density, "--clutter-density is the false plots per m^3, a finite number")
    if args.min_elevation is not None and args.max_range is None:
        raise ValueError("--min-elevation is the radar's cover with --max-range: give --max-range METRES too")
    check_positive(args.max_range, "--max-range is the slant range the radar sees up to, a finite number of metres")
    if args.min_elevation is not None and not -90.0 <= args.min_elevation < 90.0:
        raise ValueError(f"--min-elevation is in degrees, in [-90, 90); got {args.min_elevation:g}")
    if args.scene is not None and args.figure is None:
        raise ValueError("--scene marks the clutter on --figure's radar display: give --figure FILE.png too")
    if args.figure is not None:
        figure = Path(args.figure)
        if figure.suffix.lower() != ".png":
            raise ValueError(f"--figure {figure}: the radar display is a PNG file (a name ending .png)")
        check_output(figure, "--figure")


def _scene_clutter(path: Path, plots) -> np.ndarray:
    """``[P]`` True where a plot of ``plots`` is clutter, from the scene file ``path`` whose CSV they are
    (``immnet data scenes --csv``: the same scans, times and plots, in the same order); a ValueError unless they
    are."""
    from immnet.data.scenes import load_scene

    scene = load_scene(path)
    where = f"--scene {path}: not the scene of this CSV"
    if len(scene) != len(plots):
        raise ValueError(f"{where} ({len(scene)} scans, the CSV {len(plots)})")
    counts, mine = np.diff(scene.plot_offsets), np.diff(plots.offsets)
    t = np.array([float(v) for v in plots.t])
    for k in np.flatnonzero((counts != mine) | ~np.isclose(t, scene.t, rtol=0.0, atol=1e-6))[:1]:
        raise ValueError(f"{where} (the scan of line {plots.scan_lines[k]}: "
                         f"t = {plots.times[k]} with {mine[k]} plots, the scene's t = {scene.t[k]!r} with "
                         f"{counts[k]})")
    if plots.polar:
        theirs, mine = np.c_[scene.plot_polar[:, :1], np.degrees(scene.plot_polar[:, 1:])], plots.given
        az = np.abs((mine[:, 1] - theirs[:, 1] + 180.0) % 360.0 - 180.0)
        same = np.isclose(mine[:, 0], theirs[:, 0], rtol=1e-9) & (az <= 1e-9) & np.isclose(mine[:, 2], theirs[:, 2],
                                                                                           rtol=0.0, atol=1e-9)
    else:
        same = np.isclose(plots.given, scene.plots, rtol=1e-9, atol=1e-6).all(-1)
    for i in np.flatnonzero(~same)[:1]:
        raise ValueError(f"{where} (the plot of line {plots.lines[i]} is not the scene's)")
    return scene.plot_source == -1


def _gated(plots, limit: float) -> tuple[np.ndarray, np.ndarray]:
    """``(keep [P], z [P, 3])``: the plots a sensor can report (finite, ``|x|, |y|, |z| <= limit``), said on stderr
    where some cannot (they are left out of their scans)."""
    from immnet.data.validate import gate_measurements
    from immnet.tracking.networks import listed

    z, n_gated = gate_measurements(plots.z, limit)
    keep = ~np.isnan(z).any(-1)
    if n_gated:
        print(f"left out {n_gated} plot(s) a sensor cannot report (non-finite, or |x|, |y| or |z| > {limit:g} m) on "
              f"line(s) {listed(plots.lines[~keep])}", file=sys.stderr)
    return keep, z


def track_plots(args, limit: float, sigmas) -> int:
    """``immnet track`` for a CSV of unlabelled plots (module doc)."""
    from immnet.data.scratch import publishing
    from immnet.progress import progress
    from immnet.data.csvio import PLOT_OUT_COLUMNS, R_COLUMNS, plot_track_rows, read_plots_csv
    from immnet.filters.multi import DEFAULT_FILTER, ByInterval, Cover, MultiTargetTracker, TrackFilter

    plots = read_plots_csv(args.input, sigmas)
    clutter = _scene_clutter(Path(args.scene), plots) if args.scene is not None else None
    name = args.method or DEFAULT_FILTER
    filt = TrackFilter.by_name(name)
    if isinstance(filt, ByInterval) and len(plots.t) > 1:  # the radar's interval, whatever scans the CSV left out
        filt.choose(float(np.median(np.diff(np.array(plots.t, dtype=np.float64)))))
    if plots.cov is not None and args.r is not None:
        raise ValueError(f"--r and the CSV's {'plots' if plots.polar else 'covariance columns'} both give the "
                         f"plots' measurement noise: give one of the two")
    if plots.cov is None and args.r is None and filt.r is None:
        raise ValueError(f"x,y,z plots without the columns {','.join(R_COLUMNS)} need their measurement std, which "
                         f"{name} does not assume: give --r METRES")
    assoc = args.associator or "gnn"
    jpda = {k: getattr(args, k) for k in ("pd", "clutter_density") if getattr(args, k) is not None}
    cover = None if args.max_range is None else Cover(args.max_range, args.min_elevation or 0.0)
    tracker = MultiTargetTracker(filt, associator=assoc, r=args.r, cover=cover, **jpda)
    keep, z = _gated(plots, limit)
    paths: dict[int, list] = {}
    n_rows = 0
    with publishing(args.output) as tmp, tmp.open("x", newline="") as f:
        csv.writer(f).writerow(PLOT_OUT_COLUMNS)
        for k in progress(range(len(plots)), desc="track", unit="scans", disable=len(plots) < LONG):
            a, b = plots.offsets[k], plots.offsets[k + 1]
            m = keep[a:b]
            reports = tracker.step(float(plots.t[k]), z[a:b][m], None if plots.cov is None else plots.cov[a:b][m])
            if not reports:
                continue
            probs = tracker.data_mode_probs()
            ids = [r.track_id for r in reports]
            state = np.stack([r.state for r in reports])
            rows = plot_track_rows(plots.times[k], ids, state, None if probs is None else probs[tracker.confirmed],
                                   [r.updated for r in reports], np.stack([r.cov for r in reports]))
            f.writelines(rows)
            n_rows += len(rows)
            for i, s in zip(ids, state):
                paths.setdefault(i, []).append(s[[0, 3]])
        if isinstance(filt, ByInterval) and filt.chosen is not None:  # the filter by scan interval: the one it took
            name = f"{name}: {filt.chosen}"
        if args.figure is not None:
            from immnet.evaluation.figures import plot_radar_display

            with publishing(Path(args.figure), suffix=".png") as png:
                plot_radar_display(plots.z[keep], paths, png, None if clutter is None else clutter[keep],
                                   title=f"{args.input.name}: {len(paths)} confirmed tracks ({name}, {assoc.upper()})")
    print(f"tracked {len(plots)} scans, {int(keep.sum())} plots with {name} ({assoc.upper()}): {len(paths)} confirmed "
          f"track(s), {n_rows} rows -> {args.output}" + (f", {args.figure}" if args.figure is not None else ""),
          file=sys.stderr)
    return 0
