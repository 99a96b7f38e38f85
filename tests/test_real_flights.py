"""Real flights (docs/real.md): the shipped real-flight weights meet the claim of their provenance on the test
flights of collections/quickstart, and the covariances of the best model-based filter and of IMMNet are
calibrated there (the 95 % position ellipsoid holds the truth at about 95 % of the scans).

The data are written by ``immnet data adsb``'s code with the defaults the weights and the filters were tuned
with (seed 0): the same bytes, so the test flights are the ones no training or tuning saw.
"""

import json

import pytest
import torch

from immnet import keys
from immnet.data import adsb, real
from immnet.data.storage import as_batch, load_dataset
from immnet.evaluation.calibration import coverage, position_nees
from immnet.evaluation.methods import build_method
from immnet.evaluation.metrics import position_error, rmse, scored_mask
from immnet.tracking.tracker import PRETRAINED

pytestmark = [pytest.mark.slow,
              pytest.mark.skipif(adsb.samples_dir() is None, reason="traffic's sample files are not installed")]
PROVENANCE = PRETRAINED.with_name("provenance-real.json")


@pytest.fixture(scope="module")
def outputs(tmp_path_factory):
    """The quickstart test flights and the outputs of immnet-real and of the best model-based filter on them."""
    out = tmp_path_factory.mktemp("real") / "quickstart"
    real.make_adsb(out, ["collections/quickstart"], real.RealSpec(), seed=0)
    td, meta = load_dataset(out / "test")
    prov = json.loads(PROVENANCE.read_text())
    best = prov["claims"]["best_model_based"]
    runs = {}
    for name, dtype in (("immnet-real", torch.float32), (best, torch.float64)):
        batch = as_batch(td, dtype)
        method = build_method(name, return_cov=True)
        with torch.no_grad():
            runs[name] = (method, batch, method.track(batch))
    return prov, best, runs


def test_the_real_flight_weights_meet_their_claim_on_the_test_flights(outputs):
    prov, best, runs = outputs
    assert prov["weights_sha256"] and prov["guard"] is None and prov["scan_interval"] == 1.0
    avg = {name: rmse(position_error(out[keys.STATE], batch[keys.STATES]), scored_mask(batch[keys.STATES], batch[keys.MEASUREMENTS]))["avg"]
           for name, (_, batch, out) in runs.items()}  # as immnet evaluate scores
    n = runs[best][1].batch_size[0]
    assert n == prov["test"]["n"]
    assert avg["immnet-real"] / avg[best] <= prov["claims"]["ratio_to_best_model_based"], avg
    assert avg["immnet-real"] == pytest.approx(prov["metrics"]["immnet-real"]["avg"], rel=1e-4)


@pytest.mark.parametrize("name", ["best", "immnet-real"])
def test_covariances_are_calibrated_on_the_test_flights(outputs, name):
    prov, best, runs = outputs
    _, batch, out = runs[best if name == "best" else name]
    truth = batch[keys.STATES]
    nees = position_nees(out[keys.STATE], out[keys.STATE_COV], truth)
    mask = torch.zeros_like(nees, dtype=torch.bool)
    mask[:, 20:] = True  # past the track start
    cov = coverage(nees, mask)
    assert 0.90 <= cov[0.95] <= 0.98, cov
    assert 0.45 <= cov[0.5] <= 0.58, cov
