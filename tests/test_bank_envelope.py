"""A bank member runs only inside its training data's reach (``NetworkBank(envelope=...)``, the shipped bank's
``ENVELOPE``): it leaves a track, as pruned, at the track's first detection beyond its horizontal range."""

import pytest
import torch

from immnet.tracking.bank import ENVELOPE, NetworkBank


def _line(x0: float, T: int = 40) -> torch.Tensor:
    """A target flying east at 150 m/s from ``(x0, 2 km, 3 km)``, scanned every second."""
    t = torch.arange(T, dtype=torch.float64)
    return torch.stack([x0 + 150.0 * t, 2000.0 + 0 * t, 3000.0 + 0 * t], -1)


def test_a_member_leaves_a_track_beyond_its_reach_and_the_general_network_stays_out():
    """Three tracks at 1 s: one inside 40 km throughout (the same numbers as without the rule, to rounding: the members
    run on other rows of the batch), one beyond it from its first detection (the 3D-LAST network never weighed), one
    crossing it (the same until the crossing, the 3D-LAST network out from there on); the general network, which gives
    way to the 3D-LAST network at 1 s, does not come back on any of them."""
    assert ENVELOPE == {"3dlast": 40000.0}
    names = ["general", "real", "3dlast"]
    on, off = NetworkBank.from_names(names), NetworkBank.from_names(names, envelope={})
    assert on.envelope == ENVELOPE and off.envelope == {}
    z = torch.stack([_line(20000.0), _line(60000.0), _line(36000.0)])
    a, b = on.track(z), off.track(z)
    k3, kg = on.names.index("3dlast"), on.names.index("general")
    torch.testing.assert_close(a["state"][0], b["state"][0], rtol=0, atol=1e-3)
    assert (b["member_probs"][1, 1:, k3] > 0).any() and (a["member_probs"][1, :, k3] == 0).all()
    assert (a["member_probs"][..., kg] == 0).all()
    cross = int((z[2, :, :2].norm(dim=-1) > 40000.0).nonzero()[0])
    torch.testing.assert_close(a["state"][2, :cross], b["state"][2, :cross], rtol=0, atol=1e-3)
    assert (a["member_probs"][2, cross:, k3] == 0).all() and (b["member_probs"][2, cross:, k3] > 0).any()
    # streaming gives track's numbers
    on.reset(3)
    steps = torch.stack([on.step(z[:, t])["member_probs"] for t in range(z.shape[1])], 1)
    torch.testing.assert_close(steps, a["member_probs"])


def test_an_envelope_names_members_and_ranges():
    for envelope, msg in (({"nope": 1.0}, "a bank's envelope names 'nope', not a member"),
                          ({"3dlast": 0.0}, "a bank's envelope for '3dlast' is a horizontal range in metres > 0"),
                          ({"3dlast": True}, "a bank's envelope for '3dlast' is a horizontal range in metres > 0"),
                          ([40000.0], "a bank's envelope maps a member to a horizontal range")):
        with pytest.raises(ValueError, match=msg):
            NetworkBank.from_names(["real", "3dlast"], envelope=envelope)
