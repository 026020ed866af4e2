"""The data plane's backend registry: each backend the config knows (cell.config.DATAPLANE_BACKENDS:
what it is) has the class that runs it (cell.dataplane.backends), and what it says of itself holds."""

from __future__ import annotations

from cell.config import DATAPLANE_BACKENDS, load_config
from cell.dataplane.backends import BACKENDS
from cell.dataplane.native import NativeDataPlane
from cell.dataplane.plane import DataPlane, XdpDataPlane


def test_every_backend_has_its_class_and_says_what_it_is() -> None:
    assert set(BACKENDS) == set(DATAPLANE_BACKENDS) == {"numpy", "native", "xdp"}
    runs = {name: BACKENDS[name]() for name in BACKENDS}
    assert runs == {"numpy": DataPlane, "native": NativeDataPlane, "xdp": XdpDataPlane}
    kernel = [b.name for b in DATAPLANE_BACKENDS.values() if b.in_kernel]
    batched = [b.name for b in DATAPLANE_BACKENDS.values() if b.batched]
    forwards = [b.name for b in DATAPLANE_BACKENDS.values() if b.forwards]
    assert kernel == ["xdp"] and batched == ["numpy"] and forwards == ["numpy"]


def test_the_config_names_the_backend_that_runs() -> None:
    dp = load_config(None).dataplane
    assert dp.runs is DATAPLANE_BACKENDS[dp.chosen()[0]]
