#!/usr/bin/python3
"""PNG plots of `piezo eval` DIR: table3.png (study Table 3 as bars, both modes, vs measured and truth, noise
floor), final_positions.png (Fig. 14: final position after each hold vs the encoder-noise band),
traces_hysteresis.png (Figs. 11-12) and traces_creep.png (Fig. 13)."""
import csv
import json
import math
import os
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def read_csv(path):
    with open(path) as f:
        rows = list(csv.reader(f))
    head, body = rows[0], rows[1:]
    cols = {h: np.array([float(r[i]) if r[i] not in ("", "nan") else np.nan for r in body]) for i, h in enumerate(head)}
    return head, cols


def table3(rep, out):
    models = rep["models"]
    floor = rep["noise_floor_mae_nm"]
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5), sharey=False)
    for ax, part in zip(axes, ("hysteresis", "creep")):
        keys = [("one_step", "vs_measured", "one-step vs measured"), ("free_run", "vs_measured", "free-run vs measured"),
                ("one_step", "vs_truth", "one-step vs truth"), ("free_run", "vs_truth", "free-run vs truth")]
        x = np.arange(len(models))
        w = 0.2
        for k, (mode, ref, label) in enumerate(keys):
            vals = []
            for m in models:
                s = m[part][mode][ref]
                vals.append(s["mae_nm"] if s and s["mae_nm"] is not None else np.nan)
            vals = np.array(vals, dtype=float)
            capped = np.minimum(vals, 6 * floor)
            bars = ax.bar(x + (k - 1.5) * w, capped, w, label=label)
            for b, v in zip(bars, vals):
                if np.isfinite(v):
                    ax.text(b.get_x() + b.get_width() / 2, b.get_height(), f"{v:.1f}", ha="center", va="bottom", fontsize=6,
                            rotation=90)
        ax.axhline(floor, color="k", ls="--", lw=1, label=f"noise floor {floor:.1f} nm")
        ax.set_ylim(0, ax.get_ylim()[1] * 1.15)  # room for the value labels
        ax.set_xticks(x)
        ax.set_xticklabels([m["name"] for m in models], rotation=20, ha="right", fontsize=8)
        ax.set_ylabel("MAE [nm]")
        ax.set_title(f"{part} MAE (bars capped at 6x floor)")
        ax.grid(axis="y", alpha=0.3)
    axes[0].legend(fontsize=7, loc="upper left")
    fig.suptitle("Table 3: MAE per model (study: linear 8.2 / 10.0 nm, KAN 8.17 / 9.94 nm, one-step vs measured)")
    fig.tight_layout()
    fig.savefig(os.path.join(out, "table3.png"), dpi=120)
    plt.close(fig)


def finals(rep, out):
    models = rep["models"]
    if not models or not models[0]["final_positions"]:
        return
    sigma = rep["noise_sigma_nm"]
    n = len(models[0]["final_positions"])
    has_truth = models[0]["final_positions"][0]["truth_nm"] is not None
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.5), sharey=True)
    for ax, mode in zip(axes, ("one_step", "free_run")):
        x = np.arange(1, n + 1)
        ref_key = "truth_nm" if has_truth else "measured_nm"
        ax.fill_between([0.5, n + 0.5], -sigma, sigma, color="0.85", label=f"encoder noise ±{sigma:.2f} nm")
        if has_truth:
            meas = np.array([f["measured_nm"] - f["truth_nm"] for f in models[0]["final_positions"]])
            ax.plot(x, meas, "k_", ms=14, mew=2, label="measured (5-s mean)")
        for k, m in enumerate(models):
            dev = np.array([f[mode + "_nm"] - f[ref_key] for f in m["final_positions"]], dtype=float)
            ax.plot(x + (k - len(models) / 2) * 0.08, dev, "o", ms=4, label=m["name"])
        ax.axhline(0, color="k", lw=0.5)
        ax.set_xlabel("creep scenario (hold)")
        ax.set_ylabel(f"final position − {'truth' if has_truth else 'measured'} [nm]")
        ax.set_title(f"{mode.replace('_', '-')}: position after the hold (mean of last 5 s)")
        ax.set_xticks(x)
        ax.grid(alpha=0.3)
    axes[1].legend(fontsize=7)
    lim = max(4 * sigma, 1)
    for ax in axes:
        lo, hi = ax.get_ylim()
        ax.set_ylim(max(lo, -lim), min(hi, lim))
    fig.suptitle("Fig. 14: final positions after 30-min creep (points outside the axis are clipped)")
    fig.tight_layout()
    fig.savefig(os.path.join(out, "final_positions.png"), dpi=120)
    plt.close(fig)


