"""``scripts/covariance_scale.py`` (docs/real.md "Calibration"): its scaled NEES is ``immnet.evaluation.calibration``'s
on the scaled covariance, its constant scale is the closed-form maximum likelihood, its per-scan scale finds a scale
that the states carry, and the states it reads are the ones the network corrects from."""

import runpy

import pytest
import torch

from immnet import keys
from immnet.config import REPO_ROOT
from immnet.data.generate import generate
from immnet.data.spec import DataSpec
from immnet.data.storage import as_batch
from immnet.evaluation.calibration import chi2_3_cdf, position_nees
from immnet.evaluation.metrics import scored_mask
from immnet.motion import POS
from immnet.tracking.methods import IMMNetMethod

SCRIPT = REPO_ROOT / "scripts" / "covariance_scale.py"
REAL = REPO_ROOT / "immnet" / "pretrained" / "immnet-real.ckpt"
pos = list(POS)


@pytest.fixture(scope="module")
def script():
    return runpy.run_path(str(SCRIPT))


def _spd(n, seed):
    g = torch.Generator().manual_seed(seed)
    A = torch.randn(n, 3, 3, generator=g, dtype=torch.float64)
    return A @ A.transpose(-1, -2) + 0.5 * torch.eye(3, dtype=torch.float64)


def test_scaled_nees_is_the_calibration_nees_of_the_scaled_covariance(script):
    n = 50
    P = _spd(n, 0)
    g = torch.Generator().manual_seed(1)
    e, s = torch.randn(n, 3, generator=g, dtype=torch.float64), torch.randn(n, 3, generator=g, dtype=torch.float64)
    D = torch.diag_embed(torch.exp(s / 2))
    cov = _block(D @ P @ D)
    state = torch.zeros(1, n, 9, dtype=torch.float64)
    state[0, :, [0, 3, 6]] = e
    expected = position_nees(state, cov, torch.zeros_like(state))[0]
    torch.testing.assert_close(script["scaled_nees"](e, P, s), expected, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(script["scaled_nees"](e, P), position_nees(state, _block(P), torch.zeros_like(state))[0])


def _block(P):
    """``[1, n, 9, 9]`` with ``P [n, 3, 3]`` as its position block (x, y, z at 0, 3, 6)."""
    cov = torch.zeros(1, P.shape[0], 9, 9, dtype=P.dtype)
    for i, a in enumerate((0, 3, 6)):
        for j, b in enumerate((0, 3, 6)):
            cov[0, :, a, b] = P[:, i, j]
    return cov


def test_the_constant_scale_is_the_closed_form_likelihood_maximum(script):
    """With a diagonal covariance the likelihood's maximum is, per axis, the mean of e^2 / P (a closed form)."""
    n = 4000
    g = torch.Generator().manual_seed(2)
    var = torch.rand(n, 3, generator=g, dtype=torch.float64) * 4 + 0.1
    e = torch.randn(n, 3, generator=g, dtype=torch.float64) * (var * torch.tensor([0.6, 1.0, 2.5])).sqrt()
    scale = script["fit"](None, e, torch.diag_embed(var))
    torch.testing.assert_close(torch.exp(scale.b), (e**2 / var).mean(0), rtol=1e-6, atol=0)


def test_the_per_scan_scale_finds_what_the_states_carry(script):
    """Errors whose variance is exp(0.8 h_0 - 0.3 h_1) P: the fitted head recovers the coefficients, and its ellipsoids
    hold their levels where one constant scale's do not."""
    n = 20000
    g = torch.Generator().manual_seed(3)
    h = torch.randn(n, 5, generator=g, dtype=torch.float64)
    s_true = (0.8 * h[:, :1] - 0.3 * h[:, 1:2]).expand(n, 3)
    P = _spd(n, 4)
    L = torch.linalg.cholesky(P)
    e = torch.exp(s_true / 2) * (L @ torch.randn(n, 3, 1, generator=g, dtype=torch.float64)).squeeze(-1)
    head = script["fit"](h, e, P, ridge=1e-6)
    assert float((head(h) - s_true).pow(2).mean().sqrt()) < 0.03  # s spans about +-2.5
    u_head = chi2_3_cdf(script["scaled_nees"](e, P, head(h)))
    u_const = chi2_3_cdf(script["scaled_nees"](e, P, script["fit"](None, e, P)(h)))
    assert abs(float((u_head <= 0.5).double().mean()) - 0.5) < 0.015
    assert abs(float((u_const <= 0.5).double().mean()) - 0.5) > 0.03  # a mixture of scales: peaked, heavy-tailed


def test_it_reads_the_states_the_network_corrects_from(script):
    """The shipped real network told each track's r: at every scored scan the reported position less its filter's
    (the correction knocked out) is r times the mean of the members' output layers on the states collected."""
    batch = as_batch(generate(3, seed=5, spec=DataSpec(T=40, min_segment=8)))
    method = IMMNetMethod(str(REAL), name="real", return_cov=True, r="data")
    base = IMMNetMethod(str(REAL), name="real", return_cov=True, r="data", knock_out=["correction"])
    h, e, P = script["collect"](method, batch, from_scan=5)
    with torch.no_grad():
        out = method.track(batch)
        filt = base.track(batch)[keys.STATE][..., pos]
    truth = batch[keys.STATES].double()
    mask = scored_mask(truth, batch[keys.MEASUREMENTS])
    mask[:, :5] = False
    assert h.shape[0] == e.shape[0] == P.shape[0] == int(mask.sum()) > 80
    members = method.net.correct.members
    k = members[0].hidden
    with torch.no_grad():
        delta = torch.stack([m.out(h[:, i * k : (i + 1) * k].float()).double() for i, m in enumerate(members)]).mean(0)
    r = batch[keys.R].double().reshape(-1, 1).expand(mask.shape)[mask].unsqueeze(-1)
    shift = (out[keys.STATE][..., pos] - filt)[mask]
    # to the float32 rounding of the positions the step reports (tens of km); a state one scan off is 0.1 m off
    tol = 2 * torch.finfo(torch.float32).eps * float(out[keys.STATE][..., pos][mask].abs().max())
    torch.testing.assert_close(shift, r * delta, rtol=0, atol=tol)
    assert float((shift[1:] - r[1:] * delta[:-1]).abs().median()) > 0.1
    torch.testing.assert_close(e, (out[keys.STATE][..., pos] - truth[..., pos])[mask])
    torch.testing.assert_close(P, out[keys.STATE_COV][..., pos, :][..., pos][mask])


def test_a_network_without_a_correction_is_refused(script):
    method = IMMNetMethod(str(REAL.with_name("immnet-general.ckpt")), name="general", return_cov=True)
    with pytest.raises(ValueError, match="no output correction"):
        script["collect"](method, as_batch(generate(2, seed=6, spec=DataSpec(T=30, min_segment=8))))
