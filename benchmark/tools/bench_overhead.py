"""Bare Cycles time of a generated split's views (the generator's overhead ratio).

Data flow: split folder -> each ``sc%04d.json`` -> ``SceneSpec.from_json`` ->
one ``BlenderSession`` (all cores) renders every view with the JSON's settings;
only the ``bpy.ops.render.render`` calls are timed. Compare with the s/view that
``generate`` printed for the same split:

    python -m benchmark.tools.bench_overhead /tmp/g20 [--scenes 5]
"""

from __future__ import annotations

import argparse
import sys
import time


def bare_render_s_per_view(
    root: str, scenes: int | None = None, threads: int | None = None
) -> dict:
    from generators.blender_backend import BlenderSession
    from generators.pipeline import cpu_cores
    from generators.spec import SceneSpec
    from scenefmt import SplitLayout, read_json

    layout = SplitLayout(root)
    idx = layout.scene_indices()[:scenes]
    sess = BlenderSession(threads=threads or cpu_cores())
    render_s, build_s, views = 0.0, 0.0, 0
    try:
        for s in idx:
            spec = SceneSpec.from_json(read_json(layout.scene_json(s)))
            t0 = time.perf_counter()
            sess.build(spec)
            build_s += time.perf_counter() - t0
            for v in range(spec.n_views):
                render_s += sess.render_view(spec, v).render_s
                views += 1
    finally:
        sess.close()
    return {"scenes": len(idx), "views": views, "render_s_per_view": render_s / views,
            "build_s_per_scene": build_s / max(1, len(idx))}  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m benchmark.tools.bench_overhead", description=__doc__.splitlines()[0]
    )
    ap.add_argument("root")
    ap.add_argument("--scenes", type=int, default=None)
    ap.add_argument("--threads", type=int, default=None)
    a = ap.parse_args(argv)
    r = bare_render_s_per_view(a.root, a.scenes, a.threads)
    print(f"{r['views']} views: bare Cycles {r['render_s_per_view']:.3f} s/view, "
          f"scene build {r['build_s_per_scene']:.3f} s/scene")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
