"""Config: the embedded default, merging, and errors that name the key and the file."""

from __future__ import annotations

import os
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from cell.config import DEFAULT_SOURCE, ConfigError, config_from_dict, load_config
from tests.conftest import ROOT, run_cell


def test_embedded_default_is_the_two_robotrun_cell() -> None:
    cfg = load_config()
    assert cfg.source == DEFAULT_SOURCE
    assert [(r.id, r.name, r.skill_port) for r in cfg.robots] == [(1, "r1", 1234), (2, "r2", 1235)]
    r1 = cfg.robot("r1")
    assert (r1.model, r1.backend, r1.status_hz, r1.command_hz) == ("ur5e", "mujoco", 500, 125)
    assert cfg.dataplane.listen == "127.0.0.1:50000"
    assert cfg.snp.listen == "127.0.0.1:50010"


def test_default_binds_loopback_only() -> None:
    cfg = load_config()
    for endpoint in (cfg.bus.pub, cfg.bus.sub, cfg.dataplane.listen, cfg.snp.listen):
        assert "127.0.0.1" in endpoint


def test_file_merges_over_default(tmp_path: Path) -> None:
    path = tmp_path / "c.toml"
    path.write_text(
        '[bus]\nhwm = 5\n[robot_defaults]\nbackend = "kinematic"\n'
        '[[robots]]\nid = 7\nname = "arm"\nskill_port = 2000\n'
    )
    cfg = load_config(path)
    assert cfg.source == str(path)
    assert cfg.bus.hwm == 5
    assert cfg.bus.pub == load_config().bus.pub  # untouched keys keep the default
    assert [(r.id, r.name, r.backend, r.status_hz) for r in cfg.robots] == [(7, "arm", "kinematic", 500)]


def test_config_show_round_trips() -> None:
    cfg = load_config()
    assert config_from_dict(tomllib.loads(cfg.to_toml())) == cfg


@pytest.mark.parametrize(
    ("toml", "key", "problem"),
    [
        ("[bus]\nspeed = 1\n", "bus.speed", "unknown key"),
        ("colour = 1\n", "colour", "unknown key"),
        ('[[robots]]\nid = 1\nname = "a"\nskill_port = 1\nspeed = 3\n', "robots[0].speed", "unknown key"),
        ('[bus]\nhwm = "lots"\n', "bus.hwm", "must be an integer"),
        ("[bus]\nhwm = -1\n", "bus.hwm", "must be > 0"),
        ('[bus]\npub = "udp://x"\n', "bus.pub", "tcp://HOST:PORT or ipc://PATH"),
        ('[bus]\npub = "tcp://127.0.0.1:50031"\n', "bus.sub", "must differ"),
        ('[dataplane]\nlisten = "127.0.0.1"\n', "dataplane.listen", "HOST:PORT"),
        ('[dataplane]\nlisten = "my.host:5"\n', "dataplane.listen", "IP address"),
        ('[services]\non_failure = "ignore"\n', "services.on_failure", "one of 'restart', 'stop'"),
        ('[services]\nrun = ["bus", "bus"]\n', "services.run", "twice"),
        ('[services.plugins]\nx = "nocolon"\n', "services.plugins.x", "package.module:attribute"),
        ('[[robots]]\nid = 70000\nname = "a"\nskill_port = 1\n', "robots[0].id", "1..65535"),
        ('[[robots]]\nid = 1\nname = "A b"\nskill_port = 1\n', "robots[0].name", "lowercase"),
        (
            '[[robots]]\nid = 1\nname = "a"\nskill_port = 1\nbackend = "gazebo"\n',
            "robots[0].backend",
            "one of",
        ),
        ('[[robots]]\nid = 1\nname = "a"\nskill_port = 1\ncommand_hz = 1000\n', "robots[0].command_hz", "<="),
        (
            '[[robots]]\nid = 1\nname = "a"\nskill_port = 1\n'
            '[[robots]]\nid = 1\nname = "b"\nskill_port = 2\n',
            "robots[1].id",
            "used by another robot",
        ),
        ("[[robots]]\nid = 1\n", "robots[0].name", "missing"),
        ("robots = 3\n", "robots", "must be an array"),
        ('[services]\nlayout = "threads"\n', "services.layout", "one of 'groups', 'single', 'each'"),
        (
            '[[services.groups]]\nname = "rt"\nservices = ["robots"]\nrt_priority = 120\n',
            "services.groups[0].rt_priority",
            "1..99",
        ),
        (
            '[[services.groups]]\nname = "rt"\nservices = ["robots"]\nnice = -40\n',
            "services.groups[0].nice",
            "-20..19",
        ),
        (
            '[[services.groups]]\nname = "rt"\nservices = ["robots"]\ncpus = [-1]\n',
            "services.groups[0].cpus",
            ">= 0",
        ),
        ('[[services.groups]]\nname = "main"\nservices = ["robots"]\n', "services.groups[0].name", "'main'"),
        (
            '[[services.groups]]\nname = "far"\nservices = ["controller"]\nbus_pub = "tcp://127.0.0.1:1"\n',
            "services.groups[0].bus_pub",
            "go together",
        ),
        (
            '[[services.groups]]\nname = "b"\nservices = ["bus"]\nbus_pub = "tcp://h:1"\nbus_sub = "tcp://h:2"\n',
            "services.groups[0].bus_pub",
            "binds [bus] pub/sub itself",
        ),
        ('[[services.groups]]\nname = "rt"\nservices = []\n', "services.groups[0].services", "at least one"),
        (
            '[[services.groups]]\nname = "a"\nservices = ["robots"]\n'
            '[[services.groups]]\nname = "b"\nservices = ["robots", "snp"]\n',
            "services.groups[1].services",
            "in group 'a' already",
        ),
        (
            '[[services.groups]]\nname = "a"\nservices = ["robots"]\n'
            '[[services.groups]]\nname = "a"\nservices = ["snp"]\n',
            "services.groups[1].name",
            "used by another group",
        ),
    ],
)
def test_bad_config_names_key_and_file(tmp_path: Path, toml: str, key: str, problem: str) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(toml)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert info.value.key == key
    assert problem in info.value.problem
    assert str(path) in str(info.value)


