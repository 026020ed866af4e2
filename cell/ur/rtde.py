"""UR's Real-Time Data Exchange (RTDE, TCP port 30004), the controller's side, sans IO.

The wire format is UR's "Real-Time Data Exchange (RTDE) Guide" (protocol versions 1 and 2):
every package is a big-endian header (uint16 size including the header, uint8 type) and a payload.

    V  request protocol version  client: uint16 version; server: uint8 accepted
    v  get URControl version     server: uint32 major, minor, bugfix, build
    M  text message              v1: uint8 level, text; v2: uint8 n, text, uint8 n, source, uint8 level
    O  setup outputs             client: (v2: double Hz) + names, comma separated
                                 server: (v2: uint8 recipe id) + the names' types (NOT_FOUND if unknown)
    I  setup inputs              client: names; server: uint8 recipe id + types (IN_USE, NOT_FOUND)
    S  start / P  pause          server: uint8 accepted
    U  data package              uint8 recipe id (v2 outputs; always inputs) + the recipe's values

`Session` is one client connection: bytes in (`receive`), packages out (its return value and
`due()`), nothing else.  What the values are is the arm's (`Source`); which input fields a session
holds is the arm's too (`InputOwner`), so that two clients cannot write the same register.
"""

from __future__ import annotations

import struct
from collections.abc import Iterable
from dataclasses import dataclass, field
from enum import IntEnum, StrEnum
from typing import Protocol

from cell.counters import Counters

HEADER = struct.Struct(">HB")
MAX_FIELDS = 500  # fields in one recipe (a UR takes a few hundred at most)
MAX_HZ = 500.0  # the arm's own status rate: a client asking more gets this
MAX_RECIPES = 255  # output recipes per connection (v2's recipe id is a uint8)


MIN_HZ = 0.01  # an output recipe's least frequency (found by `cell fuzz`: 1e-310 Hz overflowed)


class Package(IntEnum):
    REQUEST_PROTOCOL_VERSION = ord("V")
    GET_URCONTROL_VERSION = ord("v")
    TEXT_MESSAGE = ord("M")
    DATA_PACKAGE = ord("U")
    CONTROL_PACKAGE_SETUP_OUTPUTS = ord("O")
    CONTROL_PACKAGE_SETUP_INPUTS = ord("I")
    CONTROL_PACKAGE_START = ord("S")
    CONTROL_PACKAGE_PAUSE = ord("P")


class Type(StrEnum):
    """RTDE's data types, as the setup replies name them."""

    BOOL = "BOOL"
    UINT8 = "UINT8"
    UINT32 = "UINT32"
    UINT64 = "UINT64"
    INT32 = "INT32"
    DOUBLE = "DOUBLE"
    VECTOR3D = "VECTOR3D"
    VECTOR6D = "VECTOR6D"
    VECTOR6INT32 = "VECTOR6INT32"
    VECTOR6UINT32 = "VECTOR6UINT32"


FORMAT = {
    Type.BOOL: "?", Type.UINT8: "B", Type.UINT32: "I", Type.UINT64: "Q", Type.INT32: "i",
    Type.DOUBLE: "d", Type.VECTOR3D: "3d", Type.VECTOR6D: "6d", Type.VECTOR6INT32: "6i",
    Type.VECTOR6UINT32: "6I",
}  # fmt: skip
WIDTH = {Type.VECTOR3D: 3, Type.VECTOR6D: 6, Type.VECTOR6INT32: 6, Type.VECTOR6UINT32: 6}  # (else 1)
NOT_FOUND, IN_USE = "NOT_FOUND", "IN_USE"


class Level(IntEnum):
    """A text message's warning level."""

    EXCEPTION = 0
    ERROR = 1
    WARNING = 2
    INFO = 3


class RtdeError(Exception):
    """A client's package this end cannot take: counted under `counter`, answered with a text
    message (the connection stays up unless `close`)."""

    def __init__(self, counter: str, why: str, close: bool = False) -> None:
        super().__init__(why)
        self.counter, self.why, self.close = counter, why, close


