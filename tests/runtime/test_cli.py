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


def test_every_registered_command_and_bench_has_its_help(capsys: pytest.CaptureFixture[str]) -> None:
    """Commands and benches register themselves; each is listed, and its help prints as written (a
    '%' in a help line had printed argparse's own state into it)."""
    from cell.bench.registry import discover as benches
    from cell.commands import discover as commands

    registered = [[name] for name in commands()] + [["bench", name] for name in benches()]
    assert {"bus", "dataplane", "accuracy", "snp", "rlink", "bilateral", "paper"} <= set(benches())
    for command in registered:
        with pytest.raises(SystemExit) as info:
            main([*command, "--help"])
        assert info.value.code == 0
        out = capsys.readouterr().out
        assert out.startswith(f"usage: cell {' '.join(command)}"), command
    with pytest.raises(SystemExit):
        main(["bench", "--help"])
    out = capsys.readouterr().out
    assert "option_strings" not in out and "< 0.1% late sends" in " ".join(out.split())


def test_unknown_service_alone(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["service", "nope"]) == 2
    assert "unknown service 'nope'" in capsys.readouterr().err


def test_config_show_prints_each_arms_ur_address_resolved(capsys: pytest.CaptureFixture[str]) -> None:
    import tomllib

    assert main(["config", "show"]) == 0
    data = tomllib.loads(capsys.readouterr().out)
    assert [r["ur_address"] for r in data["robots"]] == ["127.0.1.1", "127.0.1.2"]  # r1, r2 (default "")
