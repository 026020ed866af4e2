"""Vision: the Fig. 7 sharpness pipeline step by step, the thin lens, the frame buffer, the MuJoCo
camera, and the focus calibration (`ufloop`) on a whole cell."""

from __future__ import annotations

import itertools
import json
import subprocess
import sys

import cv2
import numpy as np
import pytest
from rerun.chunk import RrdReader

from cell.vision import sharpness as sh
from cell.vision.camera import Camera, CameraSpec
from cell.vision.frames import Frame, FrameBuffer
from cell.vision.optics import ReadNoise, ThinLens, expose, psf_sigma
from cell.vision.target import target_image
from tests.conftest import cell_env, cell_overrides, write_config

Q0 = np.array([0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0])


def scene(card_px_per_mm: float = 8.0, blur_px: float = 0.0, noise: float = 0.0) -> np.ndarray:
    """The card on a dark background, as a camera would see it, blurred by `blur_px`."""
    img = np.full((480, 640), 60, np.uint8)
    card = target_image(card_px_per_mm)
    h, w = card.shape
    y, x = (480 - h) // 2, (640 - w) // 2
    img[y : y + h, x : x + w] = card
    return expose(img, blur_px, noise, np.random.default_rng(1))


def test_each_step_of_the_pipeline_does_its_part() -> None:
    p = sh.Params()
    img = scene()
    light = sh.highlight_light(img, p)
    assert set(np.unique(light)) == {0, 255}
    card_rows = light[(480 - 240) // 2 : (480 + 240) // 2]
    assert (card_rows == 0).any()  # the black lines cut the light card ...
    closed = sh.erosion(light, p)
    stats = sh.find_ccomp(closed)
    region = sh.identify_object_region(stats, p, img.shape)
    assert region is not None  # ... and after the erosion of the lines the card is one component
    x, y, w, h = region
    assert (w, h) == (320, 240) and (x, y) == (160, 120)
    roi = sh.crop_roi(img, region)
    assert roi.shape == (240, 320)
    profile = sh.h_profile_sobelx(sh.sobel_x(roi))
    assert profile.shape == (320,)
    assert sh.measure_sharpness(profile) == pytest.approx(float(np.std(profile)))


def test_sharpness_falls_as_the_blur_grows() -> None:
    values = [sh.sharpness(scene(blur_px=b, noise=1.5)).sharpness for b in (0, 1, 2, 4, 8)]
    assert all(a > b for a, b in itertools.pairwise(values)), values


@pytest.mark.parametrize(
    "image, why",
    [
        (np.zeros((480, 640), np.uint8), "no calibration object"),
        (np.full((480, 640), 255, np.uint8), "no calibration object"),  # all light: no card shape
        (np.zeros((480, 640), np.float32), "not an 8-bit"),
        (np.zeros((0, 0), np.uint8), "not an 8-bit"),
    ],
)
def test_no_card_is_an_answer_not_a_crash(image: np.ndarray, why: str) -> None:
    r = sh.sharpness(image)
    assert not r.found and why in r.reason


def test_a_colour_frame_is_measured_as_grey() -> None:
    grey = scene()
    colour = cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)
    assert sh.sharpness(colour).sharpness == pytest.approx(sh.sharpness(grey).sharpness, rel=1e-6)


def test_the_thin_lens_blurs_by_distance_from_the_focus_plane() -> None:
    lens = ThinLens(35.0, 2.0, 350.0, 11.25)
    assert lens.coc_px(350.0) == 0.0
    # c = (f/N) |d - s| / d * f / (s - f), in pixels
    assert lens.coc_px(360.0) == pytest.approx(17.5 * 10 / 360 * 35 / 315 * 1000 / 11.25)
    assert lens.coc_px(340.0) > lens.coc_px(345.0) > 0
    assert psf_sigma(2 * np.sqrt(2)) == pytest.approx(1.0)  # the disc's second moment: r^2 / 2 per axis


def test_the_buffer_answers_with_the_frame_closest_in_time() -> None:
    buf = FrameBuffer(3)
    assert buf.closest(5) is None
    for t in (10, 20, 30, 40):
        buf.add(Frame(t, np.zeros((1, 1), np.uint8), 0.0, 0.0, 0))
    assert [buf.closest(t).t_ns for t in (0, 24, 26, 35, 99)] == [20, 20, 30, 40, 40]  # 10 fell out
    assert buf.newest().t_ns == 40 and buf.added == 4


def test_the_camera_sees_the_card_sharpest_at_its_focus_distance() -> None:
    values = {}
    for offset_mm in (-8.0, 0.0, 8.0):  # move the camera so that the card is off, at and past focus
        spec = CameraSpec(position_m=(-0.4919, -0.1333, 0.05 + 0.0859 + offset_mm / 1000))
        cam = Camera(spec)
        try:
            img, dist = cam.capture(Q0)
        finally:
            cam.close()
        r = sh.sharpness(img)
        assert r.found, r.reason
        values[round(dist)] = r.sharpness
    assert set(values) == {358, 350, 342}
    assert values[350] > 1.3 * max(values[358], values[342])


