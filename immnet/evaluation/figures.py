"""Figures of an evaluation, as PNG (matplotlib, Agg backend).

(a) :func:`plot_rmse_over_time`: RMSE over time per method, log scale, switches marked;
(b) :func:`plot_track`: one trajectory in 3D (truth, measurements, estimates) with a zoomed
    horizontal-plane panel at each switch; (c) :func:`plot_mode_probs`: mode probabilities of one
    trajectory against its true modes; (d) :func:`plot_confusion`: a row-normalized confusion
    matrix. :func:`write_figures` writes the set that ``immnet evaluate --figures DIR`` makes.
(e) :func:`plot_calibration`: coverage of the position ellipsoids against their confidence level
    (``scripts/calibration.py``). (f) :func:`plot_radar_display`: the multi-target tracker's plots, clutter and
    tracks on a radar display (``immnet track --figure``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from immnet import keys  # noqa: E402
from immnet.evaluation.metrics import avg_curve, position_error, switch_steps  # noqa: E402
from immnet.motion import MODE_LABELS, POS  # noqa: E402

MODE_COLORS = ("#4c72b0", "#dd8452", "#55a868", "#c44e52")
_CYCLE = plt.get_cmap("tab10").colors


def method_colors(names: Sequence[str]) -> dict[str, tuple]:
    """A fixed color per method; ``measurements`` gray, ``clairvoyant`` purple (truth is black)."""
    fixed = {"measurements": (0.6, 0.6, 0.6), "clairvoyant": (0.58, 0.0, 0.83)}
    others = [n for n in names if n not in fixed]
    return {n: fixed.get(n, _CYCLE[others.index(n) % 10] if n in others else None) for n in names}


def _np(x) -> np.ndarray:
    return x.detach().cpu().double().numpy() if isinstance(x, torch.Tensor) else np.asarray(x, dtype=float)


def _switches(mode) -> tuple[list[int], np.ndarray | None]:
    """The switch steps of ``mode [T]`` and its labels as integers (``[]`` and ``None`` without ``mode``)."""
    if mode is None:
        return [], None
    return torch.nonzero(switch_steps(torch.as_tensor(mode))).flatten().tolist(), _np(mode).astype(int)


def _mark_switches(ax, mode, label=True) -> None:
    switches, m = _switches(mode)
    for s in switches:
        ax.axvline(s, color="k", ls=":", lw=1)
        if label:
            ax.annotate(
                f"{MODE_LABELS[m[s - 1]]}→{MODE_LABELS[m[s]]}", (s, 1.0), xycoords=("data", "axes fraction"),
                xytext=(3, -12), textcoords="offset points", fontsize=8,
            )


def plot_rmse_over_time(curves: Mapping[str, object], path, title="Position RMSE over time", mode=None, dt=1.0):
    """One line per method from ``[T]`` RMSE curves (log y); ``mode [T]`` marks its switches."""
    colors = method_colors(list(curves))
    fig, ax = plt.subplots(figsize=(9, 4.5), constrained_layout=True)
    for name, c in curves.items():
        c = _np(c)
        ax.plot(np.arange(len(c)) * dt, c, label=name, color=colors[name], lw=1.4)
    _mark_switches(ax, mode)
    ax.set_yscale("log")
    ax.yaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
    ax.yaxis.set_minor_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
    ax.tick_params(axis="y", which="minor", labelsize=7)
    ax.set(xlabel="time [s]", ylabel="RMSE per axis [m]", title=title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
    return save_figure(fig, path)


def plot_track(truth, measurements, estimates: Mapping[str, object], path, mode=None, before=2, after=10, title=None):
    """3D track in km (truth, measurements as light dots, each estimate) and, for each switch
    ``s``, a zoom on the horizontal plane over steps ``[s - before, s + after]`` in metres
    relative to the true position at ``s`` (the ``measurements`` method is the dots, not a line)."""
    truth, z = _np(truth), _np(measurements)
    est = {k: _np(v) for k, v in estimates.items() if k != "measurements"}
    colors = method_colors(list(est))
    sw, m = _switches(mode)
    n_zoom = max(len(sw), 1)
    cols = 1 if n_zoom <= 2 else 2
    rows = -(-n_zoom // cols)
    fig = plt.figure(figsize=(8 + 5.5 * cols, max(6.0, 3.6 * rows)), constrained_layout=True)
    gs = fig.add_gridspec(rows, 1 + cols, width_ratios=(1.4 * cols, *[1] * cols))
    ax = fig.add_subplot(gs[:, 0], projection="3d")
    p = list(POS)
    ax.scatter(*(z[:, i] / 1e3 for i in range(3)), s=3, color="0.75", label="measurements", depthshade=False)
    ax.plot(*(truth[:, i] / 1e3 for i in p), color="k", lw=2.2, label="truth")
    for name, x in est.items():
        ax.plot(*(x[:, i] / 1e3 for i in p), color=colors[name], lw=1.0, label=name)
    ax.scatter(*(truth[0, i] / 1e3 for i in p), marker="o", s=30, color="k")
    for j, s in enumerate(sw):
        ax.scatter(*(truth[s, i] / 1e3 for i in p), marker="*", s=140, color="red", depthshade=False)
        ax.text(*(truth[s, i] / 1e3 for i in p), f"  S{j + 1}", color="red", fontsize=10)
    ax.set(xlabel="x [km]", ylabel="y [km]", zlabel="z [km]", title=title or "track (o start, * switch)")
    ax.legend(loc="upper left", fontsize=8)
    T = truth.shape[0]
    for j, s in enumerate(sw or [None]):
        zax = fig.add_subplot(gs[j // cols, 1 + j % cols])
        if s is None:
            zax.text(0.5, 0.5, "no switch", ha="center", va="center", transform=zax.transAxes)
            zax.set_axis_off()
            break
        lo, hi = max(s - before, 0), min(s + after, T - 1) + 1
        o = truth[s, [p[0], p[1]]]
        zax.scatter(z[lo:hi, 0] - o[0], z[lo:hi, 1] - o[1], s=14, color="0.7", label="measurements")
        zax.plot(truth[lo:hi, p[0]] - o[0], truth[lo:hi, p[1]] - o[1], color="k", lw=1.8, marker="o", ms=3)
        for name, x in est.items():
            zax.plot(x[lo:hi, p[0]] - o[0], x[lo:hi, p[1]] - o[1], color=colors[name], lw=1.1, marker=".", ms=5)
        for k in (lo, s + after // 2, hi - 1):  # step numbers along the truth
            if lo <= k < hi:
                zax.annotate(str(k), (truth[k, p[0]] - o[0], truth[k, p[1]] - o[1]), xytext=(4, 4),
                             textcoords="offset points", fontsize=7)
        zax.scatter([0], [0], marker="*", s=140, color="red", zorder=5)
        zax.set_aspect("equal", adjustable="datalim")
        zax.set_title(f"S{j + 1}: t = {s}, {MODE_LABELS[m[s - 1]]} → {MODE_LABELS[m[s]]} (steps {lo}..{hi - 1})", fontsize=9)
        zax.set_xlabel("x - x(S) [m]", fontsize=8)
        zax.set_ylabel("y - y(S) [m]", fontsize=8)
        zax.tick_params(labelsize=7)
        zax.grid(True, alpha=0.3)
    return save_figure(fig, path)


def plot_mode_probs(mode_probs: Mapping[str, object], mode, path, dt=1.0):
    """Stacked mode probabilities per method over time, a band of the true mode above each."""
    names = list(mode_probs)
    fig, axes = plt.subplots(len(names), 1, figsize=(10, 1.2 + 2.0 * len(names)), sharex=True,
                             squeeze=False, constrained_layout=True)
    m = _np(mode).astype(int)
    t = np.arange(len(m)) * dt
    for ax, name in zip(axes[:, 0], names):
        pr = _np(mode_probs[name])
        ax.stackplot(t, pr.T, colors=MODE_COLORS, labels=MODE_LABELS, alpha=0.85, step="mid")
        for k in range(len(MODE_LABELS)):  # true mode as a band above the plot
            ax.fill_between(t, 1.03, 1.13, where=m == k, color=MODE_COLORS[k], step="mid", lw=0)
        ax.text(1.0, 1.15, "true mode ▲", transform=ax.transAxes, ha="right", va="bottom", fontsize=7)
        _mark_switches(ax, mode, label=False)
        ax.set(ylim=(0, 1.14), yticks=[0, 0.5, 1])
        ax.set_ylabel(name, fontsize=9)
    axes[0, 0].legend(loc="lower left", bbox_to_anchor=(0, 1.12), ncol=4, fontsize=8, frameon=False)
    axes[-1, 0].set_xlabel("time [s]")
    return save_figure(fig, path)


def plot_confusion(conf, path, title="mode confusion"):
    """Row-normalized confusion matrix (true rows, predicted columns), counts' shares annotated."""
    c = _np(conf)
    share = c / np.maximum(c.sum(axis=1, keepdims=True), 1)
    fig, ax = plt.subplots(figsize=(4.8, 4.2), constrained_layout=True)
    im = ax.imshow(share, cmap="Blues", vmin=0, vmax=1)
    k = len(c)
    for i in range(k):
        for j in range(k):
            ax.text(j, i, f"{100 * share[i, j]:.1f}%", ha="center", va="center",
                    color="white" if share[i, j] > 0.6 else "black", fontsize=9)
    ax.set_xticks(range(k), MODE_LABELS[:k])
    ax.set_yticks(range(k), MODE_LABELS[:k])
    ax.set(xlabel="predicted", ylabel="true")
    acc = np.trace(c) / max(c.sum(), 1)
    ax.set_title(f"{title}\naccuracy {100 * acc:.1f} %", fontsize=10)
    fig.colorbar(im, ax=ax, fraction=0.046)
    return save_figure(fig, path)


