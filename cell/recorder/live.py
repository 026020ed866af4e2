"""What the recorder service draws: the cell's bus in Rerun, live or into an .rrd file.

- 3D: every robot from its MJCF geometry with a pose per link from ground
  truth; the tool's path; the plan's trajectory points as markers, the one
  the robot is heading for highlighted.
- Time series per robot and joint: actual vs planned position, actual vs
  commanded velocity, tracking error.
- Data plane: batch time p50/p99, packets/s, drops by reason, resubmits, TPs
  loaded.
- Events as text logs (robots, services, runs, SnP and skill errors); skill
  commands as spans (a step series per robot: the run reads as a Gantt chart).
One timeline, `cell_time`: the cell clock (this host's CLOCK_REALTIME).
Ground truth is drawn at [recorder] hz at most: the 3D scene as it comes,
the time series as columns every [recorder] series_batch_s (cell/recorder/
series.py), the tool path a few times a second.  Its share of the process
shows as busy_ms_per_s in `cell status`.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path

import numpy as np
import rerun as rr

from cell.bus.envelope import EnvelopeError
from cell.recorder import base_position, each, serve
from cell.recorder.blueprint import cell_blueprint
from cell.recorder.events import EVENT_TOPICS, Event, Events
from cell.recorder.scene import ArmDrawer, log_camera
from cell.recorder.series import SeriesBatch
from cell.robot.arm import arm_model
from cell.robot.node import output_name
from cell.service import ServiceContext
from cell.snp.state import realtime_offset_ns
from cell.v1 import controller_pb2, dataplane_pb2, health_pb2, modular_pb2, robot_pb2, skills_pb2, vision_pb2
from cell.vision.acquisition import camera_spec

log = logging.getLogger("cell.service.recorder")

PATH_POINTS = 600  # tool path points kept per robot
PATH_EVERY_NS = 200_000_000  # the tool path (a line of up to PATH_POINTS) is drawn this often
LINK_EVERY_NS = 1_000_000_000  # a node's link counters are drawn at most this often
FLEET_HZ = 5.0  # a fleet's arms (GroupTruth) are drawn at most this often
TIMELINE = "cell_time"
GANTT_BARS = 600  # the newest requests drawn in the Gantt chart
VISION_COLOR, ROBOT_COLOR = (255, 150, 30), (40, 110, 220)  # Fig. 10: vision orange, robot blue


class Recorder:
    def __init__(self, ctx: ServiceContext, rec: rr.RecordingStream) -> None:
        self.ctx, self.rec = ctx, rec
        cfg = ctx.config
        self.min_dt = int(1e9 / cfg.recorder.hz)
        self.offset = realtime_offset_ns()
        n = len(cfg.robots)
        self.names = {r.id: r.name for r in cfg.robots}
        self.drawers = {
            r.id: ArmDrawer(arm_model(r.model), r.name, base_position(i, n)) for i, r in enumerate(cfg.robots)
        }
        self.ids = {r.name: r.id for r in cfg.robots}
        self.group_drawn: dict[str, int] = {}  # a fleet's topic -> when its arms were last drawn
        self.last_drawn: dict[int, int] = {}
        self.paths: dict[int, deque[np.ndarray]] = {rid: deque(maxlen=PATH_POINTS) for rid in self.names}
        self.path_drawn: dict[int, int] = {}
        self.active_tp: dict[int, int] = {}
        self.plans: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self.series = SeriesBatch(rec, TIMELINE)
        self.last_counters: tuple[int, float] | None = None
        self.link_logged: dict[str, int] = {}  # service -> when its link counters were last drawn
        self.restarts: dict[str, int] = {}  # service -> its restart count as last drawn
        self.failed_ns: dict[str, int] = {}  # service -> when it failed, until it is back
        self.logged = 0
        self.t0_ns = time.monotonic_ns()
        self.lanes = ["vision", *(r.name for r in cfg.robots)]  # the Gantt chart's rows, top down
        self.bars: deque[tuple[float, float, int, str]] = deque(maxlen=GANTT_BARS)
        self.bars_dirty = False
        self.modular_placed = False
        self.outputs_seen: dict[str, int] = {}  # robot -> the digital outputs ever on (drawn since)

    def seconds(self, t_mono_ns: int) -> float:
        return (t_mono_ns + self.offset) / 1e9

    def at(self, t_mono_ns: int) -> None:
        self.rec.set_time(TIMELINE, timestamp=self.seconds(t_mono_ns))

    def start(self) -> None:
        for d in self.drawers.values():
            d.log_static(self.rec)
        cfg = self.ctx.config
        if "vision" in cfg.services.run and cfg.robots:
            watched = cfg.vision.robot or cfg.robots[0].name
            log_camera(self.rec, watched, camera_spec(cfg.vision))
        self.rec.log("events", rr.TextLog("recorder started", level="INFO"), static=False)

    # --- ground truth ---------------------------------------------------------------------------

    def wants_truth(self, name: str, sent_ns: int) -> bool:
        """Whether a truth message sent at sent_ns is drawn (decided before decoding it)."""
        rid = self.ids.get(name)
        return rid is not None and sent_ns - self.last_drawn.get(rid, 0) >= self.min_dt

    def group_truth(self, topic: str, m: robot_pb2.GroupTruth) -> None:
        """A fleet's ground truth (robots on one socket, one message a tick for all): each arm's pose,
        at most FLEET_HZ (hundreds of arms at the drawing rate would swamp the viewer); no series."""
        if m.joints == 0 or len(m.q) != m.joints * len(m.robot_id):  # (each() counts it, drops it)
            raise EnvelopeError(
                f"{topic}: {len(m.q)} joint values for {len(m.robot_id)} robots of {m.joints}"
            )
        if m.t_ns - self.group_drawn.get(topic, 0) < max(self.min_dt, int(1e9 / FLEET_HZ)):
            return
        self.group_drawn[topic] = m.t_ns
        self.at(m.t_ns)
        q = np.array(m.q).reshape(-1, m.joints)
        for rid, qi in zip(m.robot_id, q, strict=True):
            drawer = self.drawers.get(rid)
            if drawer is None or drawer.arm.dof != m.joints:  # (not ours, or not the arm we draw)
                continue
            for entity, pos, quat in drawer.poses(qi):
                self.rec.log(entity, rr.Transform3D(translation=pos, quaternion=rr.Quaternion(xyzw=quat)))
        self.logged += 1

    def truth(self, m: robot_pb2.RobotTruth) -> None:
        rid = m.robot_id
        drawer = self.drawers.get(rid)
        # (wants_truth judged by the send time; truth read out of the robots' ring can go out in a
        # burst, the states closer together than their sends: the drawn timeline keeps the rate)
        if drawer is None or m.t_ns - self.last_drawn.get(rid, 0) < self.min_dt:
            return
        self.last_drawn[rid] = m.t_ns
        name = self.names[rid]
        q = np.array(m.q)
        self.at(m.t_ns)
        rec = self.rec
        for entity, pos, quat in drawer.poses(q):
            rec.log(entity, rr.Transform3D(translation=pos, quaternion=rr.Quaternion(xyzw=quat)))
        self.paths[rid].append(np.array(m.tool_pose[:3]))
        if m.t_ns - self.path_drawn.get(rid, 0) >= PATH_EVERY_NS:
            self.path_drawn[rid] = m.t_ns
            rec.log(f"robots/{name}/tool_path", rr.LineStrips3D([np.array(self.paths[rid])]))
        t_s = self.seconds(m.t_ns)
        joints, series = f"joints/{name}", self.series
        series.add_joints(f"{joints}/position", "/actual", t_s, q)
        series.add_joints(f"{joints}/velocity", "/actual", t_s, np.array(m.qd))
        series.add_joints(f"{joints}/velocity", "/commanded", t_s, np.array(m.target))
        plan = self.plans.get(rid)
        if plan is not None:
            t, pq, _ = plan
            if t[0] <= m.t_ns <= t[-1] + 2_000_000_000:
                planned = np.array([np.interp(m.t_ns, t, pq[:, j]) for j in range(q.size)])
                series.add_joints(f"{joints}/position", "/planned", t_s, planned)
                series.add_joints(f"{joints}/tracking_error", "", t_s, q - planned)
                k = int(np.searchsorted(t, m.t_ns))
                if k < len(t) and self.active_tp.get(rid) != k:  # drawn when it changes
                    self.active_tp[rid] = k
                    active = drawer.arm.fk(pq[k])[0]
                    rec.log(
                        f"robots/{name}/active_tp", rr.Points3D([active], radii=0.012, colors=[255, 80, 0])
                    )
        self.logged += 1

    def outputs(self, e: robot_pb2.RobotEvent) -> None:
        """A robot's digital outputs changed: each output ever set, as a 0/1 series."""
        seen = self.outputs_seen.get(e.name, 0) | e.digital_out
        self.outputs_seen[e.name] = seen
        self.at(e.t_ns)
        for bit in range(64):
            if seen >> bit & 1:
                on = float(e.digital_out >> bit & 1)
                self.rec.log(f"robots/{e.name}/io/{output_name(bit)}", rr.Scalars(on))

    def plan(self, p: controller_pb2.Plan) -> None:
        if p.robot_id not in self.drawers or not p.t_ns:
            return
        t = np.array(p.t_ns)
        q = np.array(p.positions).reshape(-1, p.joints)
        v = np.array(p.velocities).reshape(-1, p.joints)
        self.plans[p.robot_id] = (t, q, v)
        self.active_tp.pop(p.robot_id, None)
        arm = self.drawers[p.robot_id].arm
        points = [arm.fk(qi)[0] for qi in q]
        self.at(int(t[0]))
        name = self.names[p.robot_id]
        self.rec.log(f"robots/{name}/tps", rr.Points3D(points, radii=0.006, colors=[60, 160, 255]))
        self.rec.log("events", rr.TextLog(f"{name}: a plan of {len(t)} TPs loaded", level="INFO"))

    # --- the data plane -----------------------------------------------------------------------------

    def dataplane(self, st: dataplane_pb2.DataplaneState, t_mono_ns: int) -> None:
        c = st.counters
        self.at(t_mono_ns)
        rec = self.rec
        for key in ("batch_p50_us", "batch_p99_us", "resubmits", "tps_loaded", "stalls", "holds"):
            if key in c:
                rec.log(f"dataplane/{key}", rr.Scalars(c[key]))
        for key, value in c.items():
            if key.startswith("rejected."):
                rec.log(f"dataplane/drops/{key.removeprefix('rejected.')}", rr.Scalars(value))
        packets = c.get("packets_in", 0.0)
        if self.last_counters is not None:
            t0, p0 = self.last_counters
            dt = (t_mono_ns - t0) / 1e9
            if dt > 0:
                rec.log("dataplane/packets_per_s", rr.Scalars((packets - p0) / dt))
        self.last_counters = (t_mono_ns, packets)

    # --- the Responsive Link ---------------------------------------------------------------------------

    def link(self, hb: health_pb2.Heartbeat, t_mono_ns: int) -> None:
        """A node's link counters from its service's heartbeat: rlink/<service>/L<n>/<kind>/..., drops
        by reason and the event latency; once a second per node at most (heartbeats may come faster,
        and each is some forty series)."""
        last = self.link_logged.get(hb.service, 0)
        if t_mono_ns - last < LINK_EVERY_NS:
            return
        self.link_logged[hb.service] = t_mono_ns
        self.at(t_mono_ns)
        rec = self.rec
        for key, value in hb.counters.items():
            parts = key.split(".")
            if parts[0] != "rlink" or len(parts) < 3:
                continue
            if parts[1][:1] == "L" and parts[-1] in ("packets_in", "packets_out", "overflow", "depth"):
                rec.log(f"rlink/{hb.service}/{parts[1]}/{parts[2]}/{parts[3]}", rr.Scalars(value))
            elif parts[1] == "drops":
                rec.log(f"rlink/{hb.service}/drops/{parts[2]}", rr.Scalars(value))
        for key in ("rlink.event_latency_p50_us", "rlink.event_latency_p99_us"):
            if key in hb.counters:
                rec.log(f"rlink/{hb.service}/{key.removeprefix('rlink.')}", rr.Scalars(hb.counters[key]))

    def answers(self, hb: health_pb2.Heartbeat, t_mono_ns: int) -> None:
        """dataplane/answer_p50_us and _p99_us: each status's command back, as its robots measure it
        (every backend; the kernel's has no batch timings of its own), from the robots' heartbeat."""
        c = hb.counters
        if "answer_p99_us" in c:
            self.at(t_mono_ns)
            for key in ("answer_p50_us", "answer_p99_us"):
                self.rec.log(f"dataplane/{key}", rr.Scalars(c[key]))

    # --- the services' lives ---------------------------------------------------------------------------

    def health(self, hb: health_pb2.Heartbeat, t_mono_ns: int) -> None:
        """services/<name>/restarts whenever it changes (from 0 at first sight), with the last error."""
        if self.restarts.get(hb.service) == hb.restarts:
            return
        self.at(t_mono_ns)
        self.rec.log(f"services/{hb.service}/restarts", rr.Scalars(hb.restarts))
        if hb.service in self.restarts:
            why = f": {hb.last_error}" if hb.last_error else ""
            self.rec.log(
                "events", rr.TextLog(f"service {hb.service} restarted ({hb.restarts}){why}", level="WARN")
            )
        self.restarts[hb.service] = hb.restarts

    def service_event(self, e: health_pb2.ServiceEvent, text: str, t_mono_ns: int) -> str:
        """From a service's failure to its next start: services/<name>/recover_s (the line says it too)."""
        if e.kind == health_pb2.ServiceEvent.KIND_FAILED:
            self.failed_ns.setdefault(e.service, t_mono_ns)
        elif e.kind == health_pb2.ServiceEvent.KIND_STARTED and e.service in self.failed_ns:
            took = (t_mono_ns - self.failed_ns.pop(e.service)) / 1e9
            self.at(t_mono_ns)
            self.rec.log(f"services/{e.service}/recover_s", rr.Scalars(took))
            text += f" (back {took:.2f} s after it failed)"
        return text

    # --- events and skill commands --------------------------------------------------------------------

    def text(self, t_mono_ns: int, text: str, level: str = "INFO") -> None:
        self.at(t_mono_ns)
        self.rec.log("events", rr.TextLog(text, level=level))

    def skill(self, tr: skills_pb2.SkillTrace, ev: Event) -> None:
        """A skill command as a span of skills/<robot>/busy, and its line in skills/<robot>/log."""
        entity = f"skills/{tr.robot}/busy"
        self.at(tr.started_ns)
        self.rec.log(entity, rr.Scalars(1.0))
        self.at(tr.answered_ns)
        self.rec.log(entity, rr.Scalars(0.0))
        self.rec.log(f"skills/{tr.robot}/log", rr.TextLog(ev.text, level=ev.level))

    # --- vision and the Gantt chart of requests (the Adept paper's Figs. 9 and 10) ------------------

    def image(self, m: vision_pb2.VisionImage) -> None:
        self.at(m.t_ns)
        self.rec.log("vision/camera", rr.EncodedImage(contents=m.jpeg, media_type="image/jpeg"))

    def measurement(self, m: vision_pb2.VisionReply) -> None:
        self.at(m.frame_t_ns)
        if m.found:
            self.rec.log("vision/sharpness", rr.Scalars(m.sharpness))
        else:
            self.rec.log("vision/log", rr.TextLog(f"vision {m.id}: {m.reason}", level="WARN"))

    # --- the modular robot (seed 002) -----------------------------------------------------------------

    def modular(self, m: modular_pb2.ModularState) -> None:
        """The arm as a line through its joints to the tool, beside the cell's robots; the tool's error
        against its reference, each cycle's A-D arithmetic (or, on the SnP cycle, each module's
        [A, B, C, D] and its clock's offset) and each module's guesses as plots."""
        self.at(m.t_ns)
        rec = self.rec
        if not self.modular_placed:
            beside = base_position(-1, len(self.ctx.config.robots))  # (one place before the first robot)
            rec.log("modular", rr.Transform3D(translation=beside), static=True)
            self.modular_placed = True
        frames = np.asarray(m.frames).reshape(-1, 3)
        colours = [(60, 190, 90) if s == "running" else (230, 80, 60) for s in m.states]
        rec.log("modular/arm", rr.LineStrips3D([frames], colors=[(90, 160, 230)], radii=0.025))
        rec.log(
            "modular/arm/modules",
            rr.Points3D(frames[:-1], radii=0.045, colors=colours,
                        labels=[f"j{i + 1} {s}" for i, s in enumerate(m.states)]),
        )  # fmt: skip
        rec.log("modular/tool_ref", rr.Points3D([m.tool_ref], radii=0.012, colors=[(240, 200, 40)]))
        rec.log("modular/tool_error_mm", rr.Scalars(m.tool_error_mm))
        for phase, us in zip("ABCD", m.phase_us, strict=False):
            rec.log(f"modular/cycle_us/{phase}", rr.Scalars(us))
        for i, g in enumerate(m.guessed):
            rec.log(f"modular/guessed/j{i + 1}", rr.Scalars(float(g)))
        # the SnP cycle's (transport "cycle"): each module's [A, B, C, D] and its clock's offset
        for what, values in (("cycle_us", m.module_cycle_us), ("clock_offset_us", m.clock_offset_us)):
            for i, v in enumerate(values):
                if np.isfinite(v):
                    rec.log(f"modular/{what}/j{i + 1}", rr.Scalars(v))

    def request(self, tr: skills_pb2.RequestTrace) -> None:
        """One request as a bar from its sending to its answer, on its lane (seconds since the start)."""
        lane = self.lanes.index(tr.robot) if tr.robot in self.lanes else len(self.lanes)
        if lane == len(self.lanes):
            self.lanes.append(tr.robot)
        self.bars.append(
            ((tr.sent_ns - self.t0_ns) / 1e9, (tr.received_ns - self.t0_ns) / 1e9, lane, tr.skill)
        )
        self.bars_dirty = True

    def gantt(self) -> None:
        if not self.bars_dirty:
            return
        self.bars_dirty = False
        bars = list(self.bars)
        self.rec.set_time(TIMELINE, timestamp=self.seconds(time.monotonic_ns()))
        self.rec.log(
            "gantt/requests",
            rr.Boxes2D(
                mins=[(t0, lane) for t0, _, lane, _ in bars],
                sizes=[(max(t1 - t0, 1e-5), 0.8) for t0, t1, _, _ in bars],
                colors=[
                    VISION_COLOR if self.lanes[lane] == "vision" else ROBOT_COLOR for _, _, lane, _ in bars
                ],
                labels=[f"{self.lanes[lane]}: {skill}" for _, _, lane, skill in bars],
            ),
        )


