"""``stability`` protocol, beyond the volume renderer: composition, losses, metrics, NaN guard.

Where this sits: :func:`benchmark.protocols.stability.run_stability` writes the renderer's
rows (table ``stability``) and then the rows made here, each table against its own
oracle:

- ``stability_compose``: sVORF's slot masks (masked softmax over slots) and composition,
  and the uORF-style density-weighted composition, each followed by the volume renderer,
  against the same pipeline in float64 (logits up to +-1e30, densities 0 ... 1e8, every
  slot masked, one valid slot, zero density, bf16 / fp16 autocast);
- ``stability_loss``: the connectivity (per-slot distortion) loss against the O(N^2)
  definition on float64 quadrature weights (densities 0 ... 1e8 and inf, spacings 1e-8 ...
  1e3, every slot masked, autocast);
- ``stability_metrics``: ARI / FG-ARI against ``sklearn.metrics.adjusted_rand_score`` and
  PSNR / SSIM against ``skimage.metrics`` on degenerate inputs (one cluster, empty
  foreground, one object, one pixel, all pixels distinct);
- ``stability_training``: a training run with a learning rate meant to blow up: svorf's
  NaN guard must stop it and the checkpoint of the last good step must survive.

Every row counts NaN/Inf in the outputs and in the gradients (``nonfinite_count``, which
must be 0) and carries ``pass``. Nothing here needs a dataset (the training case writes
a 4-scene synthetic split into a temporary folder).
"""

from __future__ import annotations

import contextlib
import math
import tempfile
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor

from benchmark import adapter
from benchmark.metrics import ari, fg_ari_score, psnr, ssim
from benchmark.protocols.stability.reference import (
    loguniform,
    nonfinite_count,
    reference_render,
    reference_weights,
)
from benchmark.report_row import Row

__all__ = [
    "COMPOSE_CASES",
    "LOSS_CASES",
    "METRIC_CASES",
    "compose_rows",
    "loss_rows",
    "metric_rows",
    "reference_connectivity",
    "reference_masks",
    "training_row",
]

TOL = 1e-4
#: Learning rate of the diverging run (Adam: every weight moves by ~lr on the first step).
DIVERGE_LR = 1e4

_B, _K, _R, _N = 2, 5, 32, 32
_NEAR, _FAR = 6.0, 20.0


def _autocast(dtype: torch.dtype | None):
    if dtype is None:
        return contextlib.nullcontext()
    return torch.autocast(device_type="cpu", dtype=dtype)


def _nonfinite(*xs: Tensor | None) -> int:
    return sum(nonfinite_count(x) for x in xs)


def _maxerr(a: Tensor, b: Tensor) -> float:
    return float((a.detach().double() - b.double()).abs().nan_to_num(float("inf")).max())


def _fin(x: float) -> float | None:
    return x if math.isfinite(x) else None


def _rows_of(table: str, name: str, metrics: dict[str, float], passed: bool, **extra: Any):
    reason = extra.pop("null_reason", "non_finite_error (NaN/Inf)")
    fin = {k: _fin(v) if isinstance(v, float) else v for k, v in metrics.items()}
    extra.setdefault("n_cases", 1)
    row = Row(
        table=table,
        model=name,
        dataset="synthetic inputs",
        source="measured",
        metrics=fin,
        null_reasons={k: reason for k, v in fin.items() if v is None},
        extra={"pass": bool(passed), **extra},
        fixed_id=f"{table}|{name}|cpu|measured",
    )
    return row.to_dict()


# ----------------------------------------------------------------- composition


def reference_masks(logits: Tensor, valid: Tensor | None) -> Tensor:
    """Masked softmax over the last axis in float64; a row without a valid slot is all 0."""
    x = logits.double()
    if valid is None:
        return torch.softmax(x, -1)
    x = x.masked_fill(~valid, float("-inf"))
    anyv = valid.any(-1, keepdim=True)
    p = torch.softmax(x.masked_fill(~anyv, 0.0), -1)
    return p.masked_fill(~valid, 0.0)


