"""The data plane's backends: [dataplane] backend -> the DataPlane class that runs it.

Each is looked up when it is used: the native one builds its C on first use, which a cell that runs
another backend never pays for.
"""

from __future__ import annotations

from collections.abc import Callable

from cell.dataplane.plane import DataPlane, XdpDataPlane


def _native() -> type[DataPlane]:
    from cell.dataplane.native import NativeDataPlane  # (lazy: builds its C on first use)

    return NativeDataPlane


BACKENDS: dict[str, Callable[[], type[DataPlane]]] = {
    "numpy": lambda: DataPlane,
    "native": _native,
    "xdp": lambda: XdpDataPlane,
}
