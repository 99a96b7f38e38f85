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
