"""URScript as the emulated arms take it on their client interfaces (30001-30003), sans IO.

`Framer` cuts the byte stream into programs the way a UR controller does: a top-level `def`/`sec`
runs to its top-level `end`; a line outside any definition is a program of its own.  `parse()` then
says what the program is:

- ur_rtde's control script (`def rtde_control():`): served natively (cell.ur.program.RtdeControl), its
  register offsets read from the script;
- the cell's daemon script (`def cell_daemon():`, cell.ur.daemon): served natively, its settings
  read from its `global cell_<name> = <number>` lines;
- UR's external_control program (what UR's client library and ROS 2 driver send; recognised by its
  reverse socket): served natively (cell.ur.external), where to connect back and its scales read
  from what the client filled in;
- a straight-line program: calls of movej, movel, speedj, servoj, stopj, stopl, sleep, sync,
  set_standard_digital_out, textmsg, popup, protective_stop and the socket calls (socket_open,
  socket_send_string, socket_send_line, socket_close), one a line, with literal arguments, in
  `while True:` loops or not (an external_control program's code after its control loop too);

and anything else is refused (ScriptError: the line, the column and why), as a UR's runtime
exception says it (a call of a function no UR has, in the compiler's own words).  The emulator is
not a URScript interpreter: no variables, no conditions.
"""

from __future__ import annotations

import ast
import re
import warnings
from dataclasses import dataclass, field
from typing import TypeGuard

from cell.lines import LineReader, TooLong

MAX_SCRIPT = 1 << 20  # bytes of one program; a longer one is refused and skipped to its end
MAX_LINE = 10_000  # characters of one line of a straight-line program
_TOP_DEF = re.compile(r"^(def|sec)\s+([A-Za-z_]\w*)\s*\(\s*\)\s*:")
_POSE = re.compile(r"\bp\s*\[")
# UR's external_control program (URCL's): the sockets it opens, in order, and what the client filled in
EXTERNAL_SOCKETS = ("trajectory_socket", "script_command_socket", "reverse_socket")
_CONNECT = re.compile(r'connect_socket_with_retry\(\s*"([^"]*)"\s*,\s*(\d+)\s*,\s*"(\w+)"\s*\)')
_MULT = re.compile(r"^\s*MULT_(jointstate|time)\s*=\s*([0-9.eE+]+)\s*$", re.M)
_SERVO = re.compile(r"servoj\(q,\s*t=steptime,\s*lookahead_time=([0-9.eE+-]+),\s*gain=([0-9.eE+-]+)\)")
_SPLINE_PROBE = re.compile(r"^[ \t]*write_output_float_register\((\d+),\s*splineTimerTraveled\)", re.M)
_WHILE_TRUE = re.compile(r"^while\s*(\(\s*True\s*\)|True)\s*:$")
# the statements of a URScript interpreter, which the arm has not (refused with what it runs)
_STATEMENT = re.compile(
    r"^(?:(if|elif|else|while|for|thread|def|sec|global|local|return|halt|break|continue|run|join|kill"
    r"|enter_critical|exit_critical)\b|(\w+)\s*(\[[^]]*\])?\s*=[^=])"
)
# after this marker comes what a client appends to the external_control script (run once its loop ends)
_LOOP_ENDS = "# NODE_CONTROL_LOOP_ENDS"
# what a UR's functions are called (its names and their families): refused as not run here; any
# other name gets the compiler's compile_error_name_not_found, as on a UR
_UR_FUNCTION = re.compile(
    r"^(?:(?:get|set|is|socket|read|write|end|rpc|str|pose|interpolate|force|teach|freedrive|tool|"
    r"zero|request|stop|move|speed|servo|conveyor|encoder|modbus|enable|disable|path|position|screw|"
    r"sensor|payload|textmsg|popup|varmsg|ftc|rtde|gripper|operator|tcp|safety|direct|torque|"
    r"target|high|low|mute|unmute|power|transpose|inv|wrench|length|binary|to|integer|floor|ceil|"
    r"random|norm|point|acos|asin|atan|atan2|sin|cos|tan|sqrt|pow|log|d2r|r2d|abs|max|min)(?:_\w*)?)$"
)
_SETTING = re.compile(r"^\s*global\s+cell_(\w+)\s*=\s*(\[[-+0-9.eE, ]*\]|[-+0-9.eE]+)\s*$", re.M)


class ScriptError(ValueError):
    """A program the arm does not run: where (line, column from 1) and why.  `said` is what the
    client's runtime exception says: UR's own words where a UR has them (the compiler's), else the
    reason."""

    def __init__(self, line: int, column: int, reason: str, said: str = "") -> None:
        self.line, self.column, self.reason = line, column, reason
        self.said = said or f"program refused: {reason}"
        super().__init__(f"line {line}: {reason}")