def _reference_density_weighted(sigma_k: Tensor, rgb_k: Tensor, valid: Tensor | None):
    """uORF composition in float64, with svorf's definition (eps = 1e-8 added per slot)."""
    s = sigma_k.double().transpose(1, 2) + 1e-8  # [B, P, K]
    raw = sigma_k.double().transpose(1, 2)
    if valid is not None:
        s, raw = s.masked_fill(~valid, 0.0), raw.masked_fill(~valid, 0.0)
    tot = s.sum(-1, keepdim=True)
    m = torch.where(tot > 0, s / tot.clamp_min(1e-300), torch.zeros_like(s))
    rgb = (m.transpose(1, 2)[..., None] * rgb_k.double()).sum(1)
    return raw.sum(-1), rgb, m


#: A composition case: generator -> (logits [B,P,K], valid [B,P,K] or None, sigma_k [B,K,P],
#: rgb_k [B,K,P,3], t [B,R,N]), float64.
ComposeCase = Callable[[torch.Generator], tuple[Tensor, Tensor | None, Tensor, Tensor, Tensor]]


def _t(g: torch.Generator) -> Tensor:
    t = _NEAR + (_FAR - _NEAR) * torch.rand(_B, _R, _N, generator=g, dtype=torch.float64)
    return t.sort(-1).values


def _pick(g: torch.Generator, values: list[float], shape: tuple[int, ...]) -> Tensor:
    v = torch.tensor(values, dtype=torch.float64)
    return v[torch.randint(0, len(values), shape, generator=g)]


def _fields(g: torch.Generator, sigma: Tensor) -> tuple[Tensor, Tensor]:
    return sigma, torch.rand(*sigma.shape, 3, generator=g, dtype=torch.float64)


_P = _R * _N


def _c_moderate(g):
    logits = 3.0 * torch.randn(_B, _P, _K, generator=g, dtype=torch.float64)
    sig = loguniform(g, (_B, _K, _P), 1e-3, 1e2)
    return (logits, None, *_fields(g, sig), _t(g))


def _c_extreme(g):
    logits = _pick(g, [-1e30, -1e4, -1e2, 0.0, 1e2, 1e4, 1e30], (_B, _P, _K))
    valid = torch.rand(_B, _P, _K, generator=g) < 0.7
    sig = _pick(g, [0.0, 1e-8, 1e-3, 1.0, 1e3, 1e8], (_B, _K, _P))
    return (logits, valid, *_fields(g, sig), _t(g))


def _c_all_masked(g):
    logits, _, sig, rgb, t = _c_moderate(g)
    return logits, torch.zeros(_B, _P, _K, dtype=torch.bool), sig, rgb, t


def _c_one_valid(g):
    logits, _, sig, rgb, t = _c_moderate(g)
    one = torch.randint(0, _K, (_B, _P), generator=g)
    return logits, torch.nn.functional.one_hot(one, _K).bool(), sig, rgb, t


def _c_low_valid_logits(g):
    # The valid slots' logits are all below -1e4 and the masked slots' above: a finite
    # stand-in for -inf (the code before 2026-11-24 used -1e4) would take the whole row.
    logits, _, sig, rgb, t = _c_moderate(g)
    valid = torch.rand(_B, _P, _K, generator=g) < 0.5
    valid[..., 0] = True
    logits = torch.where(valid, -1e5 + logits, torch.zeros_like(logits))
    return logits, valid, sig, rgb, t


def _c_zero_density(g):
    logits, valid, sig, rgb, t = _c_moderate(g)
    return logits, valid, torch.zeros_like(sig), rgb, t


