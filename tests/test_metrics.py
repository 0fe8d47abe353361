"""Tests of benchmark.metrics against sklearn / skimage oracles and closed forms."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from skimage.metrics import structural_similarity
from sklearn.metrics import adjusted_rand_score

from benchmark.metrics import (
    LPIPS_ENV_VAR,
    SEGMENTATION_KEYS,
    ari,
    ari_score,
    depth_errors,
    fg_ari_score,
    load_lpips_alex,
    lpips_or_null,
    psnr,
    segmentation_metrics,
    ssim,
)

# ----------------------------------------------------------------------------- ARI


def _sk_ari(pred: np.ndarray, gt: np.ndarray, keep: np.ndarray | None = None) -> float:
    """sklearn oracle for one row; NaN (our convention) when no pixel is kept."""
    if keep is not None:
        pred, gt = pred[keep], gt[keep]
    if pred.size == 0:
        return math.nan
    return adjusted_rand_score(gt, pred)


def _check_rows(values: torch.Tensor, pred, gt, ignore=None) -> None:
    assert values.dtype == torch.float64 and values.shape == (pred.shape[0],)
    for b in range(pred.shape[0]):
        keep = None if ignore is None else ~ignore[b].reshape(-1).numpy()
        want = _sk_ari(pred[b].reshape(-1).numpy(), gt[b].reshape(-1).numpy(), keep)
        if math.isnan(want):
            assert math.isnan(values[b].item())
        else:
            assert values[b].item() == pytest.approx(want, abs=1e-12)


@pytest.mark.parametrize("n_pix", [1, 2, 7, 100, 1000])
@pytest.mark.parametrize("k_pred,k_gt", [(1, 1), (1, 4), (3, 1), (2, 2), (5, 8), (11, 6), (40, 40)])
def test_ari_matches_sklearn_random(n_pix: int, k_pred: int, k_gt: int) -> None:
    gen = torch.Generator().manual_seed(n_pix * 1000 + k_pred * 50 + k_gt)
    batch = 5
    gt = torch.randint(0, k_gt, (batch, n_pix), generator=gen)
    pred = torch.randint(0, k_pred, (batch, n_pix), generator=gen)
    # Rows of a batch differ in structure: one copies gt with a little noise.
    pred[0] = torch.where(torch.rand(n_pix, generator=gen) < 0.1, pred[0], gt[0])
    _check_rows(ari(pred, gt), pred, gt)
    ignore = torch.rand(batch, n_pix, generator=gen) < 0.3
    ignore[-1] = True  # a row with nothing left -> NaN
    _check_rows(ari(pred, gt, ignore), pred, gt, ignore)


def test_ari_accepts_image_shapes_and_large_label_values() -> None:
    gen = torch.Generator().manual_seed(0)
    gt = torch.randint(0, 5, (3, 16, 16), generator=gen) * 1_000_003
    pred = torch.randint(0, 7, (3, 16, 16), generator=gen) + 2**40
    _check_rows(ari_score(pred, gt), pred, gt)
    _check_rows(ari((pred - 2**40).int(), (gt // 1_000_003).to(torch.int16)), pred, gt)
    small = torch.randint(0, 4, (2, 8, 8), generator=gen, dtype=torch.uint8)
    _check_rows(ari_score(small, small.flip(-1)), small.long(), small.flip(-1).long())


@pytest.mark.parametrize(
    "pred,gt",
    [
        ([3, 3, 3, 3], [0, 0, 0, 0]),  # both a single cluster -> 1.0
        ([0, 1, 2, 3], [5, 6, 7, 8]),  # both all-distinct -> 1.0
        ([7], [2]),  # a single pixel -> 1.0
        ([0, 0, 1, 1, 1], [1, 1, 1, 1, 1]),  # one object, split by pred -> 0.0
        ([4, 4, 4, 4, 4], [0, 0, 1, 2, 2]),  # pred all one label -> 0.0
        ([0, 0, 1, 1, 2], [0, 1, 2, 3, 4]),  # gt all-distinct
        ([0, 1, 0, 1], [0, 0, 1, 1]),  # negative ARI -> -0.5
        ([0, 0, 1, 1], [1, 1, 0, 0]),  # permuted names -> 1.0
    ],
)
def test_ari_degenerate_cases_match_sklearn(pred: list[int], gt: list[int]) -> None:
    p, g = torch.tensor([pred]), torch.tensor([gt])
    want = adjusted_rand_score(gt, pred)
    assert ari_score(p, g).item() == pytest.approx(want, abs=1e-12)
    assert ari_score(g, p).item() == pytest.approx(want, abs=1e-12)  # symmetric


def test_ari_degenerate_values() -> None:
    assert ari_score(torch.tensor([[3, 3, 3]]), torch.tensor([[0, 0, 0]])).item() == 1.0
    assert ari_score(torch.tensor([[4, 4, 4, 4]]), torch.tensor([[0, 0, 1, 1]])).item() == 0.0


def test_fg_ari_empty_foreground_is_nan() -> None:
    gt = torch.zeros(2, 10, dtype=torch.long)
    gt[1, :4] = 1
    pred = torch.arange(20).view(2, 10) % 3
    out = fg_ari_score(pred, gt)
    assert math.isnan(out[0].item())
    assert out[1].item() == pytest.approx(adjusted_rand_score(gt[1, :4], pred[1, :4]))
    assert torch.isnan(ari(pred, gt, torch.ones(2, 10, dtype=torch.bool))).all()


def test_fg_ari_matches_sklearn_on_foreground_subset() -> None:
    gen = torch.Generator().manual_seed(1)
    gt = torch.randint(0, 6, (6, 24, 24), generator=gen)
    gt[:, :8] = 0  # a background band, as in a rendered scene
    pred = torch.randint(0, 7, (6, 24, 24), generator=gen)
    pred[:3] = torch.where(torch.rand(3, 24, 24, generator=gen) < 0.2, pred[:3], gt[:3] + 1)
    _check_rows(fg_ari_score(pred, gt), pred, gt, ignore=gt == 0)
    _check_rows(ari_score(pred, gt), pred, gt)


def test_ari_permutation_invariance() -> None:
    gen = torch.Generator().manual_seed(2)
    gt = torch.randint(0, 5, (4, 300), generator=gen)
    pred = torch.randint(0, 8, (4, 300), generator=gen)
    perm_pred = torch.randperm(8, generator=gen)[pred] + 10
    # FG-ARI: background must stay 0, object ids may be renamed.
    perm_gt = torch.cat([torch.zeros(1, dtype=torch.long), torch.randperm(4, generator=gen) + 1])[
        gt
    ]
    torch.testing.assert_close(
        ari_score(perm_pred, perm_gt), ari_score(pred, gt), rtol=0, atol=1e-12
    )
    torch.testing.assert_close(
        fg_ari_score(perm_pred, perm_gt), fg_ari_score(pred, gt), rtol=0, atol=1e-12
    )
    # Pixel order does not matter either.
    order = torch.randperm(300, generator=gen)
    torch.testing.assert_close(
        ari_score(pred[:, order], gt[:, order]), ari_score(pred, gt), rtol=0, atol=1e-12
    )


def _random_scenes(seed: int, batch: int = 3, views: int = 4, side: int = 12):
    gen = torch.Generator().manual_seed(seed)
    gt = torch.randint(0, 5, (batch, views, side, side), generator=gen)
    gt[:, :, : side // 3] = 0
    noise = torch.randint(0, 6, gt.shape, generator=gen)
    pred = torch.where(torch.rand(gt.shape, generator=gen) < 0.25, noise, gt)
    return pred, gt


@pytest.mark.parametrize("input_view", [0, 2, -1])
def test_segmentation_metrics_against_sklearn(input_view: int) -> None:
    pred, gt = _random_scenes(3)
    batch, views = pred.shape[:2]
    gt[1, 1] = 0  # a novel (or input) view without foreground
    out = segmentation_metrics(pred, gt, input_view=input_view)
    assert tuple(out) == SEGMENTATION_KEYS
    iv = input_view % views
    novel = [v for v in range(views) if v != iv]
    for b in range(batch):
        p, g = pred[b].reshape(views, -1).numpy(), gt[b].reshape(views, -1).numpy()
        per_view = [_sk_ari(p[v], g[v]) for v in range(views)]
        per_view_fg = [_sk_ari(p[v], g[v], g[v] != 0) for v in range(views)]
        want = {
            "ari": per_view[iv],
            "fg_ari": per_view_fg[iv],
            "nv_ari": np.mean([per_view[v] for v in novel]),
            "nv_fg_ari": np.nanmean([per_view_fg[v] for v in novel]),
            "nv_ari_last": per_view[novel[-1]],
            "ari_all": adjusted_rand_score(g.reshape(-1), p.reshape(-1)),  # ARI* pooled
            "fg_ari_all": _sk_ari(p.reshape(-1), g.reshape(-1), g.reshape(-1) != 0),
        }
        for key, value in want.items():
            got = out[key][b].item()
            if math.isnan(value):
                assert math.isnan(got), key
            else:
                assert got == pytest.approx(value, abs=1e-12), key
    assert math.isnan(out["fg_ari"][1].item()) == (iv == 1)


def test_segmentation_metrics_pooled_requires_consistent_slots() -> None:
    # Each view is perfect alone, but object slots swap between views: ARI* < 1.
    gt = torch.tensor([[0, 0, 1, 1, 2, 2]]).view(1, 1, 2, 3).repeat(1, 2, 1, 1)
    pred = gt.clone()
    pred[0, 1] = torch.tensor([0, 0, 2, 2, 1, 1]).view(2, 3)
    out = segmentation_metrics(pred, gt)
    for key in ("ari", "fg_ari", "nv_ari", "nv_fg_ari", "nv_ari_last"):
        assert out[key].item() == 1.0
    assert out["ari_all"].item() < 1.0 and out["fg_ari_all"].item() < 1.0
    want = adjusted_rand_score(gt.reshape(-1), pred.reshape(-1))
    assert out["ari_all"].item() == pytest.approx(want, abs=1e-12)


def test_segmentation_metrics_single_view_novel_is_nan() -> None:
    pred, gt = _random_scenes(4, views=1)
    out = segmentation_metrics(pred, gt)
    for key in ("nv_ari", "nv_fg_ari", "nv_ari_last"):
        assert torch.isnan(out[key]).all()
    torch.testing.assert_close(out["ari"], out["ari_all"])


@pytest.mark.parametrize(
    "call,name",
    [
        (lambda: ari(torch.rand(2, 5), torch.zeros(2, 5, dtype=torch.long)), "pred"),
        (lambda: ari(torch.zeros(2, 5, dtype=torch.long), torch.zeros(2, 4, dtype=torch.long)), "gt"),
        (lambda: ari(torch.zeros(5, dtype=torch.long), torch.zeros(5, dtype=torch.long)), "pred"),
        (lambda: ari(torch.zeros(2, 5, dtype=torch.long), torch.zeros(2, 5, dtype=torch.long), torch.zeros(2, 5)), "ignore"),
        (lambda: ari([[0, 1]], torch.zeros(1, 2, dtype=torch.long)), "pred"),
        (lambda: segmentation_metrics(torch.zeros(2, 3, 4, dtype=torch.long), torch.zeros(2, 3, 4, dtype=torch.long)), "pred_views"),
        (lambda: segmentation_metrics(torch.zeros(1, 2, 4, 4, dtype=torch.long), torch.zeros(1, 2, 4, 4, dtype=torch.long), input_view=2), "input_view"),
        (lambda: psnr(torch.rand(2, 3, 4, 4), torch.rand(2, 3, 4, 5)), "gt"),
        (lambda: psnr(torch.rand(2, 4, 4), torch.rand(2, 4, 4)), "pred"),
        (lambda: ssim(torch.rand(1, 3, 10, 32), torch.rand(1, 3, 10, 32)), "pred"),
        (lambda: lpips_or_null(torch.rand(1, 3, 16, 16), torch.rand(1, 3, 16, 16)), "pred"),
        (lambda: depth_errors(torch.rand(2, 4, 4), torch.rand(2, 4, 4), torch.ones(2, 4, 4)), "valid_mask"),
        (lambda: depth_errors(torch.rand(2, 4, 4), torch.rand(2, 4)), "gt_depth"),
    ],
)  # fmt: skip
def test_bad_inputs_raise_value_error_naming_argument(call, name: str) -> None:
    with pytest.raises(ValueError, match=rf"^{name}: expected"):
        call()


# --------------------------------------------------------------------- PSNR / SSIM


def test_psnr_closed_form() -> None:
    gen = torch.Generator().manual_seed(5)
    gt = 0.2 + 0.6 * torch.rand(3, 3, 8, 8, generator=gen)
    sign = torch.where(torch.rand(3, 3, 8, 8, generator=gen) < 0.5, -1.0, 1.0)
    deltas = torch.tensor([0.1, 0.01, 0.05]).view(3, 1, 1, 1)
    out = psnr(gt + sign * deltas, gt)  # MSE = delta^2 exactly per image
    want = -20.0 * torch.log10(deltas.view(3).double())
    torch.testing.assert_close(out, want, rtol=0, atol=1e-5)
    assert out.dtype == torch.float64
    # Identical images -> inf; values beyond [0, 1] are clamped first.
    assert torch.isinf(psnr(gt, gt)).all()
    assert torch.isinf(psnr(torch.full((1, 3, 4, 4), 1.5), torch.ones(1, 3, 4, 4))).all()


def _sk_ssim(a: torch.Tensor, b: torch.Tensor) -> list[float]:
    return [
        structural_similarity(
            x.permute(1, 2, 0).double().numpy(),
            y.permute(1, 2, 0).double().numpy(),
            channel_axis=-1,
            data_range=1.0,
            gaussian_weights=True,
            sigma=1.5,
            use_sample_covariance=False,
        )
        for x, y in zip(a, b, strict=True)
    ]


def _structured(side_h: int, side_w: int) -> torch.Tensor:
    yy, xx = torch.meshgrid(
        torch.linspace(0, 1, side_h), torch.linspace(0, 1, side_w), indexing="ij"
    )
    checker = ((torch.arange(side_h)[:, None] // 4 + torch.arange(side_w)[None] // 4) % 2).float()
    disc = (((yy - 0.5) ** 2 + (xx - 0.4) ** 2) < 0.08).float()
    return torch.stack([xx, 0.5 * checker + 0.3 * yy, disc * 0.9 + 0.05])


@pytest.mark.parametrize("size", [(11, 11), (32, 32), (64, 64), (40, 57)])
def test_ssim_matches_skimage(size: tuple[int, int]) -> None:
    gen = torch.Generator().manual_seed(size[0] * 100 + size[1])
    h, w = size
    rand_a = torch.rand(2, 3, h, w, generator=gen)
    rand_b = (rand_a + 0.2 * torch.randn(2, 3, h, w, generator=gen)).clamp(0, 1)
    struct_a = _structured(h, w)
    struct_b = (struct_a.roll(2, dims=-1) * 0.8 + 0.1).clamp(0, 1)
    flat = torch.full((3, h, w), 0.5)  # zero variance: the constants carry it
    pred = torch.cat([rand_a, struct_a[None], flat[None], struct_a[None]])
    gt = torch.cat([rand_b, struct_b[None], struct_b[None], struct_a[None]])
    out = ssim(pred, gt)
    assert out.dtype == torch.float64 and out.shape == (5,)
    np.testing.assert_allclose(out.numpy(), _sk_ssim(pred, gt), rtol=0, atol=1e-5)
    assert out[-1].item() == pytest.approx(1.0, abs=1e-12)
    # float32 input gives the same float64 result.
    torch.testing.assert_close(ssim(pred.float(), gt.float()), out, rtol=0, atol=1e-6)


# -------------------------------------------------------------------------- LPIPS


def _random_lpips_state(seed: int = 0) -> dict[str, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    convs = {0: (64, 3, 11), 3: (192, 64, 5), 6: (384, 192, 3), 8: (256, 384, 3), 10: (256, 256, 3)}
    state = {}
    for idx, (cout, cin, k) in convs.items():
        state[f"features.{idx}.weight"] = torch.randn(cout, cin, k, k, generator=gen) / math.sqrt(
            cin * k * k
        )
        state[f"features.{idx}.bias"] = 0.01 * torch.randn(cout, generator=gen)
    for k, c in enumerate((64, 192, 384, 256, 256)):
        # Trained LPIPS heads are non-negative, so distances are >= 0.
        state[f"lin{k}.model.1.weight"] = torch.rand(1, c, 1, 1, generator=gen)
    return state


def _lpips_reference(
    pred: torch.Tensor, gt: torch.Tensor, state: dict[str, torch.Tensor]
) -> torch.Tensor:
    """Straight-line LPIPS v0.1 (alex) from the state dict, written independently."""
    shift = torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1)
    scale = torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1)

    def feats(x: torch.Tensor) -> list[torch.Tensor]:
        x = ((2 * x - 1) - shift) / scale
        out = []
        x = F.relu(
            F.conv2d(x, state["features.0.weight"], state["features.0.bias"], stride=4, padding=2)
        )
        out.append(x)
        x = F.relu(
            F.conv2d(
                F.max_pool2d(x, 3, 2),
                state["features.3.weight"],
                state["features.3.bias"],
                padding=2,
            )
        )
        out.append(x)
        x = F.relu(
            F.conv2d(
                F.max_pool2d(x, 3, 2),
                state["features.6.weight"],
                state["features.6.bias"],
                padding=1,
            )
        )
        out.append(x)
        x = F.relu(F.conv2d(x, state["features.8.weight"], state["features.8.bias"], padding=1))
        out.append(x)
        x = F.relu(F.conv2d(x, state["features.10.weight"], state["features.10.bias"], padding=1))
        out.append(x)
        return [f / (f.norm(dim=1, keepdim=True) + 1e-10) for f in out]

    total = 0
    for k, (a, b) in enumerate(zip(feats(pred), feats(gt), strict=True)):
        total = total + F.conv2d((a - b) ** 2, state[f"lin{k}.model.1.weight"]).mean(dim=(1, 2, 3))
    return total


@pytest.fixture
def no_lpips_env(monkeypatch: pytest.MonkeyPatch, tmp_path) -> None:
    """Hide any real weight file: no env var, HOME (hence the default path) in tmp."""
    monkeypatch.delenv(LPIPS_ENV_VAR, raising=False)
    monkeypatch.setenv("HOME", str(tmp_path / "home"))


def test_lpips_missing_weights_is_null_with_reason(no_lpips_env, tmp_path) -> None:
    images = torch.rand(2, 3, 32, 32)
    values, reason = lpips_or_null(images, images)
    assert values is None
    assert str(tmp_path / "home" / ".cache" / "svorf" / "lpips_alex_v0.1.pth") in reason
    assert LPIPS_ENV_VAR in reason
    missing = tmp_path / "nowhere.pth"
    values, reason = lpips_or_null(images, images, weights_path=missing)
    assert values is None and str(missing) in reason


def test_lpips_loads_documented_layout(no_lpips_env, tmp_path, monkeypatch) -> None:
    state = _random_lpips_state()
    path = tmp_path / "lpips_alex_v0.1.pth"
    torch.save(state, path)
    gen = torch.Generator().manual_seed(7)
    pred = torch.rand(3, 3, 32, 32, generator=gen)
    gt = torch.rand(3, 3, 32, 32, generator=gen)
    gt[1] = pred[1]
    values, reason = lpips_or_null(pred, gt, weights_path=path)
    assert reason is None and values.shape == (3,) and values.dtype == torch.float64
    assert torch.isfinite(values).all()
    assert values[1].item() == 0.0 and values[0].item() > 0 and values[2].item() > 0
    torch.testing.assert_close(
        values.float(), _lpips_reference(pred, gt, state), rtol=1e-4, atol=1e-6
    )
    # Same file found through the environment variable, on 64x64 images.
    monkeypatch.setenv(LPIPS_ENV_VAR, str(path))
    big = torch.rand(2, 3, 64, 64, generator=gen)
    values, reason = lpips_or_null(big, big)
    assert reason is None and values.tolist() == [0.0, 0.0]


def test_lpips_rejects_wrong_layout(tmp_path) -> None:
    state = _random_lpips_state()
    state["features.3.weight"] = state["features.3.weight"][:, :32]
    del state["lin4.model.1.weight"]
    path = tmp_path / "bad.pth"
    torch.save(state, path)
    with pytest.raises(ValueError, match="lin4.model.1.weight"):
        load_lpips_alex(path)
    # A file that exists but is not a state dict is a setup error, not "absent".
    junk = tmp_path / "junk.pth"
    junk.write_bytes(b"not a torch file")
    images = torch.rand(1, 3, 32, 32)
    with pytest.raises(ValueError, match="not a readable torch state dict"):
        lpips_or_null(images, images, weights_path=junk)


# -------------------------------------------------------------------------- depth


def test_depth_errors_closed_form() -> None:
    gt = torch.tensor(
        [[[2.0, 4.0], [0.0, float("inf")]], [[1.0, 1.0], [1.0, 1.0]], [[0.0, 0.0], [0.0, 0.0]]]
    )
    pred = torch.tensor(
        [[[3.0, 3.0], [5.0, 9.0]], [[1.0, 3.0], [1.0, 100.0]], [[1.0, 1.0], [1.0, 1.0]]]
    )
    mask = torch.ones_like(gt, dtype=torch.bool)
    mask[1, 1, 1] = False  # the 100.0 outlier is masked out
    out = depth_errors(pred, gt, mask)
    # Image 0: valid (2->3, 4->3): abs_rel = (1/2 + 1/4) / 2, rmse = 1.
    # Image 1: valid (1->1, 1->3, 1->1): abs_rel = 2/3, rmse = sqrt(4/3). Image 2: none.
    torch.testing.assert_close(
        out["abs_rel"][:2], torch.tensor([0.375, 2 / 3], dtype=torch.float64)
    )
    torch.testing.assert_close(
        out["rmse"][:2], torch.tensor([1.0, math.sqrt(4 / 3)], dtype=torch.float64)
    )
    assert math.isnan(out["abs_rel"][2].item()) and math.isnan(out["rmse"][2].item())
    unmasked = depth_errors(pred, gt)
    assert unmasked["abs_rel"][1].item() == pytest.approx((2 + 99) / 4)
