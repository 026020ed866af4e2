"""Recording the cell's runs: drawn in Rerun (live.py) and written as a ROS 2 bag (bag.py).

This module holds what both share and imports neither Rerun nor rosbags.
"""

from __future__ import annotations

from collections.abc import Callable

from cell.bus import Envelope, EnvelopeError, Subscription

SPACING = 1.2  # m between robots' bases, side by side along y (the Rerun view, the bag's /tf_static)


def base_position(i: int, n: int) -> tuple[float, float, float]:
    """Where robot i of n stands in the recordings' world frame."""
    return (0.0, (i - (n - 1) / 2) * SPACING, 0.0)


async def each(
    sub: Subscription, handle: Callable[[Envelope], None], after: Callable[[], None] | None = None
) -> None:
    """Hand every message of sub to handle, forever; a payload that does not parse is counted and
    dropped, never the recorder's end.  `after` runs after each batch."""
    while True:
        for env in await sub.recv_batch():
            try:
                handle(env)
            except EnvelopeError:
                sub.malformed += 1
        if after is not None:
            after()