#: (name, builder, autocast dtype or None)
COMPOSE_CASES: list[tuple[str, ComposeCase, torch.dtype | None]] = [
    ("moderate logits and densities", _c_moderate, None),
    ("logits +-1e30, densities 0..1e8, 30% slots masked", _c_extreme, None),
    ("every slot masked (all-zero slot weights)", _c_all_masked, None),
    ("one valid slot per point", _c_one_valid, None),
    ("valid logits below -1e4, masked ones at 0", _c_low_valid_logits, None),
    ("zero density in every slot", _c_zero_density, None),
    ("logits +-1e30, densities 0..1e8, bf16 autocast", _c_extreme, torch.bfloat16),
    ("moderate, fp16 autocast", _c_moderate, torch.float16),
]


def run_compose_case(build: ComposeCase, autocast: torch.dtype | None, seed: int) -> dict:
    """Masks, both compositions and the rendered rays against float64; metrics + pass."""
    g = torch.Generator().manual_seed(seed)
    logits64, valid, sig64, rgb64, t64 = build(g)
    logits = logits64.float().requires_grad_(True)
    sigma_k = sig64.float().requires_grad_(True)
    rgb_k = rgb64.float().requires_grad_(True)
    t = t64.float()
    with _autocast(autocast):
        m = adapter.slot_masks(logits, valid)
        sigma, rgb = adapter.compose(sigma_k, rgb_k, m)
        sigma_d, rgb_d, m_d = adapter.compose_density_weighted(sigma_k, rgb_k, valid)
        outs = [
            adapter.volume_render(
                s.reshape(_B * _R, _N), c.reshape(_B * _R, _N, 3), t.reshape(_B * _R, _N)
            )
            for s, c in ((sigma, rgb), (sigma_d, rgb_d))
        ]
    loss = sum(o[0].float().sum() + o[3].float().sum() for o in outs)
    loss.backward()

    # The oracle sees exactly the float32 inputs the code sees.
    m_ref = reference_masks(logits.detach(), valid)
    s_ref = (m_ref.transpose(1, 2) * sigma_k.detach().double()).sum(1)
    c_ref = (m_ref.transpose(1, 2)[..., None] * rgb_k.detach().double()).sum(1)
    sd_ref, cd_ref, md_ref = _reference_density_weighted(sigma_k.detach(), rgb_k.detach(), valid)
    tt = t.double().reshape(_B * _R, _N)
    refs = [
        reference_render(s.reshape(_B * _R, _N), c.reshape(_B * _R, _N, 3), tt, 1e10)
        for s, c in ((s_ref, c_ref), (sd_ref, cd_ref))
    ]
    err_m = max(_maxerr(m, m_ref), _maxerr(m_d, md_ref))
    err_rgb = max(_maxerr(o[0], r["rgb"]) for o, r in zip(outs, refs, strict=True))
    err_acc = max(_maxerr(o[3], r["acc"]) for o, r in zip(outs, refs, strict=True))
    nonfinite = _nonfinite(
        m, m_d, *(x for o in outs for x in (o[0], o[1], o[3])),
        logits.grad, sigma_k.grad, rgb_k.grad,
    )  # fmt: skip
    metrics = {
        "max_abs_err_m": err_m,
        "max_abs_err_rgb": err_rgb,
        "max_abs_err_acc": err_acc,
        "nonfinite_count": float(nonfinite),
    }
    passed = nonfinite == 0 and max(err_m, err_rgb, err_acc) <= TOL
    return {"metrics": metrics, "pass": passed}


def compose_rows(seed: int) -> list[dict[str, Any]]:
    rows = []
    for i, (name, build, ac) in enumerate(COMPOSE_CASES):
        r = run_compose_case(build, ac, seed + i)
        rows.append(
            _rows_of(
                "stability_compose",
                name,
                r["metrics"],
                r["pass"],
                autocast_dtype=None if ac is None else str(ac).replace("torch.", ""),
                n_cases=_B * _R,
                n_points=_B * _P,
                n_slots=_K,
                tolerance={"m": TOL, "rgb": TOL, "acc": TOL, "nonfinite": 0},
            )
        )
    return rows


# ----------------------------------------------------------------- losses


