"""The skill servers' ASCII protocol, byte by byte (sans IO)."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from cell.skills.protocol import (
    MAX_LINE,
    Command,
    CommandReader,
    Done,
    Error,
    ReplyReader,
    parse_command,
    parse_reply,
)


def test_the_papers_example_and_acknowledgement_bytes() -> None:
    reader = CommandReader()
    got = reader.feed(b"a1b2c3d4:move_to:100.000,-200.5,300,0,180,0\r\ne5f6a7b8:break\r\n")
    assert got == [
        Command("a1b2c3d4", "move_to", (100.0, -200.5, 300.0, 0.0, 180.0, 0.0)),
        Command("e5f6a7b8", "break"),
    ]
    done = Done("a1b2c3d4", 1.5, 2.25, (100.0, -200.5, 300.0, 0.0, 180.0, 0.0))
    assert done.encode() == b"a1b2c3d4:done:1.500,2.250:100.000,-200.500,300.000,0.000,180.000,0.000\r\n"
    assert parse_reply(done.encode()[:-2]) == done
    assert Command("a1b2c3d4", "set_speed", (50.0,)).encode() == b"a1b2c3d4:set_speed:50.000\r\n"


def test_messages_split_anywhere_come_out_whole() -> None:
    stream = b"00000001:set_speed:30\r\n00000002:move_joints:0,-90,90,-90,-90,0\r\n00000003:break\r\n"
    for cut in range(1, len(stream)):
        reader = CommandReader()
        out = reader.feed(stream[:cut]) + reader.feed(stream[cut:])
        assert [c.id for c in out] == ["00000001", "00000002", "00000003"], cut
    reader = CommandReader()
    out = [c for b in stream for c in reader.feed(bytes([b]))]  # one byte at a time
    assert [c.skill for c in out] == ["set_speed", "move_joints", "break"]


@pytest.mark.parametrize(
    ("line", "reply"),
    [
        (b"abc:break", b"00000000:error:malformed:"),  # no 8-character id
        (b"nocolonhere", b"00000000:error:malformed:"),
        (b"\xff\xfe:break", b"00000000:error:malformed:not ASCII"),
        (b"12345678:fly:1,2", b"12345678:error:unknown_skill:no skill 'fly'"),
        (b"12345678:move_to:1,2,3", b"12345678:error:arguments:move_to takes 6 arguments, got 3"),
        (b"12345678:move_to:1,2,3,4,5,x", b"12345678:error:arguments:move_to: arguments must be numbers"),
        (b"12345678:move_to:1,2,3,4,5,nan", b"12345678:error:arguments:move_to: arguments must be finite"),
        (b"12345678:break:1", b"12345678:error:arguments:break takes 0 arguments, got 1"),
        (b"12345678:set_speed:0", b"12345678:error:arguments:set_speed takes a percentage in (0, 100]"),
        (b"12345678:set_speed:101", b"12345678:error:arguments:set_speed takes a percentage in (0, 100]"),
        (b"12345678:move_to:1:2", b"12345678:error:malformed:too many ':' fields"),
        (
            b"12345678:follow",
            b"12345678:error:arguments:follow takes one name of 1-64 A-Z a-z 0-9 _ . -, got ''",
        ),
        (b"12345678:follow:a,b", b"12345678:error:arguments:follow takes one name"),
        (b"12345678:follow:p ick", b"12345678:error:arguments:follow takes one name"),
    ],
)
def test_every_error_path_has_its_reply(line: bytes, reply: bytes) -> None:
    got = CommandReader().feed(line + b"\r\n")
    assert len(got) == 1 and isinstance(got[0], Error)
    assert got[0].encode().startswith(reply)
    assert got[0].encode().endswith(b"\r\n") and got[0].encode().count(b"\r\n") == 1


def test_follow_takes_one_trajectory_name_and_encodes_back_to_its_bytes() -> None:
    (cmd,) = CommandReader().feed(b"a81bd206:follow:pick.place-2\r\n")
    assert (cmd.id, cmd.skill, cmd.names, cmd.args) == ("a81bd206", "follow", ("pick.place-2",), ())
    assert cmd.encode() == b"a81bd206:follow:pick.place-2\r\n"


def test_an_overlong_line_is_refused_once_and_the_next_one_works() -> None:
    reader = CommandReader()
    long = b"12345678:move_to:" + b"1" * (MAX_LINE + 100)
    out = reader.feed(long[:600]) + reader.feed(long[600:])  # refused as soon as it is too long
    assert out == [Error("12345678", "line_too_long", f"a command message is at most {MAX_LINE} bytes")]
    out = reader.feed(b"still the long one\r\n87654321:break\r\n")
    assert out == [Command("87654321", "break")]
    assert CommandReader().feed(b"x" * 2000 + b"\r\n")[0].id == "00000000"


def test_blank_lines_are_ignored_and_error_text_cannot_break_the_framing() -> None:
    assert CommandReader().feed(b"\r\n\r\n12345678:break\r\n") == [Command("12345678", "break")]
    assert Error("12345678", "failed", "two\r\nlines").encode() == b"12345678:error:failed:two  lines\r\n"


@given(st.binary(max_size=300))
def test_no_input_breaks_the_reader(data: bytes) -> None:
    reader = CommandReader()
    for item in reader.feed(data) + reader.feed(b"\r\n"):
        assert isinstance(item, Command | Error)
    assert reader.feed(b"12345678:break\r\n") == [Command("12345678", "break")]  # still in step


def test_replies_parse_back() -> None:
    reader = ReplyReader()
    got = reader.feed(b"12345678:error:unreachable:too far\r\n12345678:done:0.000,1.000:1,2,3,4,5,6\r\n")
    assert got == [
        Error("12345678", "unreachable", "too far"),
        Done("12345678", 0.0, 1.0, (1, 2, 3, 4, 5, 6)),
    ]
    with pytest.raises(ValueError):
        parse_reply(b"12345678:maybe:1")
    assert isinstance(parse_command(b"abcdefgh:enable_air"), Command)
