"""The shipped networks and the model-based methods give the outputs they gave before the IMM core was written once
(issue 61): ``tests/data/core_outputs.npz`` holds their outputs on a small fixed input, written by this file run as a
script (``python tests/test_core_outputs.py``) at commit 62f11b6, before the 3x3 solves, the Gaussian
log-likelihoods and the moment matches were made one each. The networks are run by ``rollout`` in the radar's
frame, as ``Tracker.track`` ran them then (it now moves each track into its own frame first)."""

from pathlib import Path

import numpy as np
import pytest
import torch

PINNED = Path(__file__).parent / "data" / "core_outputs.npz"
METHODS = ("imm-tuned", "imm-ekf-guard-sticky", "clairvoyant-switch", "real-imm-channel", "real-imm-singer")
NETWORKS = (("3dlast", True), ("general", None))  # (shipped name, guard)
FIELDS = ("state", "mode_probs", "state_cov", "loglik")


def outputs() -> dict:
    """Each method's and shipped network's outputs on 3 fresh 3D-LAST tracks of 120 scans at 1 s, float64."""
    from immnet.data.generate import generate
    from immnet.data.spec import DataSpec
    from immnet.data.times import scan_intervals
    from immnet.filters.methods import build_method
    from immnet.filters.base import before_first_detection, blank_before_first_detection
    from immnet.tracking.tracker import Tracker

    data = generate(3, seed=61, spec=DataSpec(T=120))
    out = {}
    for name in METHODS:
        res = build_method(name).track(data)
        out |= {f"{name}/{k}": res[k] for k in FIELDS if k in res.keys()}
    z = data["measurements"].float()
    for name, guard in NETWORKS:  # the network itself, in the radar's frame (the Tracker moves each track to its own)
        net = Tracker.pretrained(name, **({} if guard is None else {"guard": guard})).net
        res, _ = net.rollout(z, intervals=scan_intervals(data).float(), return_cov=True, return_loglik=True)
        res.set("mode_probs", net.to_mode_probs(res["expert_probs"]))
        res = res.apply(lambda v: blank_before_first_detection(v, before_first_detection(z)))
        out |= {f"{name}/{k}": res[k] for k in FIELDS if k in res.keys()}
    return {k: v.detach().double().numpy() for k, v in out.items()}


@pytest.mark.slow
def test_outputs_are_unchanged_to_1e_5():
    pinned = np.load(PINNED)
    now = outputs()
    assert sorted(now) == sorted(pinned.files)
    for key in pinned.files:
        want, got = pinned[key], now[key]
        assert np.array_equal(np.isnan(want), np.isnan(got)), key
        ok = ~np.isnan(want)
        # relative to each entry, with a floor of 1e-6 of the array's largest (a covariance's zero entries)
        floor = 1e-6 * np.abs(want[ok]).max()
        rel = np.abs(got[ok] - want[ok]) / np.maximum(np.abs(want[ok]), floor)
        assert rel.max() <= 1e-5, (key, float(rel.max()))


if __name__ == "__main__":
    torch.set_num_threads(1)
    np.savez_compressed(PINNED, **outputs())
