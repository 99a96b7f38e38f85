"""What a filter would need to know of the motion to be far ahead of the best model-based one: a constant-acceleration
Kalman filter told, by the truth, how each scan's acceleration changed. References, not trackers.

    python scripts/motion_oracle.py --tune runs/real/data/quickstart-1s/val --data runs/real/data/quickstart-1s/test \\
        --baseline real-imm-singer [--baseline immnet-real] [--imm real-imm-singer] [--delays 0,1,2,3,5] \\
        [--label "1 s test"] [--json oracle.json]
    python scripts/motion_oracle.py --plot A.json B.json ... --figure motion_oracle.png

The truth's change of acceleration over the interval before scan ``t`` is its jerk ``j_t = (a_t - a_{t-1}) / dt_t``
per axis (the truth of real flights is one trajectory of the white-jerk model, docs/data.md). Rows
(docs/notebook/real-flights.md "What a tracker would need to know"), each the table's Average RMSE (``immnet
evaluate``'s, from each track's first detection), the filter started as every model-based one
(``immnet.filters.imm.initial_state``) and told each track's r:

- **the size of the change**: process noise set scan by scan and axis from the truth, white-jerk spectral density
  ``q_t = c j_t^2 dt_t + floor`` (a jerk held over the interval changes the acceleration by ``j_t dt_t``, the noise's
  standard deviation over it). What a learned part that sets the filter's noise (KalmanNet's) could know at best;
- **the change itself, d scans late**: the truth's jerk of ``d`` scans before as a known input over each interval
  (``p += j dt^3 / 6``, ``v += j dt^2 / 2``, ``a += j dt``, on top of the CA prediction), with a small white-jerk
  noise ``q``. At ``d = 0`` the filter knows every maneuver as it happens; at ``d >= 1`` it learns of it ``d`` scans
  after (the acceleration keeps changing for a while, so knowing it late still helps);
- with ``--imm METHOD`` (a decoupled IMM of ``configs/methods/``, ``PerAxisIMMTracker``), the same input on each of its
  models' predictions, its process noise scaled by a factor ``s`` (a filter told the change needs less of it).

Each row's setting (``c``; ``q``; ``s``) is chosen on ``--tune`` (the validation flights) and the row is scored on
``--data`` with it; ``--baseline`` methods (``configs/methods/``) are scored on ``--data`` in the same run, the first
the ratio's reference. ``--plot`` draws the reports of several runs (``--json``) as one figure: the best filter's
ratio against how late, in seconds, the change is told, the other baselines (the shipped networks) as levels.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from unittest import mock

import torch

from immnet import keys
from immnet.config import instantiate, load_yaml
from immnet.data.storage import as_batch, load_dataset
from immnet.data.times import scan_intervals
from immnet.filters.methods import method_config
from immnet.evaluation.search import average_rmse, states_rmse
from immnet.filters import per_axis
from immnet.filters.base import output
from immnet.filters.imm import first_detection, initial_state
from immnet.imm.runner import linear_transition, predict, run
from immnet.motion import ConstantAcceleration
from immnet.motion.models import ACC

FLOOR = 1e-4
"""The size-of-change row's noise where the truth's acceleration does not change (m^2/s^5)."""


def truth_jerk(states: torch.Tensor, intervals: torch.Tensor) -> torch.Tensor:
    """``[B, T, 3]`` the truth's jerk over the interval before each scan, ``(a_t - a_{t-1}) / dt_t`` per axis, from
    truth states ``[B, T, 9]`` and the intervals ``[B, T]``; 0 at scan 0 and where either scan has no truth."""
    a = states[..., list(ACC)].double()
    j = torch.zeros_like(a)
    j[:, 1:] = (a[:, 1:] - a[:, :-1]) / intervals[:, 1:, None].double()
    return torch.nan_to_num(j, nan=0.0, posinf=0.0, neginf=0.0)


def delayed(u: torch.Tensor, d: int) -> torch.Tensor:
    """``u [B, T, ...]`` ``d`` scans late: ``u[:, t - d]`` at scan ``t``, 0 before scan ``d``."""
    out = torch.zeros_like(u)
    if d < u.shape[1]:
        out[:, d:] = u[:, :u.shape[1] - d]
    return out


def jerk_input(jerk: torch.Tensor, intervals: torch.Tensor) -> torch.Tensor:
    """``[B, T, 9]`` the state change a jerk ``[B, T, 3]`` held over each interval ``[B, T]`` adds to the CA prediction:
    ``(j dt^3 / 6, j dt^2 / 2, j dt)`` per axis."""
    dt = intervals.double()[..., None]
    return torch.stack([jerk * dt**3 / 6, jerk * dt**2 / 2, jerk * dt], -1).reshape(*jerk.shape[:2], 9)


def ca_filter(z: torch.Tensor, r: torch.Tensor, intervals: torch.Tensor, q: torch.Tensor,
              inputs: torch.Tensor | None = None) -> torch.Tensor:
    """A white-jerk CA Kalman filter (float64) of measurements ``z [B, T, 3]`` (NaN: missed) with measurement std ``r
    [B]``, spectral density ``q [B, T, 3]`` per scan and axis and known ``inputs [B, T, 9]`` added to each prediction;
    states ``[B, T, 9]``, NaN before a track's first detection."""
    z = z.double()
    B = z.shape[0]
    model = ConstantAcceleration(noise="continuous")
    F = model.F(intervals.double(), dtype=torch.float64)  # [B, T, 9, 9]
    s = q.double().sqrt().repeat_interleave(3, -1)  # per axis: the axis's three state entries
    Q = model.Q(1.0, intervals.double(), dtype=torch.float64) * s[..., :, None] * s[..., None, :]
    r = r.double().reshape(-1)
    x0, P0 = initial_state(z, r)

    def transition(t: int, x, P):
        x, P = predict(x, P, F[:, t, None], Q[:, t, None])
        return (x if inputs is None else x + inputs[:, t, None].double()), P

    one = torch.ones(B, 1, dtype=torch.float64)
    states, _, _ = run(z, x0[:, None], P0[:, None], one, one[:1], transition, r * r, start=first_detection(z))
    return output(states, {}, measurements=z)[keys.STATE]


