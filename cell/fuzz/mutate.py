"""Seeded mutations of well-formed inputs: byte havoc, as AFL does it, and moves that know each format.

A random byte string dies at the first length or CRC check; a mutated
well-formed input gets past them.  So each input here is a seed from the
format's hypothesis strategy (cell.fuzz.strategies) with one to four
mutations applied, then, for formats with CRCs, the CRCs made right again
most of the time, so that what is checked after the CRC is reached too.
Everything draws from one random.Random: a seed reproduces a run.
"""

from __future__ import annotations

import random

from cell.rlink.packet import crc16
from cell.snp.packet import crc8

INTERESTING_BYTES = (0, 1, 0x7F, 0x80, 0xFF, 0x3A, 0x2C, 0x0D, 0x0A, 0x20, 0xC3, 0xFE)
INTERESTING_INTS = (0, 1, -1, 2**7, 2**8 - 1, 2**15, 2**16 - 1, 2**31 - 1, -(2**31), 2**32 - 1, 2**63 - 1)
# tokens a command line's fields are swapped for: numbers that are not, separators, encodings, sizes
TOKENS = (
    b"nan", b"inf", b"-inf", b"1e308", b"-1e-320", b"-0", b"0x1f", b"1_000", b"", b" ", b"+", b"-", b".",
    b"9" * 400, b"1" * 1100, b"\x00", b"\xff\xfe", "é".encode(), b"\r", b"\n", b"\r\n", b"::", b",,",
    b"move_to", b"break", b"estop", b"resume", b"set_speed", b"all", b"r1", b"00000000", b"%s%n",
)  # fmt: skip


class Mutator:
    def __init__(self, seed: int = 0) -> None:
        self.rng = random.Random(seed)

    def havoc(self, data: bytes, corpus: list[bytes], rounds: int | None = None) -> bytes:
        """One to four byte-level mutations of data (another corpus entry may be spliced in)."""
        rng = self.rng
        buf = bytearray(data)
        for _ in range(rounds or rng.randint(1, 4)):
            op = rng.randrange(8)
            n = len(buf)
            if op == 0 and n:  # flip a bit
                buf[rng.randrange(n)] ^= 1 << rng.randrange(8)
            elif op == 1 and n:  # an interesting byte
                buf[rng.randrange(n)] = rng.choice(INTERESTING_BYTES)
            elif op == 2 and n >= 4:  # an interesting integer over 1, 2, 4 or 8 bytes, either order
                width = rng.choice((1, 2, 4, 8))
                if n >= width:
                    at = rng.randrange(n - width + 1)
                    v = rng.choice(INTERESTING_INTS) % (1 << 8 * width)
                    buf[at : at + width] = v.to_bytes(width, rng.choice(("big", "little")))
            elif op == 3:  # insert random bytes
                at = rng.randint(0, n)
                buf[at:at] = rng.randbytes(rng.randint(1, 16))
            elif op == 4 and n:  # delete a range
                at = rng.randrange(n)
                del buf[at : at + rng.randint(1, 16)]
            elif op == 5 and n:  # duplicate a range
                at = rng.randrange(n)
                buf[at:at] = buf[at : at + rng.randint(1, 32)]
            elif op == 6 and corpus:  # splice with another seed
                other = rng.choice(corpus)
                buf = buf[: rng.randint(0, n)] + other[rng.randint(0, len(other)) :]
            elif op == 7 and n:  # truncate
                del buf[rng.randrange(n) :]
        return bytes(buf)

    def line(self, seed: bytes, corpus: list[bytes]) -> bytes:
        """A command line mutated field by field (split at ':' and ','), or byte by byte; ends in CRLF."""
        rng = self.rng
        if rng.random() < 0.3:
            out = self.havoc(seed, corpus)
        else:
            fields = seed.rstrip(b"\r\n").replace(b",", b":,:").split(b":")
            for _ in range(rng.randint(1, 3)):
                k = rng.randrange(len(fields))
                op = rng.randrange(4)
                if op == 0:
                    fields[k] = rng.choice(TOKENS)
                elif op == 1:
                    del fields[k]
                    if not fields:
                        fields = [b""]
                elif op == 2:
                    fields.insert(k, rng.choice(TOKENS))
                else:
                    fields[k] = fields[k] * rng.randint(2, 40)
            out = b":".join(fields).replace(b":,:", b",")
        return out if out.endswith(b"\r\n") else out + b"\r\n"

    def snp(self, seed: bytes, corpus: list[bytes]) -> bytes:
        """An SnP packet mutated, its two CRCs made right again 3 times in 4."""
        out = self.havoc(seed, corpus)
        return fix_snp_crcs(out) if self.rng.random() < 0.75 else out

    def rlink(self, seed: bytes, corpus: list[bytes]) -> bytes:
        """A Responsive Link packet mutated, its CRC made right again 3 times in 4."""
        out = self.havoc(seed, corpus)
        if len(out) > 2 and self.rng.random() < 0.75:
            out = out[:-2] + crc16(out[:-2]).to_bytes(2, "big")
        return out

    def text(self, seed: str, corpus: list[bytes]) -> str:
        """A config file's text mutated byte by byte (decoded back, undecodable bytes replaced)."""
        return self.havoc(seed.encode(), corpus).decode("utf-8", "replace")


def fix_snp_crcs(raw: bytes) -> bytes:
    """The header and data CRCs of an SnP packet recomputed where its layout says they are."""
    if len(raw) < 3:
        return raw
    head_end = 3 + raw[2] + 8  # dest, pid, nrab, return address, source and destination process
    if len(raw) < head_end + 2:
        return raw
    head = raw[:head_end]
    data = raw[head_end + 1 : -1]
    return head + bytes([crc8(head)]) + data + bytes([crc8(data)])
