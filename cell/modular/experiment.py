"""The modular arm's tracking figures (`cell bench snp`, issue figures of seed 002): VDC over the four
messages on a pick-and-place path and a circle, with no loss, 1 % and 5 % of the messages lost and
a module late half the time, the modules' mass properties 40 % low (with and without VDC's
parameter adaptation), [C, D] by the master, by the modules with their neighbour's force, or
by the modules alone; against the centralised computed-torque controller on the same arm."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields
from typing import Any, cast

import numpy as np

from cell.modular.loop import Faults, Tracking, track_centralised, track_vdc
from cell.modular.reference import Reference, circle, pick_and_place
from cell.modular.vdc import WHERE_LOCAL, WHERE_MASTER, WHERE_NEIGHBOUR, Gains
from cell.modular.wire import SnpLink

CASES: dict[str, Faults] = {
    "no loss": Faults(),
    "1% loss": Faults(loss=0.01),
    "5% loss": Faults(loss=0.05),
    "module 3 late in half the cycles": Faults(late_module=2, late_share=0.5),
}
WHERE = {
    "[C,D] by the master": (WHERE_MASTER,) * 6,
    "[C,D] by the modules, the neighbour's force of this cycle": (WHERE_NEIGHBOUR,) * 6,
    "[C,D] by the modules, the neighbour's force of the cycle before": (WHERE_LOCAL,) * 6,
}
BELIEVED = 0.6  # the modules' mass properties in the model-error cases, as a share of the arm's
ADAPT = 100.0  # the adaptation gain there
MASS_ERROR, ADAPTED = "mass properties 40% low", "mass properties 40% low, adapted"
PAPER = "the slides: 0.3 ms for six joints, [A,B,C,D] within 0.05 ms, FDIR by data obsolescence"
AIMS_MM = {"no loss": 2.0, "1% loss": 5.0}  # the aims (0.5 m/s pick and place)
OVER_SNP = "[C,D] by the master, the messages as SnP-MrT packets over UDP"


@dataclass
class Row:
    path: str
    controller: str  # "vdc" or "centralised"
    case: str
    where: str
    tool_error_mm_max: float
    tool_error_mm_rms: float
    joint_error_rad_max: float
    guessed: dict[str, int]


@dataclass(frozen=True)
class Carried:  # (in the figures as vdc_snp_<field>)
    """The four messages as SnP-MrT packets over loopback UDP (cell.modular.wire.SnpLink): what one
    cycle's 24 messages took, encode to decode, and what they were."""

    exchange_us_p50: float
    exchange_us_p99: float
    datagrams: int
    bytes_mean: float
    refused: int


@dataclass
class VdcFigures:
    rows: list[Row] = field(default_factory=list)
    carried: Carried | None = None

    def worst(self, controller: str, case: str = "no loss", where: str = "[C,D] by the master") -> float:
        return max(
            r.tool_error_mm_max
            for r in self.rows
            if r.controller == controller and r.case == case and (controller != "vdc" or r.where == where)
        )

    def figures(self) -> dict[str, float]:
        return {
            "vdc_tool_error_mm_max": self.worst("vdc"),
            "vdc_tool_error_mm_max_loss1": self.worst("vdc", "1% loss"),
            "vdc_tool_error_mm_max_loss5": self.worst("vdc", "5% loss"),
            "vdc_tool_error_mm_max_late": self.worst("vdc", "module 3 late in half the cycles"),
            "vdc_tool_error_mm_max_neighbour": self.worst("vdc", "1% loss", list(WHERE)[1]),
            "vdc_tool_error_mm_max_local": self.worst("vdc", "1% loss", list(WHERE)[2]),
            "vdc_tool_error_mm_max_mass_error": self.worst("vdc", MASS_ERROR),
            "vdc_tool_error_mm_max_adapted": self.worst("vdc", ADAPTED),
            "centralised_tool_error_mm_max": self.worst("centralised"),
            **(
                {
                    "vdc_snp_tool_error_mm_max": self.worst("vdc", "no loss", OVER_SNP),
                    "vdc_snp_tool_error_mm_max_loss1": self.worst("vdc", "1% loss", OVER_SNP),
                    **{f"vdc_snp_{k}": v for k, v in asdict(self.carried).items()},
                }
                if self.carried is not None
                else {}
            ),
        }


