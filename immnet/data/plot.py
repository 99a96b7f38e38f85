"""The paper's figure: randomly sampled ground-truth trajectories in 3D (km), colored by mode."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from immnet import keys
from immnet.motion import MODE_LABELS

MODE_COLORS = {0: "tab:blue", 1: "tab:orange", 2: "tab:green", 3: "tab:red"}


def plot_trajectories(td, out, n: int = 400, seed: int = 0, title: str | None = None) -> Path:
    """Draw ``n`` randomly chosen trajectories of ``td`` (a data set TensorDict) to ``out`` (PNG).

    Uses ``states`` where present, else the measurements; segments are colored by ``mode``
    where present (else one color).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if n <= 0:
        raise ValueError(f"n must be positive, got {n}")
    N = td.batch_size[0]
    g = torch.Generator().manual_seed(int(seed))
    idx = torch.randperm(N, generator=g)[: min(n, N)].sort().values
    sub = td[idx]
    has_states = keys.STATES in sub.keys()
    pos = (sub[keys.STATES][..., [0, 3, 6]] if has_states else sub[keys.MEASUREMENTS]).double().numpy() / 1000.0
    mode = sub[keys.MODE].long().numpy() if keys.MODE in sub.keys() else None

    fig = plt.figure(figsize=(8, 7))
    ax = fig.add_subplot(projection="3d")
    for i in range(len(pos)):  # a figure, not a hot path
        p = pos[i]
        if mode is None:
            ax.plot(p[:, 0], p[:, 1], p[:, 2], color="tab:gray", lw=0.6)
            continue
        m = mode[i]
        cuts = np.flatnonzero(np.diff(m)) + 1
        for s, e in zip(np.r_[0, cuts], np.r_[cuts, len(m)]):
            lo = max(s - 1, 0)  # join to the previous segment
            ax.plot(p[lo:e, 0], p[lo:e, 1], p[lo:e, 2], color=MODE_COLORS.get(int(m[s]), "k"), lw=0.6)
    if mode is not None:
        from matplotlib.lines import Line2D

        handles = [Line2D([], [], color=MODE_COLORS[k], label=MODE_LABELS[k]) for k in range(len(MODE_LABELS))]
        ax.legend(handles=handles, loc="upper left")
    ax.scatter([0], [0], [0], marker="^", color="k", s=30)
    ax.set_xlabel("x (km)")
    ax.set_ylabel("y (km)")
    ax.set_zlabel("altitude (km)")
    what = "ground-truth trajectories" if has_states else "measured tracks"
    ax.set_title(title or f"{len(pos)} randomly sampled {what}")
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=120, bbox_inches="tight")
    plt.close(fig)
    return out