@dataclass(frozen=True, slots=True)
class Pose:
    """p[x, y, z, rx, ry, rz]: a URScript pose (m, rotation vector rad)."""

    v: tuple[float, ...]


@dataclass(frozen=True, slots=True)
class Call:
    name: str
    args: dict[str, object]
    line: int


@dataclass(frozen=True, slots=True)
class Script:
    """A program as the arm will run it: `kind` "rtde_control", "cell_daemon", "external_control" or
    "lines"."""

    name: str
    kind: str
    calls: list[Call] = field(default_factory=list)
    reg_offset_int: int = 0
    reg_offset_float: int = 0
    # its `global cell_<name> = <number or list of numbers>` lines
    settings: dict[str, float | tuple[float, ...]] = field(default_factory=dict)
    secondary: bool = False  # a `sec` program: runs beside the arm's program, never moves it
    # an external_control program's code after its control loop (what a client appended): run after
    # the loop ends, as lines
    tail: list[Call] = field(default_factory=list)


class Framer:
    """Bytes in, whole programs out: each a text, or a ScriptError for one too long to take."""

    def __init__(self) -> None:
        self.reader = LineReader(MAX_SCRIPT, b"\n")
        self.lines: list[str] = []  # the program being collected
        self.size = 0  # its bytes
        self.skipping = False  # inside a program too long to take: dropped to its end
        self.refused = 0

    def feed(self, data: bytes) -> list[str | ScriptError]:
        out: list[str | ScriptError] = []
        for line in self.reader.feed(data):
            if isinstance(line, TooLong):  # one endless line: refused, with the program it is in
                if not self.skipping:
                    self._refuse(out)
                    self.skipping = bool(self.lines)  # (the rest of that program is dropped)
                    self.lines.clear()
                    self.size = 0
            else:
                self._line(line.decode(errors="replace").rstrip("\r"), out)
        return out

    def _line(self, line: str, out: list[str | ScriptError]) -> None:
        top = bool(line) and not line[0].isspace()
        if not self.lines and not self.skipping:
            if not line.strip() or line.lstrip().startswith("#"):
                return
            if not (top and _TOP_DEF.match(line)):
                out.append(line.strip() + "\n")  # a one-line program
                return
        if not self.skipping:
            self.lines.append(line)
            self.size += len(line) + 1
            if self.size > MAX_SCRIPT:
                self.lines.clear()
                self.skipping = True
                self._refuse(out)
        if top and line.strip() == "end":
            if not self.skipping:
                out.append("\n".join(self.lines) + "\n")
            self.lines.clear()
            self.size = 0
            self.skipping = False

    def _refuse(self, out: list[str | ScriptError]) -> None:
        self.refused += 1
        out.append(ScriptError(1, 0, f"a program longer than {MAX_SCRIPT} bytes: not taken"))


# --- the straight-line programs ------------------------------------------------------------------

# name -> its parameters in order, and their defaults (None: required)
SIGNATURES: dict[str, dict[str, object]] = {
    "movej": {"q": None, "a": 1.4, "v": 1.05, "t": 0.0, "r": 0.0},
    "movel": {"pose": None, "a": 1.2, "v": 0.25, "t": 0.0, "r": 0.0},
    "speedj": {"qd": None, "a": None, "t": None},
    "servoj": {"q": None, "a": 0.0, "v": 0.0, "t": 0.002, "lookahead_time": 0.1, "gain": 300.0},
    "stopj": {"a": None},
    "stopl": {"a": None},
    "sleep": {"t": None},
    "sync": {},
    "set_standard_digital_out": {"n": None, "b": None},
    "textmsg": {"s1": None, "s2": ""},
    "protective_stop": {},
    "popup": {"s": None, "title": "Popup", "warning": False, "error": False, "blocking": False},
    "socket_open": {"address": None, "port": None, "socket_name": "socket_0", "timeout": 2.0},
    "socket_send_string": {"str": None, "socket_name": "socket_0"},
    "socket_send_line": {"str": None, "socket_name": "socket_0"},
    "socket_close": {"socket_name": "socket_0"},
}
END_LOOP = "end_loop"  # the call a `while True:` loop's `end` becomes: back to the loop's first call


