"""The optimizer of a training step: Adam, the gradient norm of the NaN guard, and the
moving average of the weights.

Where this sits: ``svorf.train`` builds its optimizer with :func:`make_optimizer`, checks
every step's gradients with :func:`grad_norm` and, with ``TrainConfig.ema_decay``, keeps a
:class:`WeightAverage` that checkpoints store as ``model_ema`` (what ``load_run``
evaluates), and with ``TrainConfig.average_probes`` the extra averages of
:class:`ProbeAverages` (``model_average_probes``, scored with ``load_run(weights=NAME)``);
``benchmark.tools.speedbench --optimizer`` times Adam and the norm against the
per-tensor forms they replace.

On a CPU the per-tensor forms took 9.6% of a cpu-recipe training step in a profile (136
parameter tensors): ``torch.optim.Adam`` without ``fused`` loops over the tensors in
Python, and ``clip_grad_norm_(params, inf)`` also multiplies every gradient by 1.0. The
fused kernel applies the same update (up to float rounding) in one call, on CPU and CUDA;
the whole step is 1.049x faster (``speedbench --optimizer``, 2 threads).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

import torch
from torch import Tensor

FUSED_DEVICES = ("cpu", "cuda")
"""Device types with a fused Adam kernel in torch (2.4 and later)."""


def param_groups(model: torch.nn.Module, enc_lr_scale: float = 1.0) -> list[dict[str, Any]]:
    """Adam's parameter groups for ``TrainConfig.enc_lr_scale``: one group (every
    parameter) at 1, else the slot inference (``model.encoder`` and ``model.slot_module``)
    in a second group whose ``"lr_scale"`` the training step multiplies its rate by."""
    if enc_lr_scale == 1.0:
        return [{"params": list(model.parameters())}]
    enc = {id(p) for m in (model.encoder, model.slot_module) for p in m.parameters()}
    rest = [p for p in model.parameters() if id(p) not in enc]
    inference = [p for p in model.parameters() if id(p) in enc]
    return [{"params": rest}, {"params": inference, "lr_scale": float(enc_lr_scale)}]


def make_optimizer(
    params: Iterable[torch.nn.Parameter] | Iterable[dict[str, Any]],
    lr: float,
    betas: tuple[float, float],
    device: torch.device | str,
    fused: bool | None = None,
) -> torch.optim.Adam:
    """Adam over ``params``; ``fused=None`` uses the fused kernel where the device has one.

    A checkpoint's optimizer state loads into either form (same state tensors); a resumed
    run keeps the form its checkpoint was written with (``param_groups`` carry it).
    """
    if fused is None:
        fused = torch.device(device).type in FUSED_DEVICES
    return torch.optim.Adam(params, lr=lr, betas=betas, fused=fused)


def grad_norm(params: Iterable[torch.nn.Parameter]) -> Tensor:
    """The L2 norm of all gradients together (what ``clip_grad_norm_(params, inf)`` returns,
    without rescaling the gradients); 0 when no parameter has a gradient."""
    grads = [p.grad for p in params if p.grad is not None]
    if not grads:
        return torch.zeros(())
    return torch.nn.utils.get_total_norm(grads, 2.0)


class WeightAverage:
    """An exponential moving average of a model's trainable weights (float32 copies).

    After optimizer step ``t`` (1-based) each average moves towards its weight by
    ``1 - d`` with ``d = min(decay, (1 + t) / (10 + t))``: early on, when the weights move
    fast, the average follows them closely (no bias towards the initialisation).

    Args:
        named_params: ``(name, parameter)`` pairs as ``model.named_parameters()`` gives
            them; the names are the model's state-dict keys.
        decay: per-step decay in (0, 1).
    """

    def __init__(self, named_params: Iterable[tuple[str, torch.nn.Parameter]], decay: float):
        if not 0.0 < decay < 1.0:
            raise ValueError(f"WeightAverage: decay must be in (0, 1), got {decay}")
        self.decay = float(decay)
        self._track(named_params)

    def _track(self, named_params: Iterable[tuple[str, torch.nn.Parameter]]) -> None:
        """Keep float32 copies of the trainable ones of ``named_params``."""
        pairs = [(n, p) for n, p in named_params if p.requires_grad]
        self.names = [n for n, _ in pairs]
        self.params = [p for _, p in pairs]
        self.averages = [p.detach().float().clone() for p in self.params]

    @torch.no_grad()
    def update(self, step: int) -> None:
        """Fold in the weights after optimizer step ``step`` (1-based)."""
        d = min(self.decay, (1.0 + step) / (10.0 + step))
        weights = [p.detach().float() for p in self.params]
        torch._foreach_lerp_(self.averages, weights, 1.0 - d)

    def state_dict(self, model_state: Mapping[str, Tensor]) -> dict[str, Tensor]:
        """``model_state`` (the model's state dict) with the averages in place of the
        trainable weights, in their dtypes: a state dict that loads into the model."""
        out = dict(model_state)
        for name, avg in zip(self.names, self.averages, strict=True):
            out[name] = avg.to(model_state[name].dtype).clone()
        return out

    def load(self, averaged_state: Mapping[str, Tensor]) -> None:
        """Restore the averages from a :meth:`state_dict` of the same model.

        Raises:
            KeyError: a trainable weight is missing from ``averaged_state``.
        """
        for avg, name in zip(self.averages, self.names, strict=True):
            avg.copy_(averaged_state[name].float())


class TailAverage(WeightAverage):
    """The uniform mean of a model's trainable weights after every optimizer step from
    ``start`` (a fraction of the run) on (stochastic weight averaging's mean, at a flat
    rate). Until then it follows the weights.

    Args:
        named_params: ``(name, parameter)`` pairs as ``model.named_parameters()`` gives them.
        start: the fraction of the run in [0, 1) from which steps are averaged.
    """

    def __init__(self, named_params: Iterable[tuple[str, torch.nn.Parameter]], start: float):
        if not 0.0 <= start < 1.0:
            raise ValueError(f"TailAverage: start must be in [0, 1), got {start}")
        self.start = float(start)
        self._track(named_params)
        self.count = 0
        """Steps averaged so far."""

    @torch.no_grad()
    def update(self, step: int, progress: float = 1.0) -> None:  # type: ignore[override]
        """Fold in the weights after optimizer step ``step`` taken at ``progress``."""
        weights = [p.detach().float() for p in self.params]
        if progress < self.start:
            torch._foreach_copy_(self.averages, weights)
            return
        self.count += 1
        torch._foreach_lerp_(self.averages, weights, 1.0 / self.count)


PROBE_KINDS = ("ema", "tail")
"""The kinds of ``TrainConfig.average_probes`` names: ``ema0.9995`` (a moving average with
this decay), ``tail0.8`` (the mean from this fraction of the run on)."""


def parse_probe(name: str) -> tuple[str, float]:
    """``(kind, value)`` of an average probe's name (``"ema0.9995"`` -> ``("ema", 0.9995)``).

    Raises:
        ValueError: not ``ema`` + a decay in (0, 1) or ``tail`` + a fraction in [0, 1).
    """
    for kind in PROBE_KINDS:
        if name.startswith(kind):
            try:
                value = float(name[len(kind) :])
            except ValueError:
                break
            ok = 0.0 < value < 1.0 if kind == "ema" else 0.0 <= value < 1.0
            if ok:
                return kind, value
            break
    raise ValueError(
        f"average probe {name!r}: use 'ema' + a decay in (0, 1) (e.g. ema0.9995) or "
        "'tail' + the fraction of the run it starts at, in [0, 1) (e.g. tail0.8)"
    )


class ProbeAverages:
    """The extra weight averages of ``TrainConfig.average_probes``, kept beside the run
    and never used by it: one run scores each of them against its own weights and its
    ``ema_decay`` average at the same steps (``load_run(weights=NAME)``).
    """

    def __init__(
        self, names: Iterable[str], named_params: Iterable[tuple[str, torch.nn.Parameter]]
    ):
        pairs = list(named_params)
        self.items: dict[str, WeightAverage | TailAverage] = {}
        for name in names:
            kind, value = parse_probe(name)
            self.items[name] = (
                WeightAverage(pairs, value) if kind == "ema" else TailAverage(pairs, value)
            )

    def update(self, step: int, progress: float) -> None:
        """After optimizer step ``step`` (1-based), taken at ``progress``."""
        for avg in self.items.values():
            if isinstance(avg, TailAverage):
                avg.update(step, progress)
            else:
                avg.update(step)

    def state_dict(self, model_state: Mapping[str, Tensor]) -> dict[str, Any]:
        """``{name: {"model": state dict, "count": steps averaged (tail only)}}``."""
        return {
            name: {"model": avg.state_dict(model_state), "count": getattr(avg, "count", None)}
            for name, avg in self.items.items()
        }

    def load(self, saved: Mapping[str, Any] | None, model_state: Mapping[str, Tensor]) -> None:
        """Restore from a :meth:`state_dict` (a probe it lacks starts from ``model_state``)."""
        for name, avg in self.items.items():
            entry = (saved or {}).get(name)
            avg.load(entry["model"] if entry else model_state)
            if isinstance(avg, TailAverage):
                avg.count = int(entry["count"]) if entry and entry["count"] is not None else 0