def save_figure(fig, path, dpi: int = 110) -> Path:
    """Write ``fig`` to ``path`` (its folder made) and close it; the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def write_figures(results: Mapping[str, dict], data, cases: Sequence[int], out_dir) -> list[Path]:
    """The evaluation's figure set in ``out_dir``: ``rmse_over_time.png`` (all trajectories),
    ``confusion_<method>.png`` per method with mode probabilities and, for each trajectory index
    in ``cases`` (kept by the runner), ``case<i>_track.png``, ``case<i>_rmse.png`` (per-step
    error of that trajectory) and ``case<i>_modes.png``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = [plot_rmse_over_time({n: avg_curve(r["rmse_over_time"]) for n, r in results.items()},
                                   out / "rmse_over_time.png", title=f"Position RMSE over time ({data.batch_size[0]} trajectories)")]
    for name, r in results.items():
        if r.get("confusion") is not None:
            written.append(plot_confusion(r["confusion"], out / f"confusion_{name}.png", title=f"{name}: mode confusion"))
    has_mode = keys.MODE in data.keys()
    for row, i in enumerate(sorted(set(cases))):
        traj = data[i]
        mode = traj[keys.MODE] if has_mode else None
        states = {n: r["kept"][keys.STATE][row] for n, r in results.items()}
        err = {n: avg_curve(position_error(s, traj[keys.STATES]).abs()) for n, s in states.items()}
        written.append(plot_rmse_over_time(err, out / f"case{i}_rmse.png", title=f"trajectory {i}: position error per axis (RMS over axes)", mode=mode))
        z = next(iter(results.values()))["kept"][keys.MEASUREMENTS][row]  # gated: as the methods saw them
        written.append(plot_track(traj[keys.STATES], z, states, out / f"case{i}_track.png",
                                  mode=mode, title=f"trajectory {i}"))
        probs = {n: r["kept"][keys.MODE_PROBS][row] for n, r in results.items() if keys.MODE_PROBS in r["kept"]}
        if probs and mode is not None:
            written.append(plot_mode_probs(probs, mode, out / f"case{i}_modes.png"))
    return written


