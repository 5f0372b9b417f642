#!/usr/bin/python3
"""Table, plots and compensation.json from the demo runs (demo-output/{sawtooth,creep,hold_trim}.{csv,json};
hold_trim and tracking_trim are optional: their sections are added when their JSON is there). `demo_report.py OUT
--hold-trim-only` / `--tracking-trim-only` prints that table alone."""
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


def print_hold_trim(ht):
    """The held error against the true position, feedforward only and trimmed."""
    print("")
    print("hold trim, axis c on physics the model lacks (a 3 %% gain), %.0f-min hold after a %.0f-s history,"
          " |true - intended| over the hold's last %.0f min:" % (ht["hold_s"] / 60, ht["history_s"],
                                                                ht["score_last_s"] / 60))
    print("                                 feedforward only     trimmed")
    for i, v in enumerate(ht["hold_v"]):
        print("  hold %d at %+5.1f V, worst [nm] %13.2f %13.2f" % (i + 1, v, ht["ff_worst_nm"][i],
                                                                ht["trimmed_worst_nm"][i]))
        print("                    MAE   [nm] %13.2f %13.2f" % (ht["ff_mae_nm"][i], ht["trimmed_mae_nm"][i]))


def print_tracking_trim(tt):
    """Moves and holds against the true position, the tracking trim off and on (the hold trim on in both)."""
    print("")
    print("tracking trim, axis c on physics the model lacks (stroke +2 %%, wider loop, creep +20 %%), %d moves and"
          " %.0f-s holds per pass, |true - intended| [nm]:" % (tt["moves"], tt["hold_s"]))
    print("  | pass | moves max | moves mean | holds from %.0f s max | holds mean |" % tt["hold_score_from_s"])
    print("  |---|---|---|---|---|")
    for name, p in (("hold trim, tracking trim off", "tracking_off_"), ("hold trim + tracking trim", "tracking_on_")):
        print("  | %s | %.1f | %.2f | %.2f | %.2f |" % (name, tt[p + "move_max_nm"], tt[p + "move_mean_nm"],
                                                       tt[p + "hold_max_nm"], tt[p + "hold_mean_nm"]))
    print("  applied voltages %.2f .. %.2f V" % (min(tt["tracking_off_applied_min_v"], tt["tracking_on_applied_min_v"]),
                                                 max(tt["tracking_off_applied_max_v"], tt["tracking_on_applied_max_v"])))


def main(out):
    saw = json.load(open(os.path.join(out, "sawtooth.json")))
    creep = json.load(open(os.path.join(out, "creep.json")))
    result = {
        "hysteresis": {k: saw[k] for k in ("uncompensated_max_pct", "compensated_max_pct",
                                           "uncompensated_rms_pct", "compensated_rms_pct")},
        "creep": {"uncompensated_drift_nm": creep["uncompensated_drift_nm"],
                  "compensated_drift_nm": creep["compensated_drift_nm"]},
    }
    ht = None
    if os.path.exists(os.path.join(out, "hold_trim.json")):
        ht = json.load(open(os.path.join(out, "hold_trim.json")))
        result["hold_trim"] = {k: ht[k] for k in (
            "hold_trim_ff_worst_nm", "hold_trim_trimmed_worst_nm", "hold_trim_ff_mae_nm", "hold_trim_trimmed_mae_nm",
            "ff_worst_nm", "trimmed_worst_nm", "ff_mae_nm", "trimmed_mae_nm", "hold_v", "intended_nm",
            "score_last_s", "history_s", "hold_s", "trimmed_active_samples", "trimmed_scored_samples")}
    tt = None
    if os.path.exists(os.path.join(out, "tracking_trim.json")):
        tt = json.load(open(os.path.join(out, "tracking_trim.json")))
        result["tracking_trim"] = {k: v for k, v in tt.items() if k.startswith("tracking_")}
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
    if ht:
        print_hold_trim(ht)
    if tt:
        print_tracking_trim(tt)
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
    if ht:
        plot_hold_trim(out, ht)


