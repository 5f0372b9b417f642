#!/usr/bin/python3
"""Table, plots and compensation.json from the demo runs (demo-output/{sawtooth,creep}.{csv,json})."""
import csv
import json
import os
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def rows(path):
    with open(path) as f:
        return list(csv.DictReader(f))


def main(out):
    saw = json.load(open(os.path.join(out, "sawtooth.json")))
    creep = json.load(open(os.path.join(out, "creep.json")))
    result = {
        "hysteresis": {k: saw[k] for k in ("uncompensated_max_pct", "compensated_max_pct",
                                           "uncompensated_rms_pct", "compensated_rms_pct")},
        "creep": {"uncompensated_drift_nm": creep["uncompensated_drift_nm"],
                  "compensated_drift_nm": creep["compensated_drift_nm"]},
    }
    with open(os.path.join(out, "compensation.json"), "w") as f:
        json.dump(result, f, indent=2)
    h, c = result["hysteresis"], result["creep"]
    print("")
    print("                                   uncompensated   compensated")
    print("hysteresis max deviation [%% stroke] %13.2f %13.2f" % (h["uncompensated_max_pct"], h["compensated_max_pct"]))
    print("hysteresis RMS deviation [%% stroke] %13.2f %13.2f" % (h["uncompensated_rms_pct"], h["compensated_rms_pct"]))
    scen = creep.get("creep_scenarios", [])
    hold_v = creep.get("hold_v", [])
    for i, (u, k) in enumerate(zip(c["uncompensated_drift_nm"], c["compensated_drift_nm"])):
        name = "history %d" % (i + 1)
        if i < len(scen) and i < len(hold_v):
            name = "scenario %2d, %+5.1f V" % (scen[i], hold_v[i])
        print("creep drift, %-22s [nm] %9.1f %13.1f" % (name, u, k))
    print("(stroke = span of the ideal positions over the sawtooth: %.0f nm)" % saw["stroke_nm"])
    if scen:
        print("(creep: scenarios of the creep protocol, seed %d, each history then the hold; drift = |true at the"
              " end of the hold - true when the hold's command was applied|)" % creep["creep_seed"])
    if "uncompensated_late_samples" in creep:
        print("(in step: %d of %d uncompensated history samples had the previous intent applied, i.e. a command"
              " one sample late)" % (creep["uncompensated_late_samples"], creep["uncompensated_history_samples"]))
    print("wrote %s" % os.path.join(out, "compensation.json"))

    s = rows(os.path.join(out, "sawtooth.csv"))
    fig, axes = plt.subplots(1, 2, figsize=(12, 5))
    for mode, name, col in (("0", "uncompensated", "tab:red"), ("1", "compensated", "tab:blue")):
        pts = [r for r in s if r["mode"] == mode and r["phase"] == "saw"]
        v = [float(r["intent_v"]) for r in pts]
        axes[0].plot(v, [float(r["true_nm"]) for r in pts], color=col, lw=0.8, label=name)
        t0 = float(pts[0]["time_s"]) if pts else 0.0
        axes[1].plot([float(r["time_s"]) - t0 for r in pts],
                     [float(r["true_nm"]) - float(r["ideal_nm"]) for r in pts], color=col, lw=0.8, label=name)
        if mode == "0":
            axes[0].plot(v, [float(r["ideal_nm"]) for r in pts], "k--", lw=0.8, label="ideal line")
    axes[0].set_xlabel("intended voltage [V]"), axes[0].set_ylabel("true position [nm]")
    axes[0].set_title("Sawtooth of increasing amplitude"), axes[0].legend()
    axes[1].set_xlabel("time [s]"), axes[1].set_ylabel("true − ideal [nm]"), axes[1].legend()
    axes[1].set_title("Deviation from the ideal line")
    fig.tight_layout(), fig.savefig(os.path.join(out, "hysteresis.png"), dpi=110)

    cr = rows(os.path.join(out, "creep.csv"))

    def label(seg):
        if seg < len(scen) and seg < len(hold_v):
            return "scenario %d (%+.1f V)" % (scen[seg], hold_v[seg])
        return "history %d" % (seg + 1)

    fig, axes = plt.subplots(1, 2, figsize=(12, 5), sharey=True)
    for mode, ax, name in (("0", axes[0], "uncompensated"), ("1", axes[1], "compensated")):
        segs = sorted({r["segment"] for r in cr if r["mode"] == mode and r["phase"] == "hold"})
        for seg in segs:
            pts = [r for r in cr if r["mode"] == mode and r["segment"] == seg and r["phase"] == "hold"]
            t0, x0 = float(pts[0]["time_s"]), float(pts[0]["true_nm"])
            ax.plot([(float(r["time_s"]) - t0) / 60 for r in pts], [float(r["true_nm"]) - x0 for r in pts],
                    lw=0.9, label=label(int(seg)))
        ax.set_title("Creep during the hold, " + name), ax.set_xlabel("time in hold [min]"), ax.legend()
    axes[0].set_ylabel("true position − start of hold [nm]")
    fig.tight_layout(), fig.savefig(os.path.join(out, "creep.png"), dpi=110)
    print("wrote %s and %s" % (os.path.join(out, "hysteresis.png"), os.path.join(out, "creep.png")))


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "demo-output")
