"""Print the probe's arms as a table (python table.py [FOLDER], default this folder): each
arm's encoder-only and refined (50 steps at 2e-2, input view, all 50 held-out scenes)
scores from its seedS_ARM/refine-input.json."""

import json
import sys
from pathlib import Path

root = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).parent
for seed in (0, 1):
    for arm in ("ctl1k", "rt"):
        run = root / f"seed{seed}_{arm}"
        if not (run / "refine-input.json").is_file():
            continue
        d = json.loads((run / "refine-input.json").read_text())
        e, r = d["encoded"], d["refined"]
        print(
            f"seed {seed} {arm:6} step {d['step']:5}  encoder FG-ARI {e['fg_ari']:5.1f} ARI "
            f"{e['ari']:5.1f} NV-ARI {e['nv_ari']:5.1f} PSNR {e['psnr']:5.2f}/{e['nv_psnr']:5.2f}"
            f"  refined FG-ARI {r['fg_ari']:5.1f} ARI {r['ari']:5.1f} NV-ARI {r['nv_ari']:5.1f} "
            f"PSNR {r['psnr']:5.2f}/{r['nv_psnr']:5.2f} bleed {r['bleed_fraction']:.2f}%"
        )