class Source(Protocol):
    """The arm a session reports: each output field's values now, flattened."""

    def values(self, name: str) -> tuple: ...


class InputOwner(Protocol):
    """The arm's input fields: which session holds which, and the values written to them."""

    def claim(self, session: object, names: list[str]) -> list[str]: ...  # the names refused: IN_USE
    def release(self, session: object) -> None: ...
    def write(self, names: list[str], values: tuple) -> None: ...


@dataclass(slots=True)
class Recipe:
    id: int
    names: list[str]
    types: list[Type]
    fmt: struct.Struct
    every: int = 1  # one package each `every` status ticks (the client's frequency)
    head: bytes = b""  # a data package's header and (v2) recipe id: the same for every package

    def pack(self, source: Source) -> bytes:
        flat: list = []
        for name in self.names:
            flat.extend(source.values(name))
        return self.head + self.fmt.pack(*flat)


@dataclass(slots=True)
class SessionCounters(Counters):
    packages_in: int = 0
    packages_out: int = 0
    data_in: int = 0
    texts_in: int = 0
    bad: dict[str, int] = field(default_factory=dict)  # refused packages by reason


class Session:
    """One RTDE client, sans IO: receive() its bytes and send what it returns; ask due(tick) after
    each status tick for the data packages to send then."""

    def __init__(
        self,
        outputs: dict[str, Type],
        inputs: dict[str, Type],
        owner: InputOwner,
        version: tuple[int, int, int, int],
        tick_hz: float = MAX_HZ,
    ) -> None:
        self.outputs, self.inputs, self.owner = outputs, inputs, owner
        self.controller_version = version
        self.tick_hz = tick_hz
        self.protocol = 1  # until the client asks for 2
        self.started = False
        # counts starts and pauses: data packages made before one are not sent after it (a client
        # that paused reads no data package after the pause's reply, as from a UR)
        self.runs = 0
        self.recipes: list[Recipe] = []  # output recipes, by id - 1
        self.input_recipes: dict[int, Recipe] = {}
        self.counters = SessionCounters()
        self._buf = bytearray()
        self._next_input_id = 1
        self.closed = ""  # why this end gave up on the connection ("" while it is up)

    # --- bytes in ----------------------------------------------------------------------------

    def receive(self, data: bytes) -> list[bytes]:
        """Take what the client sent; the packages to answer with, in order."""
        self._buf += data
        out: list[bytes] = []
        while len(self._buf) >= HEADER.size and not self.closed:
            size, kind = HEADER.unpack_from(self._buf)
            if size < HEADER.size:  # (any size a uint16 says is read whole, then judged)
                # the stream cannot be resynchronised past a bad length: as a UR, drop the client
                self._count("size")
                self.closed = f"a package header that says {size} bytes (at least {HEADER.size})"
                out.append(self.text(Level.ERROR, self.closed))
                break
            if len(self._buf) < size:
                break
            payload = bytes(self._buf[HEADER.size : size])
            del self._buf[:size]
            self.counters.packages_in += 1
            try:
                reply = self._handle(kind, payload)
            except RtdeError as exc:
                self._count(exc.counter)
                out.append(self.text(Level.ERROR, exc.why))
                if exc.close:
                    self.closed = exc.why
                continue
            except (struct.error, UnicodeDecodeError, ValueError, IndexError, ArithmeticError) as exc:
                self._count("malformed")
                out.append(self.text(Level.ERROR, f"malformed {_kind_name(kind)} package: {exc}"))
                continue
            if reply is not None:
                out.append(reply)
        self.counters.packages_out += len(out)
        return out

    def _count(self, why: str) -> None:
        self.counters.count("bad", why)

    def _handle(self, kind: int, p: bytes) -> bytes | None:
        if kind == Package.REQUEST_PROTOCOL_VERSION:
            (version,) = struct.unpack(">H", p)
            ok = version in (1, 2) and not self.started
            if ok:
                self.protocol = version
            return self._pack(Package.REQUEST_PROTOCOL_VERSION, struct.pack(">B", ok))
        if kind == Package.GET_URCONTROL_VERSION:
            return self._pack(Package.GET_URCONTROL_VERSION, struct.pack(">IIII", *self.controller_version))
        if kind == Package.TEXT_MESSAGE:
            self._read_text(p)  # (checked and counted; a UR logs them, the cell has no log of them)
            self.counters.texts_in += 1
            return None
        if kind == Package.CONTROL_PACKAGE_SETUP_OUTPUTS:
            return self._setup_outputs(p)
        if kind == Package.CONTROL_PACKAGE_SETUP_INPUTS:
            return self._setup_inputs(p)
        if kind == Package.CONTROL_PACKAGE_START:
            self.started = bool(self.recipes or self.input_recipes)
            self.runs += 1
            return self._pack(Package.CONTROL_PACKAGE_START, struct.pack(">B", self.started))
        if kind == Package.CONTROL_PACKAGE_PAUSE:
            self.started = False
            self.runs += 1
            return self._pack(Package.CONTROL_PACKAGE_PAUSE, b"\x01")
        if kind == Package.DATA_PACKAGE:
            self._data(p)
            return None
        raise RtdeError("unknown_type", f"unknown package type {kind} ({_kind_name(kind)})")

    def _read_text(self, p: bytes) -> tuple[int, str, str]:
        """(level, source, text); ValueError if the lengths inside say more than it holds."""
        if not p:
            raise ValueError("an empty text message")
        if self.protocol == 1:
            return p[0], "", p[1:].decode(errors="replace")
        n = p[0]
        if len(p) < 2 + n or len(p) != 3 + n + p[1 + n]:
            raise ValueError(f"a text message of {len(p)} bytes whose lengths say otherwise")
        text = p[1 : 1 + n].decode(errors="replace")
        m = p[1 + n]
        source = p[2 + n : 2 + n + m].decode(errors="replace")
        return p[2 + n + m], source, text

    def _names(self, raw: bytes) -> list[str]:
        names = [n.strip() for n in raw.decode("ascii").split(",")]
        names = [n for n in names if n]  # (ur_rtde ends the list with a comma)
        if not names:
            raise RtdeError("empty_recipe", "a recipe needs at least one field name")
        if len(names) > MAX_FIELDS:
            raise RtdeError("too_many_fields", f"{len(names)} fields in one recipe (at most {MAX_FIELDS})")
        return names

    def _setup_outputs(self, p: bytes) -> bytes:
        if self.started:
            raise RtdeError("setup_while_started", "pause before setting up outputs")
        hz = self.tick_hz
        if self.protocol >= 2:
            (hz,) = struct.unpack_from(">d", p)
            p = p[8:]
            if not MIN_HZ <= hz <= 1e6:
                raise RtdeError("bad_frequency", f"output frequency {hz:g} Hz (at least {MIN_HZ:g})")
            hz = min(hz, self.tick_hz)
        names = self._names(p)
        types = [self.outputs.get(n) for n in names]
        text = ",".join(NOT_FOUND if t is None else t.value for t in types)
        if None in types or len(self.recipes) >= MAX_RECIPES:
            rid = 0  # refused: no recipe made
        else:
            ok = [t for t in types if t is not None]
            every = max(1, round(self.tick_hz / hz))
            rid = len(self.recipes) + 1
            fmt, v2 = _struct(ok), self.protocol >= 2
            head = HEADER.pack(HEADER.size + v2 + fmt.size, Package.DATA_PACKAGE) + bytes([rid] if v2 else [])
            self.recipes.append(Recipe(rid, names, ok, fmt, every, head))
        body = (struct.pack(">B", rid) if self.protocol >= 2 else b"") + text.encode()
        return self._pack(Package.CONTROL_PACKAGE_SETUP_OUTPUTS, body)

    def _setup_inputs(self, p: bytes) -> bytes:
        if self.started:
            raise RtdeError("setup_while_started", "pause before setting up inputs")
        names = self._names(p)
        types = [self.inputs.get(n) for n in names]
        known = [n for n, t in zip(names, types, strict=True) if t is not None]
        in_use = set(self.owner.claim(self, known)) if None not in types else set()
        words = [
            NOT_FOUND if t is None else IN_USE if n in in_use else t.value
            for n, t in zip(names, types, strict=True)
        ]
        rid = 0
        if None not in types and not in_use and self._next_input_id <= 255:
            ok = [t for t in types if t is not None]
            rid = self._next_input_id
            self._next_input_id += 1
            self.input_recipes[rid] = Recipe(rid, names, ok, _struct(ok))
        return self._pack(
            Package.CONTROL_PACKAGE_SETUP_INPUTS, struct.pack(">B", rid) + ",".join(words).encode()
        )

    def _data(self, p: bytes) -> None:
        if not p:
            raise RtdeError("malformed", "a data package with no recipe id")
        recipe = self.input_recipes.get(p[0])
        if recipe is None:
            raise RtdeError("unknown_recipe", f"no input recipe {p[0]} on this connection")
        # (taken before start too: ur_rtde's IO interface never starts, and a UR takes its packages)
        if len(p) - 1 != recipe.fmt.size:
            raise RtdeError(
                "bad_length", f"recipe {recipe.id} takes {recipe.fmt.size} bytes of data, got {len(p) - 1}"
            )
        values = recipe.fmt.unpack_from(p, 1)
        self.owner.write(recipe.names, _group(values, recipe.types))
        self.counters.data_in += 1

    # --- packages out ------------------------------------------------------------------------

    def due(self, tick: int, source: Source) -> list[bytes]:
        """The data packages of the recipes due at status tick `tick`."""
        if not self.started:
            return []
        out = [r.pack(source) for r in self.recipes if tick % r.every == 0]
        self.counters.packages_out += len(out)
        return out

    def text(self, level: Level, text: str, source: str = "cell") -> bytes:
        msg = text.encode()[:255]
        if self.protocol == 1:
            return self._pack(Package.TEXT_MESSAGE, bytes((level,)) + msg)
        src = source.encode()[:255]
        return self._pack(
            Package.TEXT_MESSAGE, bytes((len(msg),)) + msg + bytes((len(src),)) + src + bytes((level,))
        )

    def close(self) -> None:
        self.owner.release(self)

    @staticmethod
    def _pack(kind: int, body: bytes) -> bytes:
        return HEADER.pack(HEADER.size + len(body), kind) + body


