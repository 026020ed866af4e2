"""`cell bench snp`: the SpW-SnP-MR modular robot (cell.snp.modular) on UDP, in one run:

- cycle: a master and N joint modules ([A, B] and [C, D] every 1 ms, time-bounded queries),
  the modules' clocks off the master's by up to 2 ms and 50 ppm and servoed by SnP-TSP;
- rmap: the same exchange as acknowledged RMAP writes with a fixed timeout and one retry
  (the slides' baseline: 8 T_M a cycle against 4 T_M);
- loss: both again with a share of the datagrams lost on the way;
- plug: N-1 modules running, the Nth plugged in while the cycle runs (found, configured,
  included), then one pulled out (reported silent, excluded, the cycle going on with guesses
  for it) and plugged back.

The master is one process (core 0), the modules another (core 1, one socket, address and
clock each), SCHED_FIFO where allowed.  The cycle's hot paths, the modules' and the master's,
run in C (cell.snp.native) where a C compiler builds them, and in Python as the baselines of
the same run.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import random
from typing import Any, TypedDict

import numpy as np

from cell.bench.registry import Bench, Figures, register
from cell.bench.snp_trial import SLOT_NS, VdcCycleFigures, cycle_figures, trial
from cell.snp.modular import CycleConfig
from cell.snp.runner import chain
from cell.snp.spacewire import FAILOVER_CYCLES, HOP_NS, cd_cycle_us, failover_ms

VDC_CYCLE_KEYS = (
    "missed_pct",
    "cycle_ms_p99",
    "robot_cycle_ms_p99",
    "tool_error_mm_max",
    "tool_error_mm_rms",
)
VDC_PERIOD_PY_NS = 4_000_000  # the Python cycle's period in the VDC baseline that keeps up
MASS_RUNS = ("_mass_error", "_adapted")  # (the modules' inertia BELIEVED of the truth; adapted)
CUT_MODULE = 3  # the routed runs' module whose link to R1 is cut
ROUTED_RUNS = ("_routed", "_python_routed")


class _MassError(TypedDict, total=False):
    """The modules' believed inertia and its adaptation (chain()'s extra Slot arguments)."""

    believed: float
    adapt: float


class _Routed(TypedDict, total=False):
    """trial()'s arguments of a routed run."""

    routed: bool
    cut: tuple[float, int]


def vdc_in_cycle(config: CycleConfig, native: bool, rng: random.Random) -> dict[str, VdcCycleFigures]:
    """VDC's maths in the cycle between processes (cell.modular.cycle): the six modules drive the
    MuJoCo arm along the 0.5 m/s pick and place, the master answers with VDC's recursions.  In C
    at 1 ms ("" key, if it builds), and in Python at 1 ms ("_python") and at VDC_PERIOD_PY_NS
    ("_python_4ms"), with the master computing every [C, D]; and with each module computing its own
    ("_local": one exchange a cycle), in C and in Python at 1 ms, and with the neighbour's force of
    this cycle passed in from the tip ("_neighbour", in C); and in C with the modules' mass
    properties BELIEVED of the truth, without ("_mass_error") and with ("_adapted") their adaptation;
    and over the two routers of cell.snp.routed in C at 1 ms ("_routed") and in Python at
    VDC_PERIOD_PY_NS ("_python_routed"), the link between R1 and module 4 cut halfway along the
    path (its failover: `failover_ms`).
    Each its cycle's figures and the tool's error over the path."""
    from cell.modular.cycle import SETTLE_NS
    from cell.modular.experiment import ADAPT, BELIEVED
    from cell.modular.reference import pick_and_place

    ref = pick_and_place(0.5)
    seconds = 1.2 + SETTLE_NS / 1e9 + float(ref.t[-1])
    scale = VDC_PERIOD_PY_NS // config.period_ns
    slow = dataclasses.replace(
        config,
        period_ns=VDC_PERIOD_PY_NS,
        budget_ns=config.budget_ns * scale,
        slot_ns=config.slot_ns * scale,
        management_ns=config.management_ns * scale,
    )
    runs = {
        "": (config, True, "master"),
        "_python": (config, False, "master"),
        "_python_4ms": (slow, False, "master"),
        "_local": (config, True, "local"),
        "_python_local": (config, False, "local"),
        "_neighbour": (config, True, "neighbour"),
        "_mass_error": (config, True, "master"),
        "_adapted": (config, True, "master"),
        "_routed": (config, True, "master"),
        "_python_routed": (slow, False, "master"),
    }
    cut = (1.2 + SETTLE_NS / 1e9 + float(ref.t[-1]) / 2, CUT_MODULE)
    out = {}
    for key, (cfg, in_c, cd) in runs.items():
        if in_c and not native:
            continue
        wrong: _MassError = (
            {"believed": BELIEVED, "adapt": ADAPT if key == "_adapted" else 0.0} if key in MASS_RUNS else {}
        )
        net: _Routed = {"routed": True, "cut": cut} if key in ROUTED_RUNS else {}
        slots = chain(6, rng, "snp", cd=cd, **wrong)
        r = trial(slots, seconds, config=cfg, native=in_c, reference=ref, **net)
        err = r["tool_error_mm"]
        out[key] = VdcCycleFigures(
            **dataclasses.asdict(cycle_figures(r, cfg.period_ns)),
            period_ms=cfg.period_ns / 1e6,
            runs_in="c" if in_c else "python",
            cd=cd,
            believed=wrong.get("believed", 1.0),
            adapt=wrong.get("adapt", 0.0),
            tool_error_mm_max=float(err.max()) if len(err) else None,
            tool_error_mm_rms=float(np.sqrt(np.mean(err**2))) if len(err) else None,
            path_ran_pct=100.0 * len(err) / len(ref.t),
            routed=bool(net),
            failover_ms=failover_in_cycle_ms(r, slots[CUT_MODULE]["module_id"]) if net else None,
        )
    return out


