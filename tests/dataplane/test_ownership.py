"""Which controller has each robot (cell/dataplane/ownership.py): a take-over is seen, not fought."""

from __future__ import annotations

from cell.dataplane.ownership import KEEP, Ownership

A, B, C = 11, 22, 33


def test_a_controller_that_had_loaded_a_robot_another_took_over_is_refused_until_it_takes_it_back() -> None:
    o = Ownership()
    o.applied(A, [], flushed=[1, 2])  # A starts: takes both over
    o.applied(A, [1], flushed=[])  # and moves robot 1
    assert o.owner == {1: A, 2: A} and o.refused(A, [1, 2]) == []
    o.applied(B, [], flushed=[1])  # B starts beside it and takes robot 1
    assert o.owner[1] == B and o.refused(A, [1, 2]) == [1] and o.refused(B, [1, 2]) == []
    o.applied(A, [], flushed=[1])  # A takes it back (a take-over of its own): now B has lost it
    assert o.refused(A, [1]) == [] and o.refused(B, [1]) == [1]


def test_a_controller_new_to_a_robot_shares_it_and_a_tool_is_never_held() -> None:
    o = Ownership()
    o.applied(A, [], flushed=[1])  # the cell's controller service took robot 1 over at its start
    assert o.refused(C, [1]) == []  # a script's own controller, after that: loads beside it
    o.applied(C, [1], flushed=[])
    assert o.owner[1] == A  # (loading is no take-over)
    o.applied(B, [], flushed=[1])
    assert o.refused(A, [1]) == o.refused(C, [1]) == [1]  # both had loaded it
    assert o.refused(0, [1]) == []  # a tool (no controller id) ...
    o.applied(0, [1], flushed=[1])  # ... whose flush (a test pulling the TPs away) takes nothing
    assert o.owner[1] == B and o.refused(B, [1]) == [] and o.refused(A, [1]) == [1]


def test_the_controllers_remembered_as_losers_are_bounded() -> None:
    o = Ownership()
    for k in range(1, 100):  # a controller restarted 99 times, each run taking the robot over
        o.applied(k, [], flushed=[1])
    assert o.refused(99, [1]) == [] and o.refused(98, [1]) == [1]
    assert all(o.refused(k, [1]) == [1] for k in range(99 - KEEP, 99))
    assert o.refused(1, [1]) == []  # (forgotten: the oldest)
