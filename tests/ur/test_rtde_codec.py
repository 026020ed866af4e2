"""RTDE and the dashboard, sans IO: byte by byte, as UR's RTDE guide lays the packages out."""

from __future__ import annotations

import json
import struct
import zipfile

import numpy as np

from cell.robot.arm import arm_model
from cell.ur.arm import RobotMode, SafetyMode, URArm
from cell.ur.dashboard import Dashboard
from cell.ur.fields import INPUTS, OUTPUTS
from cell.ur.programs import Programs
from cell.ur.rtde import Package, Session, encode, split

Q = np.array([0.1, -1.5, 1.4, -1.6, -1.5, 0.2])


def session(arm: URArm | None = None) -> tuple[Session, URArm]:
    arm = arm or URArm("r1", arm_model("ur5e"))
    return Session(OUTPUTS, INPUTS, arm, (5, 11, 0, 0), 500), arm


def one(s: Session, kind: Package, body: bytes = b"") -> tuple[int, bytes]:
    out = s.receive(encode(kind, body))
    assert len(out) == 1
    (got,) = split(bytearray(out[0]))
    return got


def test_version_negotiation_and_the_controller_version() -> None:
    s, _ = session()
    assert s.receive(b"\x00\x05V\x00") == []  # half a package: nothing yet
    assert s.receive(b"\x02") == [b"\x00\x04V\x01"]  # protocol 2 accepted
    assert s.protocol == 2
    assert one(s, Package.REQUEST_PROTOCOL_VERSION, b"\x00\x07") == (ord("V"), b"\x00")  # no version 7
    assert one(s, Package.GET_URCONTROL_VERSION) == (ord("v"), struct.pack(">IIII", 5, 11, 0, 0))


def test_an_output_recipe_streams_at_the_clients_frequency_with_the_arms_values() -> None:
    s, arm = session()
    one(s, Package.REQUEST_PROTOCOL_VERSION, b"\x00\x02")
    kind, body = one(
        s, Package.CONTROL_PACKAGE_SETUP_OUTPUTS, struct.pack(">d", 125.0) + b"timestamp,actual_q,"
    )
    assert (kind, body) == (ord("O"), b"\x01DOUBLE,VECTOR6D")  # recipe 1 (the trailing comma is ur_rtde's)
    assert one(s, Package.CONTROL_PACKAGE_START) == (ord("S"), b"\x01")
    arm.update(Q, np.zeros(6), np.zeros(6), 1.25)
    sent = [p for tick in range(8) for p in s.due(tick, arm)]
    assert len(sent) == 2  # 125 Hz on a 500 Hz arm: every fourth tick
    ((kind, body),) = split(bytearray(sent[0]))
    assert kind == ord("U") and body[0] == 1
    assert struct.unpack(">d6d", body[1:]) == (1.25, *Q.tolist())


def test_unknown_fields_are_not_found_and_make_no_recipe() -> None:
    s, _ = session()
    one(s, Package.REQUEST_PROTOCOL_VERSION, b"\x00\x02")
    body = one(s, Package.CONTROL_PACKAGE_SETUP_OUTPUTS, struct.pack(">d", 500.0) + b"actual_q,warp_drive")[1]
    assert body == b"\x00VECTOR6D,NOT_FOUND" and s.recipes == []
    assert one(s, Package.CONTROL_PACKAGE_START) == (ord("S"), b"\x00")  # nothing to start


def test_an_input_field_one_client_holds_is_in_use_for_another_and_writes_reach_the_arm() -> None:
    a, arm = session()
    b, _ = session(arm)
    names = b"speed_slider_mask,speed_slider_fraction,input_int_register_24"
    assert one(a, Package.CONTROL_PACKAGE_SETUP_INPUTS, names)[1] == b"\x01UINT32,DOUBLE,INT32"
    assert one(b, Package.CONTROL_PACKAGE_SETUP_INPUTS, b"input_int_register_24")[1] == b"\x00IN_USE"
    one(a, Package.CONTROL_PACKAGE_START)
    a.receive(encode(Package.DATA_PACKAGE, b"\x01" + struct.pack(">Idi", 1, 0.25, -7)))
    assert arm.speed_fraction == 0.25 and arm.int_in[24] == -7
    a.close()  # a client gone lets go of its fields
    assert one(b, Package.CONTROL_PACKAGE_SETUP_INPUTS, b"input_int_register_24")[1] == b"\x01INT32"


