"""Line framing for the text protocols (the skill servers' \\r\\n, the UR dashboard's and URScript's
\\n), sans IO: bytes in, complete lines out; an overlong line comes out once as TooLong, as soon as it
is known to be too long, and the rest of it is dropped."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class TooLong:
    """A line over the limit (its first bytes, e.g. for a command's id), skipped up to its end."""

    head: bytes


class LineReader:
    def __init__(self, max_line: int, sep: bytes = b"\r\n") -> None:
        self.max_line, self.sep = max_line, sep
        self._buf = bytearray()
        self._skipping = False  # inside an overlong line: drop bytes up to its separator

    @property
    def partial(self) -> bool:
        """A line has begun (or an overlong one is being skipped) and its separator has not come."""
        return self._skipping or bool(self._buf.strip())

    def feed(self, data: bytes) -> list[bytes | TooLong]:
        self._buf += data
        out: list[bytes | TooLong] = []
        sep, at = self.sep, 0
        while (end := self._buf.find(sep, at)) >= 0:  # (read off by position, cut once: no copy a line)
            line = bytes(self._buf[at:end])
            at = end + len(sep)
            if self._skipping:
                self._skipping = False  # the end of the overlong line: already refused
                continue
            out.append(TooLong(line[:16]) if len(line) > self.max_line else line)
        del self._buf[:at]
        keep = len(sep) - 1  # (the last bytes may be the start of a separator split between reads)
        if len(self._buf) > self.max_line + keep:
            if not self._skipping:
                self._skipping = True
                out.append(TooLong(bytes(self._buf[:16])))
            del self._buf[: len(self._buf) - keep]
        return out
