"""`cell teleop` and `cell bench bilateral`: runs of the experiment, summed up, drawn and plotted."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from cell.jsonfields import JsonFields
from cell.recorder.serve import close
from cell.teleop import figures, lockstep, realtime, stability, twindrive
from cell.teleop.figures import C
from cell.teleop.law import Mode
from cell.teleop.realtime import Setup
from cell.teleop.wire import Role

STILL_MM_S = 5.0  # a tip slower than this stands still
SWEEP_DELAYS_MS = (0, 5, 10, 15, 20)
SWEEP_PUSHES = (6.0, 6.0)
USUAL_GEAR = 100.0  # a usual drive's motor friction reaches the joint through this gear ratio


def summarize(res: dict[str, Any]) -> dict[str, Any]:
    """The figures of one real-time run: transparency, both loops' timing, the e-stop if there was one."""
    lo, re = res["local"], res["remote"]
    s = res["setup"]
    out: dict[str, Any] = {"object": s["obj"], "delay_ms": s["delay_ms"], "jitter_ms": s["jitter_ms"]}
    out["mode"] = Mode(s["mode"]).name.lower()
    if lo["contact_t"] is not None:
        out.update(figures.transparency(lo["trace"], re["trace"], lo["contact_t"], lo["lift_t"]))
    tl, tr = figures.timing(lo), figures.timing(re)
    out["timing"] = {"local": tl, "remote": tr}
    out["period_p50_ms"] = max(tl["period_p50_ms"], tr["period_p50_ms"])
    out["period_p99_ms"] = max(tl["period_p99_ms"], tr["period_p99_ms"])
    out["missed_periods_pct"] = max(tl["missed_periods_pct"], tr["missed_periods_pct"])
    out["placement"] = {"local": lo["placement"], "remote": re["placement"]}
    out["bad_payloads"] = lo["bad_payloads"] + re["bad_payloads"]
    out["data_packets"] = {
        r: res[r]["counters"].get("rlink.L1.data.packets_in", 0) for r in ("local", "remote")
    }
    sent = res["console_sent_ns"].get("ESTOP")
    if sent is not None:
        out["estop"] = estop_figures(res, sent)
    return out


def estop_figures(res: dict[str, Any], sent_ns: int) -> dict[str, Any]:
    """From the console's ESTOP to each side taking it, and to each tip standing still."""
    got, still = {}, {}
    for r in ("local", "remote"):
        side = res[r]
        at = next((ns for name, ns, _tick in side["events"] if name == "ESTOP"), None)
        got[r] = (at - sent_ns) / 1e6 if at is not None else None
        tr = side["trace"]
        t_stop = (at - side["start_ns"]) / 1e9 if at is not None else None
        if t_stop is not None:
            after = tr[tr[:, C["t"]] >= t_stop]
            speed = np.hypot(after[:, C["vx"]], after[:, C["vz"]]) * 1e3
            slow = np.nonzero(speed < STILL_MM_S)[0]
            still[r] = float(after[slow[0], C["t"]] - t_stop) * 1e3 if slow.size else None
    both = [v for v in got.values() if v is not None]
    return {
        "taken_ms": got,
        "skew_ms": (max(both) - min(both)) if len(both) == 2 else None,
        "still_after_ms": still,
    }


def teleop(setup: Setup, rerun: list[str] | None = None, png: str | None = None) -> dict[str, Any]:
    """One real-time run, drawn live in Rerun (`rerun`: spawn | serve | save PATH | off / None)."""
    view = None
    if rerun and rerun[0] != "off":
        # (lazy: the Rerun SDK, a second to load, only for a run that is drawn)
        from cell.recorder.live import open_recording
        from cell.teleop.view import TeleopView

        path = rerun[1] if rerun[0] == "save" and len(rerun) > 1 else ""
        view = TeleopView(open_recording(rerun[0], path, "teleop"), setup.obj)
    res = realtime.run(replace(setup, stream=view is not None), on_rows=view.rows if view else None)
    out = summarize(res)
    if view is not None:
        for r in Role:
            for tick, what in res[r.name.lower()]["log"]:
                view.text(tick * 1e-3, f"{r.name.lower()}: {what}")
        close(view.rec)
    if png:
        out["png"] = figures.plot_runs(
            {setup.obj: (res["local"]["trace"], res["remote"]["trace"])}, png, _title(setup)
        )
    return out


def _title(s: Setup) -> str:
    extra = (
        f", data link +{s.delay_ms:g} ms" + (f" +/- {s.jitter_ms:g}" if s.jitter_ms else "")
        if s.delay_ms
        else ""
    )
    return f"bilateral teleoperation ({Mode(s.mode).name.lower()} law{extra})"


