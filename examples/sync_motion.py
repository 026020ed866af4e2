"""Two robots start one motion at the same instant (run: `cell run examples/sync_motion.py --up`).

Requests to two skill servers start two motions whenever each is planned;
a synchronised start is the controller's: one start time for both, set in
one atomic update of the data plane's registers.
"""

from __future__ import annotations

HOME = [0.0, -90.0, 90.0, -90.0, -90.0, 0.0]  # deg


async def main(cell) -> None:
    out = [HOME[0] + 30.0, HOME[1] - 15.0, HOME[2] + 10.0, *HOME[3:]]
    t_start, t_end = await cell.move_together({"r1": out, "r2": out}, speed=60)
    print(f"both robots started at {t_start:.3f} s and ended at {t_end:.3f} s (data-plane clock)")
    t_start, t_end = await cell.move_together({"r1": HOME, "r2": HOME}, speed=60)
    print(f"and back: {t_end - t_start:.2f} s")
