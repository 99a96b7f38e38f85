"""Training losses on labelled and unlabelled scans (``immnet.training.losses``): the mode loss is the mean
cross-entropy over the scans that have a label, against its float64 definition; a set with no label (real
flights) has none, and the state loss alone trains (its gradient reaches the estimate, none the mode probs)."""

import torch

from immnet.training.losses import mode_loss


def test_mode_loss_is_the_mean_cross_entropy_over_labelled_scans():
    g = torch.Generator().manual_seed(0)
    probs = torch.softmax(torch.randn(3, 8, 4, generator=g, dtype=torch.float64), -1)
    mode = torch.randint(0, 4, (3, 8), generator=g)
    full = mode_loss(probs, mode)
    ref = -torch.log(probs.gather(-1, mode[..., None])[..., 0]).mean()
    torch.testing.assert_close(full, ref, rtol=1e-12, atol=0)
    mode[1, 2:] = -1  # a partly labelled batch: the labelled scans alone
    keep = mode >= 0
    ref = -torch.log(probs.gather(-1, mode.clamp_min(0)[..., None])[..., 0])[keep].mean()
    torch.testing.assert_close(mode_loss(probs, mode), ref, rtol=1e-12, atol=0)


def test_an_unlabelled_batch_has_no_mode_loss_and_no_gradient_from_it():
    logits = torch.randn(2, 5, 4, dtype=torch.float64, requires_grad=True)
    loss = mode_loss(torch.softmax(logits, -1), torch.full((2, 5), -1))
    assert float(loss) == 0.0
    loss.backward()
    assert logits.grad is not None and not logits.grad.any()


def test_r2_ref_scales_each_batchs_state_loss_by_its_measurement_noise():
    """``Stage2Module(r2_ref=...)``: the total loss is ``gamma * mse * r2_ref / mean(r^2) + (1 - gamma) * ce
    (+ expert_weight * own * r2_ref / mean(r^2))``, computed here from the parts the module reports; the reported
    mse is the paper's (unscaled); None leaves the paper's loss; data without r is refused by name."""
    import pytest
    from tensordict import TensorDict

    from immnet import keys
    from immnet.training import Stage2Module

    g = torch.Generator().manual_seed(1)
    B, T = 3, 6
    batch = TensorDict({keys.STATES: torch.randn(B, T, 9, generator=g), keys.MODE: torch.randint(0, 4, (B, T), generator=g),
                        keys.R: torch.tensor([5.0, 20.0, 35.0])}, batch_size=[B])
    out = TensorDict({keys.STATE: torch.randn(B, T, 9, generator=g),
                      keys.ROLLOUT_EXPERT_PROBS: torch.softmax(torch.randn(B, T, 4, generator=g), -1),
                      keys.ROLLOUT_EXPERT_POST: torch.randn(B, T, 4, 9, generator=g)}, batch_size=[B, T])
    net = {"model_set": "configs/model_sets/imm4-adaptive.yaml"}
    plain = Stage2Module(net=net, gamma=0.7, expert_weight=0.3)
    scaled = Stage2Module(net=net, gamma=0.7, expert_weight=0.3, r2_ref=19.0)
    loss0, mse0, ce0, own0 = plain.losses(out, batch)
    loss, mse, ce, own = scaled.losses(out, batch)
    assert torch.equal(mse, mse0) and torch.equal(ce, ce0) and torch.equal(own, own0)
    factor = 19.0 / ((25.0 + 400.0 + 1225.0) / 3)
    torch.testing.assert_close(loss0, 0.7 * mse0 + 0.3 * ce0 + 0.3 * own0)
    torch.testing.assert_close(loss, 0.7 * mse * factor + 0.3 * ce + 0.3 * own * factor)
    with pytest.raises(ValueError, match="r2_ref"):
        Stage2Module(net=net, r2_ref=0.0)
    with pytest.raises(ValueError, match="has no r"):
        scaled.losses(out, batch.exclude(keys.R))