def parse(text: str) -> Script:
    """What a program is; ScriptError if this arm does not run it."""
    lines = text.splitlines()
    m = _TOP_DEF.match(lines[0]) if lines else None
    name = m.group(2) if m else "program"
    if '"reverse_socket"' in text and "MULT_jointstate" in text and "socket_read_binary_integer" in text:
        settings = _external_settings(text)
        tail: list[Call] = []
        if _LOOP_ENDS in text:  # (its own closing lines are done by the runner: what follows)
            at = text[: text.index(_LOOP_ENDS)].count("\n") + 1
            after = lines[at : len(lines) - (1 if m else 0)]
            tail = _calls(after, at + 1)
        return Script(name, "external_control", settings=settings, tail=tail)
    if name in ("rtde_control", "cell_daemon"):
        settings = {}
        for key, value in _SETTING.findall(text):
            try:
                if value.startswith("["):
                    settings[key] = tuple(float(v) for v in value.strip("[]").split(",") if v.strip())
                else:
                    settings[key] = float(value)
            except ValueError:
                at = text[: text.index(f"cell_{key}")].count("\n") + 1
                raise ScriptError(at, 0, f"cell_{key}: {value!r} is not a number") from None
        if name == "cell_daemon":
            _check_daemon(settings)
        return Script(
            name,
            name,
            reg_offset_int=_offset(text, "int"),
            reg_offset_float=_offset(text, "float"),
            settings=settings,
        )
    body = lines[1:-1] if m else lines
    calls = _calls(body, 2 if m else 1)
    return Script(name, "lines", calls, secondary=m is not None and m.group(1) == "sec")


def _calls(body: list[str], first: int) -> list[Call]:
    """The lines as calls; a `while True:` loop's `end` an END_LOOP call back to its first."""
    calls: list[Call] = []
    loops: list[tuple[int, int, int]] = []  # open loops: their first call, line, column
    for n, line in enumerate(body, first):
        code = _strip_comment(line).strip()
        if not code:
            continue
        column = len(line) - len(line.lstrip()) + 1
        if _WHILE_TRUE.match(code):
            loops.append((len(calls), n, column))
        elif code == "end":
            if not loops:
                raise ScriptError(n, column, "an `end` with no `while True:` to close")
            to, at, _ = loops.pop()
            if to == len(calls):
                raise ScriptError(at, column, "an empty `while True:` loop never ends and does nothing")
            calls.append(Call(END_LOOP, {"to": to}, n))
        else:
            calls.append(_call(code, n, column))
    if loops:
        _, at, column = loops[-1]
        raise ScriptError(at, column, "a `while True:` with no `end`")
    return calls


def _external_settings(text: str) -> dict[str, float | tuple[float, ...]]:
    """The script's settings as urscript.Script carries them (floats; the host as its 4 bytes)."""
    found = {name: (host, int(port)) for host, port, name in _CONNECT.findall(text)}
    missing = [s for s in EXTERNAL_SOCKETS if s not in found]
    if missing:
        raise ScriptError(1, 0, f"external_control: no connect_socket_with_retry for {', '.join(missing)}")
    hosts = {host for host, _ in found.values()}
    if len(hosts) != 1:
        raise ScriptError(1, 0, f"external_control: its sockets name {len(hosts)} hosts")
    try:
        host = tuple(float(b) for b in bytes(int(x) for x in next(iter(hosts)).split(".")))
        if len(host) != 4:
            raise ValueError
    except ValueError:
        raise ScriptError(1, 0, f"external_control: {next(iter(hosts))!r} is not an IPv4 address") from None
    mult = dict(_MULT.findall(text))
    out: dict[str, float | tuple[float, ...]] = {"host": host}
    for name, value in (("mult_joint", mult.get("jointstate")), ("mult_time", mult.get("time"))):
        if value is None or not 0 < float(value) < 1e12:
            raise ScriptError(1, 0, f"external_control: MULT_{name[5:]} is missing or not positive")
        out[name] = float(value)
    servo = _SERVO.search(text)
    out["lookahead"], out["gain"] = (
        (float(servo.group(1)), float(servo.group(2))) if servo else (0.03, 2000.0)
    )
    for name, (_, port) in found.items():
        out[f"port_{name}"] = float(port)
    if probe := _SPLINE_PROBE.search(text):
        out["spline_register"] = float(probe[1])
    out["sends_canceled"] = float('socket_send_int(TRAJECTORY_RESULT_CANCELED, "trajectory_socket")' in text)
    return out


def _check_daemon(settings: dict[str, float | tuple[float, ...]]) -> None:
    """The daemon's settings as the emulated arm can run them (a UR would fail on a register out of
    range, a list of the wrong length, or never move with a zero limit)."""
    r, watchdog = settings.get("registers"), settings.get("watchdog")
    if not (isinstance(r, float) and r == int(r) and 0 <= r <= 42):
        raise ScriptError(1, 0, f"cell_registers = {r}: its registers r..r+5 must lie in 0..47")
    if not (isinstance(watchdog, float) and 1 <= watchdog <= 1e6):
        raise ScriptError(1, 0, f"cell_watchdog = {watchdog}: must be 1..1e6 cycles")
    for key in ("v_max", "a_max"):
        v = settings.get(key)
        if not (isinstance(v, tuple) and len(v) == 6 and all(0 < x <= 1e4 for x in v)):
            raise ScriptError(1, 0, f"cell_{key} = {v}: must list six limits in (0, 1e4]")


