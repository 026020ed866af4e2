"""Every module of the package and of its services imports: a name moved between modules and left
behind in an importer fails here, not in the one service process that imports it."""

from __future__ import annotations

import importlib
import pkgutil

import cell.services
import pytest

import cell

MODULES = sorted(
    m.name
    for pkg in (cell, cell.services)
    for m in pkgutil.walk_packages(pkg.__path__, pkg.__name__ + ".")
    if m.name != "cell.__main__"  # (it runs the command line)
)


def test_the_walk_finds_the_house() -> None:
    assert {"cell.robot.node", "cell.snp.link", "cell.models.ur", "cell.services.robots"} <= set(MODULES)


@pytest.mark.parametrize("name", MODULES)
def test_each_module_imports(name: str) -> None:
    assert importlib.import_module(name).__name__ == name