def carried_of(figures: dict[str, object]) -> Carried | None:
    """The Carried figures back from a figures dict (vdc_snp_<field>), if it has them."""
    names = [f.name for f in fields(Carried)]
    if not all(f"vdc_snp_{n}" in figures for n in names):
        return None
    return Carried(**cast(dict[str, Any], {n: figures[f"vdc_snp_{n}"] for n in names}))  # (Carried's own)


def _row(ref: Reference, run: Tracking, case: str, where: str) -> Row:
    return Row(
        ref.name,
        run.name,
        case,
        where,
        run.tool_error_mm_max,
        run.tool_error_mm_rms,
        run.joint_error_rad_max,
        dict(run.guessed),
    )


def measure(speed: float = 0.5, over_snp: bool = True) -> VdcFigures:
    """over_snp: the pick-and-place path also with the messages carried as SnP-MrT packets between
    UDP sockets (no loss and 1 %: 10 s more)."""
    out = VdcFigures()
    if over_snp:
        ref = pick_and_place(speed)
        link = SnpLink()
        try:
            for case in ("no loss", "1% loss"):
                out.rows.append(_row(ref, track_vdc(ref, CASES[case], link=link), case, OVER_SNP))
        finally:
            link.close()
        c = link.counters
        took = np.array(c.transit_ns) / 1e3
        out.carried = Carried(
            float(np.percentile(took, 50)), float(np.percentile(took, 99)), c.datagrams,
            c.bytes / max(c.datagrams, 1), c.refused,
        )  # fmt: skip
    for ref in (pick_and_place(speed), circle(speed=speed)):
        out.rows.append(_row(ref, track_centralised(ref), "no loss", "one computer"))
        for case, faults in CASES.items():
            out.rows.append(_row(ref, track_vdc(ref, faults), case, "[C,D] by the master"))
        for where, places in list(WHERE.items())[1:]:
            out.rows.append(_row(ref, track_vdc(ref, CASES["1% loss"], places), "1% loss", where))
        master = next(iter(WHERE))
        wrong = track_vdc(ref, believed=BELIEVED)
        out.rows.append(_row(ref, wrong, MASS_ERROR, master))
        adapted = track_vdc(ref, gains=Gains(adapt=ADAPT), believed=BELIEVED)
        out.rows.append(_row(ref, adapted, ADAPTED, master))
    return out


def format_figures(f: VdcFigures) -> str:
    lines = ["  tracking, six-module MuJoCo arm, 0.5 m/s tool paths (tool error max / rms, guesses):"]
    for r in f.rows:
        guesses = sum(r.guessed.values())
        lines.append(
            f"    {r.path:<15} {r.controller:<12} {r.case:<33} {r.where:<63} "
            f"{r.tool_error_mm_max:6.3f} / {r.tool_error_mm_rms:6.3f} mm"
            + (f"  ({guesses} guessed)" if guesses else "")
        )
    if (c := f.carried) is not None:
        lines.append(
            f"    over SnP-MrT: a cycle's 24 messages (six [A,B] and six [C,D] queries and replies) took "
            f"{c.exchange_us_p50:.0f} us p50, {c.exchange_us_p99:.0f} us p99 encode to decode in one process "
            f"(the slides: 0.3 ms for six joints); {c.datagrams:,} datagrams of {c.bytes_mean:.0f} B, "
            f"{c.refused} refused"
        )
    lines.append(
        f"    aims: <= {AIMS_MM['no loss']} mm with no loss, <= {AIMS_MM['1% loss']} mm at 1% ({PAPER})"
    )
    return "\n".join(lines)
