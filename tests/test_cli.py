"""Every command answers --help; the CLI never prints a bare traceback for user errors."""

from __future__ import annotations

import pytest

from cell.cli import build_parser, main

COMMANDS = [
    [],
    ["up"],
    ["service"],
    ["status"],
    ["config"],
    ["config", "show"],
    ["bench"],
    ["bench", "bus"],
    ["bench", "robots"],
    ["bench", "dataplane"],
    ["bench", "bilateral"],
    ["teleop"],
]


@pytest.mark.parametrize("command", COMMANDS, ids=lambda c: " ".join(c) or "cell")
def test_help(command: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main([*command, "--help"])
    assert info.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: cell")


def test_every_subcommand_is_listed() -> None:
    text = build_parser().format_help()
    for name in ("up", "service", "status", "config", "bench", "teleop"):
        assert f"    {name} " in text


def test_unknown_service_alone(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["service", "nope"]) == 2
    assert "unknown service 'nope'" in capsys.readouterr().err