def open_recording(mode: str, path: str, name: str) -> rr.RecordingStream:
    """The run's recording: saved to `path`, served on loopback (its address logged: the one that
    opens the viewer on this recording, not on Rerun's welcome page) or in a spawned viewer."""
    rec = rr.RecordingStream(application_id=f"cell-{name}")
    if mode == "save":
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        rec.save(path)
    elif mode == "serve":  # loopback only (cell/recorder/serve.py): the SDK's own serve binds everything
        log.info("Rerun web viewer (loopback only): %s", serve.serve(rec))
    elif mode == "spawn":
        rec.spawn()
    return rec


async def record(ctx: ServiceContext, ready: Callable[[], None]) -> None:
    """Draw the cell until cancelled, as [recorder] says (its mode is not "off")."""
    cfg = ctx.config.recorder
    rec = open_recording(cfg.mode, cfg.path, ctx.config.cell.name)
    camera = "vision" in ctx.config.services.run
    modular = "modular" in ctx.config.services.run
    rec.send_blueprint(cell_blueprint([r.name for r in ctx.config.robots], camera, modular))
    r = Recorder(ctx, rec)
    r.start()
    bus = ctx.bus
    subs = {
        "truth": await bus.subscribe("truth/"),
        "fleet": await bus.subscribe("fleet/"),
        "plan": await bus.subscribe("plan/"),
        "dataplane": await bus.subscribe("dataplane/counters"),
        "events": await bus.subscribe(*EVENT_TOPICS),
        "health": await bus.subscribe("health/"),
        "vision": await bus.subscribe("vision/image", "vision/measurement"),
        "modular": await bus.subscribe("modular/state"),
        "requests": await bus.subscribe(
            "run/vision/request", *(f"run/{rb.name}/request" for rb in ctx.config.robots)
        ),
    }

    def on_truth(env) -> None:
        if r.wants_truth(env.topic.removeprefix("truth/"), env.sent_ns):
            r.truth(env.decode(robot_pb2.RobotTruth))

    def on_health(env) -> None:
        if env.type_name != health_pb2.Heartbeat.DESCRIPTOR.full_name:
            return
        hb = env.decode(health_pb2.Heartbeat)
        r.health(hb, env.sent_ns)
        if hb.service == "robots":
            r.answers(hb, env.sent_ns)
        if any(k.startswith("rlink.L") for k in hb.counters):
            r.link(hb, env.sent_ns)

    events = Events()

    def on_event(env) -> None:
        ev = events.describe(env)
        if ev is None:
            return
        msg, text = ev.msg, ev.text
        if isinstance(msg, skills_pb2.SkillTrace):
            r.skill(msg, ev)
            return
        if isinstance(msg, robot_pb2.RobotEvent) and msg.kind == robot_pb2.RobotEvent.KIND_OUTPUTS:
            r.outputs(msg)
        elif isinstance(msg, health_pb2.ServiceEvent):
            text = r.service_event(msg, text, ev.t_ns)
        r.text(ev.t_ns, text, ev.level)

    if cfg.mode == "save":
        ctx.log.info("recording to %s", cfg.path)

    def on_vision(env) -> None:
        if env.topic == "vision/image":
            r.image(env.decode(vision_pb2.VisionImage))
        else:
            r.measurement(env.decode(vision_pb2.VisionReply))

    async def flush_series() -> None:
        while True:
            await asyncio.sleep(cfg.series_batch_s)
            r.series.flush()
            r.gantt()
            ctx.counters["truth_logged"] = r.logged

    try:
        async with asyncio.TaskGroup() as tg:
            tg.create_task(each(subs["truth"], on_truth))
            tg.create_task(
                each(subs["fleet"], lambda env: r.group_truth(env.topic, env.decode(robot_pb2.GroupTruth)))
            )
            tg.create_task(each(subs["plan"], lambda env: r.plan(env.decode(controller_pb2.Plan))))
            tg.create_task(
                each(
                    subs["dataplane"],
                    lambda env: r.dataplane(env.decode(dataplane_pb2.DataplaneState), env.sent_ns),
                )
            )
            tg.create_task(each(subs["events"], on_event))
            tg.create_task(each(subs["health"], on_health))
            tg.create_task(each(subs["vision"], on_vision))
            tg.create_task(each(subs["modular"], lambda env: r.modular(env.decode(modular_pb2.ModularState))))
            tg.create_task(each(subs["requests"], lambda env: r.request(env.decode(skills_pb2.RequestTrace))))
            tg.create_task(flush_series())
            ready()
    finally:
        r.series.flush()
        r.gantt()
        serve.close(rec)
