"""Print the refinement grid's JSONs as a table: python table.py train|test."""

import glob
import json
import re
import sys
from pathlib import Path

split = sys.argv[1] if len(sys.argv) > 1 else "train"
here = Path(__file__).parent
rows = []
for f in sorted(glob.glob(str(here / f"{split}-s*-*.json"))):
    d = json.loads(Path(f).read_text())
    s = re.search(r"-s(\d)-", f).group(1)
    rows.append((int(s), d["refine"]["steps"], d["refine"]["lr"], d))
rows.sort(key=lambda r: (r[0], r[1], r[2]))
for s, st, lr, d in rows:
    dd = d["delta"]
    print(
        f"seed {s} steps {st:3} lr {lr:<6g} ARI {dd['ari']:+5.1f} FG-ARI {dd['fg_ari']:+5.1f} "
        f"NV-ARI {dd['nv_ari']:+5.1f} PSNR in/novel {dd['psnr']:+.2f} / {dd['nv_psnr']:+.2f}"
    )
