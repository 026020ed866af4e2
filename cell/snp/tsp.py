"""SnP-TSP as a protocol, sans IO: the master's time beacons and each node's clock servo.

A node asks the master for beacons (TIME_SUBSCRIBE: a period and the precision it wants); the
master sends each subscriber a TIME_BEACON with its own clock as the beacon leaves, at the
period granted.  The node measures the path delay with the two-way exchange (TIME_REQUEST /
TIME_RESPONSE, the shortest round trip kept) and fits its clock to the last beacons (rate
and offset; see ClockServo).

Times here are integers (ns) passed in: a node's `raw` clock is its own oscillator, which
runs at its own rate and from its own origin; the servo maps raw to the master's time.
"""

from __future__ import annotations

from collections import Counter, deque
from dataclasses import dataclass, field

MIN_PERIOD_NS = 1_000_000  # the fastest beacons the master grants (1 kHz)


class ClockServo:
    """A node's clock, servoed to the master's beacons: now(raw) is the master's time.

    Each beacon gives a point (raw at arrival, master time at arrival = its send time plus the
    path delay); the clock is the least-squares line through the last `window` points (rate
    and offset at once), fitted again without the points the network held up: queueing only
    ever delays a beacon, so those sit below the line and are left out (as NTP's clock filter
    keeps its least-delayed samples).  A PI servo on single beacons was tried first: with a
    10 ms beacon period, 15 us of queueing jitter kicked its rate by hundreds of ppm."""

    def __init__(self, window: int = 32) -> None:
        self.window = window
        self.anchor_raw = 0  # raw time of the last fit
        self.base = 0  # master time at anchor_raw
        self.rate = 0.0  # fractional rate correction: master ns per raw ns - 1
        self.delay_ns = 0  # the one-way path delay, from the shortest two-way exchange
        self._best_rtt: int | None = None
        self._points: deque[tuple[int, int]] = deque(maxlen=window)
        self.samples = 0
        self.last_error_ns = 0  # the master's time minus ours at the last beacon, before fitting

    def now(self, raw: int) -> int:
        """The master's time now, by this node's servoed clock."""
        return self.base + round((raw - self.anchor_raw) * (1.0 + self.rate))

    def to_raw(self, master_ns: int) -> int:
        """When (raw) this node's clock will read master_ns: for waking up on the master's grid."""
        return self.anchor_raw + round((master_ns - self.base) / (1.0 + self.rate))

    def exchange(self, t1: int, t2: int, t3: int, t4: int) -> None:
        """A TIME_REQUEST / TIME_RESPONSE: t1, t4 raw on this node; t2, t3 the master's.  Keeps the
        delay of the shortest round trip (the least queued); the clock comes from the beacons."""
        rtt = (t4 - t1) - (t3 - t2)
        if self._best_rtt is None or rtt < self._best_rtt:
            self._best_rtt = rtt
            self.delay_ns = max(0, rtt // 2)
        if self.samples == 0:  # no beacon yet: start from the exchange's offset
            self.anchor_raw, self.base = t4, t3 + self.delay_ns

    def beacon(self, raw_rx: int, t_master: int) -> int:
        """A beacon that left the master at t_master came in at raw_rx; returns the error (ns)."""
        arrived = t_master + self.delay_ns
        err = arrived - self.now(raw_rx)
        self.last_error_ns = err
        self._points.append((raw_rx, arrived))
        self.samples += 1
        if len(self._points) < 2:
            self.anchor_raw, self.base = raw_rx, arrived
            return err
        x = [float(r - raw_rx) for r, _ in self._points]
        y = [float(m - r) for r, m in self._points]  # master - raw: slope the rate, value the offset
        a, b = _line(x, y)
        if len(x) >= 8:  # leave out the held-up beacons (below the line) and fit again
            r = [yi - (a + b * xi) for xi, yi in zip(x, y, strict=True)]
            q = sorted(r)
            med, q1 = q[len(q) // 2], q[len(q) // 4]
            lo = med - 2.0 * (med - q1) - 200.0  # (median - 2 IQR/2)
            keep = [i for i, ri in enumerate(r) if ri >= lo]
            if len(keep) >= 4:
                a, b = _line([x[i] for i in keep], [y[i] for i in keep])
        self.rate = b
        self.anchor_raw, self.base = raw_rx, raw_rx + round(a)
        return err


def _line(x: list[float], y: list[float]) -> tuple[float, float]:
    """Least squares y = a + b x, in closed form (plain floats: for 32 points numpy's per-call
    cost is ten times the arithmetic, and np.polyfit ten times that)."""
    n = len(x)
    mx, my = sum(x) / n, sum(y) / n
    sxx = sxy = 0.0
    for xi, yi in zip(x, y, strict=True):
        dx = xi - mx
        sxx += dx * dx
        sxy += dx * (yi - my)
    b = sxy / sxx if sxx else 0.0
    return my - b * mx, b


class Oscillator:
    """A node's own clock as a real module would have it: its origin and rate off the master's
    (drift in ppm), read from a true clock (the host's, which is the master's here)."""

    def __init__(self, offset_ns: int, drift_ppm: float, true_origin: int) -> None:
        self.offset_ns, self.drift, self.origin = offset_ns, drift_ppm * 1e-6, true_origin

    def raw(self, true_ns: int) -> int:
        return self.origin + self.offset_ns + round((true_ns - self.origin) * (1.0 + self.drift))

    def true(self, raw_ns: int) -> int:
        """The true time at which this oscillator reads raw_ns (to sleep until it)."""
        return self.origin + round((raw_ns - self.origin - self.offset_ns) / (1.0 + self.drift))


def on_grid(t: int, grid: tuple[int, int]) -> int:
    """The first point of grid (period, offset) at or after t."""
    period, offset = grid
    return t + (offset - t) % period


@dataclass(order=True)
class _Subscriber:
    due: int
    addr: object = field(compare=False)
    period_ns: int = field(compare=False)
    seq: int = field(default=0, compare=False)


class BeaconSchedule:
    """The master's side: who asked for beacons at what period, and whose are due.

    grid: (period, offset) of the master's time at which beacons may leave (its cycle's
    management slot, clear of the joints' exchanges; None: whenever due).  Periods are then
    granted in whole grid periods, and each new subscriber gets the grid point within its period
    that the fewest subscribers of that period share, so that one cycle period carries one
    subscriber's beacon rather than all of them."""

    def __init__(self, precision_ns: int = 50_000, grid: tuple[int, int] | None = None) -> None:
        self.precision_ns = precision_ns  # what the master's beacons give (its send jitter)
        self.grid = grid
        self._subs: dict[object, _Subscriber] = {}

    def subscribe(self, addr: object, period_ns: int, now: int) -> int:
        """The period granted (at least MIN_PERIOD_NS, whole grid periods); 0 removes the
        subscription."""
        if period_ns == 0:
            self._subs.pop(addr, None)
            return 0
        granted = max(MIN_PERIOD_NS, period_ns)
        self._subs.pop(addr, None)
        due = now
        if self.grid is not None:
            g = self.grid[0]
            granted = -(-granted // g) * g
            first, n = on_grid(now, self.grid), granted // g
            taken = Counter((s.due - first) // g % n for s in self._subs.values() if s.period_ns == granted)
            due = first + g * min(range(n), key=lambda k: (taken[k], k))
        self._subs[addr] = _Subscriber(due, addr, granted)
        return granted

    def drop(self, addr: object) -> None:
        self._subs.pop(addr, None)

    def due(self, now: int) -> list[tuple[object, int]]:
        """(subscriber, beacon seq) for each beacon due by now; their next ones are scheduled."""
        out = []
        for s in self._subs.values():
            if s.due <= now:
                s.seq += 1
                out.append((s.addr, s.seq))
                s.due += s.period_ns * max(1, (now - s.due) // s.period_ns + 1)
        return out

    def next_due(self) -> int | None:
        return min((s.due for s in self._subs.values()), default=None)

    def __len__(self) -> int:
        return len(self._subs)
