#!/usr/bin/python3
"""PNGs of `piezo residual DIR`: residual over time before/after, TEST MAE per step, and for each effect found the
residual against its explaining variable before and after (binned means over the scatter)."""
import csv
import json
import os
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def read_csv(path):
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    header, body = rows[0], np.array(rows[1:], dtype=float)
    return {name: body[:, i] for i, name in enumerate(header)}


def binned(x, y, bins=40):
    edges = np.quantile(x, np.linspace(0, 1, bins + 1))
    edges = np.unique(edges)
    idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, len(edges) - 2)
    centres, means = [], []
    for b in range(len(edges) - 1):
        sel = idx == b
        if sel.sum() >= 5:
            centres.append(np.mean(x[sel]))
            means.append(np.mean(y[sel]))
    return np.array(centres), np.array(means)


def main(out):
    report = json.load(open(os.path.join(out, "report.json")))
    ex = read_csv(os.path.join(out, "explain.csv"))
    t_h = (ex["time_s"] - ex["time_s"][0]) / 3600.0
    before, after = ex["residual_before_nm"], ex["residual_after_nm"]

    fig, ax = plt.subplots(figsize=(10, 4))
    ax.plot(t_h, before, lw=0.3, color="tab:red", alpha=0.6, label="before: MAE %.1f nm" % report["before"]["mae_nm"])
    ax.plot(t_h, after, lw=0.3, color="tab:blue", alpha=0.6, label="after: MAE %.1f nm" % report["after"]["mae_nm"])
    ax.set_xlabel("TEST time [h]")
    ax.set_ylabel("measured − predicted [nm]")
    ax.set_title("Residual on TEST, axis %s, %s (%s)" % (report["axis"], report["base_model"], report["mode"]))
    ax.legend(loc="upper right")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(os.path.join(out, "residual_timeseries.png"), dpi=110)
    plt.close(fig)

    steps = report["steps_test_mae_nm"]
    labels = ["base"] + ["+ " + e["family"] for e in report["effects"]]
    fig, ax = plt.subplots(figsize=(max(5, 1.6 * len(steps)), 3.8))
    ax.bar(range(len(steps)), steps, color=["tab:red"] + ["tab:blue"] * (len(steps) - 1))
    for i, v in enumerate(steps):
        ax.text(i, v, "%.1f" % v, ha="center", va="bottom")
    floor = report["remainder"]["noise_floor_mae_nm"]
    if floor is not None:
        ax.axhline(floor, color="k", ls="--", lw=1,
                   label="noise floor σ√(2/π) = %.1f nm (σ from the data)" % floor)
    ax.set_xticks(range(len(steps)))
    ax.set_xticklabels(labels, rotation=15)
    ax.set_ylabel("TEST MAE [nm]")
    ax.legend(loc="lower left")
    fig.tight_layout()
    fig.savefig(os.path.join(out, "residual_steps.png"), dpi=110)
    plt.close(fig)

    # Effect k: the residual just before it was added (after effects 1..k-1) and the final residual.
    # Diagonal stripes at slope −1, 20 nm apart, are the encoder quantisation seen during slow motion.
    names = [n for n in ex if n.startswith("effect")]
    for i, name in enumerate(names):
        x = ex[name]
        effects = report["effects"]
        label = effects[i]["explaining_variable"] if i < len(effects) else name
        prior = before if i == 0 else ex["residual_step%d_nm" % i]
        fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
        step = max(1, len(x) // 6000)
        for a, y, what, colour in ((axes[0], prior, "before", "tab:red"), (axes[1], after, "after", "tab:blue")):
            a.scatter(x[::step], y[::step], s=2, alpha=0.25, color=colour)
            c, m = binned(x, y)
            a.plot(c, m, color="k", lw=2, label="binned mean")
            a.set_title("%s — %s" % (what, name.split("_", 1)[1]))
            a.set_xlabel(label)
            a.grid(alpha=0.3)
            a.legend(loc="upper right")
        axes[0].set_ylabel("TEST residual [nm]")
        lo, hi = np.percentile(np.concatenate([before, after]), [0.5, 99.5])
        axes[0].set_ylim(lo, hi)
        fig.tight_layout()
        fig.savefig(os.path.join(out, "residual_%s.png" % name), dpi=110)
        plt.close(fig)


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit("usage: residual_plots.py OUT_DIR")
    main(sys.argv[1])
