#!/usr/bin/python3
"""Figures and numbers of the simulated MM3E for docs/simulator.md, made with `piezo simulate` itself.

usage: scripts/plotting/simulator_figures.py [--out docs/img] [--data DIR] [--seed N]
Runs `scripts/piezo simulate` for the sweep, creep, random-walk and noise protocols (CSV into --data), then writes
sim_loops_step_sizes.png, sim_loops_ranges.png, sim_creep_15.png, sim_random_walk.png, sim_noise.png and prints
the measured numbers (loop widths and spans, 30-min drifts, encoder σ).
"""
import argparse
import os
import subprocess
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))
RATE = 11.0
SWEEP, HOLD, RECORD = 4, 1, 3  # phase codes (protocols/protocol.h)


def simulate(data_dir, protocol, seed, extra=()):
    out = os.path.join(data_dir, f"{protocol}.csv")
    cmd = [os.path.join(ROOT, "scripts", "piezo"), "simulate", "--protocol", protocol, "--seed", str(seed),
           "--out", out, *extra]
    subprocess.run(cmd, check=True, stdout=sys.stderr)
    with open(out) as f:  # a data file may start with its origin line (`# origin: simulated`)
        skip = 1 if f.readline().startswith("#") else 0
    return np.genfromtxt(out, delimiter=",", names=True, skip_header=skip)


