"""``ns-viewer --load-config`` on a checkpoint from the real trainer serves the web client and streams rendered frames
to a real websocket client.

The client (``viewer_client.py``) speaks viser 0.2.7's protocol the way the prebuilt browser client does: it
receives the scene state (including nerfstudio's training-camera frustums with their thumbnails), sends a
``ViewerCameraMessage`` and decodes the ``BackgroundImageMessage`` JPEG/PNG frames that the viewer's render thread
pushes back. The viewer runs as the real CLI in its own process group on a free 127.0.0.1 port; every wait is
bounded and the process group is killed at the end whatever happens. The bounds are hang guards far above a normal
run (multiplied by ``GSMSDR_TEST_TIMEOUT_SCALE``, see ``conftest.py``); nothing is asserted about speed.
"""

from __future__ import annotations

import asyncio
import os
import re
import time
from dataclasses import dataclass
from typing import Dict, Iterator, List, Tuple

import numpy as np
import pytest
from conftest import scaled
from viewer_client import (
    LOOPBACK,
    CliProcess,
    DecodedImage,
    Frustum,
    ViserProtocolClient,
    console_script,
    free_loopback_port,
    http_get,
    wait_for_port,
)

STARTUP_TIMEOUT_S = scaled(300.0)  # imports + checkpoint load + viser start
BANNER_TIMEOUT_S = scaled(30.0)  # the banner follows the open port
SCENE_TIMEOUT_S = scaled(120.0)  # training-camera frustums arrive once the viewer has drawn them (init_scene)
FRAME_TIMEOUT_S = scaled(120.0)  # first frame after a camera message
SESSION_TIMEOUT_S = scaled(420.0)  # the whole websocket session: scene state, then frames for two cameras
HIGH_RES_SIDE = 256  # the static pass renders at the control panel's max_res (512 by default)


@dataclass
class RunningViewer:
    process: CliProcess
    port: int
    startup_s: float

    @property
    def http_url(self) -> str:
        return f"http://{LOOPBACK}:{self.port}"

    @property
    def ws_url(self) -> str:
        return f"ws://{LOOPBACK}:{self.port}"


def _wait_for_banner(process: CliProcess, port: int, timeout_s: float) -> None:
    """viser moves to the next port silently when the asked one is taken: make sure it serves the one we asked."""
    deadline = time.monotonic() + timeout_s
    pattern = re.compile(rf"ws://{re.escape(LOOPBACK)}:(\d+)")
    while True:
        match = pattern.search(process.stdout_path.read_text(errors="replace"))
        if match:
            assert int(match.group(1)) == port, f"viser bound port {match.group(1)}, not {port}\n{process.logs()}"
            return
        if not process.alive():
            raise RuntimeError(f"ns-viewer exited\n{process.logs()}")
        if time.monotonic() > deadline:
            raise TimeoutError(f"no viser banner for port {port} after {timeout_s:.0f} s\n{process.logs()}")
        time.sleep(0.2)


@pytest.fixture(scope="module")
def ns_viewer(trained_run, tmp_path_factory: pytest.TempPathFactory) -> Iterator[RunningViewer]:
    """The real ``ns-viewer`` CLI on the session's trained run, bound to 127.0.0.1 on a free port."""
    work = tmp_path_factory.mktemp("ns_viewer")
    port = free_loopback_port()
    argv = [
        console_script("ns-viewer"),
        "--load-config", str(trained_run.config),
        "--viewer.websocket-host", LOOPBACK,
        "--viewer.websocket-port", str(port),
    ]  # fmt: skip
    env = dict(os.environ, PYTHONUNBUFFERED="1", COLUMNS="200")
    process = CliProcess(argv, log_dir=work / "logs", env=env, cwd=work)
    start = time.monotonic()
    process.start()
    try:
        wait_for_port(process, port, STARTUP_TIMEOUT_S)
        _wait_for_banner(process, port, BANNER_TIMEOUT_S)
        yield RunningViewer(process, port, time.monotonic() - start)
        assert process.alive(), f"ns-viewer died during the tests\n{process.logs()}"
    finally:
        process.stop(grace_s=10.0)
    assert process.popen is not None and process.popen.returncode is not None, "ns-viewer survived SIGKILL"


# ----------------------------------------------------------------------------------------------------------------------
# image checks


def _assert_textured(frame: DecodedImage, what: str) -> None:
    rgb = frame.rgb
    assert rgb.dtype == np.uint8 and rgb.ndim == 3 and rgb.shape[2] == 3, (what, rgb.shape, rgb.dtype)
    luminance = rgb.astype(np.float64) @ np.array([0.299, 0.587, 0.114])
    distinct = len(np.unique(rgb.reshape(-1, 3), axis=0))
    assert luminance.std() > 2.0 and distinct >= 16, (
        f"{what}: {rgb.shape[1]}x{rgb.shape[0]} looks constant (luminance std {luminance.std():.2f}, "
        f"{distinct} distinct colours)"
    )


def _assert_size(frame: DecodedImage, aspect: float, what: str) -> None:
    height, width = frame.rgb.shape[:2]
    assert min(height, width) >= 16 and max(height, width) <= 4096, f"{what}: odd size {width}x{height}"
    # nerfstudio renders at the requested aspect and pads to it; allow rounding to whole pixels.
    assert abs(width / height - aspect) <= 2.0 / height + 0.02 * aspect, f"{what}: {width}x{height} vs aspect {aspect}"


