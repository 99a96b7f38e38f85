"""What the velocity each aircraft reports of itself is worth to a tracker of the radar's positions: the best
model-based filter told, besides the radar's detections, the ground speed, track angle and vertical rate in the
aircraft's own ADS-B rows (what a Mode S radar also reads from the aircraft: EHS registers 5,0 and 6,0). A measured
reference, not a tracker of the package.

    python scripts/downlinked_velocity.py --tune runs/real/data/quickstart-1s/val \\
        --data runs/real/data/quickstart-1s/test --imm real-imm-singer \\
        --baseline real-imm-singer [--baseline immnet-bank] [--label "1 s test"] [--json report.json]

A real-flight data set (``immnet data adsb``) stores the radar's windows, not the rows they came from; the script
builds each window again from its sample file (checked by checksum) with the set's own parameters and seed
(``immnet.data.real.simulate``), refuses the set unless the rebuilt truth and detections equal the stored ones, and
reads at each scan the aircraft's latest velocity report at most ``--max-age`` seconds old (the row's time; none
yet: the scan has no report). A report is ground speed ``g``, track ``chi`` and vertical rate ``c`` in the aircraft's
east-north-up frame, ``(g sin chi, g cos chi, c)``, turned into the radar site's frame through ECEF.

The filter (docs/notebook/real-flights.md "Told the aircraft's velocity"): the decoupled IMM ``--imm``
(``PerAxisIMMTracker``) whose per-axis measurement is ``(position, reported velocity)`` with

    H = [[1, 0, 0], [0, 1, -L]],   R = diag(r^2, s_a^2)

or a joint IMM (``IMMTracker``, e.g. ``radar-imm-5s``, told each plot's covariance ``R_p``; docs/radar.md, "What would")
whose measurement is the plot and the three reported velocities, ``H`` the positions' rows and ``[0, 1, -L]`` per
axis, ``R = blockdiag(R_p, diag(s_a^2))``; a missed plot is a missed scan for both

a report ``L`` seconds late measuring ``v(t - L) = v(t) - L a(t)`` (exact under constant acceleration), ``s_a`` the
reports' error per axis measured on ``--tune`` against the truth (horizontal axes together, vertical apart), times a
factor ``k``; a scan without a report measures the position alone (its velocity's variance ``NO_REPORT``). Its process
noise is the method's times a factor. On ``--tune`` (the validation flights) ``L`` is chosen, then the noise factor
and ``k`` together on their grid, then ``L`` again; then each row is scored on ``--data`` once: every axis told, the
horizontal ones only, the vertical one only. ``--baseline`` methods are scored in the same run, the first the ratio's
reference. ``--rows-within S`` scores only the windows from sample files whose rows are at most ``S`` s apart (a
property of the file, ``row_interval``): traffic's resampled samples hold a report over several rows, through turns.
``--by-sample`` adds a table per sample file of ``--data``: the reports' error, ``--imm`` and its every-axis row.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import NamedTuple
from unittest import mock

import numpy as np
import torch

from immnet import keys
from immnet.config import instantiate, load_yaml
from immnet.data import adsb, real
from immnet.data.geodesy import enu_rotation
from immnet.data.storage import as_batch, load_dataset
from immnet.filters.methods import method_config
from immnet.evaluation.metrics import position_error, scored_distance, scored_mask
from immnet.evaluation.search import average_rmse, states_rmse
from immnet.filters import imm as joint_imm
from immnet.filters import per_axis
from immnet.filters.trackers import IMMTracker
from immnet.motion import AXES

NO_REPORT = 1e12
"""The velocity variance (m^2/s^2) of a scan without a report: no information, without a second measurement model."""
RTOL = 2 * float(np.finfo(np.float32).eps)
"""The rebuilt windows against the stored ones: float32 storage, one unit in the last place (0.05 m at 200 km)."""
AXIS_SETS = {"every axis": (0, 1, 2), "horizontal only": (0, 1), "vertical only": (2,)}


def site_velocity(speed, track, climb, lat, lon, site) -> np.ndarray:
    """``[n, 3]`` velocities in the east-north-up frame of ``site = (lat, lon, h)`` from reports at ``(lat, lon)``:
    ground speed (m/s), track (degrees from true north, clockwise), vertical rate (m/s)."""
    chi = np.radians(np.asarray(track, float))
    local = np.stack([speed * np.sin(chi), speed * np.cos(chi), np.asarray(climb, float)], -1)  # [n, 3] local ENU
    ecef = np.einsum("nij,ni->nj", enu_rotation(lat, lon), local)  # each report's rows' transpose: local ENU -> ECEF
    return ecef @ enu_rotation(site[0], site[1]).T


def latest(times: np.ndarray, values: np.ndarray, at: np.ndarray, max_age: float) -> np.ndarray:
    """``[S, 3]`` the latest of ``values [n, 3]`` (at increasing ``times [n]``) at or before each of ``at [S]``, NaN
    where none is at most ``max_age`` old."""
    out = np.full((len(at), 3), np.nan)
    if not len(times):
        return out
    i = np.searchsorted(times, at, side="right") - 1
    ok = (i >= 0) & (at - times[np.maximum(i, 0)] <= max_age)
    out[ok] = values[i[ok]]
    return out


def flight_reports(rec: adsb.Records, flight: adsb.Flight, site) -> tuple[np.ndarray, np.ndarray]:
    """``(times [n], velocities [n, 3])``: the airborne rows of ``flight``'s aircraft, over its time span, that carry a
    whole velocity report, in ``site``'s frame (the reporting position taken from the flight's track at the row's
    time, so that a row without a fresh position still has one)."""
    sel = np.flatnonzero((rec.icao24 == flight.icao24) & ~rec.onground & np.isfinite(rec.timestamp)
                         & np.isfinite(rec.groundspeed) & np.isfinite(rec.track) & np.isfinite(rec.vertical_rate)
                         & (rec.timestamp >= flight.t[0]) & (rec.timestamp <= flight.t[-1]))
    sel = sel[np.argsort(rec.timestamp[sel], kind="stable")]
    t = rec.timestamp[sel]
    keep = np.diff(t, prepend=-np.inf) > 0  # one report per time
    sel, t = sel[keep], t[keep]
    lat, lon = np.interp(t, flight.t, flight.lat), np.interp(t, flight.t, flight.lon)
    return t, site_velocity(rec.groundspeed[sel], rec.track[sel], rec.vertical_rate[sel], lat, lon, site)


class Reports(NamedTuple):
    velocity: np.ndarray  # [B, T, 3] each scan's report in the site's frame (m/s), NaN: none
    rows: np.ndarray  # [B] the row interval of each window's sample file (s; ``row_interval``)
    samples: np.ndarray  # [B] the name of each window's sample


def row_interval(rec: adsb.Records) -> float:
    """A sample file's row interval (s): the median over its aircraft of the median time between their rows (1 s for
    state vectors as recorded; traffic's resampled samples 5-10 s)."""
    order = np.lexsort((rec.timestamp, rec.icao24))
    icao, t = rec.icao24[order], rec.timestamp[order]
    same = icao[1:] == icao[:-1]
    steps = np.diff(t)[same]
    per = [np.median(steps[icao[1:][same] == a]) for a in np.unique(icao[1:][same])]
    return float(np.median(per)) if per else float("nan")