def reference_connectivity(
    sigma_k: Tensor, t: Tensor, far_r: Tensor, near: float, far: float, slot_mask: Tensor | None
) -> float:
    """The connectivity loss from its definition in float64: per-slot quadrature weights
    with a finite last interval (to the ray's far bound), the O(N^2) distortion sum on
    normalised distances, mean over rays, mean over active slots."""
    from svorf.losses import distortion_loss_reference

    edges = torch.cat([t.double(), far_r.double()[..., None]], -1)
    edges = torch.maximum(edges, torch.cummax(edges, -1).values)
    delta = (edges[..., 1:] - edges[..., :-1])[:, None]  # [B, 1, R, N]
    w = reference_weights(sigma_k, delta.expand_as(sigma_k))
    sn = ((edges - near) / (far - near))[:, None].expand(*w.shape[:-1], w.shape[-1] + 1)
    per_slot = distortion_loss_reference(w, sn).mean(-1)  # [B, K]
    if slot_mask is None:
        return float(per_slot.mean())
    m = slot_mask.double()
    return float((per_slot * m).sum() / m.sum().clamp_min(1.0))


LossCase = Callable[[torch.Generator], tuple[Tensor, Tensor, Tensor, Tensor | None]]


def _l_moderate(g):
    t = _t(g)
    sig = loguniform(g, (_B, _K, _R, _N), 1e-3, 1e2)
    return sig, t, torch.full((_B, _R), _FAR, dtype=torch.float64), None


def _l_extreme(g):
    t = _t(g)
    sig = _pick(g, [0.0, 1e-8, 1e-3, 1.0, 1e3, 1e8, float("inf")], (_B, _K, _R, _N))
    return sig, t, torch.full((_B, _R), _FAR, dtype=torch.float64), None


def _l_spacings(g):
    t = _NEAR + torch.cumsum(loguniform(g, (_B, _R, _N), 1e-8, 1e3), -1)
    sig = _pick(g, [0.0, 1e-3, 1.0, 1e3, 1e8], (_B, _K, _R, _N))
    return sig, t, t[..., -1] + 1.0, torch.rand(_B, _K, generator=g) < 0.7


def _l_all_masked(g):
    sig, t, far_r, _ = _l_moderate(g)
    return sig, t, far_r, torch.zeros(_B, _K, dtype=torch.bool)


def _l_zero(g):
    sig, t, far_r, mask = _l_moderate(g)
    return torch.zeros_like(sig), t, far_r, mask


def _l_opaque_first(g):
    sig, t, far_r, mask = _l_moderate(g)
    sig[..., 0] = 1e8
    return sig, t, far_r, mask


#: (name, builder, autocast dtype or None)
LOSS_CASES: list[tuple[str, LossCase, torch.dtype | None]] = [
    ("moderate densities", _l_moderate, None),
    ("densities 0..1e8 and inf", _l_extreme, None),
    ("spacings 1e-8..1e3, densities 0..1e8, 30% slots masked", _l_spacings, None),
    ("every slot masked", _l_all_masked, None),
    ("zero density", _l_zero, None),
    ("opaque first sample (1e8)", _l_opaque_first, None),
    ("densities 0..1e8 and inf, bf16 autocast", _l_extreme, torch.bfloat16),
    ("moderate densities, fp16 autocast", _l_moderate, torch.float16),
]


def loss_rows(seed: int) -> list[dict[str, Any]]:
    rows = []
    for i, (name, build, ac) in enumerate(LOSS_CASES):
        g = torch.Generator().manual_seed(seed + i)
        sig64, t64, far64, mask = build(g)
        sig = sig64.float().requires_grad_(True)
        t, far_r = t64.float(), far64.float()
        with _autocast(ac):
            loss = adapter.connectivity_loss(sig, t, far_r, _NEAR, _FAR, mask)
        loss.backward()
        ref = reference_connectivity(sig.detach(), t, far_r, _NEAR, _FAR, mask)
        got = float(loss.detach())
        err = abs(got - ref) / max(1.0, abs(ref)) if math.isfinite(got) else math.inf
        nonfinite = _nonfinite(loss, sig.grad)
        rows.append(
            _rows_of(
                "stability_loss",
                name,
                {"max_rel_err": err, "nonfinite_count": float(nonfinite)},
                nonfinite == 0 and err <= TOL,
                loss=got if math.isfinite(got) else None,
                reference_loss=ref,
                autocast_dtype=None if ac is None else str(ac).replace("torch.", ""),
                n_cases=_B * _K * _R,
                tolerance={"rel": TOL, "nonfinite": 0},
            )
        )
    return rows


