"""The daemon's URScript program: what runs on a UR controller to make it a robot of the cell.

The paper's URCap daemon (seed 000, Sec. 4) translates between the robot's URScript interface and the
cell's datagrams.  Here the translation runs beside the cell (cell.ur.remote), and the program on the
controller stays as small as a program can: every control cycle it reads six joint velocities from
the RTDE input double registers, moves each joint's velocity toward its own within the joint's limits
and `speedj`s the result for one cycle, and writes back the number of the command window they came
with (the input integer register) and a heartbeat, so the cell can tell its program runs and which
window the arm is executing.  If the number stops changing for `watchdog` cycles (the cell's side is
gone) the program brings the arm to a stop at its joints' accelerations.

The same text is what an emulated arm runs (cell.ur.program.DaemonProgram serves it natively, its
parameters read from the `global cell_*` lines), so the bytes tested are the bytes a UR gets.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

NAME = "cell_daemon"


@dataclass(frozen=True, slots=True)
class Registers:
    """Where the program and the cell meet, from [ur] daemon_registers = r: input int r (the window's
    number), input doubles r..r+5 (the joints' velocities, rad/s), output ints r (the number taken)
    and r+1 (the heartbeat: cycles run)."""

    first: int = 24

    @property
    def window(self) -> str:
        return f"input_int_register_{self.first}"

    @property
    def velocities(self) -> list[str]:
        return [f"input_double_register_{self.first + j}" for j in range(6)]

    @property
    def taken(self) -> str:
        return f"output_int_register_{self.first}"

    @property
    def heartbeat(self) -> str:
        return f"output_int_register_{self.first + 1}"


def script(registers: Registers, watchdog_cycles: int, v_max: Sequence[float], a_max: Sequence[float]) -> str:
    """The program's text, as sent to the controller's primary interface.  Each joint's velocity
    moves toward the cell's command within that joint's own limits (v_max, rad/s; a_max, rad/s^2),
    as the cell's drive model has it and its controller plans for (speedj alone ramps every joint
    at the leading joint's acceleration, which bends the path whenever the joints' changes differ)."""
    r = registers.first
    reads = ", ".join(f"read_input_float_register({r + j})" for j in range(6))
    vs = ", ".join(f"{v:.6g}" for v in v_max)
    accs = ", ".join(f"{a:.6g}" for a in a_max)
    return f"""def {NAME}():
  # the cell's daemon (docs/ur.md): each cycle, speedj the joint velocities the cell wrote
  global cell_registers = {r}
  global cell_watchdog = {watchdog_cycles}
  global cell_v_max = [{vs}]
  global cell_a_max = [{accs}]
  window = read_input_integer_register({r})
  idle = 0
  beat = 0
  qd = get_actual_joint_speeds()
  while True:
    taken = read_input_integer_register({r})
    if taken != window:
      window = taken
      idle = 0
    elif idle < cell_watchdog:
      idle = idle + 1
    end
    goal = [0, 0, 0, 0, 0, 0]
    if idle < cell_watchdog:
      goal = [{reads}]
    end
    dt = get_steptime()
    j = 0
    while j < 6:
      g = goal[j]
      if g > cell_v_max[j]:
        g = cell_v_max[j]
      elif g < -cell_v_max[j]:
        g = -cell_v_max[j]
      end
      d = g - qd[j]
      step = cell_a_max[j] * dt
      if d > step:
        d = step
      elif d < -step:
        d = -step
      end
      qd[j] = qd[j] + d
      j = j + 1
    end
    speedj(qd, {max(a_max):.6g}, dt)
    beat = beat + 1
    if beat > 1000000000:
      beat = 1
    end
    write_output_integer_register({r}, window)
    write_output_integer_register({r + 1}, beat)
  end
end
"""
