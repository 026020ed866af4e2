"""Arithmetic the way a P4 switch does it: match tables instead of multipliers (NSDI'22, Sec. 5.3-5.4).

Transform tables approximate x -> c*x with a ternary/longest-prefix match on
the n most significant bits after the leading 1 (for negative x: after the
leading 0, i.e. on ~x), ignoring the bits below; each entry returns c times
the middle of the range it covers, so the relative error is at most 2^-n
(the paper's bound is 1/2^(n-1)).  LimitVelocity decides x > c and x < -c
with at most one prefix entry per bit of the constant, as in Sec. 5.4.

Everything here is integer arithmetic on the wire's fixed-point values; the
floats only appear when a table is generated from its constant.
"""

from __future__ import annotations

import numpy as np

WORD = 64


def bit_length(y: np.ndarray) -> np.ndarray:
    """Bit length of non-negative int64 values: where a TCAM's leading-one match lands.

    The float64 exponent gives it in one vector operation (y = m 2^e, 1/2 <= m < 1);
    above 2^53 the conversion may round y up to the next power of two, which shows
    as bit e-1 not being set, and is taken back.  Exact for every int64 >= 0, and a
    few operations instead of a binary search's two dozen: most of a small batch's cost.
    """
    e = np.frexp(y.astype(np.float64))[1].astype(np.int64)
    rounded_up = (y >> np.maximum(e - 1, 0)) == 0
    rounded_up &= e > 0
    return e - rounded_up


def table_index(x: np.ndarray, n: int) -> np.ndarray:
    """The Transform entry matching each int64 x, as (sign * entries_per_sign + index).

    Key: the sign, then the bit length b of y (y = x, or ~x for x < 0) and the n
    leading significant bits p = y >> (b - n); values with b <= n are matched
    exactly.  Entries run [exact 0 .. 2^n), then 2^(n-1) per bit length above n,
    so the index is p + (b - n) 2^(n-1) (p itself when b <= n).
    """
    y = x ^ (x >> 63)  # ~x where x < 0
    shift = np.maximum(bit_length(y) - n, 0)
    idx = (y >> shift) + shift * (1 << (n - 1))
    idx += (x < 0) * entries_per_sign(n)
    return idx


def entries_per_sign(n: int) -> int:
    return (1 << n) + (WORD - 1 - n) * (1 << (n - 1))


class TransformTable:
    """x -> round(c * x) for int64 x, approximated by (2^n + (63 - n) 2^(n-1)) entries per sign.

    Entry key: (sign, bit length b, the n leading significant bits p).  Values
    with b <= n are matched exactly.
    """

    def __init__(self, c: float, n_bits: int) -> None:
        if not 2 <= n_bits <= 16:
            raise ValueError(f"n_bits must be 2..16 (got {n_bits})")
        self.c = float(c)
        self.n = n = n_bits
        self.half = h = 1 << (n - 1)
        exact = np.arange(1 << n, dtype=np.float64)  # |key| < 2^n: the value itself
        rows = [exact]
        for b in range(n + 1, WORD):  # bit lengths n+1 .. 63
            shift = b - n
            p = np.arange(h, 2 * h, dtype=np.float64)
            rows.append(p * 2.0**shift + 2.0 ** (shift - 1))  # the middle of [p << s, (p+1) << s)
        reps = np.concatenate(rows)  # representative of each entry, for y = x (x >= 0) or y = ~x (x < 0)
        pos = np.rint(self.c * reps)
        neg = np.rint(self.c * (-reps - 1.0))  # x = ~y = -y - 1
        limit = float(2**62)
        self.table = np.clip(np.stack([pos, neg]), -limit, limit).astype(np.int64)

    @property
    def entries(self) -> int:
        return self.table.size

    def __call__(self, x: np.ndarray) -> np.ndarray:
        return self.table.reshape(-1)[table_index(np.asarray(x, np.int64), self.n)]


