"""`cell fuzz` on an arm's UR interfaces: dashboard lines, URScript programs and RTDE packages, mutated.

What would change the arm if it were valid (a `power off`, a `movej`) is not bad input: each mutant
is checked with the interfaces' own sans-IO code first and sent only if the arm would refuse it.
Every bad dashboard line must get exactly one reply, every bad program one runtime exception on the
secondary interface, and the RTDE session must still answer afterwards.
"""

from __future__ import annotations

import asyncio
import struct
from typing import Any

from cell.config import RobotConfig, URConfig
from cell.fuzz.mutate import Mutator
from cell.robot.arm import arm_model
from cell.ur import primary, rtde
from cell.ur.arm import URArm
from cell.ur.dashboard import Dashboard
from cell.ur.rtde import Package
from cell.ur.urscript import Framer, ScriptError, parse

DASHBOARD = [
    b"robotmode", b"power on", b"power off", b"brake release", b"load prog.urp", b"popup hello",
    b"safetystatus", b"PolyscopeVersion", b"is in remote control", b"unlock protective stop",
    b"programState", b"get loaded program", b"addToLog x", b"close safety popup", b"play", b"stop",
]  # fmt: skip
SCRIPTS = [
    b"movej([0, -1.57, 1.57, -1.57, -1.57, 0], a=1.2, v=0.5)", b'textmsg("x", 1)',
    b"set_standard_digital_out(2, True)", b"sleep(0.1)", b'popup("p")', b"stopj(2)",
    b"movel(p[0.1, -0.4, 0.4, 0, 3.14, 0])", b"while True:", b"speedj([0.1,0,0,0,0,0], 1, 0.1)",
]  # fmt: skip
RTDE = [
    rtde.encode(Package.REQUEST_PROTOCOL_VERSION, struct.pack(">H", 2)),
    rtde.encode(Package.GET_URCONTROL_VERSION),
    rtde.encode(Package.CONTROL_PACKAGE_SETUP_OUTPUTS, struct.pack(">d", 125.0) + b"timestamp,actual_q"),
    rtde.encode(Package.CONTROL_PACKAGE_SETUP_INPUTS, b"input_int_register_40,input_double_register_40"),
    rtde.encode(Package.TEXT_MESSAGE, b"\x05hello\x03ur\x02"),
    rtde.encode(Package.DATA_PACKAGE, b"\x01" + bytes(12)),
    rtde.encode(Package.CONTROL_PACKAGE_PAUSE),
]


async def probe(robot: RobotConfig, ur: URConfig) -> None:
    """`robotmode` on a new dashboard connection, answered."""
    reader, writer = await asyncio.open_connection(robot.ur_host, ur.dashboard_port)
    try:
        await reader.readline()  # the welcome
        writer.write(b"robotmode\n")
        if not (await reader.readline()).startswith(b"Robotmode: "):
            raise ValueError("the dashboard did not answer robotmode")
    finally:
        writer.close()


async def fuzz(robot: RobotConfig, ur: URConfig, n: int, mut: Mutator) -> tuple[int, int, dict[str, Any]]:
    """(inputs sent, answers received, detail): a third each to the dashboard, the secondary interface
    and RTDE."""
    third = max(1, n // 3)
    host = robot.ur_host
    lines, answered = await _dashboard(host, ur.dashboard_port, third, mut, robot.model)
    programs, refused = await _scripts(host, ur.secondary_port, third, mut)
    packages, alive = await _rtde(host, ur.rtde_port, n - 2 * third, mut)
    detail = {
        "dashboard_lines": lines,
        "dashboard_answers": answered,
        "programs": programs,
        "programs_refused": refused,
        "rtde_packages": packages,
        "rtde_alive": alive,
    }
    return lines + programs + packages, answered + refused + alive, detail


async def _dashboard(host: str, port: int, n: int, mut: Mutator, model: str) -> tuple[int, int]:
    judge = Dashboard(URArm("fuzz", arm_model(model)), model, "0")
    out: list[bytes] = []
    while len(out) < n:
        line = mut.havoc(mut.rng.choice(DASHBOARD), DASHBOARD).replace(b"\n", b" ")
        if judge.handle(line.decode(errors="replace").rstrip("\r")).startswith("could not understand"):
            out.append(line + b"\n")  # (valid ones would power the arm off or stop its program)
    reader, writer = await asyncio.open_connection(host, port)
    try:
        await reader.readline()
        writer.write(b"".join(out))
        got = 0
        async with asyncio.timeout(30):
            while got < len(out):
                await reader.readline()
                got += 1
        return len(out), got
    finally:
        writer.close()


async def _scripts(host: str, port: int, n: int, mut: Mutator) -> tuple[int, int]:
    out: list[bytes] = []
    while len(out) < n:
        line = mut.havoc(mut.rng.choice(SCRIPTS), SCRIPTS).replace(b"\n", b" ").replace(b"\r", b" ")
        programs = Framer().feed(line + b"\n")
        if len(programs) != 1 or isinstance(programs[0], ScriptError):
            continue
        try:
            parse(programs[0])
        except ScriptError:
            out.append(line + b"\n")  # refused: bad input (a valid one would run)
    reader, writer = await asyncio.open_connection(host, port)
    try:
        buf, refused = bytearray(), 0
        writer.write(b"".join(out))
        async with asyncio.timeout(30):
            while refused < len(out):
                data = await reader.read(65536)
                if not data:
                    break
                buf += data
                for kind, body in primary.split(buf):
                    if kind == primary.ROBOT_MESSAGE:
                        refused += (
                            primary.read_robot_message(body)[0] == primary.RobotMessage.RUNTIME_EXCEPTION
                        )
        return len(out), refused
    finally:
        writer.close()


async def _rtde(host: str, port: int, n: int, mut: Mutator) -> tuple[int, int]:
    """Mutated packages with their lengths made right again (the stream stays readable), then a
    version request on the same connection: 1 if it is answered."""
    out = []
    for _ in range(n):
        raw = bytearray(mut.havoc(mut.rng.choice(RTDE), RTDE))
        if len(raw) < 3:
            raw = bytearray(rtde.encode(Package.TEXT_MESSAGE))
        raw[:2] = struct.pack(">H", min(len(raw), 0xFFFF))
        out.append(bytes(raw[:0xFFFF]))
    reader, writer = await asyncio.open_connection(host, port)
    try:
        writer.write(b"".join(out))
        writer.write(rtde.encode(Package.GET_URCONTROL_VERSION))
        buf, versions = bytearray(), 0
        # every well-formed version request among the mutants is answered too: ours is the last
        wanted = sum(1 for p in out if p[2] == Package.GET_URCONTROL_VERSION and len(p) == 3) + 1
        async with asyncio.timeout(30):
            while versions < wanted:
                data = await reader.read(65536)
                if not data:
                    return len(out), 0
                buf += data
                versions += sum(1 for kind, _ in rtde.split(buf) if kind == Package.GET_URCONTROL_VERSION)
        return len(out), 1
    finally:
        writer.close()
