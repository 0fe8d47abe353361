"""Time-vs-error of the Cycles quality knobs (how the render defaults were chosen).

Data flow: preset scenes (``sampling.make_scene``) -> ``BlenderSession`` renders
each view with a high-sample reference and with every candidate setting ->
PSNR of the 8-bit sRGB images against the reference, seconds per view -> a table
on stdout (and JSON with ``--json``).

    python -m benchmark.tools.bench_quality --scenes 2 --ref-samples 512
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict, replace

import numpy as np

from generators.spec import RenderSettings

#: (label, overrides of RenderSettings)
CANDIDATES: list[tuple[str, dict]] = [
    ("4spp+oidn", {"samples": 4}),
    ("8spp+oidn", {"samples": 8}),
    ("16spp+oidn", {"samples": 16}),
    ("16spp+oidn glossy0", {"samples": 16, "glossy_bounces": 0}),
    ("16spp+oidn q=FAST", {"samples": 16, "denoise_quality": "FAST"}),
    ("16spp+oidn q=HIGH", {"samples": 16, "denoise_quality": "HIGH"}),
    ("32spp+oidn", {"samples": 32}),
    ("16spp raw", {"samples": 16, "denoise": False}),
    ("64spp raw", {"samples": 64, "denoise": False}),
]


def reference_settings(base: RenderSettings, ref_samples: int) -> RenderSettings:
    """The high-sample reference render: no denoiser, more bounces than any candidate."""
    return replace(base, samples=ref_samples, denoise=False, max_bounces=8, diffuse_bounces=8,
                   glossy_bounces=4)  # fmt: skip


def psnr8(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR (dB) of two uint8 images, data range 255."""
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float("inf") if mse == 0 else float(10 * np.log10(255.0**2 / mse))


def run(
    preset_name: str,
    n_scenes: int,
    resolution: int,
    ref_samples: int,
    threads: int,
    candidates: list[tuple[str, dict]] | None = None,
) -> list[dict]:
    """Render ``n_scenes`` test scenes of the preset with the reference and every candidate.

    Args:
        candidates: (label, RenderSettings overrides) pairs; None = :data:`CANDIDATES`.

    Returns:
        One row per candidate: label, settings, ``s_per_view`` (Cycles render seconds),
        ``psnr_db`` (8-bit sRGB against the reference, mean over views) and
        ``masks_identical`` / ``depth_identical``: whether every view's instance ids and
        planar depth equal the reference render's exactly.
    """
    from generators.blender_backend import BlenderSession
    from generators.imageops import linear_to_srgb8
    from generators.presets import get_preset
    from generators.sampling import make_scene

    preset = get_preset(preset_name)
    base = RenderSettings(resolution=resolution)
    sess = BlenderSession(threads=threads)
    specs = [make_scene(preset, "test", i, 0, base) for i in range(n_scenes)]
    ref_settings = reference_settings(base, ref_samples)
    refs, ref_passes = [], []
    for s in specs:
        views = sess.render_scene(s.with_render(ref_settings))
        refs.append([linear_to_srgb8(v.rgb_linear) for v in views])
        ref_passes.append([(v.ids, v.depth_z) for v in views])
    rows = []
    for label, kw in CANDIDATES if candidates is None else candidates:
        settings = replace(base, **kw)
        times, psnrs = [], []
        masks_same = depth_same = True
        for s, ref, passes in zip(specs, refs, ref_passes, strict=True):
            views = sess.render_scene(s.with_render(settings))
            times += [v.render_s for v in views]
            psnrs += [
                psnr8(linear_to_srgb8(v.rgb_linear), r) for v, r in zip(views, ref, strict=True)
            ]
            for v, (ids, depth) in zip(views, passes, strict=True):
                masks_same &= bool(np.array_equal(v.ids, ids))
                depth_same &= bool(np.array_equal(v.depth_z, depth, equal_nan=True))
        row = {"label": label, "settings": asdict(settings), "s_per_view": float(np.mean(times)),
               "psnr_db": float(np.mean(psnrs)), "masks_identical": masks_same,
               "depth_identical": depth_same}  # fmt: skip
        rows.append(row)
        print(f"{label:24s} {np.mean(times):6.3f} s/view  {np.mean(psnrs):6.2f} dB", flush=True)
    sess.close()
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m benchmark.tools.bench_quality", description=__doc__.splitlines()[0]
    )
    ap.add_argument("--preset", default="clevr567")
    ap.add_argument("--scenes", type=int, default=2)
    ap.add_argument("--resolution", type=int, default=128)
    ap.add_argument("--ref-samples", type=int, default=512)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", default=None, help="also write the rows to this JSON file")
    a = ap.parse_args(argv)
    rows = run(a.preset, a.scenes, a.resolution, a.ref_samples, a.threads)
    if a.json:
        with open(a.json, "w") as f:
            json.dump(rows, f, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