def prefix_entries(c: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Ternary (value, mask) entries matching x > c and x < -c for int64 x (0 <= c < 2^62).

    x > c: x has the sign bit 0 and, at the first bit where it differs from c,
    a 1 where c has a 0: one entry per 0 bit of c.  x < -c: in two's
    complement, negatives order like their bit patterns, so one entry per 1
    bit of -c, with a 0 there (and for c = 0, the sign bit).  At most 63 entries each.
    """
    if not 0 <= c < 2**62:
        raise ValueError(f"limit {c} out of range")
    hi_v, hi_m, lo_v, lo_m = [], [], [], []
    d = (-c) & (2**64 - 1)
    cu = c
    for i in range(62, -1, -1):
        mask = (2**64 - 1) ^ ((1 << i) - 1)  # bits 63..i
        above = (2**64 - 1) ^ ((1 << (i + 1)) - 1)  # bits 63..i+1
        if not (cu >> i) & 1:
            hi_v.append((cu & above) | (1 << i))
            hi_m.append(mask)
        if (d >> i) & 1:
            lo_v.append(d & above)
            lo_m.append(mask)

    if c == 0:  # -0 has no 1 bits: x < 0 is exactly "the sign bit is set"
        lo_v.append(1 << 63)
        lo_m.append(1 << 63)

    def arr(v: list[int]) -> np.ndarray:
        return np.array(v, np.uint64).view(np.int64)

    return arr(hi_v), arr(hi_m), arr(lo_v), arr(lo_m)


class LimitVelocity:
    """Per-joint velocity limits as prefix tables: |out| <= limit for every int64 input.

    Entries are stored by the bit they end at (the one where x first differs from
    the constant), so a lookup goes straight to the only entry that can match,
    found from bit_length(x ^ constant) as an LPM engine's walk would find it,
    and checks that entry's (value, mask): one candidate per side, not 63.
    """

    def __init__(self, limits: np.ndarray) -> None:
        self.limits = np.asarray(limits, np.int64)
        joints = len(self.limits)
        # entry ending at bit i (0..63); a missing entry (mask 0, value 1) never matches
        self.hi_v = np.ones((joints, WORD), np.int64)
        self.hi_m = np.zeros((joints, WORD), np.int64)
        self.lo_v = np.ones((joints, WORD), np.int64)
        self.lo_m = np.zeros((joints, WORD), np.int64)
        self.neg = np.zeros(joints, np.int64)  # -limit, as the negative side's entries are cut from it
        self.entries = 0
        for j, c in enumerate(self.limits):
            hv, hm, lv, lm = prefix_entries(int(c))
            for vals, masks, tv, tm in ((hv, hm, self.hi_v, self.hi_m), (lv, lm, self.lo_v, self.lo_m)):
                for v, m in zip(vals.tolist(), masks.tolist(), strict=True):
                    bit = _lowest_bit(m)
                    tv[j, bit], tm[j, bit] = v, m
            self.neg[j] = -int(c)
            self.entries += hv.size + lv.size

    def __call__(self, x: np.ndarray, joint: np.ndarray) -> np.ndarray:
        x = np.asarray(x, np.int64)
        c, d = self.limits[joint], self.neg[joint]
        # the one entry per side that can match: the bit where x first differs from the constant
        # (both sides in one pass; a differing sign bit is bit 63)
        z = np.concatenate([x ^ c, x ^ d])
        neg = z < 0
        bit = np.maximum(bit_length(np.where(neg, 0, z)) - 1, 0)
        bit[neg] = WORD - 1
        hi, lo = bit[: x.size], bit[x.size :]
        over = (x & self.hi_m[joint, hi]) == self.hi_v[joint, hi]
        under = (x & self.lo_m[joint, lo]) == self.lo_v[joint, lo]
        return np.where(over, c, np.where(under, d, x))


def _lowest_bit(mask: int) -> int:
    return (mask & -mask).bit_length() - 1 if mask else 0
