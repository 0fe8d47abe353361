"""Image encoder E(I): ResNet34-style trunk + U-Net expansive path (paper appendix A).

Where it sits: ``SVORF.encode`` feeds the input view (values in [0, 1]) to
:class:`ImageEncoder`; its feature map goes to the slot decoder (``svorf.decoder``).

Paper: features F1 (conv2, 64 ch, H/2), F2 (conv3, 128 ch, H/4), F3 (conv4, 256 ch, H/8)
of ResNet34 with the max-pool of conv2 removed, then Conv1 (F3 -> 512), bilinear x2,
Conv2 ([up, F2] -> 512), bilinear x2, Conv3 ([up, F1] -> 512): a 512 x H/2 x W/2 map
(128 x 128 at 256 input). All up-sampling convs are 3x3 + ReLU. Written here (no
torchvision), trained from scratch with He init and zero biases.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn


def make_norm(kind: str, channels: int) -> nn.Module:
    """Normalisation layer for the trunk: "batch", "group" (8 groups if divisible) or "none"."""
    if kind == "batch":
        return nn.BatchNorm2d(channels)
    if kind == "group":
        return nn.GroupNorm(8 if channels % 8 == 0 else 1, channels)
    if kind == "none":
        return nn.Identity()
    raise ValueError(f"make_norm: kind must be 'batch', 'group' or 'none', got {kind!r}")


class BasicBlock(nn.Module):
    """ResNet BasicBlock: two 3x3 convs with a residual (1x1 projection when shape changes).

    Shapes: [B, C_in, H, W] -> [B, C_out, H/stride, W/stride].
    """

    def __init__(self, c_in: int, c_out: int, stride: int = 1, norm: str = "batch") -> None:
        super().__init__()
        bias = norm == "none"
        self.conv1 = nn.Conv2d(c_in, c_out, 3, stride, 1, bias=bias)
        self.norm1 = make_norm(norm, c_out)
        self.conv2 = nn.Conv2d(c_out, c_out, 3, 1, 1, bias=bias)
        self.norm2 = make_norm(norm, c_out)
        self.shortcut: nn.Module = nn.Identity()
        if stride != 1 or c_in != c_out:
            self.shortcut = nn.Sequential(
                nn.Conv2d(c_in, c_out, 1, stride, bias=bias), make_norm(norm, c_out)
            )

    def forward(self, x: Tensor) -> Tensor:
        h = F.relu(self.norm1(self.conv1(x)))
        h = self.norm2(self.conv2(h))
        return F.relu(h + self.shortcut(x))


class ImageEncoder(nn.Module):
    """ResNet34 trunk (conv1 7x7/2, conv2 without max-pool, conv3, conv4) + 3 up-sampling convs.

    Args:
        width: conv2 channels (ResNet34: 64); conv3 = 2x, conv4 = 4x.
        blocks: BasicBlocks in conv2, conv3, conv4 (ResNet34: (3, 4, 6)).
        feat_dim: output channels (paper: 512).
        norm: "batch" | "group" | "none".
        up_kernel: kernel side of the up-sampling convs (paper: 3; 1 is a cheaper head).
        full_res: also up-sample to the input resolution, through a stride-1 3x3 conv of
            the image merged with the last map by a 1x1 conv (not the paper).

    Input ``images`` [B, 3, H, W] with values in [0, 1] (H, W multiples of 8); they are
    mapped to [-1, 1] here (with PyTorch-style [0, 1] inputs and default biases the features
    were found to be nearly image-independent, docs/notes/cpu_recipe.md). Output [B, feat_dim, H/2, W/2],
    or [B, feat_dim, H, W] with ``full_res``.

    On CPU the convolutions run on channels-last tensors (:attr:`channels_last_on_cpu`):
    oneDNN's kernels are faster in that layout (the encoder's forward + backward about 1.2x
    at the cpu scale), the weights and the math are the same, and the output map is
    channels-last, so the slot decoder flattens it into tokens without a copy.
    """

    #: Run the convolutions on channels-last tensors on CPU (False: the default layout).
    channels_last_on_cpu: bool = True

    def __init__(
        self,
        width: int = 64,
        blocks: tuple[int, ...] = (3, 4, 6),
        feat_dim: int = 512,
        norm: str = "batch",
        up_kernel: int = 3,
        full_res: bool = False,
    ) -> None:
        super().__init__()
        w = width
        bias = norm == "none"
        self.stem = nn.Sequential(
            nn.Conv2d(3, w, 7, 2, 3, bias=bias), make_norm(norm, w), nn.ReLU(inplace=True)
        )
        self.conv2 = self._stage(w, w, blocks[0], 1, norm)
        self.conv3 = self._stage(w, 2 * w, blocks[1], 2, norm)
        self.conv4 = self._stage(2 * w, 4 * w, blocks[2], 2, norm)
        if up_kernel not in (1, 3):
            raise ValueError(f"ImageEncoder: up_kernel must be 1 or 3, got {up_kernel!r}")
        k, pad = up_kernel, up_kernel // 2
        self.up1 = nn.Conv2d(4 * w, feat_dim, k, 1, pad)
        self.up2 = nn.Conv2d(feat_dim + 2 * w, feat_dim, k, 1, pad)
        self.up3 = nn.Conv2d(feat_dim + w, feat_dim, k, 1, pad)
        self.full_res = full_res
        if full_res:
            self.stem_full = nn.Conv2d(3, w, 3, 1, 1)
            self.up4 = nn.Conv2d(feat_dim + w, feat_dim, 1)
        self.out_dim = feat_dim
        self.reset_parameters()

    @staticmethod
    def _stage(c_in: int, c_out: int, n: int, stride: int, norm: str) -> nn.Sequential:
        layers = [BasicBlock(c_in, c_out, stride, norm)]
        layers += [BasicBlock(c_out, c_out, 1, norm) for _ in range(n - 1)]
        return nn.Sequential(*layers)

    def reset_parameters(self) -> None:
        """He (fan-out, ReLU) init for convs, zero biases, unit/zero norm affine."""
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
                if m.bias is not None:
                    nn.init.zeros_(m.bias)
            elif isinstance(m, (nn.BatchNorm2d, nn.GroupNorm)):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)

    def forward(self, images: Tensor) -> Tensor:
        """[B, 3, H, W] in [0, 1] -> feature map [B, feat_dim, H/2, W/2] ([B, feat_dim, H, W]
        with ``full_res``)."""
        if images.dim() != 4 or images.shape[1] != 3:
            raise ValueError(
                f"ImageEncoder: images must be [B, 3, H, W], got {tuple(images.shape)}"
            )
        if images.shape[-1] % 8 or images.shape[-2] % 8:
            raise ValueError(
                f"ImageEncoder: H and W must be multiples of 8, got {tuple(images.shape[-2:])}"
            )
        x = images * 2.0 - 1.0
        if self.channels_last_on_cpu and x.device.type == "cpu":
            x = x.contiguous(memory_format=torch.channels_last)
        f1 = self.conv2(self.stem(x))  # [B, w, H/2, W/2]
        f2 = self.conv3(f1)  # [B, 2w, H/4, W/4]
        f3 = self.conv4(f2)  # [B, 4w, H/8, W/8]
        h = F.relu(self.up1(f3))
        h = F.interpolate(h, size=f2.shape[-2:], mode="bilinear", align_corners=False)
        h = F.relu(self.up2(torch.cat([h, f2], dim=1)))
        h = F.interpolate(h, size=f1.shape[-2:], mode="bilinear", align_corners=False)
        h = F.relu(self.up3(torch.cat([h, f1], dim=1)))
        if not self.full_res:
            return h
        h = F.interpolate(h, size=x.shape[-2:], mode="bilinear", align_corners=False)
        f0 = F.relu(self.stem_full(x))  # [B, w, H, W]
        return F.relu(self.up4(torch.cat([h, f0], dim=1)))