def traces_hysteresis(out):
    path = os.path.join(out, "traces_test.csv")
    if not os.path.exists(path):
        return
    head, c = read_csv(path)
    if len(c["time_s"]) == 0:
        return
    names = sorted({h.split(":")[0] for h in head if ":" in h}, key=lambda n: head.index(n + ":one_step"))
    t = (c["time_s"] - c["time_s"][0]) / 60
    fig, axes = plt.subplots(3, 1, figsize=(12, 9), sharex=True, gridspec_kw={"height_ratios": [1, 3, 2]})
    axes[0].plot(t, c["voltage_v"], "k", lw=0.8)
    axes[0].set_ylabel("voltage [V]")
    axes[1].plot(t, c["measured_nm"], color="0.6", lw=0.5, label="measured")
    if np.isfinite(c["truth_nm"]).any():
        axes[1].plot(t, c["truth_nm"], "k", lw=1, label="true")
    for n in names:
        axes[1].plot(t, c[n + ":one_step"], lw=0.8, label=f"{n} one-step")
        axes[1].plot(t, c[n + ":free_run"], lw=0.8, ls="--", label=f"{n} free-run")
        ref = c["truth_nm"] if np.isfinite(c["truth_nm"]).any() else c["measured_nm"]
        axes[2].plot(t, c[n + ":free_run"] - ref, lw=0.6, label=f"{n} free-run")
    axes[1].set_ylabel("position [nm]")
    axes[1].legend(fontsize=6, ncol=3)
    axes[2].set_ylabel("free-run − truth [nm]" if np.isfinite(c["truth_nm"]).any() else "free-run − measured [nm]")
    axes[2].set_xlabel("time in window [min]")
    axes[2].grid(alpha=0.3)
    lim = np.nanpercentile(np.abs(np.concatenate([c[n + ":free_run"] - c["measured_nm"] for n in names])), 99) * 1.5
    if np.isfinite(lim) and lim > 0:
        axes[2].set_ylim(-lim, lim)
    axes[2].legend(fontsize=6, ncol=3)
    fig.suptitle("Figs. 11-12: recorded vs predicted position (hysteresis test window)")
    fig.tight_layout()
    fig.savefig(os.path.join(out, "traces_hysteresis.png"), dpi=120)
    plt.close(fig)


def traces_creep(out):
    path = os.path.join(out, "traces_creep.csv")
    if not os.path.exists(path):
        return
    head, c = read_csv(path)
    if len(c["time_s"]) == 0:
        return
    names = sorted({h.split(":")[0] for h in head if ":" in h}, key=lambda n: head.index(n + ":one_step"))
    seg = c["segment"]
    # Holds are contiguous runs; split where time jumps by more than 2 samples.
    dt = np.median(np.diff(c["time_s"])) if len(c["time_s"]) > 1 else 1
    breaks = np.where((np.diff(c["time_s"]) > 2.5 * dt) | (np.diff(seg) != 0))[0] + 1
    runs = np.split(np.arange(len(c["time_s"])), breaks)
    runs = [r for r in runs if len(r) > 10]
    pick = [runs[int(i)] for i in np.linspace(0, len(runs) - 1, min(4, len(runs)))] if runs else []
    if not pick:
        return
    fig, axes = plt.subplots(2, 2, figsize=(12, 8))
    for ax, r in zip(axes.flat, pick):
        t = (c["time_s"][r] - c["time_s"][r][0]) / 60
        ax.plot(t, c["measured_nm"][r], color="0.8", lw=0.4, label="measured")
        x = c["measured_nm"][r]
        # 10-s mean of the encoder, as the study's Fig. 10 reads; at most the hold (np.convolve "same" returns the
        # longer of the two: a 2000-row kernel on a 352-row hold at 200 Hz broke the plot)
        k = min(max(1, int(round(10.0 / dt))), len(x))
        mean10 = np.convolve(x, np.ones(k), mode="same") / np.convolve(np.ones_like(x), np.ones(k), mode="same")
        ax.plot(t, mean10, color="0.4", lw=0.8, label=f"measured, {k * dt:.3g}-s mean")
        if np.isfinite(c["truth_nm"][r]).any():
            ax.plot(t, c["truth_nm"][r], "k", lw=1, label="true")
        lo, hi = np.nanpercentile(c["measured_nm"][r], [0.5, 99.5])
        pad = max(hi - lo, 20)
        for n in names:
            y = c[n + ":free_run"][r]
            off = np.nanmean(y - x)
            # a model far off the hold is named with its offset rather than drawn off the axes unseen
            outside = np.isfinite(off) and not (lo - pad <= np.nanmean(y) <= hi + pad)
            ax.plot(t, y, lw=0.9, label=f"{n} free-run" + (f" (off-scale, {off:+.0f} nm)" if outside else ""))
        ax.set_title(f"hold in segment {int(seg[r][0])}")
        ax.set_xlabel("time since hold start [min]")
        ax.set_ylabel("position [nm]")
        ax.set_ylim(lo - pad, hi + pad)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6)
    for ax in axes.flat[len(pick):]:
        ax.set_visible(False)
    fig.suptitle(f"Fig. 13: recorded and predicted creep (free-run) for {len(pick)} hold{'s' if len(pick) > 1 else ''}")
    fig.tight_layout()
    fig.savefig(os.path.join(out, "traces_creep.png"), dpi=120)
    plt.close(fig)


def main():
    if len(sys.argv) != 2:
        print("usage: eval_plots.py DIR", file=sys.stderr)
        return 2
    out = sys.argv[1]
    with open(os.path.join(out, "report.json")) as f:
        rep = json.load(f)
    table3(rep, out)
    finals(rep, out)
    traces_hysteresis(out)
    traces_creep(out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