def set_reports(data, max_age: float = 3.0, atol: float = 1e-3) -> Reports:
    """The velocity reports at each scan of a real-flight data set's windows, in its order (``Reports``).
    A ValueError unless the set is one ``immnet data adsb`` wrote and its windows, rebuilt from the sample files, are
    the stored ones (truth within ``atol`` m, detections too)."""
    data = Path(data)
    td, meta = load_dataset(data)
    if meta.get("format") != "adsb":
        raise ValueError(f"{data}: not a real-flight set (format {meta.get('format')!r}); the reports come from its "
                         f"sample files")
    spec = real.RealSpec.from_dict(meta["params"])
    wanted = set(meta["window_flights"])
    flights, records = real.set_flights(meta, data)
    rows = {name: row_interval(rec) for name, rec in records.items()}
    by_id = {}
    flights = [f for f in flights if f.id in wanted]
    sites = {k: (v["lat"], v["lon"], v["h"]) for k, v in meta["sites"].items()}
    site = lambda f: sites[f.id] if f.id in sites else sites[f.sample]  # a radar per flight, or per sample
    prepared = real.truth(flights, [site(f) for f in flights], spec, meta["seed"])
    for p in sorted(prepared, key=lambda p: p["flight"].id):
        f = p["flight"]
        t, v = flight_reports(records[f.sample], f, site(f))
        by_id[f.id] = [(st, z, latest(t, v, scans, max_age), rows[f.sample], f.sample)
                       for st, z, _, scans in real.simulate(p, spec)]
    wins = [w for fid in dict.fromkeys(meta["window_flights"]) for w in by_id.get(fid, [])]
    states, z = td[keys.STATES].double().numpy(), td[keys.MEASUREMENTS].double().numpy()
    if len(wins) != len(states) or not all(
            np.allclose(w[0], s, rtol=RTOL, atol=atol, equal_nan=True)
            and np.allclose(w[1], m, rtol=RTOL, atol=atol, equal_nan=True)
            for w, s, m in zip(wins, states, z)):
        raise ValueError(f"{data}: its windows are not the ones its sample files and parameters give now (rebuilt "
                         f"{len(wins)} windows, stored {len(states)}); write the set again with `immnet data adsb`")
    return Reports(np.stack([w[2] for w in wins]), np.array([w[3] for w in wins]), np.array([w[4] for w in wins]))


