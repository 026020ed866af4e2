"""An RTDE client, sans IO: the daemon's side of a UR controller's RTDE interface (cell.ur.remote).

The handshake goes one step at a time, each sent only once the controller has answered the last, as
UR's guide has it: protocol version 2, the controller's version, the output recipe (the fields at the
client's frequency), the input recipe, start.  A controller that refuses a step (a field it does not
know, an input another client holds, version 2 itself) ends the handshake with SetupRefused, which
says what it refused.  Once started, `feed()` returns each data package's values, one per field, and
`write()` makes the input package that sets the input recipe's fields.
"""

from __future__ import annotations

import struct
from enum import Enum, auto

from cell.ur.rtde import FORMAT, IN_USE, NOT_FOUND, WIDTH, Level, Package, Type, encode, split

VERSION = 2


class Step(Enum):
    VERSION = auto()
    CONTROLLER = auto()
    OUTPUTS = auto()
    INPUTS = auto()
    START = auto()
    STARTED = auto()


class SetupRefused(Exception):
    """The controller said no to a step of the handshake."""


class Client:
    """One connection.  Send `hello()` first, then whatever `feed()` leaves in `outbox`."""

    def __init__(self, outputs: list[str], inputs: list[str], hz: float) -> None:
        self.outputs, self.inputs, self.hz = outputs, inputs, hz
        self.step = Step.VERSION
        self.controller: tuple[int, int, int, int] | None = None
        self.outbox = bytearray()  # packages to send now
        self.texts: list[tuple[Level, str]] = []  # the controller's text messages
        self.malformed = 0  # packages that could not be read (counted and dropped)
        self._buf = bytearray()
        self._out_id = 0
        self._out_fmt: struct.Struct | None = None
        self._widths: list[int] = []
        self._in_id = 0
        self._in_fmt: struct.Struct | None = None

    def hello(self) -> bytes:
        return encode(Package.REQUEST_PROTOCOL_VERSION, struct.pack(">H", VERSION))

    @property
    def started(self) -> bool:
        return self.step == Step.STARTED

    def feed(self, data: bytes) -> list[tuple]:
        """The controller's bytes in; the data packages' values out (a field of several values is a
        tuple).  Raises SetupRefused if it refuses the handshake."""
        self._buf += data
        try:
            packages = split(self._buf)
        except ValueError as exc:  # (a stream no one can read on past)
            raise SetupRefused(f"the controller sent {exc}") from None
        out: list[tuple] = []
        for kind, body in packages:
            if kind == Package.DATA_PACKAGE:
                values = self._data(body)
                if values is not None:
                    out.append(values)
            elif kind == Package.TEXT_MESSAGE:
                self._text(body)
            else:
                self._handshake(kind, body)
        return out

    def write(self, values: tuple) -> bytes:
        """The input package setting the input recipe's fields to `values` (flat, in order)."""
        assert self._in_fmt is not None, "no input recipe"
        return encode(Package.DATA_PACKAGE, bytes((self._in_id,)) + self._in_fmt.pack(*values))

    # --- the handshake -----------------------------------------------------------------------

    def _handshake(self, kind: int, body: bytes) -> None:
        step = self.step
        try:
            if step == Step.VERSION and kind == Package.REQUEST_PROTOCOL_VERSION:
                if not body or not body[0]:
                    raise SetupRefused(f"the controller does not speak RTDE version {VERSION}")
                self._next(Step.CONTROLLER, encode(Package.GET_URCONTROL_VERSION))
            elif step == Step.CONTROLLER and kind == Package.GET_URCONTROL_VERSION:
                self.controller = struct.unpack(">IIII", body[:16])
                recipe = struct.pack(">d", self.hz) + self._names(self.outputs)
                self._next(Step.OUTPUTS, encode(Package.CONTROL_PACKAGE_SETUP_OUTPUTS, recipe))
            elif step == Step.OUTPUTS and kind == Package.CONTROL_PACKAGE_SETUP_OUTPUTS:
                self._out_id, types = body[0], self._types(body[1:], self.outputs, "output")
                self._out_fmt = struct.Struct(">" + "".join(FORMAT[t] for t in types))
                self._widths = [WIDTH.get(t, 1) for t in types]
                if self.inputs:
                    recipe = self._names(self.inputs)
                    self._next(Step.INPUTS, encode(Package.CONTROL_PACKAGE_SETUP_INPUTS, recipe))
                else:
                    self._next(Step.START, encode(Package.CONTROL_PACKAGE_START))
            elif step == Step.INPUTS and kind == Package.CONTROL_PACKAGE_SETUP_INPUTS:
                self._in_id, types = body[0], self._types(body[1:], self.inputs, "input")
                self._in_fmt = struct.Struct(">" + "".join(FORMAT[t] for t in types))
                self._next(Step.START, encode(Package.CONTROL_PACKAGE_START))
            elif step == Step.START and kind == Package.CONTROL_PACKAGE_START:
                if not body or not body[0]:
                    raise SetupRefused("the controller would not start sending")
                self.step = Step.STARTED
            else:
                self.malformed += 1  # (an answer to nothing asked: dropped)
        except (IndexError, struct.error, ValueError) as exc:
            if isinstance(exc, SetupRefused):
                raise
            raise SetupRefused(f"an unreadable answer to {step.name.lower()}: {exc}") from None

    def _next(self, step: Step, package: bytes) -> None:
        self.step = step
        self.outbox += package

    @staticmethod
    def _names(names: list[str]) -> bytes:
        return ",".join(names).encode()

    @staticmethod
    def _types(raw: bytes, names: list[str], what: str) -> list[Type]:
        words = raw.decode("ascii", errors="replace").split(",")
        if len(words) != len(names):
            raise SetupRefused(f"{len(words)} types for the {len(names)} {what} fields asked")
        bad = [f"{n} ({w})" for n, w in zip(names, words, strict=True) if w in (NOT_FOUND, IN_USE)]
        if bad:
            raise SetupRefused(f"the controller refused {what} fields: {', '.join(bad)}")
        try:
            return [Type(w) for w in words]
        except ValueError:
            raise SetupRefused(f"unknown types in {words}") from None

    # --- once started ------------------------------------------------------------------------

    def _data(self, body: bytes) -> tuple | None:
        fmt = self._out_fmt
        if fmt is None or not body or body[0] != self._out_id or len(body) - 1 != fmt.size:
            self.malformed += 1
            return None
        flat = fmt.unpack_from(body, 1)
        if len(self._widths) == len(flat):  # (every field a scalar)
            return flat
        out, i = [], 0
        for w in self._widths:
            out.append(flat[i] if w == 1 else flat[i : i + w])
            i += w
        return tuple(out)

    def _text(self, body: bytes) -> None:
        try:
            n = body[0]
            text = body[1 : 1 + n].decode(errors="replace")
            level = Level(body[2 + n + body[1 + n]])
        except (IndexError, ValueError):
            self.malformed += 1
            return
        self.texts.append((level, text))
        del self.texts[:-64]