def plot_hold_trim(out, ht):
    """hold_trim.png: the hold's true − intended, feedforward only vs trimmed; the trimmed pass's fused estimate
    with its ±σ band; the trim itself."""
    r = rows(os.path.join(out, "hold_trim.csv"))
    f = lambda x: float(x) if x not in ("", "nan", "-nan") else float("nan")  # noqa: E731
    skip_min = (ht["hold_s"] - ht["score_last_s"]) / 60
    fig, axes = plt.subplots(3, 1, figsize=(11, 10), sharex=True,
                             gridspec_kw={"height_ratios": [1.2, 1.2, 0.8]})
    for mode, name, col in (("0", "feedforward only", "tab:red"), ("1", "hold trim on", "tab:blue")):
        pts = [p for p in r if p["mode"] == mode and p["phase"] == "hold"]
        if not pts:
            continue
        t0 = f(pts[0]["time_s"])
        t = [(f(p["time_s"]) - t0) / 60 for p in pts]
        err = [f(p["true_nm"]) - f(p["ideal_nm"]) for p in pts]
        i = int(mode)
        axes[0].plot(t, err, color=col, lw=0.8, label="%s: worst %.2f nm, MAE %.2f nm (last %.0f min)" % (
            name, ht[("trimmed_" if i else "ff_") + "worst_nm"][0], ht[("trimmed_" if i else "ff_") + "mae_nm"][0],
            ht["score_last_s"] / 60))
        if mode == "1":
            fused = [f(p["fused_nm"]) - f(p["ideal_nm"]) for p in pts]
            sig = [f(p["fused_sigma_nm"]) for p in pts]
            axes[1].fill_between(t, [a - b for a, b in zip(fused, sig)], [a + b for a, b in zip(fused, sig)],
                                 color="tab:gray", alpha=0.35, lw=0, label="fused ±1σ")
            axes[1].plot(t, fused, color="k", lw=0.7, label="fused − intended")
            axes[1].plot(t, err, color=col, lw=0.8, label="true − intended")
            # The readings themselves (20 nm steps, σ 21 nm) do not fit this scale: their trailing 1-min mean shows
            # the averaging limit σ/√660 ≈ 0.8 nm the fused estimate works at.
            n, acc, win, mean_t, mean_v = 660, [], [], [], []
            for tt, p in zip(t, pts):
                v = f(p["encoder_nm"]) - f(p["ideal_nm"])
                if v == v:
                    win.append(v)
                    if len(win) > n:
                        win.pop(0)
                    if len(win) == n:
                        mean_t.append(tt), mean_v.append(sum(win) / n)
            axes[1].plot(mean_t, mean_v, color="tab:cyan", lw=0.6, alpha=0.8,
                         label="readings − intended, trailing 1-min mean", zorder=0)
            axes[2].plot(t, [f(p["hold_trim_nm"]) for p in pts], color=col, lw=0.9, label="hold trim")
    for ax in axes[:2]:
        ax.axhline(2.0, color="k", ls=":", lw=0.7)
        ax.axhline(-2.0, color="k", ls=":", lw=0.7)
        ax.axvspan(0, skip_min, color="0.9", zorder=-1)
    axes[0].set_ylabel("true − intended [nm]"), axes[0].legend(loc="upper right", fontsize=8)
    axes[0].set_title("Hold on physics the model lacks (axis c, 3 % gain): feedforward only vs hold trim; "
                      "grey: not scored, dotted: ±2 nm")
    lim = max(5.0, 1.3 * max(ht["trimmed_worst_nm"]))
    axes[1].set_ylim(-lim, lim), axes[1].set_ylabel("trimmed pass [nm]"), axes[1].legend(loc="upper right", fontsize=8)
    axes[2].set_ylabel("trim [nm]"), axes[2].set_xlabel("time in hold [min]"), axes[2].legend(loc="upper right", fontsize=8)
    fig.tight_layout(), fig.savefig(os.path.join(out, "hold_trim.png"), dpi=110)
    print("wrote %s" % os.path.join(out, "hold_trim.png"))


if __name__ == "__main__":
    if len(sys.argv) > 2 and sys.argv[2] == "--hold-trim-only":
        print_hold_trim(json.load(open(os.path.join(sys.argv[1], "hold_trim.json"))))
    elif len(sys.argv) > 2 and sys.argv[2] == "--tracking-trim-only":
        print_tracking_trim(json.load(open(os.path.join(sys.argv[1], "tracking_trim.json"))))
    else:
        main(sys.argv[1] if len(sys.argv) > 1 else "demo-output")