def report_errors(reports: np.ndarray, states: np.ndarray, lag: float) -> tuple[float, float, float]:
    """``(horizontal, vertical, share)``: the RMS error per axis of ``reports [B, T, 3]`` against the truth's velocity
    ``lag`` s before (``v - lag a``, states ``[B, T, 9]``), and the share of scans with truth that have a report."""
    truth = states[..., [1, 4, 7]] - lag * states[..., [2, 5, 8]]
    e = reports - truth
    ok = np.isfinite(e).all(-1)
    share = float(ok.sum() / max(np.isfinite(truth).all(-1).sum(), 1))
    if not ok.any():
        return float("nan"), float("nan"), share
    return float(np.sqrt(np.mean(e[ok][:, :2] ** 2))), float(np.sqrt(np.mean(e[ok][:, 2] ** 2))), share


def told_velocity(method, batch, reports: torch.Tensor, sigma: tuple[float, float], lag: float, axes=(0, 1, 2)):
    """``method.track(batch)`` with each axis's reported velocity (``reports [B, T, 3]``, NaN: none) measured beside
    the position (module docstring); ``sigma``: the reports' error, horizontal and vertical (m/s); ``axes``: the axes
    told. The tracker's output (states ``[B, T, 9]`` and the rest)."""
    v = reports.double().clone()
    for a in set(range(AXES)) - set(axes):
        v[..., a] = float("nan")
    if isinstance(method, IMMTracker):
        return _told_joint(method, batch, v, sigma, lag)
    B, T = v.shape[:2]
    va = v.permute(2, 0, 1).reshape(AXES * B, T)  # the tracker's axis-major tracks
    known = torch.isfinite(va)
    var = torch.tensor([sigma[0] ** 2, sigma[0] ** 2, sigma[1] ** 2], dtype=torch.float64).repeat_interleave(B)
    inner = per_axis.run

    def with_velocity(za, x, P, mu, Pi, transition, R, H=None, **kw):
        z2 = torch.cat([za, torch.nan_to_num(va, nan=0.0).to(za.dtype)[..., None]], -1)
        H2 = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, -lag]], dtype=za.dtype)
        r2 = torch.as_tensor(R, dtype=za.dtype).expand(AXES * B)

        def R2(t: int) -> torch.Tensor:
            cov = torch.zeros(AXES * B, 1, 2, 2, dtype=za.dtype)
            cov[:, 0, 0, 0] = r2
            cov[:, 0, 1, 1] = torch.where(known[:, t], var, torch.full_like(var, NO_REPORT))
            return cov

        return inner(z2, x, P, mu, Pi, transition, R2, H=H2, **kw)

    with mock.patch.object(per_axis, "run", with_velocity):
        return method.track(batch)


def _told_joint(method: IMMTracker, batch, v: torch.Tensor, sigma: tuple[float, float], lag: float):
    """``told_velocity`` of a joint IMM: the plot and the reports ``v [B, T, 3]`` (NaN: none) as one measurement."""
    known = torch.isfinite(v)
    var = torch.tensor([sigma[0] ** 2, sigma[0] ** 2, sigma[1] ** 2], dtype=torch.float64)
    inner = joint_imm.run

    def with_velocity(z, x, P, mu, Pi, transition, R, H=None, **kw):
        B = z.shape[0]
        z2 = torch.cat([z, torch.nan_to_num(v, nan=0.0).to(z.dtype)], -1)
        H2 = torch.zeros(6, 9, dtype=z.dtype)
        for a in range(AXES):
            H2[a, 3 * a], H2[3 + a, 3 * a + 1], H2[3 + a, 3 * a + 2] = 1.0, 1.0, -lag
        plots = R if callable(R) else (lambda t: torch.as_tensor(R, dtype=z.dtype))

        def R2(t: int) -> torch.Tensor:
            cov = torch.zeros(B, 1, 6, 6, dtype=z.dtype)
            Rp = plots(t)
            cov[..., :3, :3] = Rp if Rp.dim() >= 2 else Rp.reshape(-1, 1, 1, 1) * torch.eye(3, dtype=z.dtype)
            for a in range(AXES):
                cov[:, 0, 3 + a, 3 + a] = torch.where(known[:, t, a], var[a], torch.full_like(var[a], NO_REPORT))
            return cov

        return inner(z2, x, P, mu, Pi, transition, R2, H=H2, **kw)

    if method.robust is not None or method.reacquire is not None:
        raise ValueError(f"{method.name}: a joint IMM told the reports is the plain one (no robust update, no "
                         f"re-acquisition)")
    with mock.patch.object(joint_imm, "run", with_velocity):
        return method.track(batch)


