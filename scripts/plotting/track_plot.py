#!/usr/bin/python3
"""`piezo track --plot`: DIR/track.csv -> PNG. Top: measured readings, the model alone, the fused estimate with its
±2σ band and (simulated data) the truth. Bottom: errors against the truth (or the readings) of the model and the
fused estimate, with the ±2σ band. Long recordings are thinned for drawing only."""
import csv
import sys

import matplotlib
matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

src, out = sys.argv[1], sys.argv[2]
with open(src) as f:
    rows = list(csv.DictReader(f))
if not rows:
    sys.exit(f"track_plot: {src} has no rows")
col = lambda k: np.array([float(r[k]) for r in rows]) if k in rows[0] else None
t, y, m, fu, sg, tr = (col(k) for k in ("time_s", "measured_nm", "model_nm", "fused_nm", "fused_sigma_nm", "true_nm"))
step = max(1, len(t) // 20000)
s = slice(None, None, step)
th = (t - t[0]) / 3600.0
ref = tr if tr is not None else y
fig, (a1, a2) = plt.subplots(2, 1, figsize=(12, 7), sharex=True)
a1.plot(th[s], y[s], ".", ms=1, color="0.7", label="readings")
a1.plot(th[s], m[s], lw=0.8, color="tab:orange", label="model alone")
a1.plot(th[s], fu[s], lw=0.8, color="tab:blue", label="fused")
if tr is not None:
    a1.plot(th[s], tr[s], lw=0.6, color="k", label="truth")
a1.set_ylabel("position [nm]")
a1.legend(loc="upper right", fontsize=8, markerscale=8)
a2.fill_between(th[s], -2 * sg[s], 2 * sg[s], color="tab:blue", alpha=0.2, label="±2σ of the fused estimate")
a2.plot(th[s], (m - ref)[s], lw=0.6, color="tab:orange", label="model − " + ("truth" if tr is not None else "readings"))
a2.plot(th[s], (fu - ref)[s], lw=0.6, color="tab:blue", label="fused − " + ("truth" if tr is not None else "readings"))
a2.set_ylim(-40, 40)
a2.set_xlabel("time [h]")
a2.set_ylabel("error [nm]")
a2.legend(loc="upper right", fontsize=8)
fig.tight_layout()
fig.savefig(out, dpi=110)
print(f"wrote {out}")
