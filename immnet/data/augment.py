"""Fresh views of each training batch: the same flights seen from another heading with new measurement noise.

A real-flight training set is a few hundred windows of one region, each measured once (``immnet data adsb``): a
network that passes over it many times can learn that region's headings and the very noise draws of its windows.
``FlightAugment`` gives each training batch a view of its own, drawn from a generator seeded by the training step
(so a resumed run sees the views an uninterrupted one sees):

- ``rotate``: each track's truth (position, velocity, acceleration) turned about the radar site's vertical by an
  angle drawn uniformly from ``[0, 2 pi)``: what the same motion is on another heading. The vertical, the range
  from the site, speeds and turn rates are unchanged; so are the mode labels (a rotation does not change a turn's
  sense). Without ``renoise`` the measurements turn with the truth (isotropic noise keeps its law under a turn).
- ``renoise``: new measurements of the (turned) truth, ``z = H x + r e``, ``e ~ N(0, I3)``, each track's ``r``
  drawn from ``U[r_range]`` (None: the track's own ``r``) and written to the batch's ``r``; the scans missed in the
  data stay missed. This is the measurement model of every data set the package writes, 3D-LAST's and
  ``immnet data adsb``'s (docs/data.md).

Validation and test batches are never changed. ``LASTDataModule(augment=...)`` applies it (docs/training.md).
"""

from __future__ import annotations

import math

import torch
from tensordict import TensorDict

from immnet import keys
from immnet.motion.models import ACC, POS, VEL


class FlightAugment:
    """``rotate`` and ``renoise`` as the module says; ``r_range``: ``[r_min, r_max]`` (m) of the new measurement
    noise, None: each track's own ``r``; ``seed``: with the training step, the generator's seed."""

    def __init__(self, rotate: bool = True, renoise: bool = True, r_range: tuple[float, float] | None = None,
                 seed: int = 0):
        if r_range is not None:
            if len(r_range) != 2 or not all(math.isfinite(float(v)) for v in r_range) or not (
                    0 < float(r_range[0]) <= float(r_range[1])):
                raise ValueError(f"r_range must be [r_min, r_max] with 0 < r_min <= r_max (m), or None, got {r_range!r}")
            if not renoise:
                raise ValueError("r_range draws new measurement noise: it needs renoise=True")
            r_range = (float(r_range[0]), float(r_range[1]))
        self.rotate, self.renoise, self.r_range, self.seed = bool(rotate), bool(renoise), r_range, int(seed)

    def __repr__(self) -> str:
        return (f"FlightAugment(rotate={self.rotate}, renoise={self.renoise}, r_range={self.r_range}, "
                f"seed={self.seed})")

    def __call__(self, batch: TensorDict, step: int) -> TensorDict:
        """The view of ``batch`` (any leading batch dims, time second to last) for training step ``step``."""
        if not (self.rotate or self.renoise):
            return batch
        g = torch.Generator().manual_seed(self.seed * 1_000_003 + int(step))
        out = batch.copy()  # shallow: the tensors it changes are replaced, never written in place
        states = out[keys.STATES]
        z = out[keys.MEASUREMENTS]
        lead = states.shape[:-2]
        if self.rotate:
            theta = torch.rand(lead, generator=g, dtype=torch.float64) * (2 * math.pi)
            c, s = theta.cos()[..., None], theta.sin()[..., None]

            def turn(x, y):
                return c * x - s * y, s * x + c * y

            turned = states.to(torch.float64, copy=True)  # in float64: positions are ~1e5 m from the site
            for ix, iy in zip((POS[0], VEL[0], ACC[0]), (POS[1], VEL[1], ACC[1])):
                turned[..., ix], turned[..., iy] = turn(turned[..., ix].clone(), turned[..., iy].clone())
            states = turned.to(states.dtype)
            out[keys.STATES] = states
            if not self.renoise:
                x, y = turn(z[..., 0].to(torch.float64), z[..., 1].to(torch.float64))
                z = torch.stack([x.to(z.dtype), y.to(z.dtype), z[..., 2]], -1)
        if self.renoise:
            if self.r_range is None:
                if keys.R not in out.keys():
                    raise ValueError("FlightAugment(renoise=True, r_range=None) measures each track again with its own "
                                     "r, and this batch holds no 'r': give r_range")
                r = out[keys.R].to(torch.float64)
            else:
                lo, hi = self.r_range
                r = lo + (hi - lo) * torch.rand(lead, generator=g, dtype=torch.float64)
                out[keys.R] = r.to(out[keys.R].dtype if keys.R in out.keys() else states.dtype)
            e = torch.randn(*states.shape[:-1], 3, generator=g, dtype=torch.float64)
            fresh = (turned if self.rotate else states.to(torch.float64))[..., list(POS)] + r[..., None, None] * e
            z = torch.where(torch.isnan(z), z, fresh.to(z.dtype))
        out[keys.MEASUREMENTS] = z
        return out
