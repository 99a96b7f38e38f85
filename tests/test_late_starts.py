"""A track whose first scans are missed starts at its first detection, and filters that detection once.

The independent fact: a tracker that starts each track from its first detection gives, from that scan on, what it
gives for the same track with the scans before cut off (the estimate at scan ``k`` of a track first seen at ``k``
is the start's; nothing before it is reported). Every method that starts from the first detection is held to it,
through each of the core's paths: the scan loop (``runner.run``), the linear IMM's lean path and its batch-last
step for ``torch.compile`` (run eagerly), the decoupled and per-channel IMMs, the clairvoyant bound, and IMMNet's
step (IMM-EKF).
"""

from __future__ import annotations

import pytest
import torch

from immnet import keys
from immnet.data.generate import generate
from immnet.data.spec import DataSpec

LATE = 5  # scans missed at the start of every track


def _late_and_cut(jitter: float):
    """The same tracks seen from scan 0 with their first ``LATE`` scans missed, and cut to start at scan ``LATE``."""
    data = generate(6, seed=13, spec=DataSpec(T=70, min_segment=20, dt_jitter=jitter))
    data[keys.MEASUREMENTS][2, 30:33] = float("nan")  # a gap after the start too
    late = data.clone()
    late[keys.MEASUREMENTS][:, :LATE] = float("nan")
    late[keys.MEASUREMENTS][4, LATE] = float("nan")  # this track starts one scan later still
    cut = data.apply(lambda v: v[:, LATE:] if v.dim() >= 2 else v, batch_size=data.batch_size)
    cut[keys.MEASUREMENTS][4, 0] = float("nan")
    return late, cut


def _same_from_start(late_state: torch.Tensor, cut_state: torch.Tensor):
    """Nothing before the first detection, and from it on, the cut track's estimates (1e-9 of each track's scale)."""
    assert torch.isnan(late_state[:, :LATE]).all()
    ours, ref = late_state[:, LATE:], cut_state
    assert torch.equal(torch.isnan(ours), torch.isnan(ref))
    assert torch.isnan(ref[4, 0]).all() and not torch.isnan(ref[:, 1:]).any()
    scale = ref.nan_to_num().abs().amax((1, 2), keepdim=True)
    assert ((ours - ref).nan_to_num().abs() <= 1e-9 * scale).all()


@pytest.mark.parametrize("jitter", [0.0, 0.5])
@pytest.mark.parametrize("method", ["imm-tuned", "real-imm", "real-imm-axis", "real-imm-singer", "real-imm-channel", "real-ca", "imm-ekf",
                                    "clairvoyant", "clairvoyant-switch"])
def test_a_method_starts_a_late_track_at_its_first_detection(method, jitter):
    """Issue 21 (one core, one start): each method's estimates of a track whose first scans are missed are those of
    the track cut to start at its first detection; at 1 s scans (every track's F and Q shared) and at irregular ones."""
    from immnet.filters.methods import build_method

    late, cut = _late_and_cut(jitter)
    tracker = build_method(method)
    _same_from_start(tracker.track(late)[keys.STATE], tracker.track(cut)[keys.STATE])


@pytest.mark.parametrize("path", ["core", "fused"])
def test_each_path_of_the_linear_imm_starts_a_late_track_at_its_first_detection(path):
    """The same for each of ``imm_filter``'s formulations with ``start`` (``first_detection``), the combined state and
    the mode probabilities; without ``start`` a late track filters its first detection twice, which the test sees."""
    from immnet.filters.methods import build_method
    from immnet.filters.imm import first_detection, imm_filter, initial_state
    from immnet.filters.imm_fused import fused_step, imm_filter_fused

    late, cut = _late_and_cut(0.0)
    tracker = build_method("imm-tuned")
    F, Q, Pi, mu0 = tracker.matrices(1.0)
    R = torch.tensor(tracker.r**2, dtype=torch.float64)

    def filtered(z, start):
        x0, P0 = initial_state(z, tracker.r)
        if path == "fused":
            return imm_filter_fused(z, x0, P0, F, Q, R, Pi, mu0, False, step=fused_step, start=start)[:2]
        return imm_filter(z, x0, P0, F, Q, R, Pi, mu0, start=start)[:2]

    z_late, z_cut = late[keys.MEASUREMENTS], cut[keys.MEASUREMENTS]
    state, probs = filtered(z_late, first_detection(z_late))
    ref, ref_probs = filtered(z_cut, first_detection(z_cut))
    for b in range(z_late.shape[0]):  # from each track's first detection on
        k = 1 if b == 4 else 0
        scale = ref[b].abs().max()
        assert ((state[b, LATE + k:] - ref[b, k:]).abs() <= 1e-9 * scale).all()
        torch.testing.assert_close(probs[b, LATE + k:], ref_probs[b, k:], rtol=0, atol=1e-9)
    twice, _ = filtered(z_late, None)
    assert not ((twice[0, LATE + 1:] - ref[0, 1:]).abs() <= 1e-6 * ref[0].abs().max()).all()