def test_invalid_toml_and_missing_file(tmp_path: Path) -> None:
    path = tmp_path / "broken.toml"
    path.write_text("[bus\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(path)
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path / "nope.toml")


@pytest.mark.parametrize(
    "command", [["config", "show"], ["up", "--duration", "1"], ["status"], ["bench", "headroom", "--quick"]]
)
def test_cli_exits_2_naming_key_and_file(tmp_path: Path, command: list[str]) -> None:
    path = tmp_path / "bad.toml"
    path.write_text("[robot_defaults]\nstatus_hz = 0\n")
    result = run_cell(*command, "--config", str(path))
    assert result.returncode == 2
    assert "robot_defaults.status_hz" in result.stderr
    assert str(path) in result.stderr
    assert "Traceback" not in result.stderr


def test_unknown_service_is_a_config_error(tmp_path: Path) -> None:
    path = tmp_path / "c.toml"
    path.write_text('[services]\nrun = ["bus", "telepathy"]\n')
    result = run_cell("up", "--duration", "1", "--config", str(path))
    assert result.returncode == 2
    assert "unknown service 'telepathy'" in result.stderr
    assert "services.run" in result.stderr


def test_config_show_prints_effective_toml(tmp_path: Path) -> None:
    path = tmp_path / "c.toml"
    path.write_text("[bus]\nhwm = 77\n")
    result = run_cell("config", "show", "--config", str(path))
    assert result.returncode == 0
    shown = tomllib.loads(result.stdout)
    assert shown["bus"]["hwm"] == 77
    assert shown["robots"][1]["name"] == "r2"


def test_a_process_group_inherits_what_it_leaves_out(tmp_path: Path) -> None:
    path = tmp_path / "c.toml"
    path.write_text(
        "[services.group_defaults]\nnice = 5\n"
        '[[services.groups]]\nname = "physics"\nservices = ["robots"]\ncpus = [0]\n'
    )
    (g,) = load_config(path).services.groups  # the array replaces the default's whole
    assert (g.name, g.services, g.cpus, g.rt_priority, g.nice) == ("physics", ["robots"], [0], 0, 5)