def test_bad_packages_are_counted_and_answered_and_the_session_goes_on() -> None:
    s, _ = session()
    one(s, Package.REQUEST_PROTOCOL_VERSION, b"\x00\x02")
    kind, body = one(s, 0x7A)  # an unknown type: a text message, level ERROR
    assert kind == ord("M") and b"unknown package type" in body
    one(s, Package.CONTROL_PACKAGE_SETUP_INPUTS, b"input_double_register_3")
    one(s, Package.CONTROL_PACKAGE_START)
    assert one(s, Package.DATA_PACKAGE, b"\x01\x00\x00")[0] == ord("M")  # 2 bytes for a DOUBLE
    assert one(s, Package.DATA_PACKAGE, b"\x09" + bytes(8))[0] == ord("M")  # no recipe 9
    many = ",".join(f"input_int_register_{i % 48}" for i in range(2000)).encode()
    assert one(s, Package.CONTROL_PACKAGE_PAUSE)[1] == b"\x01"
    assert b"2000 fields" in one(s, Package.CONTROL_PACKAGE_SETUP_OUTPUTS, struct.pack(">d", 1.0) + many)[1]
    kind, body = one(s, Package.CONTROL_PACKAGE_SETUP_OUTPUTS, struct.pack(">d", 1e-310) + b"timestamp")
    assert kind == ord("M") and b"frequency" in body  # (a frequency so small it overflowed a division)
    for text in (b"", b"\x05ab", b"\x01a\x09b"):  # (found by `cell fuzz`: lengths past the end)
        kind, body = one(s, Package.TEXT_MESSAGE, text)
        assert kind == ord("M") and b"malformed" in body
    assert s.counters.bad == {
        "unknown_type": 1, "bad_length": 1, "unknown_recipe": 1, "too_many_fields": 1, "malformed": 3,
        "bad_frequency": 1,
    }  # fmt: skip
    assert one(s, Package.GET_URCONTROL_VERSION)[0] == ord("v")  # still answering
    out = s.receive(struct.pack(">HB", 2, ord("U")))  # a length no stream can be read past
    assert s.closed and out and split(bytearray(out[0]))[0][0] == ord("M")


def test_the_dashboard_changes_the_arms_modes_and_answers_as_a_ur() -> None:
    arm = URArm("r1", arm_model("ur5e"))
    changed = []
    d = Dashboard(arm, "ur5e", "20205000001", lambda: changed.append(arm.can_move))
    assert d.handle("robotmode") == "Robotmode: RUNNING" and arm.can_move
    assert d.handle("power off") == "Powering off" and not arm.can_move
    assert d.handle("power on") == "Powering on" and arm.robot_mode == RobotMode.IDLE
    assert d.handle("brake release") == "Brake releasing" and arm.can_move
    assert d.handle("power off") == "Powering off" and not arm.can_move
    assert d.handle("brake release") == "Brake releasing" and arm.can_move  # (powered on first, as a UR)
    arm.safety_mode = SafetyMode.PROTECTIVE_STOP
    assert not arm.can_move and d.handle("safetystatus") == "Safetystatus: PROTECTIVE_STOP"
    assert d.handle("unlock protective stop") == "Protective stop releasing" and arm.can_move
    assert d.handle("get robot model") == "UR5" and d.handle("is in remote control") == "true"
    assert d.handle("warp 9") == "could not understand: 'warp 9'" and d.unknown == 1
    assert changed == [False, False, True, False, True, True]
    assert d.handle("quit") == "Disconnected" and d.closed


def test_every_field_of_the_guide_is_offered_with_its_type_and_streams_at_500_hz() -> None:
    """A recipe of every output field (as UR's client library's exhaustive recipe asks, 406 of them)
    is taken whole, each with UR's type, and each package carries exactly their bytes."""
    s, arm = session()
    one(s, Package.REQUEST_PROTOCOL_VERSION, b"\x00\x02")
    names = list(OUTPUTS)
    assert len(names) >= 406
    kind, body = one(
        s, Package.CONTROL_PACKAGE_SETUP_OUTPUTS, struct.pack(">d", 500.0) + ",".join(names).encode()
    )
    types = body[1:].decode().split(",")
    assert kind == ord("O") and body[0] == 1 and "NOT_FOUND" not in types
    assert types == [OUTPUTS[n].value for n in names]
    for name, want in {  # (as the RTDE guide and UR's client library type them)
        "joint_position_deviation_ratio": "DOUBLE", "tcp_offset": "VECTOR6D",
        "target_gravity": "VECTOR3D", "control_step": "UINT64", "encoder0_raw": "INT32",
        "actual_configurable_digital_output_bits": "UINT64",
    }.items():  # fmt: skip
        assert types[names.index(name)] == want, name
    one(s, Package.CONTROL_PACKAGE_START)
    arm.update(Q, np.zeros(6), np.zeros(6), 2.0)
    ((kind, body),) = split(bytearray(s.due(0, arm)[0]))
    size = {"DOUBLE": 8, "VECTOR6D": 48, "VECTOR3D": 24, "INT32": 4, "UINT32": 4, "UINT64": 8, "UINT8": 1,
            "BOOL": 1, "VECTOR6INT32": 24, "VECTOR6UINT32": 24}  # fmt: skip
    assert kind == ord("U") and len(body) == 1 + sum(size[t] for t in types)