def late_input(batch, d: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``(intervals [B, T], input [B, T, 9])``: the state change of the truth's jerk ``d`` scans late."""
    iv = scan_intervals(batch, torch.float64)
    return iv, jerk_input(delayed(truth_jerk(batch[keys.STATES], iv), d), iv)


def size_oracle(batch, c: float) -> torch.Tensor:
    """The size-of-change row's states: ``q_t = c j_t^2 dt_t + FLOOR``."""
    iv = scan_intervals(batch, torch.float64)
    q = c * truth_jerk(batch[keys.STATES], iv) ** 2 * iv[..., None] + FLOOR
    return ca_filter(batch[keys.MEASUREMENTS], batch[keys.R], iv, q)


def input_oracle(batch, d: int, q: float) -> torch.Tensor:
    """The change-itself row's states, ``d`` scans late, white-jerk noise ``q``."""
    iv, u = late_input(batch, d)
    z = batch[keys.MEASUREMENTS]
    return ca_filter(z, batch[keys.R], iv, torch.full((*z.shape[:2], 3), q, dtype=torch.float64), u)


def imm_input_oracle(batch, imm: per_axis.PerAxisIMMTracker, d: int, scale: float) -> torch.Tensor:
    """The change-itself row of a decoupled IMM (``main`` checks ``--imm`` is one), ``d`` scans late: the input
    added to every model's prediction (each axis's three entries), ``sigma_q`` times ``scale``."""
    method = imm.scaled(scale)
    _, u = late_input(batch, d)
    B, T = u.shape[:2]
    u = u.reshape(B, T, 3, 3).permute(2, 0, 1, 3).reshape(3 * B, T, 3)  # the tracker's axis-major tracks

    def with_input(F, Q):
        inner = linear_transition(F, Q)

        def transition(t: int, x, P):
            x, P = inner(t, x, P)
            return x + u[:, t, None], P

        return transition

    with mock.patch.object(per_axis, "linear_transition", with_input):
        return method.track(batch)[keys.STATE]


def _numbers(text: str, cast=float) -> list:
    try:
        return [cast(v) for v in text.split(",") if v]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None


def figure(reports: list[dict], path: Path) -> None:
    """The ratio to each report's first baseline against how late the best filter is told the change (s: scans times
    the set's interval), a line per report; its other baselines (the shipped networks) dotted levels of its colour, the
    0.90x target a black dashed one. The CA rows are in the table, not here."""
    from immnet.evaluation.figures import save_figure  # matplotlib on its Agg backend

    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 4.5))
    for i, rep in enumerate(reports):
        color = f"C{i}"
        base = next(r for r in rep["rows"] if r["kind"] == "baseline")
        pts = sorted((r["delay"] * rep["interval"], r["average"] / base["average"]) for r in rep["rows"]
                     if r["kind"] == "imm")
        ax.plot(*zip(*pts), color=color, lw=2, marker="o", label=rep.get("label") or rep["data"])
        for r in rep["rows"]:
            if r["kind"] == "baseline" and r is not base:
                ax.axhline(r["average"] / base["average"], color=color, ls=":", lw=1.5)
    ax.axhline(0.90, color="k", ls="--", lw=1, label="the 0.90x target")
    ax.axhline(1.0, color="0.5", lw=0.8)
    ax.set_xlabel("how late the best filter is told each scan's change of acceleration [s]")
    ax.set_ylabel("Average RMSE / the best filter's")
    ax.legend(fontsize=8, loc="lower right")
    ax.set_title("What a tracker would need to know (dotted: the shipped network on that set)", fontsize=9)
    fig.tight_layout()
    save_figure(fig, path, dpi=130)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--tune", help="the set each row's setting is chosen on (the validation flights)")
    p.add_argument("--data", help="the set the table scores (with truth and each track's r)")
    p.add_argument("--baseline", action="append", default=[],
                   help="a method of configs/methods/ scored beside (the first: the ratio's reference)")
    p.add_argument("--delays", type=_numbers, default=[0, 1, 2, 3, 5], help="scans late, comma-separated")
    p.add_argument("--scales", type=_numbers, default=[0.5, 1, 2, 4, 8], help="the size row's c to choose from")
    p.add_argument("--noises", type=_numbers, default=[1e-5, 1e-4, 1e-3, 1e-2, 0.04, 0.1],
                   help="the input rows' q (m^2/s^5) to choose from")
    p.add_argument("--imm", help="a decoupled IMM of configs/methods/ to tell the change too")
    p.add_argument("--imm-scales", type=_numbers, default=[1, 0.3, 0.1, 0.03, 0.01, 0.003, 0.001],
                   help="the factors of its process noise to choose from")
    p.add_argument("--label", help="the set's name in the JSON and the figure (default: --data)")
    p.add_argument("--json", type=Path)
    p.add_argument("--plot", nargs="+", type=Path, metavar="JSON",
                   help="no run: draw --figure from reports this script wrote with --json")
    p.add_argument("--figure", type=Path)
    args = p.parse_args(argv)
    if args.plot:
        if not args.figure:
            p.error("--plot draws --figure: give its path")
        try:
            reports = [json.loads(f.read_text()) for f in args.plot]
            figure(reports, args.figure)
        except (OSError, ValueError, KeyError, StopIteration) as e:
            print(f"error: --plot needs this script's --json reports with a baseline ({type(e).__name__}: {e})",
                  file=sys.stderr)
            return 2
        print(f"wrote {args.figure}")
        return 0
    if not (args.tune and args.data):
        p.error("--tune and --data are required (or --plot)")
    sets = {}
    for name in ("tune", "data"):
        td, _ = load_dataset(getattr(args, name))
        if keys.R not in td.keys():
            print(f"error: {getattr(args, name)} has no r per track (the oracle filter is told it)", file=sys.stderr)
            return 2
        sets[name] = as_batch(td)
    try:
        baselines = {m: instantiate(load_yaml(method_config(m))) for m in args.baseline}
        imm = instantiate(load_yaml(method_config(args.imm))) if args.imm else None
        if imm is not None and not isinstance(imm, per_axis.PerAxisIMMTracker):
            raise ValueError(f"--imm {args.imm}: not a decoupled IMM (PerAxisIMMTracker); the input goes on each "
                             f"axis's models")
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    rows = [{"row": m, "kind": "baseline", "setting": "", "average": average_rmse(method, sets["data"])}
            for m, method in baselines.items()]

    def chosen(label: str, kind: str, delay, run_with, settings):
        tuned = {s: states_rmse(run_with(sets["tune"], s), sets["tune"]) for s in settings}
        best = min(tuned, key=tuned.get)
        print(f"[oracle] {label}: {', '.join(f'{s:g} {v:.4f}' for s, v in tuned.items())} on --tune; {best:g}",
              file=sys.stderr, flush=True)
        rows.append({"row": label, "kind": kind, "delay": delay, "setting": f"{best:g}",
                     "average": states_rmse(run_with(sets["data"], best), sets["data"])})

    chosen("CA told the size of each scan's change of acceleration (noise per scan and axis), c", "size", None,
           size_oracle, args.scales)
    for d in map(int, args.delays):
        chosen(f"CA told the change itself, {d} scans late, q", "ca", d, lambda b, q, d=d: input_oracle(b, d, q),
               args.noises)
    for d in map(int, args.delays) if imm else ():
        chosen(f"{args.imm} told the change itself, {d} scans late, noise x", "imm", d,
               lambda b, s, d=d: imm_input_oracle(b, imm, d, s), args.imm_scales)
    base = rows[0]["average"] if baselines else None
    ratio = (lambda v: f" {v / base:.3f}x |") if base else (lambda v: "")
    head = f" / {rows[0]['row']} |" if base else ""
    print(f"| {args.data} | setting (chosen on {args.tune}) | Average [m] |{head}")
    print("|:---|---:|---:|" + ("---:|" if base else ""))
    for r in rows:
        print(f"| {r['row']} | {r['setting']} | {r['average']:.3f} |" + ratio(r["average"]))
    if args.json:
        interval = float(scan_intervals(sets["data"], torch.float64)[:, 1:].nanmean())
        args.json.write_text(json.dumps({"tune": args.tune, "data": args.data, "label": args.label or args.data,
                                         "interval": interval, "rows": rows}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