def test_the_default_layout_gives_the_packet_path_real_time_processes() -> None:
    groups = {g.name: g for g in load_config().services.groups}
    assert load_config().services.layout == "groups"
    assert groups["robots"].services == ["robots", "rlink"] and groups["dataplane"].services == ["dataplane"]
    # the robots preempt the data plane, and both preempt everything else (SCHED_FIFO > normal)
    assert groups["robots"].rt_priority > groups["dataplane"].rt_priority > 0


def test_a_group_may_reach_the_bus_through_other_endpoints(tmp_path: Path) -> None:
    from cell.layout import process_for

    path = tmp_path / "c.toml"
    path.write_text(
        '[[services.groups]]\nname = "far"\nservices = ["controller"]\n'
        'bus_pub = "tcp://10.0.0.2:6000"\nbus_sub = "tcp://10.0.0.2:6001"\n'
    )
    config = load_config(path)
    far = process_for(config, ["controller"]).config_for(config)
    assert (far.bus.pub, far.bus.sub) == ("tcp://10.0.0.2:6000", "tcp://10.0.0.2:6001")
    assert far.bus.hwm == config.bus.hwm  # the rest of [bus] as it was
    near = process_for(config, ["skills"]).config_for(config)
    assert near.bus == config.bus


PLANT = ROOT / "deploy" / "plant.toml"


def test_a_plant_file_gives_each_host_its_services_robots_and_certificate() -> None:
    a = load_config(PLANT, overrides={"cell": {"host": "a"}})
    b = load_config(PLANT, overrides={"cell": {"host": "b"}})
    assert "bus" in a.services.run and b.services.run == ["robots"]
    assert (a.bus.client, b.bus.client) == ("a", "b")
    assert [r.name for r in a.local_robots()] == ["r1"] and [r.name for r in b.local_robots()] == ["r2"]
    assert [r.name for r in b.rlink_robots()] == ["r1"]  # the hub's host's robots report to it
    assert a.here().address == "10.0.0.1"
    assert load_config().local_robots() == load_config().robots  # one host: every robot is its


@pytest.mark.parametrize(
    ("change", "key", "problem"),
    [
        ({"cell": {"host": ""}}, "cell.host", "must name this host, one of a, b"),
        ({"cell": {"host": "c"}}, "cell.host", "'c' is not one of a, b"),
        ({"dataplane": {"listen": "10.0.0.2:50000"}}, "dataplane.listen", "must bind that host's address"),
        ({"skills": {"host": "127.0.0.1"}}, "skills.host", "must bind that host's address 10.0.0.1"),
        ({"hosts": {"b": {"run": ["robots", "snp"]}}}, "hosts.b.run", "'snp' runs on host 'a' already"),
        ({"hosts": {"b": {"run": ["vision"]}}}, "robots[1].host", "does not run service 'robots'"),
    ],
)
def test_a_plant_file_that_cannot_work_is_refused(change: dict, key: str, problem: str) -> None:
    with pytest.raises(ConfigError) as info:
        load_config(PLANT, overrides={"cell": {"host": "a"}} | change)
    assert info.value.key == key and problem in info.value.problem, info.value


def test_a_neighbours_cd_on_the_running_cycle_must_run_out_to_the_tip() -> None:
    with pytest.raises(ConfigError) as info:
        load_config(overrides={"modular": {"transport": "cycle", "where": ["neighbour"] + ["local"] * 5}})
    assert info.value.key == "modular.where" and "must run out to the tip" in info.value.problem
    ok = ["master", "local", "master", "neighbour", "neighbour", "neighbour"]
    assert load_config(overrides={"modular": {"transport": "cycle", "where": ok}}).modular.where == ok
    with pytest.raises(ConfigError) as info:  # (the routers carry the SnP cycle's own processes)
        load_config(overrides={"modular": {"transport": "memory", "network": "routed"}})
    assert info.value.key == "modular.network" and 'transport "cycle"' in info.value.problem
    # (in process, VdcArm takes any mix)
    assert load_config(overrides={"modular": {"where": ["neighbour"] + ["local"] * 5}}).modular.where[0]


def test_robots_name_no_host_in_a_cell_of_one() -> None:
    with pytest.raises(ConfigError) as info:
        load_config(overrides={"robot_defaults": {"host": "a"}})
    assert info.value.key == "robots[0].host" and "no [hosts]" in info.value.problem