def test_a_still_scene_is_rendered_once_and_each_frame_gets_its_own_noise() -> None:
    cam = Camera(CameraSpec())
    try:
        a, dist_a = cam.capture(Q0)
        b, dist_b = cam.capture(Q0 + 1e-7)  # (well under a hundredth of a pixel at the card)
        assert (cam.renders, cam.reused) == (1, 1) and dist_a == dist_b
        diff = a.astype(float) - b.astype(float)
        # the same picture (no offset between the two) under independent noise: sqrt(2) x 1.5 grey
        # levels, less the quantisation's share; a frame with the first frame's noise again would be 0
        assert abs(diff.mean()) < 0.05 and 1.6 < diff.std() < 2.6
        moved = Q0.copy()
        moved[5] += 0.2  # the wrist turns the card under the camera: rendered anew
        c, _ = cam.capture(moved)
        assert (cam.renders, cam.reused) == (2, 1)
        assert np.abs(c.astype(float) - a.astype(float)).mean() > 2 * np.abs(diff).mean()
    finally:
        cam.close()


def test_read_noise_windows_are_gaussian_and_differ_from_frame_to_frame() -> None:
    noise = ReadNoise((48, 64), 1.5, np.random.default_rng(3))
    zero = np.zeros((48, 64), np.float32)
    frames = [noise.add_to(zero) for _ in range(200)]
    stack = np.stack(frames)
    assert abs(stack.mean()) < 0.05 and 1.45 < stack.std() < 1.55
    assert all(f.shape == (48, 64) and f.dtype == np.float32 for f in frames)
    same = sum(np.array_equal(frames[k], frames[k + 1]) for k in range(len(frames) - 1))
    assert same == 0
    assert zero.max() == 0  # (added to a new array: the clean image is kept for the next frame)


@pytest.mark.slow
def test_the_focus_calibration_finds_the_focus_plane_on_a_whole_cell(tmp_path) -> None:
    rrd = tmp_path / "focus.rrd"
    # free ports: the default config's fixed bus port may still be held by a cell an earlier test stopped
    data = cell_overrides()
    data["recorder"] = {"mode": "save", "path": str(rrd)}
    config = write_config(tmp_path / "rec.toml", data)
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "cell",
            "run",
            "examples/focus_calibration.py",
            "--up",
            "--config",
            str(config),
        ],
        # the paper's 25 % approach speed would only make the test longer: the loop is the same
        env={**cell_env(), "APPR_SPEED": "60"},
        capture_output=True,
        text=True,
        timeout=180,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    line = next(x for x in reversed(proc.stdout.splitlines()) if x.startswith("{"))
    r = json.loads(line)
    assert abs(r["focus_error_mm"]) <= r["delta_z_mm"]
    s = r["sharpness"]
    assert r["increments"] == len(s) - 1 >= 3
    assert 0 < r["peak_index"] < len(s) - 1  # the peak is inside the sweep, not at its ends
    assert s[-1] < s[-2]  # the loop stopped because the sharpness fell
    rows: dict[str, int] = {}
    for chunk in RrdReader(rrd).stream():
        rows[str(chunk.entity_path)] = rows.get(str(chunk.entity_path), 0) + chunk.num_rows
    assert rows.get("/vision/camera", 0) > 10  # the camera's frames
    assert rows.get("/vision/sharpness", 0) >= len(s)  # the curve: every measurement
    assert rows.get("/gantt/requests", 0) >= 1  # vision and robot requests as bars


@pytest.mark.slow
async def test_requests_for_odd_instants_get_a_frame_and_a_killed_camera_comes_back(start_cell) -> None:
    """vision.measure with instants it cannot have (far ahead, before any frame, negative) is answered
    with the closest frame it has, in bounded time; SIGKILL of the camera's process is restarted and
    measures again."""
    import asyncio
    import os
    import signal
    import time

    from cell.bus import Bus
    from cell.launcher import fetch_status
    from cell.v1 import vision_pb2
    from cell.vision.client import VisionClient
    from tests.conftest import free_port

    robots = [{"id": 1, "name": "r1", "skill_port": free_port(), "backend": "kinematic"}]
    cell = await start_cell(run=["bus", "dataplane", "robots", "vision"], robots=robots)
    async with Bus.connect(cell.config.bus, "test") as bus:
        vision = VisionClient(bus)
        now = time.monotonic_ns()
        for t_ns in (now + 10**12, 1, -(10**9)):  # 1000 s ahead; the boot; before the clock began
            t0 = time.monotonic()
            req = vision_pb2.VisionRequest(id="odd", t_ns=t_ns)
            r = await bus.request("vision", "measure", req, vision_pb2.VisionReply, 5.0)
            assert r.id == "odd" and r.found and r.sharpness > 0 and r.frame_t_ns > 0
            assert time.monotonic() - t0 < 1.0  # at most two frame periods (0.2 s) waited, plus work
        assert (await vision.request()).found  # and an ordinary request after them
        status = await fetch_status(cell.config)
        pid = next(s for s in status.services if s.name == "vision").last.pid
        os.kill(pid, signal.SIGKILL)
        async with asyncio.timeout(30):
            while True:
                s = next(s for s in (await fetch_status(cell.config)).services if s.name == "vision")
                if s.health == "ok" and s.last.pid not in (0, pid):
                    break
                await asyncio.sleep(0.2)
        assert s.last.restarts >= 1
        m = await vision.request(timeout=10.0)
        assert m.found and m.sharpness > 0
