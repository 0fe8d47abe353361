"""The project's one adjusted Rand index (``svorf.ari``) against
``sklearn.metrics.adjusted_rand_score``, and the two callers that use it: the benchmark's
segmentation metrics and the cpu recipe's held-out evaluation."""

from __future__ import annotations

import math

import pytest
import torch
from sklearn.metrics import adjusted_rand_score

from benchmark.metrics import ari, fg_ari_score
from benchmark.tools import recipe
from svorf.ari import adjusted_rand_index, ari_rows


def _cases() -> list[tuple[torch.Tensor, torch.Tensor]]:
    g = torch.Generator().manual_seed(0)
    cases = [
        (torch.randint(0, k, (n,), generator=g), torch.randint(0, m, (n,), generator=g))
        for n, k, m in [(2, 2, 2), (7, 3, 2), (64, 8, 5), (500, 11, 7), (1024, 2, 9)]
    ]
    gt = torch.tensor([0, 0, 1, 1, 2, 2])
    cases += [
        (gt, gt),  # identical
        (torch.tensor([5, 5, 3, 3, 7, 7]), gt),  # same partition, other names
        (torch.tensor([0, 0, 1, 2, 1, 2]), gt),
        (torch.zeros(6, dtype=torch.long), torch.zeros(6, dtype=torch.long)),  # one cluster each
        (torch.zeros(6, dtype=torch.long), gt),  # one cluster against three
        (torch.arange(6), torch.arange(6) + 10),  # all singletons
        (torch.arange(6), gt),
        (torch.tensor([4]), torch.tensor([9])),  # one pixel
    ]
    return cases


@pytest.mark.parametrize(("pred", "gt"), _cases())
def test_ari_equals_sklearn(pred, gt):
    want = adjusted_rand_score(gt.numpy(), pred.numpy())
    assert adjusted_rand_index(pred, gt) == pytest.approx(want, abs=1e-12)
    assert adjusted_rand_index(gt, pred) == pytest.approx(want, abs=1e-12)  # symmetric
    ones = torch.ones(1, pred.numel(), dtype=torch.bool)
    row = ari_rows(pred.view(1, -1), gt.view(1, -1), ones)
    assert row.dtype == torch.float64 and row.item() == pytest.approx(want, abs=1e-12)


def test_masked_rows_equal_sklearn_on_the_kept_pixels():
    g = torch.Generator().manual_seed(1)
    pred = torch.randint(0, 6, (4, 300), generator=g)
    gt = torch.randint(0, 4, (4, 300), generator=g)
    keep = gt != 0
    got = ari_rows(pred, gt, keep)
    for b in range(4):
        want = adjusted_rand_score(gt[b][keep[b]].numpy(), pred[b][keep[b]].numpy())
        assert got[b].item() == pytest.approx(want, abs=1e-12)
        assert adjusted_rand_index(pred[b], gt[b], keep[b]) == pytest.approx(want, abs=1e-12)
    assert torch.equal(fg_ari_score(pred, gt), got)  # the benchmark's FG-ARI is this ARI
    assert torch.equal(ari(pred, gt), ari_rows(pred, gt, torch.ones_like(keep)))


def test_no_pixel_scored_is_nan_and_bad_shapes_are_refused():
    gt = torch.tensor([0, 0, 1, 1])
    assert math.isnan(adjusted_rand_index(gt, gt, torch.zeros(4, dtype=torch.bool)))
    assert math.isnan(ari_rows(gt.view(1, -1), gt.view(1, -1), torch.zeros(1, 4).bool()).item())
    empty = torch.zeros(0, 4, dtype=torch.long)
    assert ari_rows(empty, empty, empty.bool()).shape == (0,)
    with pytest.raises(ValueError, match="pred has 3 labels, gt 4"):
        adjusted_rand_index(gt[:3], gt)
    with pytest.raises(ValueError, match="mask has 3 elements"):
        adjusted_rand_index(gt, gt, torch.ones(3, dtype=torch.bool))


def test_the_recipe_scores_with_the_same_ari():
    assert recipe.adjusted_rand_index is adjusted_rand_index