def loop_metrics(v, y):
    peak = int(np.argmax(v))
    mid = 0.5 * (v.min() + v.max())
    up = y[:peak + 1][np.argmin(np.abs(v[:peak + 1] - mid))]
    down = y[peak:][np.argmin(np.abs(v[peak:] - mid))]
    return y.max() - y.min(), down - up


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=os.path.join(ROOT, "docs", "img"))
    ap.add_argument("--data", default="/tmp/piezo_sim_figures")
    ap.add_argument("--seed", type=int, default=1)
    a = ap.parse_args()
    os.makedirs(a.out, exist_ok=True)
    os.makedirs(a.data, exist_ok=True)

    # --- loops at several step sizes (study Fig. 6) and sweep ranges (Fig. 7)
    d = simulate(a.data, "sweep", a.seed, ["--axes", "c"])
    steps = [1.25, 0.5, 0.1, 0.05, 0.01]
    fig, ax = plt.subplots(figsize=(7.5, 5.5))
    print("full-range loops on c (true position):")
    for k, step in enumerate(steps):
        m = (d["segment"] == 12 + k) & (d["phase"] == SWEEP)
        v, y = d["c_voltage_v"][m], d["c_true_position_nm"][m]
        span, width = loop_metrics(v, y)
        print(f"  step {step:5.2f} V ({len(v) / RATE / 60:5.1f} min): span {span:7.1f} nm, width at 0 V "
              f"{width:6.1f} nm = {100 * width / span:4.1f} % of span")
        ax.plot(v, y, lw=1.0, label=f"{step} V/sample ({len(v) / RATE / 60:.1f} min)")
    ax.set_xlabel("voltage [V]")
    ax.set_ylabel("true position c [nm]")
    ax.set_title("Simulated full-range hysteresis loops at different step sizes (11 Hz)")
    ax.legend(title="step size (loop duration)")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(os.path.join(a.out, "sim_loops_step_sizes.png"), dpi=110)
    plt.close(fig)

    fig, axes = plt.subplots(1, 3, figsize=(14, 4.6), sharey=True)
    for ax, (title, segs) in zip(axes, [("25 % of the range", range(0, 7)), ("50 %", range(7, 10)),
                                        ("75 %", range(10, 12))]):
        full = (d["segment"] == 12) & (d["phase"] == SWEEP)
        ax.plot(d["c_voltage_v"][full], d["c_true_position_nm"][full], color="0.75", lw=1, label="full range")
        for s in segs:
            m = (d["segment"] == s) & (d["phase"] == SWEEP)
            ax.plot(d["c_voltage_v"][m], d["c_true_position_nm"][m], lw=1.2)
            span, width = loop_metrics(d["c_voltage_v"][m], d["c_true_position_nm"][m])
            print(f"  partial segment {s:2d} [{d['c_voltage_v'][m].min():6.1f}, {d['c_voltage_v'][m].max():6.1f}] V:"
                  f" span {span:6.1f} nm, width {width:5.1f} nm")
        ax.set_title(f"minor loops, {title}")
        ax.set_xlabel("voltage [V]")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("true position c [nm]")
    axes[0].legend()
    fig.tight_layout()
    fig.savefig(os.path.join(a.out, "sim_loops_ranges.png"), dpi=110)
    plt.close(fig)

    # --- the 15 creep histories (Fig. 9 and 10)
    d = simulate(a.data, "creep", a.seed + 2, ["--axes", "c"])
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(14, 5))
    drifts = []
    cmap = plt.get_cmap("tab20")
    for s in range(15):
        m = (d["segment"] == s) & (d["phase"] == HOLD)
        t = (np.arange(m.sum())) / RATE / 60.0
        y0 = d["c_true_position_nm"][m][0]
        meas = d["c_position_nm"][m] - y0
        true = d["c_true_position_nm"][m] - y0
        drifts.append(true[-1])
        smooth = np.convolve(meas, np.ones(110) / 110, mode="valid")  # 10-s mean: the encoder beside the truth
        ax1.plot(t[109:], smooth, color=cmap(s), lw=0.6, alpha=0.5)
        ax1.plot(t, true, color=cmap(s), lw=1.5, label=f"{s}: {d['c_voltage_v'][m][0]:.0f} V")
    ax1.set_xlabel("time since the start of the hold [min]")
    ax1.set_ylabel("drift of c [nm] (thin: encoder 10-s mean, thick: true)")
    ax1.set_title("Creep during 30 min at constant voltage, 15 histories")
    ax1.legend(fontsize=7, ncol=3, title="scenario: hold voltage")
    ax1.grid(alpha=0.3)
    s0 = d["segment"] == 0
    t0 = np.arange(s0.sum()) / RATE / 60.0
    ax0.plot(t0, d["c_voltage_v"][s0], color="C0")
    ax0.set_xlabel("time [min]")
    ax0.set_ylabel("voltage c [V]", color="C0")
    ax0b = ax0.twinx()
    ax0b.plot(t0, d["c_position_nm"][s0], color="C1", lw=0.4, alpha=0.6)
    ax0b.plot(t0, d["c_true_position_nm"][s0], color="C3", lw=1.0)
    ax0b.set_ylabel("position c [nm] (encoder, true)", color="C3")
    ax0.set_title("Scenario 0: 30-min history, then 30-min hold")
    fig.tight_layout()
    fig.savefig(os.path.join(a.out, "sim_creep_15.png"), dpi=110)
    plt.close(fig)
    drifts = np.array(drifts)
    print("30-min drifts on c [nm]:", " ".join(f"{x:.1f}" for x in drifts))
    print(f"  max |drift| {np.abs(drifts).max():.1f} nm = {100 * np.abs(drifts).max() / 2000:.1f} % of 2 µm; "
          f"{(drifts > 0).sum()} positive, {(drifts < 0).sum()} negative")

    # --- a random walk (Fig. 8)
    d = simulate(a.data, "random_walk", a.seed, ["--duration", "3600"])
    fig, axes = plt.subplots(2, 1, figsize=(12, 6), sharex=True)
    t = d["time_s"] / 60.0
    for axn in "abc":
        axes[0].plot(t, d[f"{axn}_voltage_v"], lw=0.8, label=axn)
    axes[0].set_ylabel("voltage [V]")
    axes[0].legend(ncol=3)
    axes[0].set_title("Random walk (three independent axes; flat parts are pauses for creep)")
    axes[1].plot(t, d["c_position_nm"], lw=0.4, color="C1", label="c encoder")
    axes[1].plot(t, d["c_true_position_nm"], lw=1.0, color="C3", label="c true")
    axes[1].set_ylabel("position c [nm]")
    axes[1].set_xlabel("time [min]")
    axes[1].legend()
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(os.path.join(a.out, "sim_random_walk.png"), dpi=110)
    plt.close(fig)

    # --- encoder noise as in §4.1.1 (Fig. 5): zero each 20-s record, pool
    d = simulate(a.data, "noise", a.seed, ["--axes", "c"])
    zeroed = []
    for s in range(5):
        m = (d["segment"] == s) & (d["phase"] == RECORD)
        x = d["c_position_nm"][m]
        zeroed.append(x - x.mean())
    zeroed = np.concatenate(zeroed)
    err = d["c_position_nm"] - d["c_true_position_nm"]
    print(f"encoder noise on c: sigma of zeroed 20-s records {zeroed.std(ddof=1):.2f} nm (n={len(zeroed)}), "
          f"sigma of measured − true over the whole run {err.std(ddof=1):.2f} nm (n={len(err)})")
    fig, ax = plt.subplots(figsize=(7, 4.5))
    ax.hist(err, bins=np.arange(-100, 101, 20) - 10, density=True, alpha=0.6, label="measured − true (all samples)")
    xs = np.linspace(-100, 100, 400)
    sd = err.std(ddof=1)
    ax.plot(xs, np.exp(-0.5 * (xs / sd) ** 2) / (sd * np.sqrt(2 * np.pi)), "k", label=f"Gaussian σ = {sd:.2f} nm")
    ax.set_xlabel("encoder deviation [nm] (20 nm quantisation)")
    ax.set_ylabel("density")
    ax.set_title("Simulated encoder noise on c (study: σ = 20.79 nm)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(os.path.join(a.out, "sim_noise.png"), dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
