#!/usr/bin/python3
"""PNG time series from a bag of the driver and predictor topics (rqt_plot is not packaged in Debian).

usage: bag_plots.py BAG --out DIR
One figure per manipulator axis found: positions (measured, true, predicted, intended), voltages (applied,
commanded, corrected), predicted drift at each horizon. Times are header stamps relative to the first message.
"""
import argparse
import collections
import math
import os
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def fail(msg):
    print("plot: " + msg, file=sys.stderr)
    sys.exit(1)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("bag")
    ap.add_argument("--out", required=True)
    a = ap.parse_args()
    try:
        import rosbag
    except ImportError:
        fail("python3-rosbag is not installed")
    try:
        bag = rosbag.Bag(a.bag)
    except Exception as e:  # rosbag raises several kinds for a broken file
        fail("%s: cannot read bag: %s" % (a.bag, e))
    series = collections.defaultdict(lambda: collections.defaultdict(list))  # (ns, axis) -> name -> [(t, v)]
    t0 = None
    for topic, m, t in bag.read_messages():
        parts = topic.strip("/").split("/")
        if len(parts) < 2 or parts[-2] not in ("a", "b", "c"):
            continue
        key = ("/".join(parts[:-2]), parts[-2])
        kind = parts[-1]
        stamp = m.header.stamp.to_sec() if hasattr(m, "header") and not m.header.stamp.is_zero() else t.to_sec()
        t0 = stamp if t0 is None else min(t0, stamp)
        s = series[key]
        if kind == "voltage":
            s["applied voltage [V]"].append((stamp, m.voltage))
        elif kind == "encoder":
            s["measured [nm]"].append((stamp, m.position * 1e9))
        elif kind == "true_position":
            s["true [nm]"].append((stamp, m.position * 1e9))
        elif kind == "command":
            s["command [V]"].append((stamp, m.voltage))
        elif kind == "intended":
            s["intent [V]"].append((stamp, m.voltage))
        elif kind == "prediction":
            s["predicted [nm]"].append((stamp, m.predicted_position * 1e9))
            s["intended [nm]"].append((stamp, m.intended_position * 1e9))
            if not math.isnan(m.corrected_voltage):
                s["corrected voltage [V]"].append((stamp, m.corrected_voltage))
            if m.fallback:
                s["fallback"].append((stamp, 1.0))
            for h, d in zip(m.drift_horizons, m.drift):
                if not math.isnan(d):
                    s["drift %g s [nm]" % h].append((stamp, d * 1e9))
    if not series:
        fail("%s: no <ns>/<axis>/{voltage,encoder,prediction,...} topics" % a.bag)
    os.makedirs(a.out, exist_ok=True)
    for (ns, axis), s in sorted(series.items()):
        fig, axs = plt.subplots(3, 1, figsize=(12, 9), sharex=True)
        for name, ax, style in (("measured [nm]", 0, "."), ("true [nm]", 0, "-"), ("predicted [nm]", 0, "-"),
                                ("intended [nm]", 0, "--"), ("applied voltage [V]", 1, "-"), ("intent [V]", 1, "--"),
                                ("command [V]", 1, "-"), ("corrected voltage [V]", 1, ":")):
            if s.get(name):
                axs[ax].plot([p[0] - t0 for p in s[name]], [p[1] for p in s[name]], style, ms=1.5, lw=0.8,
                             label=name)
        for name in sorted(k for k in s if k.startswith("drift")):
            axs[2].plot([p[0] - t0 for p in s[name]], [p[1] for p in s[name]], lw=0.8, label=name)
        if s.get("fallback"):
            for ax in axs:
                ax.plot([p[0] - t0 for p in s["fallback"]], [0] * len(s["fallback"]), "rx", ms=4, label="fallback")
        axs[0].set_ylabel("position [nm]"), axs[1].set_ylabel("voltage [V]"), axs[2].set_ylabel("predicted drift [nm]")
        axs[2].set_xlabel("time [s]")
        for ax in axs:
            if ax.lines:
                ax.legend(fontsize=8, loc="upper right")
        axs[0].set_title("%s axis %s — %s" % (ns or "/", axis, os.path.basename(a.bag)))
        fig.tight_layout()
        path = os.path.join(a.out, "%s_%s.png" % ((ns or "root").replace("/", "_"), axis))
        fig.savefig(path, dpi=100)
        plt.close(fig)
        print("wrote " + path)


if __name__ == "__main__":
    main()