# ----------------------------------------------------------------- metrics


def _sk_ari(pred: Tensor, gt: Tensor, keep: Tensor | None = None) -> float:
    from sklearn.metrics import adjusted_rand_score

    p, g = pred.flatten(), gt.flatten()
    if keep is not None:
        p, g = p[keep.flatten()], g[keep.flatten()]
    return float(adjusted_rand_score(g.numpy(), p.numpy()))


def _sk_psnr(a: Tensor, b: Tensor) -> float:
    import warnings

    from skimage.metrics import peak_signal_noise_ratio

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # skimage warns (divide by zero) for identical images
        return float(peak_signal_noise_ratio(b[0].double().numpy(), a[0].double().numpy(),
                                             data_range=1.0))  # fmt: skip


def _sk_ssim(a: Tensor, b: Tensor) -> float:
    from skimage.metrics import structural_similarity

    return float(
        structural_similarity(
            a[0].permute(1, 2, 0).double().numpy(), b[0].permute(1, 2, 0).double().numpy(),
            channel_axis=-1, data_range=1.0, gaussian_weights=True, sigma=1.5,
            use_sample_covariance=False,
        )
    )  # fmt: skip


def _metric_cases() -> list[tuple[str, str, Callable[[], tuple[float, float]], str | None]]:
    """(name, metric, () -> (ours, reference), expected convention or None = equal)."""
    g = torch.Generator().manual_seed(0)
    one = torch.zeros(1, 64, dtype=torch.long)
    four = torch.randint(0, 5, (1, 64), generator=g)
    four[0, :5] = torch.arange(5)
    distinct = torch.arange(64)[None]
    obj = torch.zeros(1, 64, dtype=torch.long)
    obj[0, 20:40] = 3  # one object on background
    split_obj = obj.clone()
    split_obj[0, 30:40] = 7  # the object cut in two
    big_gt = torch.randint(0, 12, (1, 512 * 512), generator=g)
    big_pred = torch.where(torch.rand(1, 512 * 512, generator=g) < 0.8, big_gt, 5)
    img = torch.rand(1, 3, 16, 16, generator=g)
    black, white = torch.zeros(1, 3, 16, 16), torch.ones(1, 3, 16, 16)
    grey = torch.full((1, 3, 16, 16), 0.5)

    def a(p, t):
        return lambda: (float(ari(p, t)[0]), _sk_ari(p, t))

    def fg(p, t):
        return lambda: (float(fg_ari_score(p, t)[0]), _sk_ari(p, t, t != 0))

    def ps(x, y):
        return lambda: (float(psnr(x, y)[0]), _sk_psnr(x, y))

    def ss(x, y):
        return lambda: (float(ssim(x, y)[0]), _sk_ssim(x, y))

    return [
        ("one cluster in both", "ARI", a(one, one), None),
        ("prediction one cluster, truth 5", "ARI", a(one, four), None),
        ("truth one cluster, prediction 5", "ARI", a(four, one), None),
        ("every pixel its own cluster in both", "ARI", a(distinct, distinct), None),
        ("every pixel its own cluster vs one cluster", "ARI", a(distinct, one), None),
        ("one pixel", "ARI", a(one[:, :1], one[:, :1]), None),
        ("512x512, 12 ids, 20% pixels relabelled (int64 pair counts)", "ARI",
         a(big_pred, big_gt), None),
        ("empty foreground (truth all background)", "FG-ARI", fg(four, one), "nan"),
        ("one object, found whole", "FG-ARI", fg(obj, obj), None),
        ("one object, cut in two", "FG-ARI", fg(split_obj, obj), None),
        ("one object, prediction one cluster", "FG-ARI", fg(one, obj), None),
        ("identical images", "PSNR", ps(img, img), None),
        ("black vs white", "PSNR", ps(black, white), None),
        ("identical constant images", "SSIM", ss(grey, grey), None),
        ("black vs white (constant images)", "SSIM", ss(black, white), None),
        ("random vs constant", "SSIM", ss(img, grey), None),
    ]  # fmt: skip