def plot_calibration(curves: Mapping[str, Mapping[float, float]], path, title="Position ellipsoid coverage"):
    """Coverage against confidence level, one line per method (``{level: fraction}``, e.g.
    ``immnet.evaluation.calibration.track_coverage``'s); the diagonal is a calibrated filter, below it an
    overconfident one (ellipsoids too small), above it a cautious one."""
    colors = method_colors(list(curves))
    fig, ax = plt.subplots(figsize=(5.2, 5.0))
    ax.plot([0, 1], [0, 1], color="k", ls=":", lw=1, label="calibrated")
    for name, curve in curves.items():
        points = sorted((float(p), float(c)) for p, c in curve.items())  # levels as floats or JSON's strings
        ax.plot(*zip(*points), marker=".", color=colors[name], label=name)
    ax.set(xlim=(0, 1), ylim=(0, 1), xlabel="confidence level p of the position ellipsoid",
           ylabel="fraction of scans whose ellipsoid holds the truth")
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    return save_figure(fig, path, dpi=120)


def _ring_step(extent_km: float) -> float:
    """A round spacing (1, 2 or 5 times a power of ten, km) giving three to six range rings out to ``extent_km``."""
    for power in range(-1, 6):
        for m in (1.0, 2.0, 5.0):
            step = m * 10.0**power
            if extent_km / step <= 6:
                return step
    return 10.0**6