def test_the_newer_fields_report_the_arm() -> None:
    """tcp_offset follows set_tcp (as URCL's default recipe reads it); control_step counts the
    controller's 2 ms steps; the configurable outputs are bits 8-15 of the digital outputs."""
    s, arm = session()
    one(s, Package.REQUEST_PROTOCOL_VERSION, b"\x00\x02")
    names = b"tcp_offset,control_step,actual_configurable_digital_output_bits,target_gravity"
    assert one(s, Package.CONTROL_PACKAGE_SETUP_OUTPUTS, struct.pack(">d", 500.0) + names)[1][0] == 1
    one(s, Package.CONTROL_PACKAGE_START)
    arm.tool.set_tcp(np.array([0.0, 0.0, 0.15, 0.0, 0.0, 0.3]))
    arm.digital_out = 0b1010_0000_0000_0001
    arm.update(Q, np.zeros(6), np.zeros(6), 4.0)
    ((_, body),) = split(bytearray(s.due(0, arm)[0]))
    got = struct.unpack(">6dQQ3d", body[1:])
    assert got[:6] == (0.0, 0.0, 0.15, 0.0, 0.0, 0.3)
    assert got[6:8] == (2000, 0b1010_0000) and got[8:] == (0.0, 0.0, 9.82)


def test_the_dashboard_loads_from_the_programs_folder_and_writes_its_files_there(tmp_path) -> None:
    """As URSim's /ursim/programs: `load` finds .urp files there (by name, or a path inside it), and
    programState names the file; installations likewise; saveLog, flight reports and support files
    are written there; a name that leads out of the folder is not found."""
    programs = Programs(str(tmp_path / "programs"))
    programs.ensure()
    (programs.root / "sub").mkdir()
    (programs.root / "sub" / "wait_program.urp").write_text("<urp/>")
    (tmp_path / "outside.urp").write_text("<urp/>")
    arm = URArm("r1", arm_model("ur5e"))
    d = Dashboard(arm, "ur5e", "20205000001", programs=programs)
    path = programs.root / "sub" / "wait_program.urp"
    assert d.handle("load sub/wait_program.urp") == f"Loading program: {path}"
    assert d.handle("programState") == "STOPPED wait_program.urp"
    assert d.handle("get loaded program") == f"Loaded program: {path}"
    assert d.handle(f"load {path}") == f"Loading program: {path}"  # (an absolute path inside it)
    assert d.handle("load ../outside.urp") == "File not found: ../outside.urp"
    assert d.handle(f"load {tmp_path / 'outside.urp'}") == f"File not found: {tmp_path / 'outside.urp'}"
    assert d.handle("load nothing.urp") == "File not found: nothing.urp"
    for junk in ("a\x00b.urp", "x" * 3000 + ".urp"):  # (no file system takes these: not found, no crash)
        assert d.handle(f"load {junk}") == f"File not found: {junk}"
        assert d.handle(f"load installation {junk}") == f"File not found: {junk}"
    assert d.handle("generate support file a\x00b").startswith("Error")
    assert d.handle("load installation default.installation") == (
        f"Loading installation: {programs.root / 'default.installation'}"
    )
    assert d.handle("load installation none.installation") == "File not found: none.installation"
    assert d.handle("isProgramSaved") == "true wait_program.urp"
    assert d.handle("addToLog first line") == "Added log message"
    assert d.handle("saveLog") == "Log saved to disk"
    assert (programs.root / "log_history.txt").read_text() == "first line\n"
    reply = d.handle("generate flight report controller")
    assert reply.startswith("Flight Report generated with id: ")
    report = programs.root / "flight_reports" / f"flight_report_{reply.rsplit(' ', 1)[1]}.json"
    assert json.loads(report.read_text())["state"]["program"] == "wait_program.urp"
    reply = d.handle("generate support file .")
    assert reply.startswith("Completed successfully: ")
    with zipfile.ZipFile(reply.split(": ", 1)[1]) as z:
        assert sorted(z.namelist()) == ["log_history.txt", "state.json"]
    assert d.handle("generate support file ../..").startswith("Error")  # (nothing written outside)
    assert d.handle("set operational mode manual") == "Operational mode MANUAL is set"
    assert d.handle("get operational mode") == "MANUAL"
    assert d.handle("clear operational mode").startswith("No longer controlling the operational mode")