def failover_in_cycle_ms(r: dict[str, Any], module_id: int) -> float | None:
    """From the cut of a module's link to its first whole cycle after (None: none came)."""
    cut = r.get("cut_ns")
    mod = next((m for m in r["modules"] if m["module_id"] == module_id), None)
    if cut is None or mod is None:
        return None
    c = mod["cycles"]
    after = c[(c[:, 0] > cut) & (c[:, 3] == 0)]
    return float(after[0, 2] - cut) / 1e6 if len(after) else None


def plug_figures(r: dict[str, Any], late_id: int, pulled_id: int, plug_s: float, unplug_s: float) -> dict:
    """How long until a module plugged in runs in the cycle; how long a pulled one takes to be
    reported and excluded; the other modules' misses meanwhile."""
    mods = [m for m in r["modules"] if m["module_id"] == late_id]
    late = mods[0] if mods else None
    events = r["master"]["events"]
    t_start = min(m["plugged_at"] for m in r["modules"])
    out: dict[str, Any] = {}
    if late is not None and len(late["cycles"]):
        out["include_ms"] = (late["cycles"][0, 2] - late["plugged_at"]) / 1e6
        out["included_joint"] = late["joint"]
    t_pull = t_start + unplug_s * 1e9

    def after(what: str, mid: int) -> float | None:
        ts = [t for t, w, m, _ in events if w == what and m == mid and t >= t_pull]
        return (ts[0] - t_pull) / 1e6 if ts else None

    out["silent_ms"] = after("silent", pulled_id)
    out["lost_ms"] = after("lost", pulled_id)
    back = [m for m in r["modules"] if m["module_id"] == pulled_id and m["plugged_at"] > t_pull]
    if back and len(back[0]["cycles"]):
        out["back_ms"] = (back[0]["cycles"][0, 2] - back[0]["plugged_at"]) / 1e6
    others = [m for m in r["modules"] if m["module_id"] not in (late_id, pulled_id)]
    n = sum(len(m["cycles"]) for m in others)
    out["others_missed_pct"] = 100.0 * sum(sum(m["missed"].values()) for m in others) / max(1, 2 * n)
    out["guessed_by_master"] = int(r["master"]["counters"]["guessed"])
    out["events"] = [(round((t - t_start) / 1e6, 1), w, m, j) for t, w, m, j in events]
    return out


@dataclasses.dataclass
class SnpResult:
    """What `cell bench snp` hands on: run()'s figures (their keys partly named by the runs made, so a
    map: the tests and the text read it by key) and whether a hog ran beside them."""

    figures: dict[str, Any]
    hog: bool = False

    def to_json(self) -> dict[str, Any]:
        return self.figures | {"hog": self.hog}