def delay_sweep(delays_ms: tuple[int, ...] = SWEEP_DELAYS_MS) -> list[dict[str, Any]]:
    """Both objects, both laws, over added delays: in lockstep (simulated time, the same sides)."""
    rows = []
    for obj in ("sponge", "wood"):
        for mode in (Mode.MODIFIED, Mode.CONVENTIONAL):
            for d in delays_ms:
                run = lockstep.run(obj, delay_s=d / 1e3, mode=mode, pushes=SWEEP_PUSHES, max_s=8.0)
                f = run.transparency()
                rho = stability.spectral_radius(obj, mode=mode, delay_s=d / 1e3)
                rows.append({
                    "object": obj, "mode": mode.name.lower(), "delay_ms": d,
                    "force_error_rms_n": f["force_error_rms_n"],
                    "peak_force_remote_n": f["peak_force_remote_n"],
                    "spectral_radius": rho, "stable_linear": rho < 1.0,
                })  # fmt: skip
    return rows


def drive_comparison(gear: float = USUAL_GEAR) -> dict[str, dict[str, float]]:
    """The arms' joints as twin drives (no Coulomb friction at the output) against usual drives (the
    motor's Coulomb friction through a gear), on the sponge, in lockstep: what friction does to what the
    operator feels."""
    out = {}
    for name, coulomb in (("twin", 0.0), ("usual", twindrive.COULOMB * gear)):
        run = lockstep.run("sponge", pushes=(4.0, 6.0), coulomb_nm=coulomb)
        f = run.transparency()
        out[name] = {
            "coulomb_nm": coulomb,
            "force_error_rms_n": f["force_error_rms_n"],
            "peak_force_diff_pct": f["peak_force_diff_pct"],
        }
    return out


@dataclass
class BilateralResult(JsonFields):
    """`cell bench bilateral`'s figures: each run's summary (summarize(), as `cell teleop` prints it),
    the twin drive's ramp, the joints' drives, the delay sweep, and the keys the issue names."""

    sponge: dict[str, Any]
    wood: dict[str, Any]
    estop_delayed: dict[str, Any]
    twin_drive: dict[str, float]
    joint_drives: dict[str, dict[str, float]]
    delay_sweep: list[dict[str, Any]]
    critical_delay_ms: dict[str, int | None]
    png: dict[str, str]
    sponge_peak_force_n: float
    sponge_peak_force_local_n: float
    wood_peak_force_n: float
    wood_peak_force_local_n: float
    peak_force_diff_pct: float
    sponge_position_pp_mm: float
    wood_position_pp_mm: float
    force_error_rms_n: float
    force_error_max_n: float
    period_p50_ms: float
    period_p99_ms: float
    missed_periods_pct: float
    estop_skew_ms: float | None
    estop_taken_ms: float
    usual_follows_from_rad_s: float
    twin_follows_from_rad_s: float


def bench(out_dir: str, estop_delay_ms: float = 10.0, estop_jitter_ms: float = 2.0) -> BilateralResult:
    """The scripted experiment on both objects in real time, the twin-drive ramp, the delay sweep, and
    an e-stop with a delayed data link; PNGs into out_dir."""
    out = Path(out_dir)
    runs: dict[str, dict[str, Any]] = {}
    traces = {}
    for obj in ("sponge", "wood"):
        res = realtime.run(Setup(obj=obj, stream=False))
        runs[obj] = summarize(res)
        traces[obj] = (res["local"]["trace"], res["remote"]["trace"])
    # the e-stop while the remote presses into the sponge at the operator's speed
    es = summarize(
        realtime.run(
            Setup(
                obj="sponge", delay_ms=estop_delay_ms, jitter_ms=estop_jitter_ms, estop_at_s=1.0, stream=False
            )
        )
    )
    ramp = twindrive.ramp()
    drives = drive_comparison()
    sweep = delay_sweep()
    sp, wo, es_f = runs["sponge"], runs["wood"], es["estop"]
    all_runs = (sp, wo, es)
    return BilateralResult(
        sponge=sp,
        wood=wo,
        estop_delayed=es,
        twin_drive=ramp.summary(),
        joint_drives=drives,
        delay_sweep=sweep,
        critical_delay_ms={
            f"{obj}_{m.name.lower()}": stability.critical_delay_ms(obj, mode=m)
            for obj in ("sponge", "wood")
            for m in (Mode.MODIFIED, Mode.CONVENTIONAL)
        },
        png={
            "runs": figures.plot_runs(traces, out / "bilateral-runs.png", _title(Setup())),
            "twin_drive": figures.plot_ramp(ramp, out / "bilateral-twin-drive.png"),
            "delays": figures.plot_delays(sweep, out / "bilateral-delays.png"),
        },
        # the JSON keys the issue names, and a few more
        sponge_peak_force_n=sp["peak_force_remote_n"],
        sponge_peak_force_local_n=sp["peak_force_local_n"],
        wood_peak_force_n=wo["peak_force_remote_n"],
        wood_peak_force_local_n=wo["peak_force_local_n"],
        peak_force_diff_pct=max(sp["peak_force_diff_pct"], wo["peak_force_diff_pct"]),
        sponge_position_pp_mm=sp["position_pp_remote_mm"],
        wood_position_pp_mm=wo["position_pp_remote_mm"],
        force_error_rms_n=max(sp["force_error_rms_n"], wo["force_error_rms_n"]),
        force_error_max_n=max(sp["force_error_max_n"], wo["force_error_max_n"]),
        period_p50_ms=max(x["period_p50_ms"] for x in all_runs),
        period_p99_ms=max(x["period_p99_ms"] for x in all_runs),
        missed_periods_pct=max(x["missed_periods_pct"] for x in all_runs),
        estop_skew_ms=es_f["skew_ms"],
        estop_taken_ms=max(v for v in es_f["taken_ms"].values() if v is not None),
        usual_follows_from_rad_s=ramp.usual_follows_from,
        twin_follows_from_rad_s=ramp.twin_follows_from,
    )