def over_limit(state: torch.Tensor, batch, limit: float) -> int:
    """The tracks of ``batch`` whose position error (3-D) ever exceeds ``limit`` m at a scored scan."""
    mask = scored_mask(batch[keys.STATES], batch[keys.MEASUREMENTS])
    return int((scored_distance(position_error(state, batch[keys.STATES]), mask).amax(1) > limit).sum())


def decoupled(config: dict):
    """The decoupled IMM (or a plain joint IMM) a method config builds; a ValueError for any other method."""
    method = instantiate(config)
    if not isinstance(method, (per_axis.PerAxisIMMTracker, IMMTracker)):
        raise ValueError(f"--imm takes a decoupled IMM (PerAxisIMMTracker) or a joint one (IMMTracker), got "
                         f"{type(method).__name__}")
    return method


def _numbers(text: str) -> list[float]:
    try:
        return [float(v) for v in text.split(",") if v]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--tune", required=True, help="the real-flight set the settings are chosen on (validation)")
    p.add_argument("--data", required=True, help="the real-flight set the table scores")
    p.add_argument("--imm", required=True, help="a decoupled IMM of configs/methods/ told the reports")
    p.add_argument("--baseline", action="append", default=[],
                   help="a method of configs/methods/ scored beside (the first: the ratio's reference)")
    p.add_argument("--max-age", type=float, default=3.0, help="a report older than this (s) is not used")
    p.add_argument("--lags", type=_numbers, default=[0, 0.5, 1, 1.5, 2, 3], help="L (s) to choose from")
    p.add_argument("--scales", type=_numbers, default=[4, 2, 1, 0.5, 0.25], help="process noise factors")
    p.add_argument("--factors", type=_numbers, default=[0.25, 0.5, 1, 2, 4], help="factors k of the reports' error")
    p.add_argument("--rows-within", type=float, default=float("inf"),
                   help="score only --data's windows from sample files whose rows are at most this far apart (s)")
    p.add_argument("--by-sample", action="store_true",
                   help="also score --imm and its every-axis row on each sample's windows of --data")
    p.add_argument("--label", help="the set's name in the JSON (default: --data)")
    p.add_argument("--json", type=Path)
    args = p.parse_args(argv)
    try:
        imm = decoupled(load_yaml(method_config(args.imm)))
        baselines = {m: instantiate(load_yaml(method_config(m))) for m in args.baseline}
        sets = {}
        for name in ("tune", "data"):
            td, _ = load_dataset(getattr(args, name))
            if keys.R not in td.keys():
                raise ValueError(f"{getattr(args, name)} has no r per track (the filter is told it)")
            print(f"[velocity] rebuilding the windows of {getattr(args, name)} from its sample files", file=sys.stderr,
                  flush=True)
            got = set_reports(getattr(args, name), args.max_age)
            keep = torch.from_numpy(got.rows <= (args.rows_within if name == "data" else float("inf")))
            if not keep.any():
                raise ValueError(f"{args.data}: no window from a sample whose rows are at most {args.rows_within:g} s "
                                 f"apart (its samples' row intervals: {sorted(set(got.rows.tolist()))})")
            sets[name] = (as_batch(td)[keep], torch.from_numpy(got.velocity)[keep], got.samples[keep.numpy()])
            if not keep.all():
                print(f"[velocity] {args.data}: {int(keep.sum())} of {len(keep)} windows, from samples whose rows are "
                      f"at most {args.rows_within:g} s apart", file=sys.stderr, flush=True)
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    tune, tune_v, _ = sets["tune"]
    data, data_v, data_samples = sets["data"]
    tune_states = tune[keys.STATES].double().numpy()

    def told(batch, v, lag, scale, k, axes):  # the reports' error measured on --tune, whichever set is scored
        h, vert, _ = report_errors(tune_v.numpy(), tune_states, lag)
        return told_velocity(imm.scaled(scale), batch, v, (k * h, k * vert), lag, axes)[keys.STATE]

    def score(batch, v, lag, scale, k, axes):
        return states_rmse(told(batch, v, lag, scale, k, axes), batch)

    def scored(state) -> dict:  # a row's numbers on --data
        return {"average": states_rmse(state, data), "over_1km": over_limit(state, data, 1000.0)}

    rows = [{"row": m, "kind": "baseline", "setting": "", **scored(method.track(data)[keys.STATE])}
            for m, method in baselines.items()]
    chosen = {}
    for label, axes in AXIS_SETS.items():
        best = {"lag": 0.0, "scale": 1.0, "k": 1.0}
        grids = (("lag",), [(g,) for g in args.lags]), (("scale", "k"), [(a, b) for a in args.scales
                                                                          for b in args.factors])
        for names, grid in (*grids, grids[0]):  # L, then the noise and k together, then L again
            tried = {g: score(tune, tune_v, **{**best, **dict(zip(names, g))}, axes=axes) for g in grid}
            best.update(zip(names, min(tried, key=tried.get)))
            print(f"[velocity] {label}: {'/'.join(names)} " + ", ".join(
                f"{'/'.join(f'{v:g}' for v in g)} {s:.4f}" for g, s in tried.items())
                + f" on --tune; {'/'.join(f'{best[n]:g}' for n in names)}", file=sys.stderr, flush=True)
        h, vert, share = report_errors(tune_v.numpy(), tune_states, best["lag"])
        chosen[label] = best
        rows.append({"row": f"{args.imm} told the reported velocity, {label}", "kind": "told", "axes": list(axes),
                     "setting": f"L {best['lag']:g} s, noise x{best['scale']:g}, k {best['k']:g}",
                     "sigma": [best["k"] * h, best["k"] * vert], "reports": share,
                     **scored(told(data, data_v, **best, axes=axes))})
    h0, v0, share = report_errors(data_v.numpy(), data[keys.STATES].double().numpy(), 0.0)
    base = rows[0]["average"] if baselines else None
    print(f"reports on {args.data}: {share:.1%} of scans with truth; RMS error against the truth's velocity at the "
          f"scan {h0:.2f} m/s horizontal, {v0:.2f} m/s vertical")
    print(f"| {args.data} | setting (chosen on {args.tune}) | Average [m] | tracks ever over 1 km |"
          + (f" / {rows[0]['row']} |" if base else ""))
    print("|:---|---:|---:|---:|" + ("---:|" if base else ""))
    for r in rows:
        print(f"| {r['row']} | {r['setting']} | {r['average']:.3f} | {r['over_1km']} of {len(data)} |"
              + (f" {r['average'] / base:.3f}x |" if base else ""))
    per_sample = []
    for name in sorted(set(data_samples)) if args.by_sample else ():
        m = torch.from_numpy(data_samples == name)
        b, v = data[m], data_v[m]
        hs, vs, got = report_errors(v.numpy(), b[keys.STATES].double().numpy(), 0.0)
        per_sample.append({"sample": str(name), "windows": int(m.sum()), "reports": got, "error_at_scan": [hs, vs],
                           args.imm: average_rmse(imm, b),
                           "told": score(b, v, **chosen["every axis"], axes=AXIS_SETS["every axis"])})
    if per_sample:
        print(f"\n| sample | windows | scans with a report | report error h / v [m/s] | {args.imm} [m] | told, every axis "
              f"[m] | ratio |\n|:---|---:|---:|---:|---:|---:|---:|")
        for r in per_sample:
            print(f"| {r['sample']} | {r['windows']} | {r['reports']:.0%} | {r['error_at_scan'][0]:.2f} / "
                  f"{r['error_at_scan'][1]:.2f} | {r[args.imm]:.3f} | {r['told']:.3f} | {r['told'] / r[args.imm]:.3f}x |")
    if args.json:
        args.json.write_text(json.dumps({"tune": args.tune, "data": args.data, "label": args.label or args.data,
                                         "rows_within": args.rows_within if args.rows_within < float("inf") else None,
                                         "windows": len(data), "reports": share, "error_at_scan": [h0, v0],
                                         "rows": rows, "per_sample": per_sample}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