def _offset(text: str, kind: str) -> int:
    m = re.search(rf"global\s+reg_offset_{kind}\s*=\s*(\d+)", text)
    return int(m.group(1)) if m else 0


def _strip_comment(line: str) -> str:
    quoted = False
    for i, ch in enumerate(line):
        if ch == '"':
            quoted = not quoted
        elif ch == "#" and not quoted:
            return line[:i]
    return line


def _call(code: str, line: int, column: int) -> Call:
    if len(code) > MAX_LINE:
        raise ScriptError(line, column, f"a line of {len(code)} characters (at most {MAX_LINE})")
    if st := _STATEMENT.match(code):
        what = f"`{st.group(1)}`" if st.group(1) else "an assignment"
        raise ScriptError(
            line,
            column,
            f"{what}: this arm has no URScript interpreter (it runs calls, one a line, with literal "
            "arguments, and `while True:` loops of them)",
        )
    try:
        with warnings.catch_warnings():  # (Python's own warnings about the text are not the arm's)
            warnings.simplefilter("ignore")
            node = ast.parse(_POSE.sub("P+[", code), mode="eval").body
    except SyntaxError as exc:
        raise ScriptError(
            line, column + (exc.offset or 1) - 1, f"cannot read {code[:80]!r}: {exc.msg}"
        ) from None
    except (RecursionError, MemoryError):
        raise ScriptError(line, column, "an expression nested too deep to read") from None
    if not isinstance(node, ast.Call) or not isinstance(node.func, ast.Name):
        raise ScriptError(line, column, f"{code[:80]!r} is not a call: this arm runs straight-line programs")
    name = node.func.id
    sig = SIGNATURES.get(name)
    if sig is None:
        runs = f"it runs straight-line programs of {', '.join(SIGNATURES)}"
        if _UR_FUNCTION.match(name):
            raise ScriptError(line, column, f"{name}() is not run by this arm ({runs})")
        raise ScriptError(  # (no UR has it: the compiler's words)
            line, column, f"no function {name}() ({runs})", said=f"compile_error_name_not_found:{name}:"
        )
    params = list(sig)
    if len(node.args) > len(params):
        raise ScriptError(line, column, f"{name}() takes at most {len(params)} arguments")
    args: dict[str, object] = {}
    try:
        for p, a in zip(params, node.args, strict=False):
            args[p] = _value(a)
        for kw in node.keywords:
            if kw.arg not in sig:
                raise ScriptError(line, column, f"{name}() has no parameter {kw.arg!r}")
            args[kw.arg] = _value(kw.value)
    except ValueError as exc:
        raise ScriptError(line, column, f"{name}(): {exc}") from None
    except RecursionError:
        raise ScriptError(line, column, f"{name}(): an argument nested too deep to read") from None
    for p, default in sig.items():
        if p not in args:
            if default is None:
                raise ScriptError(line, column, f"{name}() needs {p}")
            args[p] = default
    return Call(name, args, line)


def _is_number(x: object) -> TypeGuard[int | float]:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def _value(node: ast.expr) -> object:
    """A literal: a number, a bool, a string, a list of numbers, a pose; with + - * / on numbers."""
    if isinstance(node, ast.Constant) and isinstance(node.value, (int, float, str, bool)):
        return node.value
    if isinstance(node, ast.Name) and node.id in ("True", "False", "pi"):
        return {"True": True, "False": False, "pi": 3.141592653589793}[node.id]
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)):
        v = _value(node.operand)
        if _is_number(v):
            return -v if isinstance(node.op, ast.USub) else v
    if isinstance(node, ast.List):
        items = [_value(e) for e in node.elts]
        numbers = [x for x in items if _is_number(x)]
        if len(numbers) == len(items):
            return [float(x) for x in numbers]
    if isinstance(node, ast.BinOp):
        if isinstance(node.left, ast.Name) and node.left.id == "P" and isinstance(node.op, ast.Add):
            v = _value(node.right)
            if isinstance(v, list) and len(v) == 6:
                return Pose(tuple(v))
            raise ValueError("a pose is p[x, y, z, rx, ry, rz]")
        a, b = _value(node.left), _value(node.right)
        if _is_number(a) and _is_number(b):
            ops = {ast.Add: a + b, ast.Sub: a - b, ast.Mult: a * b}
            if type(node.op) in ops:
                return ops[type(node.op)]
            if isinstance(node.op, ast.Div) and b:
                return a / b
    raise ValueError(f"{ast.unparse(node)!r} is not a literal value this arm takes")
