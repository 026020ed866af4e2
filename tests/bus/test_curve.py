"""CurveZMQ on the bus: keys from `cell keys generate`, allow-listed clients in, everyone else out."""

from __future__ import annotations

import stat
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest
import zmq
import zmq.auth

from cell.bus import Bus, BusUnavailable, Forwarder
from cell.config import BusConfig
from cell.v1 import bus_pb2
from tests.conftest import ROOT, cell_env


@pytest.fixture
def keys(tmp_path: Path) -> Path:
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "cell",
            "keys",
            "generate",
            "--dir",
            str(tmp_path / "keys"),
            "--client",
            "hosta",
            "hostb",
        ],
        cwd=ROOT,
        env=cell_env(),
        capture_output=True,
        text=True,
        check=True,
    )
    assert "mode 600" in out.stdout
    return tmp_path / "keys"


def test_keys_generate_writes_private_secrets_and_an_allow_list(keys: Path) -> None:
    for name in ("server", "hosta", "hostb"):
        assert (keys / f"{name}.key").is_file()
        assert stat.S_IMODE((keys / f"{name}.key_secret").stat().st_mode) == 0o600
    assert sorted(p.name for p in (keys / "allowed").iterdir()) == [
        "hosta.key",
        "hostb.key",
    ]  # not the server
    first = (keys / "hosta.key_secret").read_bytes()
    subprocess.run(
        [sys.executable, "-m", "cell", "keys", "generate", "--dir", str(keys), "--client", "hostc"],
        cwd=ROOT,
        env=cell_env(),
        check=True,
        capture_output=True,
    )
    assert (keys / "hosta.key_secret").read_bytes() == first  # kept: generating again only adds
    assert (keys / "allowed" / "hostc.key").is_file()


async def test_allow_listed_clients_talk_and_others_are_refused(bus_config: BusConfig, keys: Path) -> None:
    secure = replace(bus_config, curve=True, keys=str(keys), client="hosta")
    fwd = Forwarder(secure)
    fwd.start()
    try:
        async with Bus.connect(secure, "a") as a, Bus.connect(replace(secure, client="hostb"), "b") as b:
            await a.serve("svc", {"echo": (bus_pb2.BenchPayload, lambda r: r)})
            sub = await a.subscribe("news/")
            b.publish("news/x", bus_pb2.BenchPayload(data=b"secret"))
            assert (await sub.recv(timeout=5)).message() == bus_pb2.BenchPayload(data=b"secret")
            assert await b.request("svc", "echo", bus_pb2.BenchPayload(data=b"hi"), bus_pb2.BenchPayload) == (
                bus_pb2.BenchPayload(data=b"hi")
            )
            # a plain (no CURVE) node gets nothing through: the handshake never completes
            with pytest.raises(BusUnavailable):
                async with Bus.connect(replace(bus_config, connect_timeout_s=0.5), "plain"):
                    pass
            # a node with a certificate the forwarder does not allow is refused, and told so
            zmq.auth.create_certificates(keys, "rogue")  # a well-formed key nobody allow-listed
            fwd_keys = replace(secure, client="rogue", connect_timeout_s=1.0)
            with pytest.raises(BusUnavailable, match="refused this node's CurveZMQ key"):
                async with Bus.connect(fwd_keys, "intruder"):
                    pass
            # the allowed ones carry on
            assert await a.request("svc", "echo", bus_pb2.BenchPayload(data=b"x"), bus_pb2.BenchPayload)
    finally:
        fwd.stop()


def test_a_raw_zeromq_peer_reads_nothing_off_a_secured_bus(bus_config: BusConfig, keys: Path) -> None:
    secure = replace(bus_config, curve=True, keys=str(keys), client="hosta")
    fwd = Forwarder(secure)
    fwd.start()
    try:
        sub = zmq.Context.instance().socket(zmq.SUB)
        sub.linger = 0
        sub.subscribe(b"")
        sub.connect(bus_config.sub)
        sub.rcvtimeo = 500
        with pytest.raises(zmq.Again):
            sub.recv()
        sub.close()
    finally:
        fwd.stop()