METRIC_CASES = [c[:2] for c in _metric_cases()]
_REFERENCE_IMPL = {
    "ARI": "sklearn.metrics.adjusted_rand_score",
    "FG-ARI": "sklearn.metrics.adjusted_rand_score",
    "PSNR": "skimage.metrics.peak_signal_noise_ratio",
    "SSIM": "skimage.metrics.structural_similarity",
}


def metric_rows() -> list[dict[str, Any]]:
    """Our metrics against sklearn / scikit-image on degenerate inputs.

    Equal means equal to 1e-9 (infinities equal when both are +inf). The one deliberate
    difference: FG-ARI without a foreground pixel is NaN here (undefined; left out of every
    mean) where sklearn returns 1.0 for two empty labelings; that row passes when ours is NaN.
    """
    rows = []
    for name, metric, fn, convention in _metric_cases():
        ours, ref = fn()
        ours, ref = ours + 0.0, ref + 0.0  # no -0.0 in the report
        if convention == "nan":
            passed, err = math.isnan(ours), None
        elif math.isinf(ours) or math.isinf(ref):
            passed, err = ours == ref, (0.0 if ours == ref else math.inf)
        else:
            err = abs(ours - ref)
            passed = err <= 1e-9
        reason = (
            "undefined: no foreground pixel (our convention: NaN, left out of means; "
            "sklearn returns 1.0 for two empty labelings)"
            if convention == "nan"
            else "non_finite_value (+inf: identical images)"
        )
        rows.append(
            _rows_of(
                "stability_metrics",
                f"{metric}: {name}",
                {
                    "value": ours,
                    "reference_value": ref,
                    "abs_err": err if err is not None else math.nan,
                },
                passed,
                metric=metric,
                reference_impl=_REFERENCE_IMPL[metric],
                null_reason=reason,
            )
        )
    return rows


# ----------------------------------------------------------------- training


def training_row(scale: str, seed: int) -> dict[str, Any]:
    """The scale's model trained with learning rate :data:`DIVERGE_LR`: the NaN guard must
    stop it, and the checkpoint must hold the step before, with finite weights."""
    with tempfile.TemporaryDirectory(prefix="svorf_diverge_") as d:
        r = adapter.diverging_run(d, scale, DIVERGE_LR, seed=seed)
    at, ck = r.get("diverged_at_step"), r.get("checkpoint_step")
    passed = bool(
        r["diverged"]
        and at is not None
        and ck == at - 1
        and r.get("checkpoint_loads")
        and r.get("nonfinite_params") == 0
        and r.get("temp_files") == 0
    )
    return _rows_of(
        "stability_training",
        f"lr {DIVERGE_LR:g} at {scale} scale: NaN guard, last good checkpoint",
        {
            "diverged_at_step": float(at) if at is not None else math.nan,
            "checkpoint_step": float(ck) if ck is not None else math.nan,
            "nonfinite_count": (
                float(r["nonfinite_params"]) if r.get("nonfinite_params") is not None else math.nan
            ),
        },
        passed,
        guard_message=r.get("message"),
        checkpoint_loads=r.get("checkpoint_loads"),
        temp_files=r.get("temp_files"),
        load_error=r.get("load_error"),
        null_reason="the NaN guard did not fire within 30 steps",
    )