def test_status_names_a_service_by_host_and_a_restart_counts_only_on_its_own() -> None:
    from cell.status import StatusRegistry
    from cell.v1 import health_pb2

    a = load_config(PLANT, overrides={"cell": {"host": "a"}})
    reg = StatusRegistry.of(a)
    assert "robots@a" in reg.expected and "robots@b" in reg.expected and "bus@a" in reg.expected
    ok = health_pb2.SERVICE_STATE_RUNNING
    for host, pid in (("a", 10), ("b", 20)):  # both hosts run a process named "robots"
        hb = health_pb2.Heartbeat(
            service="robots", host=host, pid=pid, state=ok, process="robots", interval_s=5
        )
        reg.observe(hb)
    reg.process_restarted("robots", "process 'robots' exited with code -9")
    by = {s.name: s for s in reg.status().services}
    assert (by["robots@a"].health, by["robots@a"].last.restarts) == ("backoff", 1)
    assert (by["robots@b"].health, by["robots@b"].last.restarts, by["robots@b"].last.last_error) == (
        "ok",
        0,
        "",
    )
    assert by["bus@a"].health == "missing"


@pytest.mark.parametrize(
    ("dataplane", "key", "problem"),
    [
        ({"backend": "xdp", "listen": "127.0.0.2:50000"}, "dataplane.listen", "switch_addr (10.199.0.2)"),
        (
            {"backend": "xdp", "listen": "10.199.0.2:50000", "xdp": {"switch_addr": "10.200.0.2"}},
            "dataplane.listen",
            "switch_addr (10.200.0.2)",
        ),
        (
            {"backend": "xdp", "listen": "10.200.0.2:50000", "xdp": {"switch_addr": "10.200.0.2"}},
            "dataplane.xdp.switch_addr",
            "another address in 10.199.0.0/24",
        ),
        (
            {"backend": "xdp", "listen": "10.199.0.2:50000", "egress": {"rate_mbps": 100.0}},
            "dataplane.backend",
            "no forwarding rules or egress model",
        ),
        (
            {"backend": "xdp", "listen": "10.199.0.2:50000", "max_entities": 5000},
            "dataplane.max_entities",
            "the XDP program holds 4096",
        ),
        ({"xdp": {"netns": "a name with spaces"}}, "dataplane.xdp.netns", "A-Z a-z 0-9"),
        ({"backend": "ebpf"}, "dataplane.backend", "numpy"),
    ],
)
def test_an_xdp_data_plane_that_cannot_work_is_refused(dataplane: dict, key: str, problem: str) -> None:
    with pytest.raises(ConfigError) as info:
        load_config(overrides={"dataplane": dataplane})
    assert key in str(info.value) and problem in str(info.value)


def test_the_xdp_backend_alone_moves_the_default_listen_address_onto_the_switch() -> None:
    """The listen address follows the backend unless the user set it (then it is checked)."""
    dp = load_config(overrides={"dataplane": {"backend": "xdp"}}).dataplane
    assert dp.listen == "10.199.0.2:50000"
    moved = {"backend": "xdp", "xdp": {"host_addr": "10.5.0.1", "switch_addr": "10.5.0.2"}}
    assert load_config(overrides={"dataplane": moved}).dataplane.listen == "10.5.0.2:50000"
    assert load_config(None).dataplane.listen == "127.0.0.1:50000"  # (numpy: untouched)


def test_the_xdp_example_is_a_valid_cell() -> None:
    config = load_config(ROOT / "examples" / "xdp.toml")
    dp = config.dataplane
    assert dp.backend == "xdp" and dp.listen.startswith(dp.xdp.switch_addr)


def test_the_xdp_programs_entity_count_is_the_one_the_config_checks_against() -> None:
    from cell.config import XDP_MAX_ENTITIES
    from cell.dataplane.xdp.program import MAX_ENTITIES

    source = (Path(__file__).resolve().parents[2] / "cell/dataplane/xdp/dataplane.bpf.c").read_text()
    assert XDP_MAX_ENTITIES == MAX_ENTITIES and f"#define MAX_ENTITIES {MAX_ENTITIES}" in source
    assert load_config(None).dataplane.max_entities <= XDP_MAX_ENTITIES  # (the default suits both)


