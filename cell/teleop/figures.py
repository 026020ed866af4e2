"""The experiment's figures from the two sides' traces, and its plots (the paper's Figs. 12-13, 16-17).

The sides' traces are aligned on their period number (both count from the
same START time).  Forces are as each sensor measures them; the local one is
shown with its sign reversed, as in the paper, so that the two curves lie on
each other when the operator feels what the object does.  Everything about
transparency is taken over the pushing, from the first touch to the end of
the last push (the approach and the final lift are free motion).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from cell.teleop.side import COLUMNS, PERIOD_S
from cell.teleop.twindrive import standing_band

C = {c: i for i, c in enumerate(COLUMNS)}


def align(local: np.ndarray, remote: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rows of both traces for the periods both have."""
    tl = np.rint(local[:, C["t"]] / PERIOD_S).astype(np.int64)
    tr = np.rint(remote[:, C["t"]] / PERIOD_S).astype(np.int64)
    _, il, ir = np.intersect1d(tl, tr, assume_unique=True, return_indices=True)
    return local[il], remote[ir]


def transparency(
    local: np.ndarray, remote: np.ndarray, contact_t: float | None, lift_t: float | None
) -> dict[str, float]:
    """Peak forces, force error |f_l + f_r| and tip travel over the pushing."""
    lo, re = align(local, remote)
    t = lo[:, C["t"]]
    a = contact_t if contact_t is not None else t[0]
    b = lift_t if lift_t is not None else t[-1]
    w = (t >= a) & (t <= b)
    if not w.any():
        raise ValueError("the traces have no pushing in them (the object was never touched)")
    fl, fr = -lo[:, C["fz"]], re[:, C["fz"]]
    err = lo[w, C["fz"]] + re[w, C["fz"]]
    peak_l, peak_r = float(fl.max()), float(fr.max())
    return {
        "peak_force_local_n": peak_l,
        "peak_force_remote_n": peak_r,
        "peak_force_diff_pct": abs(peak_l - peak_r) / max(peak_l, peak_r) * 100,
        "force_error_rms_n": float(np.sqrt(np.mean(err**2))),
        "force_error_max_n": float(np.abs(err).max()),
        "position_pp_remote_mm": float(np.ptp(re[w, C["z"]]) * 1e3),
        "position_pp_local_mm": float(np.ptp(lo[w, C["z"]]) * 1e3),
        "pushing_s": float(b - a),
    }


def timing(side: dict[str, Any]) -> dict[str, float]:
    """A real-time side's loop: period between wake-ups, lateness, work per period, missed periods."""
    per, late, work = side["period_ms"], side["wake_late_ms"], side["work_ms"]
    return {
        "period_p50_ms": float(np.percentile(per, 50)),
        "period_p99_ms": float(np.percentile(per, 99)),
        "period_max_ms": float(per.max()),
        "wake_late_p99_ms": float(np.percentile(late, 99)),
        "work_p99_ms": float(np.percentile(work, 99)),
        "missed_periods": int(side["missed_periods"]),
        "periods": int(side["ticks"]),
        "missed_periods_pct": 100.0 * side["missed_periods"] / max(1, side["ticks"]),
    }


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_runs(runs: dict[str, tuple[np.ndarray, np.ndarray]], path: str | Path, title: str = "") -> str:
    """Figs. 16 and 17: per object, force (remote solid, local reversed dotted) and tip z over time."""
    plt = _plt()
    fig, axes = plt.subplots(2, len(runs), figsize=(6 * len(runs), 6), squeeze=False, sharex="col")
    for col, (name, (local, remote)) in enumerate(runs.items()):
        lo, re = align(local, remote)
        t = lo[:, C["t"]]
        f, z = axes[0][col], axes[1][col]
        f.plot(t, re[:, C["fz"]], "-", lw=1.2, label="remote")
        f.plot(t, -lo[:, C["fz"]], ":", lw=1.6, label="local (sign reversed)")
        f.set_ylabel("force z (N)")
        f.set_title(f"{name}")
        z.plot(t, re[:, C["z"]] * 1e3, "-", lw=1.2, label="remote")
        z.plot(t, lo[:, C["z"]] * 1e3, ":", lw=1.6, label="local")
        z.set_ylabel("tip z (mm)")
        z.set_xlabel("time (s)")
        for ax in (f, z):
            ax.grid(alpha=0.3)
    # one legend for all, above the plots: inside them it covered the last push
    handles, _ = axes[0][0].get_legend_handles_labels()
    top = 0.9 if title else 0.94
    fig.legend(
        handles,
        ["remote", "local (force with its sign reversed)"],
        loc="lower center",
        bbox_to_anchor=(0.5, top),
        ncol=2,
        fontsize=9,
    )
    if title:
        fig.suptitle(title, y=0.99, fontsize=11)
    fig.tight_layout(rect=(0, 0, 1, top))
    return _save(fig, path, plt)


def plot_ramp(ramp: Any, path: str | Path) -> str:
    """Figs. 12 and 13: the usual motor and the twin drive under the same speed ramp."""
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
    t = np.arange(len(ramp.command)) * 1e-3
    for ax, speed, name, lag in (
        (axes[0], ramp.usual, "usual motor", ramp.usual_lag),
        (axes[1], ramp.twin, "twin drive", ramp.twin_lag),
    ):
        ax.plot(t, ramp.command * 1e3, "--", color="gray", lw=1, label="command")
        ax.plot(t, speed * 1e3, lw=1.3, label="output speed")
        # what the eye sees: where it stands still, and how far behind the command it then runs
        still = standing_band(ramp.command, speed)
        stands = f"stands still below {still * 1e3:.1f} mrad/s, then" if still > 0 else "never sticks,"
        ax.set_title(f"{name}: {stands} {lag * 1e3:.2f} mrad/s behind the command", fontsize=10)
        ax.set_xlabel("time (s)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    axes[0].set_ylabel("speed (mrad/s)")
    fig.tight_layout()
    return _save(fig, path, plt)


def plot_delays(sweep: list[dict[str, Any]], path: str | Path) -> str:
    """Force error and peak remote force against the added data-link delay, per object and law."""
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    keys = sorted({(r["object"], r["mode"]) for r in sweep})
    for obj, mode in keys:
        rows = sorted(
            (r for r in sweep if r["object"] == obj and r["mode"] == mode), key=lambda r: r["delay_ms"]
        )
        d = [r["delay_ms"] for r in rows]
        style = "-o" if mode == "modified" else "--s"
        axes[0].plot(d, [r["force_error_rms_n"] for r in rows], style, label=f"{obj}, {mode}", ms=4)
        axes[1].plot(d, [r["peak_force_remote_n"] for r in rows], style, label=f"{obj}, {mode}", ms=4)
    axes[0].set_ylabel("force error |f_l + f_r| RMS (N)")
    axes[1].set_ylabel("peak remote force (N)")
    for ax in axes:
        ax.set_xlabel("added data-link delay (ms)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    return _save(fig, path, plt)


def _save(fig: Any, path: str | Path, plt: Any) -> str:
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(p, dpi=110)
    plt.close(fig)
    return str(p)
