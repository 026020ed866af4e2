"""Every command answers --help; the CLI never prints a bare traceback for user errors."""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
from pathlib import Path

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


@pytest.mark.slow
def test_what_a_user_gets_wrong_is_one_line_and_its_exit_code(tmp_path) -> None:
    """No traceback for anything but a bug: no cell to talk to, a robot that is not there, a negative
    time, a reader that stops reading."""

    from tests.conftest import cell_env, cell_overrides, free_port, run_cell, write_config

    # a config whose bus nobody serves (free ports), so that "no cell" is certain
    data = cell_overrides(run=["bus"])
    data["bus"] = {"pub": f"tcp://127.0.0.1:{free_port()}", "sub": f"tcp://127.0.0.1:{free_port()}"}
    cfg = str(write_config(tmp_path / "c.toml", data))
    script = tmp_path / "s.py"
    script.write_text("async def main(cell):\n    pass\n")
    for argv, rc, words in (
        (["run", str(script)], 1, "cell run: no cell answered (no bus forwarder answered"),
        (["estop", "99"], 2, "cell estop: no robot '99' in this cell (robots: r1 (1), r2 (2))"),
        (["estop", "--timeout", "-5"], 2, "argument --timeout: must be > 0 s (got -5)"),
        (["up", "--duration", "-1"], 2, "argument --duration: must be > 0 s (got -1)"),
    ):
        got = run_cell(*argv, "--config", cfg, timeout=60)
        assert got.returncode == rc and words in got.stderr, (argv, got.returncode, got.stderr[-2000:])
        assert "Traceback" not in got.stderr, got.stderr
    if True:  # a reader that stops after one line (`cell config show | head -1`): no BrokenPipeError
        proc = subprocess.Popen(
            [sys.executable, "-m", "cell", "config", "show"], env=cell_env(), stdout=subprocess.PIPE,
            stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        assert proc.stdout is not None and proc.stdout.readline().startswith("# effective configuration")
        proc.stdout.close()
        _, err = proc.communicate(timeout=60)
        assert proc.returncode in (0, 141) and "Traceback" not in err, err


@pytest.mark.slow
def test_a_clean_stop_says_nothing_of_the_bus_going_away(tmp_path) -> None:
    """At a clean stop the bus goes as everything goes: no service warns that it dropped (each used to,
    twice, which read as a failure)."""
    from tests.conftest import cell_env, cell_overrides, write_config

    path = write_config(tmp_path / "c.toml", cell_overrides())  # the default cell, in its process groups
    # stopped once it says it is up (a fixed --duration of 3 s once ended a loaded CI host's cell
    # before its groups were up); killed if it never says so
    proc = subprocess.Popen(
        [sys.executable, "-m", "cell", "up", "--config", str(path)],
        env=cell_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    watchdog = threading.Timer(60, proc.kill)
    watchdog.start()
    try:
        assert proc.stderr is not None
        head = []
        for line in proc.stderr:
            head.append(line)
            if "is up in" in line:
                break
        proc.send_signal(signal.SIGTERM)
        _, rest = proc.communicate(timeout=30)
    finally:
        watchdog.cancel()
        if proc.poll() is None:
            proc.kill()
    err = "".join(head) + rest
    assert proc.returncode == 0, err[-2000:]
    assert "is up in" in err, err[-2000:]  # (its log is there ...)
    assert "the bus connection dropped" not in err and " WARNING " not in err, err[-3000:]


def test_every_package_of_cell_is_in_the_packaging() -> None:
    """pyproject.toml lists the packages by hand (services/ installs as cell.services): one left out is
    missing from a wheel, and pip warns about it at every install."""
    import tomllib

    root = Path(__file__).resolve().parents[2]
    listed = set(tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = {".".join(p.parent.relative_to(root).parts) for p in (root / "cell").rglob("__init__.py")}
    assert found <= listed, sorted(found - listed)
