"""The cell's events as log lines: one wording for the Rerun log and the bag's /rosout.

`Events.describe` decodes an envelope of the event topics (EVENT_TOPICS) and says what happened
in one line, with the level a log viewer filters on and who said it.  What each recorder draws
besides the line (the Gantt spans of skill commands, the outputs' series, a service's recovery
time) it takes from the decoded message, `Event.msg`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from cell.bus import Envelope
from cell.snp.packet import Denial
from cell.v1 import health_pb2, robot_pb2, skills_pb2, snp_pb2

EVENT_TOPICS = ("events/", "run/events", "skills/", "announce/robot/")
Level = Literal["INFO", "WARN", "ERROR"]


@dataclass(frozen=True)
class Event:
    t_ns: int  # CLOCK_MONOTONIC, when it happened
    text: str
    level: Level
    source: str  # who says it: robot/<name>, skills/<robot>, run, snp, service/<name>
    msg: object  # the decoded message


class Events:
    """Envelopes of EVENT_TOPICS to Events (None: not an event, e.g. a robot announced again)."""

    def __init__(self) -> None:
        self.joined: set[int] = set()  # robots whose first announce was told

    def describe(self, env: Envelope) -> Event | None:
        topic = env.topic
        if topic.startswith("skills/") and topic.endswith("/trace"):
            tr = env.decode(skills_pb2.SkillTrace)
            took = (tr.answered_ns - tr.started_ns) / 1e6
            code = f" {tr.code}" if tr.code else ""
            text = f"{tr.robot}: {tr.id}:{tr.skill} {tr.status}{code} in {took:.1f} ms"
            level: Level = "INFO" if tr.status == "done" else "WARN"
            return Event(tr.answered_ns, text, level, f"skills/{tr.robot}", tr)
        if topic.startswith("skills/") and topic.endswith("/air"):
            a = env.decode(skills_pb2.AirState)
            text = f"{a.robot}: vacuum {'on' if a.on else 'off'}"
            return Event(a.t_ns, text, "INFO", f"skills/{a.robot}", a)
        if topic == "run/events":
            e = env.decode(skills_pb2.RunEvent)
            text = f"task script {e.script}: {e.state} {e.text}".strip()
            return Event(e.t_ns, text, "ERROR" if e.state == "failed" else "INFO", "run", e)
        if topic.startswith("announce/robot/"):
            a = env.decode(robot_pb2.RobotAnnounce)
            if a.robot_id in self.joined:
                return None
            self.joined.add(a.robot_id)
            text = f"robot {a.name} (id {a.robot_id}, {a.backend}) joined at {a.udp_address}"
            return Event(env.sent_ns, text, "INFO", f"robot/{a.name}", a)
        if topic == "events/snp/denial":
            d = env.decode(snp_pb2.SnpDenial)
            why = Denial(d.explanation).name if d.explanation in tuple(Denial) else str(d.explanation)
            return Event(d.t_ns, f"SnP query {d.query_id} from {d.peer} denied: {why}", "WARN", "snp", d)
        if topic.startswith("events/robot/"):
            e = env.decode(robot_pb2.RobotEvent)
            if e.kind == robot_pb2.RobotEvent.KIND_OUTPUTS:
                return Event(e.t_ns, f"{e.name}: outputs {e.text}", "INFO", f"robot/{e.name}", e)
            kind = robot_pb2.RobotEvent.Kind.Name(e.kind)
            return Event(e.t_ns, f"{e.name}: {kind} {e.text}", "WARN", f"robot/{e.name}", e)
        if topic.startswith("events/service/"):
            SE = health_pb2.ServiceEvent
            s = env.decode(SE)
            text = f"service {s.service}: {SE.Kind.Name(s.kind)} {s.text}".strip()
            level = "INFO" if s.kind == SE.KIND_STARTED else "WARN"
            return Event(env.sent_ns, text, level, f"service/{s.service}", s)
        return None