def run(
    slaves: int = 6,
    seconds: float = 3.0,
    loss: float = 0.02,
    seed: int = 1,
    slot_ns: int = SLOT_NS,
    native: bool | None = None,
    management_ns: int | None = None,
    tracking: bool = True,
) -> dict[str, Any]:
    """native: the cycle in C at both ends, the modules' and the master's (cell.snp.native; None:
    if it builds here).  Baselines in the same run: all in Python, and the modules in C with the
    master in Python.  The RMAP comparison runs both transports in Python (the C paths speak the
    queries only), so like is weighed against like."""
    from cell.snp.native import available

    why_not = available()
    if native is None:
        native = why_not is None
    elif native and why_not is not None:
        raise RuntimeError(f"the C cycle cannot run here: {why_not}")
    rng = random.Random(seed)
    config = CycleConfig(slot_ns=slot_ns)
    if management_ns is not None:
        config = dataclasses.replace(config, management_ns=management_ns)
    snp = cycle_figures(trial(chain(slaves, rng, "snp"), seconds, config=config, native=native))
    python = cycle_figures(trial(chain(slaves, rng, "snp"), seconds, config=config)) if native else snp
    py_master = snp
    if native:  # the modules in C, the master in Python
        mixed = trial(chain(slaves, rng, "snp"), seconds, config=config, native=True, native_master=False)
        py_master = cycle_figures(mixed)
    # how many modules this machine keeps within the aim: fewer, shorter runs
    scale = {
        n: cycle_figures(trial(chain(n, rng, "snp"), 2.0, config=config, native=native))
        for n in (2, 4)
        if n < slaves
    }
    scale[slaves] = snp
    within = [n for n, f in scale.items() if f.meets_aim]
    rm = cycle_figures(trial(chain(slaves, rng, "rmap"), seconds, config=config))
    short = max(1.0, seconds / 2)
    snp_loss = cycle_figures(trial(chain(slaves, rng, "snp"), short, loss, config=config))
    rmap_loss = cycle_figures(trial(chain(slaves, rng, "rmap"), short, loss, config=config))
    # plug and operate: the last module plugged in at 1 s; the middle one pulled at 2 s, back at 2.5 s
    modules = chain(slaves, rng, "snp")
    late, pulled = modules[-1], modules[slaves // 2]
    late["plug_s"] = 1.0
    pulled["unplug_s"] = 2.0
    back = {**pulled, "plug_s": 2.5, "unplug_s": None}
    plugged = trial([*modules, back], 3.5, config=config, native=native)
    plug = plug_figures(plugged, late["module_id"], pulled["module_id"], 1.0, 2.0)
    vdc, in_cycle = None, {}
    if tracking:  # the arm the cycle serves: VDC over the four messages, on the MuJoCo arm
        from cell.modular.experiment import measure as measure_tracking

        vdc = measure_tracking()
        if slaves == 6:  # (the modular arm has six modules)
            in_cycle = vdc_in_cycle(config, native, rng)
    return (vdc.figures() if vdc is not None else {}) | {
        **{f"vdc_cycle{k}_{f}": getattr(v, f) for k, v in in_cycle.items() for f in VDC_CYCLE_KEYS},
        "vdc_cycle": {k: dataclasses.asdict(v) for k, v in in_cycle.items()},
        "path_failover_ms": failover_ms(),
        # (the same in the running cycle over routers: a cut link to the module's first whole cycle)
        "cycle_path_failover_ms": next((in_cycle[k].failover_ms for k in ROUTED_RUNS if k in in_cycle), None),
        **{f"cd_cycle_us_{w}": cd_cycle_us(w, slaves) for w in ("master", "neighbour", "local")},
        "vdc": [dataclasses.asdict(row) for row in vdc.rows] if vdc is not None else [],
        "slaves": slaves,
        "seconds": seconds,
        "modules": "c" if native else "python",
        "master": "c" if native else "python",
        "c_unavailable": why_not,
        "cycle_ms_p50": snp.cycle_ms_p50,
        "cycle_ms_p99": snp.cycle_ms_p99,
        "missed_pct": snp.missed_pct,
        "python_cycle_ms_p50": python.cycle_ms_p50,
        "python_cycle_ms_p99": python.cycle_ms_p99,
        "python_missed_pct": python.missed_pct,
        "python_master_cycle_ms_p50": py_master.cycle_ms_p50,
        "python_master_cycle_ms_p99": py_master.cycle_ms_p99,
        "python_master_missed_pct": py_master.missed_pct,
        "rmap_cycle_ms_p50": rm.cycle_ms_p50,
        "rmap_cycle_ms_p99": rm.cycle_ms_p99,
        "rmap_missed_pct": rm.missed_pct,
        "tsp_offset_us_max": snp.tsp_offset_us_max,
        "robot_cycle_ms_p50": snp.robot_cycle_ms_p50,
        "robot_cycle_ms_p99": snp.robot_cycle_ms_p99,
        "slaves_within_aim": max(within, default=0),
        "slot_us": slot_ns / 1e3,
        "management_us": config.management_ns / 1e3,
        "loss": loss,
        "scale": {
            str(n): {k: getattr(f, k) for k in ("cycle_ms_p50", "cycle_ms_p99", "missed_pct")}
            for n, f in scale.items()
        },
        **{
            name: dataclasses.asdict(f)
            for name, f in (
                ("snp", snp),
                ("python", python),
                ("python_master", py_master),
                ("rmap", rm),
                ("snp_loss", snp_loss),
                ("rmap_loss", rmap_loss),
            )
        },
        "plug": plug,
    }


def _ms(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.3f} ms"


def _tracking_text(rows: list[dict[str, Any]], figures: dict[str, Any]) -> str:
    from cell.modular.experiment import Row, VdcFigures, carried_of, format_figures

    return format_figures(VdcFigures([Row(**row) for row in rows], carried_of(figures)))


def format_result(result: SnpResult) -> str:
    r = result.figures

    def line(name: str, f: dict[str, Any]) -> str:
        return (
            f"  {name:<22} {f['cycles']:>6} cycles of {f['modules_ran']} modules: "
            f"p50 {f['cycle_ms_p50']:.3f} ms, "
            f"p99 {f['cycle_ms_p99']:.3f} ms (the robot's: p50 {_ms(f['robot_cycle_ms_p50'])}, p99 "
            f"{_ms(f['robot_cycle_ms_p99'])}), {f['missed_pct']:.2f}% of exchanges missed their deadline "
            f"(guessed); start late p99 {f['start_late_us_p99']:.0f} us; clock error "
            f"p50 {f['tsp_offset_us_p50']:.1f} us, max {f['tsp_offset_us_max']:.1f} us "
            f"({'two' if f['tsp_two_step'] else 'one'}-step); cores used: "
            f"master {f['master_cpu']:.2f}, modules {f['modules_cpu']:.2f}"
        )

    p, nan = r["plug"], float("nan")
    return "\n".join(
        [
            f"SpW-SnP-MR modular robot: master + {r['slaves']} joint modules, [A,B] and [C,D] every 1 ms "
            "(the slides' budget: 0.3 ms for six joints)",
            f"  the cycle (modules and master) in {'C' if r['modules'] == 'c' else 'Python'}"
            + (f" (C not available: {r['c_unavailable']})" if r["c_unavailable"] else ""),
            line("time-bounded queries", r["snp"]),
            line("C modules, Py master", r["python_master"]),
            "  the queries against RMAP, both all in Python (like against like):",
            line("queries, all Python", r["python"]),
            line("RMAP writes + acks", r["rmap"]),
            line(f"queries, {r['loss']:.0%} loss", r["snp_loss"]),
            line(f"RMAP, {r['loss']:.0%} loss", r["rmap_loss"]),
            "  (the slides: 0.3 ms for six joints, 0.05 ms per [A,B,C,D] exchange; a time-bounded query "
            "takes 4 T_M where RMAP's write and acknowledgement take 8)",
            "  modules within the aim (p99 <= 1 ms, < 1% missed): "
            + ", ".join(
                f"{n}: p99 {f['cycle_ms_p99']:.3f} ms, {f['missed_pct']:.2f}% missed"
                for n, f in r["scale"].items()
            )
            + f" -> up to {r['slaves_within_aim']}",
            "  plug and operate: a module plugged in while the cycle runs ran its first cycle after "
            f"{p.get('include_ms', nan):.0f} ms (as joint {p.get('included_joint')}); one pulled out "
            f"was reported silent after {p.get('silent_ms') or nan:.1f} ms and excluded after "
            f"{p.get('lost_ms') or nan:.0f} ms, plugged back it ran again after "
            f"{p.get('back_ms', nan):.0f} ms; the others missed {p['others_missed_pct']:.2f}% "
            f"meanwhile, the master guessed {p['guessed_by_master']} module-cycles",
        ]
        + [
            f"  routed network, single redundancy (two routers): a permanently failed path left for the "
            f"other {r['path_failover_ms']:.1f} ms after the failure ({FAILOVER_CYCLES} cycles missed in a "
            "row, each guessed, no retry: the slides' FDIR)",
            f"  [C,D] by the master / along the modules' chain / by each module alone: the routed network "
            f"adds {r['cd_cycle_us_master']:.0f} / {r['cd_cycle_us_neighbour']:.0f} / "
            f"{r['cd_cycle_us_local']:.0f} us to a cycle ({HOP_NS / 1e3:g} us a hop; the slides: [A,B,C,D] "
            "within 50 us)",
        ]
        + ([_tracking_text(r["vdc"], r)] if r.get("vdc") else [])
        + _vdc_cycle_text(r.get("vdc_cycle") or {})
    )


def _vdc_cycle_text(runs: dict[str, dict[str, Any]]) -> list[str]:
    if not runs:
        return []
    out = [
        "VDC's maths in the running cycle (master and modules in their own processes, the MuJoCo arm "
        "stepped in real time by the modules'), the 0.5 m/s pick and place:"
    ]
    for f in runs.values():
        err = f["tool_error_mm_max"]
        out.append(
            f"  {f['runs_in']:<6} at {f['period_ms']:g} ms, [C, D] by "
            + {"local": "each module", "neighbour": "each module, the neighbour's"}.get(f["cd"], "the master")
            + (f", inertia {f['believed']:.0%} of the truth" if f["believed"] != 1.0 else "")
            + (", over two routers" if f.get("routed") else "")
            + (f", adapted (gain {f['adapt']:g})" if f["adapt"] else "")
            + ": "
            + f"{f['missed_pct']:.2f}% of exchanges missed, "
            f"cycle p99 {f['cycle_ms_p99']:.3f} ms (the robot's {_ms(f['robot_cycle_ms_p99'])}); tool error "
            + (f"max {err:.3f} mm, rms {f['tool_error_mm_rms']:.3f} mm" if err is not None else "n/a")
            + f" over {f['path_ran_pct']:.0f}% of the path"
            + (
                f"; a link cut, {_ms(f.get('failover_ms'))} to its first whole cycle"
                if f.get("routed")
                else ""
            )
            + f"; cores: master {f['master_cpu']:.2f}, modules "
            f"{f['modules_cpu']:.2f}"
        )
    return out


def _arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--slaves", type=int, default=6, help="joint modules (default 6)")
    p.add_argument("--seconds", type=float, default=3.0, help="length of the main trials (default 3)")
    p.add_argument("--loss", type=float, default=0.02, help="share of datagrams lost in the loss trials")
    p.add_argument(
        "--slot-us",
        type=float,
        default=30.0,
        help="joint j's cycle starts j slots into the period (time slots; default 30; 0: all at once)",
    )
    p.add_argument(
        "--management-us",
        type=float,
        help="where in the period the master sends beacons and probes and the bench samples the "
        "clocks: its management slot, after the joints' exchanges (default: CycleConfig's)",
    )
    p.add_argument(
        "--no-tracking",
        dest="tracking",
        action="store_false",
        help="leave out the arm's tracking figures (VDC on the MuJoCo arm, about 20 s)",
    )
    p.add_argument(
        "--cycle",
        "--modules",
        dest="cycle",
        choices=("auto", "c", "python"),
        default="auto",
        help="where the cycle's hot paths (the modules' and the master's) run: c (built with cc on first "
        "use), python, or auto (c if it builds)",
    )
    p.add_argument(
        "--hog",
        action="store_true",
        help="a busy process at the normal priority on every core throughout (a host's other work)",
    )


def _main(args: argparse.Namespace) -> Figures:
    from cell.hog import hog

    native = {"auto": None, "c": True, "python": False}[args.cycle]
    management_ns = None if args.management_us is None else int(args.management_us * 1000)
    with hog() if args.hog else contextlib.nullcontext():
        result = run(
            args.slaves,
            args.seconds,
            args.loss,
            slot_ns=int(args.slot_us * 1000),
            native=native,
            management_ns=management_ns,
            tracking=args.tracking,
        )
    snp = SnpResult(result, args.hog)
    return Figures(snp, format_result(snp))


register(
    Bench(
        "snp",
        "the SpW-SnP-MR modular robot: its 1 ms cycle over time-bounded queries and over RMAP, "
        "SnP-TSP clocks, plug and operate",
        _arguments,
        _main,
    )
)
