#!/usr/bin/python3
"""Draws docs/img/architecture.png: nodes, topics and the ROS-free core library."""
import sys

import matplotlib
matplotlib.use("Agg")
import matplotlib.pyplot as plt
from matplotlib.patches import FancyBboxPatch

out = sys.argv[1] if len(sys.argv) > 1 else "docs/img/architecture.png"
fig, ax = plt.subplots(figsize=(13, 6.6))
ax.set_xlim(0, 13)
ax.set_ylim(0, 6.6)
ax.axis("off")


def box(x, y, w, h, title, body, color):
    ax.add_patch(FancyBboxPatch((x, y), w, h, boxstyle="round,pad=0.05", fc=color, ec="black", lw=1.2))
    ax.text(x + w / 2, y + h - 0.22, title, ha="center", va="top", fontsize=11, weight="bold")
    ax.text(x + w / 2, y + h - 0.6, body, ha="center", va="top", fontsize=8.5, linespacing=1.35)


def arrow(x0, y0, x1, y1, label, dy=0.12):
    ax.annotate("", xy=(x1, y1), xytext=(x0, y0), arrowprops=dict(arrowstyle="-|>", lw=1.3))
    ax.text((x0 + x1) / 2, (y0 + y1) / 2 + dy, label, ha="center", fontsize=8, family="monospace")


ros = "#dce9f7"
box(0.2, 4.0, 2.2, 2.2, "piezo_recorder", "(or the operator)\nstudy protocols\nbag chunks, resume\nprogress, phases", ros)
box(3.4, 3.6, 2.9, 2.6, "piezo_predictor", "feature stream → model\ninverse → corrected V\ndrift forecast (clone, hold)\ntf2, markers, diagnostics", ros)
box(7.3, 3.6, 2.4, 2.6, "mm3e_driver", "clamp ±80 V, slew limit\nwatchdog hold, NaN reject\none commander\nreconnect, diagnostics", ros)
box(10.6, 3.6, 2.2, 2.6, "MM3E | mm3e_sim", "piezo a, b, c\nencoder 11 Hz\n20 nm, σ 20.79 nm\n(simulator + /clock)", "#f7e3cf")
arrow(2.4, 5.4, 3.4, 5.4, "<axis>/intended")
arrow(6.3, 5.5, 7.3, 5.5, "<axis>/command")
arrow(7.3, 4.3, 6.3, 4.3, "voltage, encoder", dy=-0.3)
arrow(9.7, 5.2, 10.6, 5.2, "CAN")
arrow(10.6, 4.5, 9.7, 4.5, "CAN", dy=-0.3)
ax.text(10.1, 3.1, "SocketCAN (CAN_RAW) or UDP\ncarrying the same struct can_frame", ha="center", fontsize=8)
ax.text(4.85, 3.35, "<axis>/prediction, /tf, rviz", ha="center", fontsize=8, family="monospace")

core = "#e4f2dd"
ax.add_patch(FancyBboxPatch((0.2, 0.2), 12.6, 2.7, boxstyle="round,pad=0.05", fc="#f4f4f4", ec="gray", lw=1, ls="--"))
ax.text(6.5, 2.75, "piezo_core — ROS-free library (Eigen, yaml-cpp), tested with plain GoogleTest", ha="center",
        fontsize=10, weight="bold")
parts = [("io", "Dataset, CSV"), ("sim", "PI hysteresis,\ncreep modes,\neffects"), ("protocols", "noise, walk,\nsweeps, creep"),
         ("features", "causal stream,\nwindows in s"), ("models", "linear, PI+creep,\ndense, LSTM, KAN"),
         ("training", "lasso, Adam,\nTPE search"), ("compensation", "inverse,\ndrift forecast"),
         ("analysis", "eval, residual\nloop"), ("can", "codec,\ntransports")]
w = 12.2 / len(parts)
for i, (name, body) in enumerate(parts):
    box(0.35 + i * w, 0.45, w - 0.18, 1.9, name + "/", body, core)
ax.text(6.5, 0.02, "offline: bag/CSV → Dataset → fit / eval / residual / export (scripts/piezo) → model file → predictor",
        ha="center", fontsize=9, style="italic")
fig.tight_layout()
fig.savefig(out, dpi=110)
print("wrote", out)