def _similarity(a: np.ndarray, b: np.ndarray, size: Tuple[int, int] = (32, 24)) -> float:
    """Pearson correlation of two RGB images after resizing both to ``size`` (blur-tolerant)."""
    from PIL import Image

    def prep(rgb: np.ndarray) -> np.ndarray:
        small = np.asarray(Image.fromarray(rgb).resize(size, Image.BILINEAR), dtype=np.float64).ravel()
        return small - small.mean()

    x, y = prep(a), prep(b)
    return float(x @ y / max(np.sqrt((x @ x) * (y @ y)), 1e-12))


def _most_different_pair(frustums: List[Frustum]) -> Tuple[Frustum, Frustum]:
    """The first training camera and the one whose thumbnail resembles its thumbnail least."""
    first = frustums[0]
    thumb = first.thumbnail()
    other = min(frustums[1:], key=lambda f: _similarity(thumb, f.thumbnail()))
    return first, other


# ----------------------------------------------------------------------------------------------------------------------
# tests


def test_ns_viewer_serves_web_client_over_http(ns_viewer: RunningViewer) -> None:
    status, headers, body = http_get(ns_viewer.http_url + "/")
    assert status == 200
    assert headers.get("Content-Type", "").startswith("text/html"), headers
    html = body.decode("utf-8", errors="replace")
    assert "<html" in html.lower(), html[:500]
    # The page's script bundle is served too (the viewer needs no node / client build at run time).
    scripts = re.findall(r'<script[^>]+src="([^"]+\.js)"', html)
    assert scripts, html[:1000]
    status, headers, js = http_get(ns_viewer.http_url + "/" + scripts[0].lstrip("/"))
    assert status == 200 and len(js) > 100_000, (scripts[0], status, len(js))
    assert "javascript" in headers.get("Content-Type", ""), headers


@pytest.mark.timeout(480, func_only=True)  # scaled in conftest; above SESSION_TIMEOUT_S
def test_ns_viewer_streams_rendered_frames_to_websocket_client(ns_viewer: RunningViewer) -> None:
    timings: Dict[str, float] = {"viewer_startup_s": ns_viewer.startup_s}

    async def session() -> Tuple[Dict[str, List[DecodedImage]], List[Frustum]]:
        async with ViserProtocolClient.connect(ns_viewer.ws_url) as client:
            start = time.monotonic()
            # nerfstudio draws one frustum (pose + thumbnail) per training camera right after the server starts.
            await client.wait_until(lambda: len(client.posed_frustums()) >= 2, SCENE_TIMEOUT_S)
            await client.drain(quiet_s=0.5, max_s=10.0)
            frustums = [f for f in client.posed_frustums() if f.image_binary is not None]
            assert len(frustums) >= 2, (client.type_counts, sorted(client.frustums))
            timings["scene_state_s"] = time.monotonic() - start

            frames: Dict[str, List[DecodedImage]] = {}
            for frustum in _most_different_pair(frustums):
                # Each camera message is a "move": a quick low-resolution frame comes first, then static
                # passes up to max_res. Collect until a high-resolution frame for this camera arrived.
                sent = time.monotonic()
                await client.send_camera(frustum.camera_message())
                received = [await client.next_frame(FRAME_TIMEOUT_S)]
                timings.setdefault("first_frame_s", time.monotonic() - sent)
                while max(received[-1].rgb.shape[:2]) < HIGH_RES_SIDE:
                    received.append(await client.next_frame(FRAME_TIMEOUT_S))
                timings[f"high_res_frame_s[{frustum.name}]"] = time.monotonic() - sent
                # Nothing rendered for this camera may be mistaken for the next one's frames.
                await client.drain(quiet_s=1.0, max_s=10.0)
                frames[frustum.name] = received
            return frames, frustums

    start = time.monotonic()
    try:
        frames, frustums = asyncio.run(asyncio.wait_for(session(), timeout=SESSION_TIMEOUT_S))
    except Exception as exc:  # timeouts, a closed connection, a failed check: show what the viewer said
        raise AssertionError(
            f"websocket session failed after {time.monotonic() - start:.1f} s ({type(exc).__name__}: {exc}); "
            f"timings so far {timings}\n{ns_viewer.process.logs()}"
        ) from exc
    timings["websocket_session_s"] = time.monotonic() - start
    print("ns-viewer timings:", {k: round(v, 2) for k, v in timings.items()})

    by_name = {f.name: f for f in frustums}
    for name, received in frames.items():
        aspect = by_name[name].aspect
        for index, frame in enumerate(received):
            what = f"frame {index} for {name} ({frame.media_type})"
            _assert_size(frame, aspect, what)
            _assert_textured(frame, what)

    # The renders show the scene from the camera that was sent: each high-resolution frame resembles its own
    # training image (the frustum's thumbnail) more than the other camera's.
    (name_a, frames_a), (name_b, frames_b) = frames.items()
    thumb_a, thumb_b = by_name[name_a].thumbnail(), by_name[name_b].thumbnail()
    render_a, render_b = frames_a[-1].rgb, frames_b[-1].rgb
    scores = {
        "a~thumb_a": _similarity(render_a, thumb_a),
        "a~thumb_b": _similarity(render_a, thumb_b),
        "b~thumb_b": _similarity(render_b, thumb_b),
        "b~thumb_a": _similarity(render_b, thumb_a),
    }
    print("render/thumbnail correlations:", {k: round(v, 3) for k, v in scores.items()}, name_a, name_b)
    assert scores["a~thumb_a"] > max(scores["a~thumb_b"], 0.2), scores
    assert scores["b~thumb_b"] > max(scores["b~thumb_a"], 0.2), scores

    # The render thread and viser's handlers report their exceptions on stderr only.
    stderr = ns_viewer.process.stderr_path.read_text(errors="replace")
    assert "Traceback" not in stderr, ns_viewer.process.logs()
