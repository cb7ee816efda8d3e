"""``fleet report DIR``: figures in the style of the paper's Fig. 6–9, from ``DIR/trace.npz``.

* ``trajectories.png``: the arena, obstacles, each robot's true path, its
  committed reference, footprints (radius r_i around the reference) every few
  seconds, and start/goal markers (Fig. 6 and 8).
* ``distances.png``: every pairwise distance over time: true centres against
  two body radii, and committed references against r_i + r_j (Fig. 7 and 9).
"""

from __future__ import annotations

import math
from itertools import combinations
from pathlib import Path
from typing import Any

import numpy as np

from supervisor.trace import Trace


def strict_json(obj: Any) -> Any:
    """``obj`` with every non-finite float replaced by None, so that it is strict JSON."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: strict_json(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [strict_json(v) for v in obj]
    return obj


def write_report(out: Path) -> list[Path]:
    """Write the figures for the run in ``out``; returns their paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tr = Trace.load(out / "trace.npz")
    R, T, _ = tr.poses.shape
    t = np.arange(T) * tr.Ts
    colours = plt.get_cmap("tab20" if R > 10 else "tab10")
    paths = []

    fig, ax = plt.subplots(figsize=(7, 7))
    xmin, xmax, ymin, ymax = tr.arena
    ax.plot([xmin, xmax, xmax, xmin, xmin], [ymin, ymin, ymax, ymax, ymin], "k-", lw=1.5)
    for ob in tr.obstacles:
        ax.fill(ob[:, 0], ob[:, 1], color="0.6", zorder=1)
    every = max(1, round(3.0 / tr.Ts))
    for i, rid in enumerate(tr.ids):
        c = colours(i % colours.N)
        ax.plot(tr.poses[i, :, 0], tr.poses[i, :, 1], "-", color=c, lw=1.4, label=f"{rid} true")
        ax.plot(tr.refs[i, :, 0], tr.refs[i, :, 1], ":", color=c, lw=1.0)
        for k in range(0, T, every):
            if np.all(np.isfinite(tr.refs[i, k])):
                ax.add_patch(
                    plt.Circle(tuple(tr.refs[i, k]), tr.footprint, fill=False, color=c, lw=0.5, alpha=0.5)
                )
        ax.plot(*tr.poses[i, 0, :2], "o", color=c)
        ax.plot(*tr.goals[i], "x", color=c, ms=9, mew=2)
    ax.set_aspect("equal")
    ax.set_xlim(xmin - 0.05, xmax + 0.05)
    ax.set_ylim(ymin - 0.05, ymax + 0.05)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(
        f"{tr.name}: axle-centre paths (solid), references (dotted),\n"
        f"footprints r_i around the reference every {every * tr.Ts:g} s",
        fontsize=10,
    )
    if R <= 10:
        ax.legend(loc="upper right", fontsize=7)
    fig.tight_layout()
    p = out / "trajectories.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    paths.append(p)

    fig, (a1, a2) = plt.subplots(2, 1, figsize=(8, 7), sharex=True)
    for n, (i, j) in enumerate(combinations(range(R), 2)):
        c = colours(n % colours.N)
        d = np.linalg.norm(tr.poses[i, :, :2] - tr.poses[j, :, :2], axis=1)
        a1.plot(t, d, color=c, lw=1.0, label=f"{tr.ids[i]}–{tr.ids[j]}")
        dr = np.linalg.norm(tr.refs[i] - tr.refs[j], axis=1)
        a2.plot(t, dr, color=c, lw=1.0)
    a1.axhline(2 * tr.robot_radius, color="r", ls="--", label="collision (2 body radii)")
    a2.axhline(2 * tr.footprint, color="r", ls="--", label="required r_i + r_j")
    a1.set_ylabel("true centre distance [m]")
    a2.set_ylabel("reference distance [m]")
    a2.set_xlabel("time [s]")
    a1.set_title(f"{tr.name}: pairwise distances")
    if R <= 5:
        a1.legend(fontsize=7, loc="upper right")
    a2.legend(fontsize=7, loc="upper right")
    a1.set_ylim(bottom=0)
    a2.set_ylim(bottom=0)
    fig.tight_layout()
    p = out / "distances.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    paths.append(p)
    return paths