def plot_radar_display(plots, tracks: Mapping[int, object], path, clutter=None, title=None) -> Path:
    """A radar display of a run of the multi-target tracker: every plot ``plots [P, >=2]`` (east, north, m) as a grey
    dot, or with ``clutter [P]`` (True: a false plot, known from a scene's truth) the clutter apart; each track of
    ``tracks`` (id -> positions ``[n, >=2]``, m, in time order) as a line with its id at its last point. East and
    north in km, the radar at the origin, range rings at a round spacing."""
    P = np.asarray(plots, dtype=np.float64)[:, :2] / 1e3
    lines = {int(k): np.asarray(v, dtype=np.float64)[:, :2] / 1e3 for k, v in tracks.items()}
    every = np.concatenate([P, *lines.values(), np.zeros((1, 2))])
    extent = max(float(np.hypot(every[:, 0], every[:, 1]).max()), 1.0)
    step = _ring_step(extent)
    fig, ax = plt.subplots(figsize=(7.0, 7.0))
    for r in np.arange(step, extent + step, step):
        ax.add_patch(matplotlib.patches.Circle((0.0, 0.0), r, fill=False, color="0.8", lw=0.7, zorder=0))
        ax.text(r * 0.7071, r * 0.7071, f"{r:g} km", color="0.55", fontsize=7, zorder=0)
    if clutter is None:
        ax.scatter(P[:, 0], P[:, 1], s=4, color="0.6", lw=0, label="plots", zorder=1)
    else:
        c = np.asarray(clutter, dtype=bool)
        ax.scatter(P[~c, 0], P[~c, 1], s=4, color="0.5", lw=0, label="plots of aircraft", zorder=1)
        ax.scatter(P[c, 0], P[c, 1], s=9, color="tab:orange", marker="x", lw=0.6, alpha=0.7, label="clutter", zorder=1)
    colors = plt.get_cmap("tab10")
    for i, (tid, xy) in enumerate(sorted(lines.items())):
        color = colors(i % 10)
        ax.plot(xy[:, 0], xy[:, 1], color=color, lw=1.3, zorder=2, label="tracks (id at the last point)" if i == 0 else None)
        ax.text(xy[-1, 0], xy[-1, 1], f" {tid}", color=color, fontsize=8, fontweight="bold", zorder=3)
    ax.plot([0.0], [0.0], marker="^", color="k", ms=7, ls="", label="radar", zorder=3)
    lim = extent + step * 0.25
    ax.set(xlim=(-lim, lim), ylim=(-lim, lim), aspect="equal", xlabel="east (km)", ylabel="north (km)",
           title=title or f"{len(lines)} tracks, {len(P)} plots")
    ax.legend(loc="upper right", fontsize=7, framealpha=0.85)
    fig.tight_layout()
    return save_figure(fig, path)
