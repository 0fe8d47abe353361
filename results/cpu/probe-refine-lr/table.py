import json, glob, sys, re
split = sys.argv[1] if len(sys.argv) > 1 else "train"
rows = []
for f in sorted(glob.glob(f"/work/runs/rfc/{split}-s*-*.json")):
    d = json.load(open(f))
    s = re.search(r"-s(\d)-", f).group(1)
    rows.append((int(s), d["refine"]["steps"], d["refine"]["lr"], d))
rows.sort(key=lambda r: (r[0], r[1], r[2]))
print(f"{'seed':4} {'steps':>5} {'lr':>6} | {'ARI':>5} {'FG':>5} {'NV':>5} {'NVFG':>5} {'PSNRin':>6} {'PSNRnv':>6} | enc ARI FG NV")
for s, st, lr, d in rows:
    e, r = d["encoded"], d["refined"]; dd = d["delta"]
    print(f"{s:4} {st:5} {lr:6g} | {dd['ari']:+5.1f} {dd['fg_ari']:+5.1f} {dd['nv_ari']:+5.1f} {dd['nv_fg_ari']:+5.1f} {dd['psnr']:+6.2f} {dd['nv_psnr']:+6.2f} | {e['ari']:.1f} {e['fg_ari']:.1f} {e['nv_ari']:.1f} -> {r['ari']:.1f} {r['fg_ari']:.1f} {r['nv_ari']:.1f}")
