"""Forward error correction for a lossy line: each 4-bit nibble as an extended Hamming (8,4) codeword.

The Responsive Link adds 4 redundancy bits to each byte and corrects one-bit
errors in hardware, so that nothing is ever sent again.  Correcting every
single-bit error *and* detecting every double-bit error (SEC-DED) takes an
extended Hamming code, which for 8 data bits needs 5 check bits; with 4 it
is the (8,4) code, so each nibble is sent as one 8-bit codeword: a packet
doubles on the line, every single-bit error in a codeword is corrected, every
double-bit error detected.  Decoding is one 256-entry table lookup per byte.

Codeword bits (LSB first): p1 p2 d1 p4 d2 d3 d4 p0, Hamming positions 1..7
in bits 0..6 and the overall parity p0 in bit 7.
"""

from __future__ import annotations

import numpy as np

_OK, _CORRECTED, _DOUBLE = 0, 1, 2


def _codeword(nibble: int) -> int:
    d1, d2, d3, d4 = (nibble >> i & 1 for i in range(4))
    p1, p2, p4 = d1 ^ d2 ^ d4, d1 ^ d3 ^ d4, d2 ^ d3 ^ d4
    bits = (p1, p2, d1, p4, d2, d3, d4)
    word = sum(b << i for i, b in enumerate(bits))
    return word | (bin(word).count("1") & 1) << 7


ENCODE = np.array([_codeword(n) for n in range(16)], np.uint8)


def _decode_table() -> tuple[np.ndarray, np.ndarray]:
    nibble = np.zeros(256, np.uint8)
    status = np.zeros(256, np.uint8)
    for word in range(256):
        syndrome = 0
        for pos in range(1, 8):  # Hamming positions 1..7 hold bits 0..6
            if word >> (pos - 1) & 1:
                syndrome ^= pos
        parity = bin(word).count("1") & 1
        fixed = word
        if syndrome and parity:  # one error among positions 1..7: flip it
            fixed ^= 1 << (syndrome - 1)
            status[word] = _CORRECTED
        elif syndrome:  # two errors: the parity holds, the syndrome does not
            status[word] = _DOUBLE
        elif parity:  # the overall parity bit itself flipped
            status[word] = _CORRECTED
        d1, d2, d3, d4 = (fixed >> bit & 1 for bit in (2, 4, 5, 6))
        nibble[word] = d1 | d2 << 1 | d3 << 2 | d4 << 3
    return nibble, status


_NIBBLE, _STATUS = _decode_table()


class Uncorrectable(ValueError):
    """A codeword with two (or more, detected as two) bit errors."""


def protect(data: bytes) -> bytes:
    """The line form: two codewords per byte, low nibble first."""
    b = np.frombuffer(data, np.uint8)
    out = np.empty(b.size * 2, np.uint8)
    out[0::2] = ENCODE[b & 0x0F]
    out[1::2] = ENCODE[b >> 4]
    return out.tobytes()


def recover(line: bytes) -> tuple[bytes, int]:
    """The data back and how many bit errors were corrected; Uncorrectable if a codeword had two."""
    if len(line) % 2:
        raise Uncorrectable(f"{len(line)} bytes on the line: codewords come in pairs")
    w = np.frombuffer(line, np.uint8)
    status = _STATUS[w]
    if (status == _DOUBLE).any():
        raise Uncorrectable(f"{int((status == _DOUBLE).sum())} codeword(s) with a double-bit error")
    n = _NIBBLE[w]
    return (n[0::2] | n[1::2] << 4).tobytes(), int((status == _CORRECTED).sum())
