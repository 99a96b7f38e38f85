"""Is a tracker's covariance honest? The position NEES and the coverage of its confidence ellipsoids.

With the position error ``e = p_hat - p`` and the filter's position covariance ``P_pos`` (the 3x3 block of
``state_cov`` at ``[lx, ly, lz]``), the normalized estimation error squared ``NEES = e^T P_pos^{-1} e`` of a
consistent filter is chi-square with 3 degrees of freedom (Bar-Shalom, Li & Kirubarajan, section 5.4). So
``u = F_3(NEES)``, with the chi-square CDF ``F_3(x) = erf(sqrt(x/2)) - sqrt(2x/pi) exp(-x/2)``, is uniform on
[0, 1], and the ``p`` ellipsoid (``NEES <= F_3^{-1}(p)``) holds the truth at a fraction ``p`` of the scans:
``coverage(p) = mean(u <= p)``. A curve below the diagonal is an overconfident filter (its ellipsoids too
small), above it a cautious one.
"""

from __future__ import annotations

import math

import torch

from immnet.motion import POS


def chi2_3_cdf(x: torch.Tensor) -> torch.Tensor:
    """The chi-square CDF with 3 degrees of freedom, in closed form."""
    x = x.clamp_min(0)
    return torch.erf(torch.sqrt(x / 2)) - torch.sqrt(2 * x / math.pi) * torch.exp(-x / 2)


def position_nees(state: torch.Tensor, cov: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    """``e^T P_pos^{-1} e`` ``[B, T]`` of states ``[B, T, 9]``, covariances ``[B, T, 9, 9]`` and the truth ``[B, T, 9]``
    (NaN where either is)."""
    pos = list(POS)
    e = (state[..., pos] - truth[..., pos]).to(torch.float64)
    P = cov[..., pos, :][..., pos].to(torch.float64)
    ok = torch.isfinite(e).all(-1) & torch.isfinite(P).flatten(-2).all(-1)
    eye = torch.eye(3, dtype=P.dtype, device=P.device)
    sol = torch.linalg.solve(torch.where(ok[..., None, None], P, eye), torch.nan_to_num(e).unsqueeze(-1)).squeeze(-1)
    return torch.where(ok, (e.nan_to_num() * sol).sum(-1), torch.full_like(ok, float("nan"), dtype=P.dtype))


LEVELS = (0.5, 0.68, 0.8, 0.9, 0.95, 0.99)


def coverage(nees: torch.Tensor, mask: torch.Tensor, levels=LEVELS) -> dict[float, float]:
    """The fraction of the scans in ``mask [B, T]`` whose ``p`` ellipsoid holds the truth, for each level ``p``."""
    u = chi2_3_cdf(nees[mask & torch.isfinite(nees)])
    if u.numel() == 0:
        raise ValueError("no scan with a finite NEES to score")
    return {float(p): float((u <= p).to(torch.float64).mean()) for p in levels}


CURVE_LEVELS = tuple(round(0.05 * k, 2) for k in range(1, 20)) + (0.99,)
"""The confidence levels of a calibration curve (``plot_calibration``): 0.05 to 0.95 by 0.05, and 0.99."""


def track_coverage(method, data, from_scan: int = 20, levels=LEVELS) -> dict:
    """Run ``method`` (its output must hold ``state_cov``) on ``data`` (a 3D-LAST ``TensorDict [N]`` with
    ``states``) and score its position ellipsoids from scan ``from_scan`` on, where the truth is and the track
    has started: ``{"coverage": {p: fraction}, "nees_mean": mean NEES (3 when calibrated), "scans": count}``;
    where the data has its modes, also ``"post_switch"`` and ``"steady"``: the coverage in the scans after a
    switch of mode (``immnet.evaluation.metrics.post_switch_mask``) and in the others."""
    from immnet import keys
    from immnet.evaluation.metrics import post_switch_mask, scored_mask

    out = method.track(data)
    if keys.STATE_COV not in out.keys():
        raise ValueError(f"{getattr(method, 'name', method)} gives no state_cov (build it with return_cov=True)")
    truth = data[keys.STATES]
    nees = position_nees(out[keys.STATE], out[keys.STATE_COV], truth)
    mask = scored_mask(truth, data[keys.MEASUREMENTS]).to(nees.device)
    mask[:, :from_scan] = False
    ok = mask & torch.isfinite(nees)
    out = {"coverage": coverage(nees, mask, levels), "nees_mean": float(nees[ok].mean()), "scans": int(ok.sum())}
    if keys.MODE in data.keys() and bool((data[keys.MODE] >= 0).any()):  # real flights have no mode labels
        switch = post_switch_mask(data[keys.MODE]).to(mask.device)
        out["post_switch"] = coverage(nees, mask & switch, levels)
        out["steady"] = coverage(nees, mask & ~switch, levels)
    return out