def test_auto_puts_the_data_plane_in_the_kernel_where_xdp_can_run_and_says_why_not_elsewhere(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """auto: XDP where it can run (root, ip, libbpf, the built program) for a cell that runs its data
    plane on one host; else the native data plane, with the reason XDP was not taken."""
    import cell.config

    monkeypatch.setattr(cell.config, "xdp_missing", lambda: None)
    dp = load_config(None).dataplane
    assert dp.chosen()[0] == "xdp" and dp.runs.in_kernel and "XDP can run here" in dp.chosen()[1]
    monkeypatch.setattr(cell.config, "xdp_missing", lambda: "it needs root")
    backend, why = load_config(None).dataplane.chosen()
    assert backend == "native" and why.endswith("(not XDP: it needs root)")
    monkeypatch.setattr(cell.config, "xdp_missing", lambda: None)
    cases = [
        ({"dataplane": {"listen": "10.0.0.5:50000"}}, "not on loopback"),
        ({"services": {"run": ["bus", "robots"]}}, "runs no data plane of its own"),
        ({"dataplane": {"max_entities": 5000}}, "over the program's 4096"),
    ]
    for overrides, reason in cases:
        backend, why = load_config(overrides=overrides).dataplane.chosen()
        assert backend == "native" and reason in why, (overrides, why)
    backend, why = load_config(overrides={"dataplane": {"egress": {"rate_mbps": 10.0}}}).dataplane.chosen()
    assert backend == "numpy" and "egress" in why
    # what a service process reads back from the launcher's file is what the launcher chose
    again = load_config(overrides=tomllib.loads(load_config(None).to_toml())).dataplane
    assert again.chosen()[0] == "xdp" and again.address == load_config(None).dataplane.address


def test_auto_gives_each_cell_a_switch_of_its_own_by_its_listen_port(monkeypatch: pytest.MonkeyPatch) -> None:
    """Two cells on two ports: two namespaces, two veth pairs, two /30s (so both run at once); the
    robots send to the switch's end on listen's port.  backend = "xdp" keeps [dataplane.xdp] as set."""
    import ipaddress

    import cell.config

    monkeypatch.setattr(cell.config, "xdp_missing", lambda: None)
    a, b = (
        load_config(overrides={"dataplane": {"listen": f"127.0.0.1:{p}"}}).dataplane for p in (50000, 50001)
    )
    sa, sb = a.switch, b.switch
    assert (sa.netns, sa.veth, sb.netns, sb.veth) == ("cellsw50000", "csw50000", "cellsw50001", "csw50001")
    nets = [ipaddress.IPv4Network(f"{s.host_addr}/{s.prefix}", strict=False) for s in (sa, sb)]
    assert not nets[0].overlaps(nets[1]) and all(
        n.subnet_of(ipaddress.IPv4Network("10.199.0.0/16")) for n in nets
    )
    for s, net in zip((sa, sb), nets, strict=True):
        assert s.prefix == 30 and s.host_addr != s.switch_addr
        assert {ipaddress.IPv4Address(s.host_addr), ipaddress.IPv4Address(s.switch_addr)} <= set(net.hosts())
    assert a.address == f"{sa.switch_addr}:50000" and b.address == f"{sb.switch_addr}:50001"
    assert a.listen == "127.0.0.1:50000"  # (as set: a user-space data plane's, were XDP to go)
    explicit = load_config(overrides={"dataplane": {"backend": "xdp"}}).dataplane
    assert explicit.switch == explicit.xdp and explicit.address == "10.199.0.2:50000"
    monkeypatch.setattr(cell.config, "xdp_missing", lambda: "no")
    assert load_config(None).dataplane.address == "127.0.0.1:50000"  # (native: listen itself)


def test_root_without_the_capabilities_xdp_needs_gets_the_native_data_plane_and_the_reason() -> None:
    """Root in a container is often without CAP_NET_ADMIN and CAP_BPF: auto must not pick XDP there
    (its switch and program would fail at start); a process started without them says so."""
    code = "from cell.config import load_config; print(*load_config(None).dataplane.chosen(), sep='|')"
    drop = ["setpriv", "--bounding-set=-net_admin,-sys_admin,-bpf"] if os.geteuid() == 0 else []
    out = subprocess.run([*drop, sys.executable, "-c", code], capture_output=True, text=True, check=True)
    backend, why = out.stdout.strip().split("|")
    assert backend == "native" and "CAP_NET_ADMIN and CAP_BPF" in why
