"""Where a ray-sampling strategy's rays land: on objects, and on small objects, by the truth.

Measurement only: the ground-truth instance ids of a generated split score the pixels a
strategy of ``svorf.ray_sampling.RAY_SAMPLING`` draws; training never sees them. For each
scene the input view is view 0 and the rays come from the other views (the novel-view
setup of ``svorf.data.RaySampler``), ``--rays`` per scene as in one training step.

    python -m benchmark.tools.raystats --data data/cpu/clevr567/train --scenes 120

prints, per strategy: the share of rays that land on an object, the mean number of rays a
step gives an object smaller than ``--small`` pixels per view (and a larger one), the
share of the small objects that get no ray at all, and the rays per pixel on an object's
edge (object pixels 8-connected to the background) and on the floor ring beside it
(background pixels 8-connected to an object), each over the uniform rate: where the edge
gets more rays than the ring, the loss pays a model to grow its objects into the floor.
``--json FILE`` writes the same.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor

from scenefmt import atomic_write_json
from svorf.data import MultiViewDataset
from svorf.ray_sampling import RAY_SAMPLING, STATEFUL_RAY_SAMPLING

__all__ = ["edge_and_ring", "main", "ray_stats"]


def ray_stats(
    ds: MultiViewDataset, strategy: str, rays: int = 128, small: float = 30.0, seed: int = 0
) -> dict[str, float]:
    """Truth-scored statistics of ``strategy``'s rays over every scene of ``ds``.

    Raises:
        ValueError: an unknown or stateful strategy, or a split without instance ids.
    """
    if strategy not in RAY_SAMPLING or strategy in STATEFUL_RAY_SAMPLING:
        known = sorted(set(RAY_SAMPLING) - STATEFUL_RAY_SAMPLING)
        raise ValueError(
            f"raystats: strategy {strategy!r} unknown or stateful; choose from {known}"
        )
    if len(ds) and ds[0].instances is None:
        raise ValueError("raystats: the split has no instance masks; use a generated split")
    fn, gen = RAY_SAMPLING[strategy], torch.Generator().manual_seed(seed)
    views = torch.arange(1, ds.n_views)
    on_object = total = 0
    band_rays, band_pixels, pixels = torch.zeros(2), torch.zeros(2), 0  # edge, ring
    small_rays: list[int] = []
    large_rays: list[int] = []
    for s in range(len(ds)):
        inst = ds[s].instances[views]
        ids = inst.reshape(-1)
        rgb = ds.images(s, views).permute(0, 2, 3, 1).mul(255.0).round().to(torch.uint8)
        drawn = fn(rgb, rays, gen)
        hit = ids[drawn]
        bands = edge_and_ring(inst).reshape(2, -1)
        band_rays += bands[:, drawn].sum(dim=1)
        band_pixels += bands.sum(dim=1)
        pixels += len(ids)
        total += len(hit)
        on_object += int((hit > 0).sum())
        area = torch.bincount(ids, minlength=256).float() / len(views)
        for obj in area.nonzero().squeeze(1).tolist():
            if obj:
                (small_rays if area[obj] < small else large_rays).append(int((hit == obj).sum()))
    sm, lg = (
        torch.tensor(small_rays, dtype=torch.float),
        torch.tensor(large_rays, dtype=torch.float),
    )
    # rays per pixel of each band over the uniform rate (total / pixels)
    edge, ring = (band_rays / band_pixels.clamp(min=1) * pixels / max(total, 1)).tolist()
    return {
        "rays_on_objects": on_object / max(total, 1),
        "edge_rate": edge,
        "ring_rate": ring,
        "edge_over_ring": edge / ring if ring > 0 else float("nan"),
        "small_objects": len(small_rays),
        "rays_per_small_object": float(sm.mean()) if len(sm) else float("nan"),
        "rays_per_large_object": float(lg.mean()) if len(lg) else float("nan"),
        "small_objects_without_rays": float((sm == 0).float().mean()) if len(sm) else float("nan"),
    }


def edge_and_ring(ids: Tensor) -> Tensor:
    """bool [2, V, H, W] of ``ids`` [V, H, W] (0 = background): the object pixels
    8-connected to the background (the edge), and the background pixels 8-connected to an
    object (the ring)."""
    obj = (ids > 0).float()[:, None]
    near_obj = F.max_pool2d(obj, 3, stride=1, padding=1)[:, 0] > 0
    near_bg = F.max_pool2d(1.0 - obj, 3, stride=1, padding=1)[:, 0] > 0
    is_obj = ids > 0
    return torch.stack([is_obj & near_bg, ~is_obj & near_obj])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmark.tools.raystats", description=__doc__)
    ap.add_argument("--data", type=Path, required=True, help="a generated split folder")
    ap.add_argument("--scenes", type=int, default=120, help="first N scenes (default 120)")
    ap.add_argument("--rays", type=int, default=128, help="rays per scene (default 128)")
    ap.add_argument("--small", type=float, default=30.0, help="small: under N px a view")
    ap.add_argument(
        "--strategies",
        default="uniform,object_heavy,object_contrast,object_balanced,object_balanced_sqrt",
    )
    ap.add_argument("--json", type=Path, default=None, help="also write the numbers here")
    args = ap.parse_args(argv)
    try:
        ds = MultiViewDataset(args.data, max_scenes=args.scenes)
        rows = {
            name: ray_stats(ds, name, args.rays, args.small) for name in args.strategies.split(",")
        }
    except (ValueError, OSError) as err:
        print(f"raystats: {err}", file=sys.stderr)
        return 2
    for name, r in rows.items():
        print(
            f"{name:16s} on objects {r['rays_on_objects']:.3f}  rays/step: small "
            f"{r['rays_per_small_object']:.2f}, large {r['rays_per_large_object']:.2f}  "
            f"small without rays {r['small_objects_without_rays']:.2f}  "
            f"({r['small_objects']} small objects)  edge / ring rays per pixel "
            f"{r['edge_rate']:.2f} / {r['ring_rate']:.2f} = {r['edge_over_ring']:.2f}"
        )
    if args.json is not None:
        meta = {"data": str(args.data), "scenes": len(ds), "rays": args.rays, "small": args.small}
        atomic_write_json(args.json, {"settings": meta, "strategies": rows})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