def format_result(r: BilateralResult) -> str:
    lines = ["Bilateral teleoperation over the Responsive Link (Responsive Processor paper, Sec. 4)", ""]
    lines.append(f"{'':8} {'peak local':>10} {'peak remote':>11} {'|fl+fr| rms':>11} {'max':>6} "
                 f"{'z p-p remote':>12} {'local':>7} {'period p50/p99':>15} {'missed':>7}")  # fmt: skip
    for obj in ("sponge", "wood"):
        x = r.sponge if obj == "sponge" else r.wood
        lines.append(
            f"{obj:8} {x['peak_force_local_n']:9.2f}N {x['peak_force_remote_n']:10.2f}N "
            f"{x['force_error_rms_n']:10.3f}N {x['force_error_max_n']:5.2f}N "
            f"{x['position_pp_remote_mm']:10.2f}mm "
            f"{x['position_pp_local_mm']:5.2f}mm {x['period_p50_ms']:7.3f}/{x['period_p99_ms']:.3f}ms "
            f"{x['missed_periods_pct']:6.3f}%"
        )
    lines.append(
        "paper (Figs. 16-17): forces reach about 6 N on both sides, the curves on each other; the tip's "
        "z swings much more on the sponge than on the wood"
    )
    e = r.estop_delayed
    es = e["estop"]
    lines += [
        "",
        f"e-stop with the data link at +{e['delay_ms']:g} +/- {e['jitter_ms']:g} ms: taken by the local "
        f"side {es['taken_ms']['local']:.2f} ms, the remote {es['taken_ms']['remote']:.2f} ms after the "
        "console sent it "
        f"(skew {es['skew_ms']:.2f} ms); tips still after {_ms(es['still_after_ms'].get('local'))} / "
        f"{_ms(es['still_after_ms'].get('remote'))}",
    ]
    t = r.twin_drive
    lines += [
        "",
        f"twin drive (Table 2, K_v {t['kv_nms_per_rad']:.3f} N m s/rad): the usual motor follows speed "
        f"commands from {t['usual_follows_from_rad_s'] * 1e3:.2f} mrad/s "
        f"(sticks below {t['stick_band_rad_s'] * 1e3:.2f}) and then runs "
        f"{t['usual_lag_rad_s'] * 1e3:.2f} mrad/s behind; the twin drive from "
        f"{t['twin_follows_from_rad_s'] * 1e3:.3f} mrad/s, {t['twin_lag_rad_s'] * 1e3:.3f} mrad/s behind",
        "arms' joints (sponge, lockstep): "
        + "; ".join(
            f"{k} drives {v['force_error_rms_n']:.3f} N |fl+fr| rms, "
            f"peaks {v['peak_force_diff_pct']:.1f}% apart"
            for k, v in r.joint_drives.items()
        ),
        "",
        "added data-link delay (lockstep; rho: the linear model's spectral radius, < 1 stable):",
    ]
    for row in r.delay_sweep:
        lines.append(
            f"  {row['object']:6} {row['mode']:12} +{row['delay_ms']:3d} ms: "
            f"|fl+fr| rms {row['force_error_rms_n']:6.3f} N, "
            f"peak {row['peak_force_remote_n']:6.2f} N, rho {row['spectral_radius']:.4f}"
        )
    crit = r.critical_delay_ms
    lines.append(
        "  unstable from (linear model): "
        + "; ".join(
            f"{obj} {_delay(crit[f'{obj}_modified'])} (modified law), "
            f"{_delay(crit[f'{obj}_conventional'])} (conventional)"
            for obj in ("sponge", "wood")
        )
    )
    lines.append("")
    lines.append("PNGs: " + ", ".join(r.png.values()))
    return "\n".join(lines)


def _delay(ms: int | None) -> str:
    return f"+{ms} ms" if ms is not None else "none up to +50 ms"


def _ms(v: float | None) -> str:
    return f"{v:.0f} ms" if v is not None else "-"