def _struct(types: Iterable[Type]) -> struct.Struct:
    return struct.Struct(">" + "".join(FORMAT[t] for t in types))


def _group(values: tuple, types: list[Type]) -> tuple:
    """Flat unpacked values back into one value (a scalar or a tuple) per field."""
    out, i = [], 0
    for t in types:
        n = WIDTH.get(t, 1)
        out.append(values[i] if n == 1 else values[i : i + n])
        i += n
    return tuple(out)


def _kind_name(kind: int) -> str:
    try:
        return Package(kind).name.lower()
    except ValueError:
        return f"0x{kind:02x}"


# --- client side (for tests, the daemon and the benches; ur_rtde is the users' client) -------------


def encode(kind: Package, body: bytes = b"") -> bytes:
    return HEADER.pack(HEADER.size + len(body), kind) + body


def split(buf: bytearray) -> list[tuple[int, bytes]]:
    """Whole packages off the front of buf (removed from it): (type, payload)."""
    out = []
    while len(buf) >= HEADER.size:
        size, kind = HEADER.unpack_from(buf)
        if size < HEADER.size:
            raise ValueError(f"a package header says {size} bytes")
        if len(buf) < size:
            break
        out.append((kind, bytes(buf[HEADER.size : size])))
        del buf[:size]
    return out
