"""Focal loss: reduces to cross-entropy at gamma = 0, class weights, soft targets."""

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from hypothesis import given, settings
from hypothesis import strategies as st

from fusion.model.regions import class_weights
from fusion.train.losses import FocalLoss, focal_loss


def batch(seed=0, b=16, k=5):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(b, k, generator=g) * 3, torch.randint(0, k, (b,), generator=g)


@given(st.integers(0, 10_000), st.integers(2, 20))
@settings(max_examples=30, deadline=None)
def test_gamma_zero_uniform_alpha_is_cross_entropy(seed, k):
    logits, y = batch(seed, k=k)
    alpha = torch.full((k,), 1.0 / k)
    assert focal_loss(logits, y, alpha, gamma=0.0).item() == pytest.approx(F.cross_entropy(logits, y).item(), rel=1e-5)
    assert focal_loss(logits, y, None, gamma=0.0).item() == pytest.approx(F.cross_entropy(logits, y).item(), rel=1e-5)


def test_gamma_zero_with_class_weights_is_weighted_cross_entropy():
    logits, y = batch(1)
    alpha = torch.tensor([0.1, 0.4, 0.2, 0.2, 0.1])
    assert focal_loss(logits, y, alpha, 0.0).item() == pytest.approx(
        F.cross_entropy(logits, y, weight=alpha).item(), rel=1e-5
    )


def test_focal_term_down_weights_easy_samples():
    logits, y = batch(2)
    p_true = F.softmax(logits, -1).gather(1, y[:, None]).squeeze(1)
    per_ce = F.cross_entropy(logits, y, reduction="none")
    expected = ((1 - p_true) ** 2 * per_ce).mean()
    assert focal_loss(logits, y, None, 2.0).item() == pytest.approx(expected.item(), rel=1e-5)
    assert focal_loss(logits, y, None, 2.0) < focal_loss(logits, y, None, 0.0)


def test_soft_one_hot_targets_equal_hard_labels():
    logits, y = batch(3)
    alpha = torch.tensor([0.3, 0.1, 0.2, 0.25, 0.15])
    q = F.one_hot(y, 5).float()
    for gamma in (0.0, 2.0):
        assert focal_loss(logits, q, alpha, gamma).item() == pytest.approx(
            focal_loss(logits, y, alpha, gamma).item(), rel=1e-6
        )


def test_soft_targets_at_gamma_zero_are_soft_cross_entropy():
    logits, _ = batch(4)
    q = F.softmax(torch.randn(16, 5), -1)
    expected = -(q * F.log_softmax(logits, -1)).sum(-1).mean()
    assert focal_loss(logits, q, None, 0.0).item() == pytest.approx(expected.item(), rel=1e-5)


def test_alpha_from_training_labels_sums_to_one_and_module_matches_function():
    labels = np.random.default_rng(0).integers(0, 6, 500)
    alpha = class_weights(labels, 6)
    assert alpha.sum() == pytest.approx(1.0)
    assert np.all(alpha > 0)
    counts = np.bincount(labels, minlength=6)
    assert np.argmax(alpha) == np.argmin(counts)
    logits, y = batch(5, k=6)
    loss = FocalLoss(torch.tensor(alpha, dtype=torch.float32), gamma=2.0)
    assert loss(logits, y).item() == pytest.approx(focal_loss(logits, y, torch.tensor(alpha), 2.0).item(), rel=1e-6)
