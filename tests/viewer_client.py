"""A minimal client for viser 0.2.7's websocket protocol (the one nerfstudio 1.1.5's ``ns-viewer`` serves),
plus helpers to run the real ``ns-viewer`` CLI as a bounded subprocess.

Protocol, as implemented by ``viser/infra/_infra.py`` and the prebuilt web client
(``viser/client/build/assets/WebsocketServerWorker-*.js``):

* HTTP and websocket share one port. A plain ``GET /`` (no ``Upgrade`` header) returns the client's
  ``index.html``; an upgrade request opens the websocket (no subprotocol, binary frames only).
* Server -> client: every binary frame is one msgpack *array* of messages (``client_api_version=1``
  windows them, up to 128 per frame). Each message is a msgpack map whose ``"type"`` is the Python
  class name in ``viser/_messages.py``; the other keys are that dataclass's fields; ``bytes`` travel as msgpack
  ``bin``. New connections first get the persistent broadcast state (GUI, scene nodes such as nerfstudio's
  training-camera frustums), then live updates.
* Client -> server: every binary frame is one msgpack *map* (a single message). The server rebuilds the
  dataclass with exactly these keys, so a message must carry all fields and nothing else.
* A client counts as connected (``ViserServer.on_client_connect`` fires; nerfstudio starts that client's
  ``RenderStateMachine``) when its first ``ViewerCameraMessage`` arrives: ``wxyz`` / ``position`` are
  T_world_camera in OpenCV axes (+Z forward, -Y up) in viser's world units, ``fov`` is the vertical field of
  view in radians, ``aspect`` is width / height.
* nerfstudio answers each camera update (and then, on its own, with higher-resolution static passes) by
  sending that client a ``BackgroundImageMessage`` (``media_type`` ``image/jpeg`` or ``image/png``,
  ``rgb_bytes``, optional ``depth_bytes``).
"""

from __future__ import annotations

import asyncio
import contextlib
import io
import math
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Sequence

import msgspec
import numpy as np
from websockets.asyncio.client import ClientConnection, connect

Message = Dict[str, Any]

LOOPBACK = "127.0.0.1"


# ----------------------------------------------------------------------------------------------------------------------
# Subprocess handling
# ----------------------------------------------------------------------------------------------------------------------


def free_loopback_port() -> int:
    """A TCP port that was free on 127.0.0.1 a moment ago (the OS picks it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind((LOOPBACK, 0))
        return int(sock.getsockname()[1])


def console_script(name: str) -> str:
    """Path of a console script installed next to the running interpreter (the venv's ``bin``)."""
    candidate = Path(sys.executable).parent / name
    if candidate.exists():
        return str(candidate)
    return name


def _tail(path: Path, max_chars: int = 6000) -> str:
    try:
        text = path.read_text(errors="replace")
    except OSError:
        return ""
    return text if len(text) <= max_chars else "...\n" + text[-max_chars:]


@dataclass
class CliProcess:
    """A CLI started in its own session (process group) with stdout / stderr in files, so that it can
    neither block on a full pipe nor outlive the test."""

    argv: Sequence[str]
    log_dir: Path
    env: Optional[Dict[str, str]] = None
    cwd: Optional[Path] = None
    popen: Optional[subprocess.Popen] = None
    stdout_path: Path = field(init=False)
    stderr_path: Path = field(init=False)

    def __post_init__(self) -> None:
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.stdout_path = self.log_dir / "stdout.txt"
        self.stderr_path = self.log_dir / "stderr.txt"

    def start(self) -> "CliProcess":
        with open(self.stdout_path, "wb") as out, open(self.stderr_path, "wb") as err:
            self.popen = subprocess.Popen(
                list(self.argv),
                stdin=subprocess.DEVNULL,
                stdout=out,
                stderr=err,
                env=self.env,
                cwd=self.cwd,
                start_new_session=True,  # own process group: killpg reaches its children too
            )
        return self

    def alive(self) -> bool:
        return self.popen is not None and self.popen.poll() is None

    def logs(self) -> str:
        return (
            f"$ {' '.join(map(str, self.argv))}\n"
            f"--- returncode: {None if self.popen is None else self.popen.poll()}\n"
            f"--- stdout (tail):\n{_tail(self.stdout_path)}\n--- stderr (tail):\n{_tail(self.stderr_path)}"
        )

    def stop(self, grace_s: float = 10.0) -> None:
        """SIGTERM the whole process group, then SIGKILL it if it is still there after ``grace_s``."""
        if self.popen is None:
            return
        try:
            pgid = os.getpgid(self.popen.pid)
        except ProcessLookupError:
            pgid = None
        if pgid is not None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(pgid, signal.SIGTERM)
        try:
            self.popen.wait(timeout=grace_s)
        except subprocess.TimeoutExpired:
            pass
        if pgid is not None:
            # Children may survive their leader; make sure the group is gone.
            with contextlib.suppress(ProcessLookupError):
                os.killpg(pgid, signal.SIGKILL)
        with contextlib.suppress(subprocess.TimeoutExpired):
            self.popen.wait(timeout=grace_s)


def wait_for_port(process: CliProcess, port: int, timeout_s: float, host: str = LOOPBACK) -> float:
    """Poll until ``host:port`` accepts TCP connections; return the seconds it took.

    Raises ``TimeoutError`` (with the process's logs) after ``timeout_s`` and ``RuntimeError`` as soon as the
    process exits."""
    start = time.monotonic()
    while True:
        if not process.alive():
            raise RuntimeError(f"process exited before {host}:{port} opened\n{process.logs()}")
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
            sock.settimeout(1.0)
            if sock.connect_ex((host, port)) == 0:
                return time.monotonic() - start
        if time.monotonic() - start > timeout_s:
            raise TimeoutError(f"{host}:{port} not open after {timeout_s:.0f} s\n{process.logs()}")
        time.sleep(0.25)


def http_get(url: str, timeout_s: float = 15.0) -> tuple[int, Dict[str, str], bytes]:
    """Plain HTTP GET (no gzip asked for): status, headers, body."""
    request = urllib.request.Request(url, headers={"Accept-Encoding": "identity"})
    with urllib.request.urlopen(request, timeout=timeout_s) as response:
        return response.status, dict(response.headers.items()), response.read()


# ----------------------------------------------------------------------------------------------------------------------
# The websocket protocol
# ----------------------------------------------------------------------------------------------------------------------


def encode_client_message(message: Message) -> bytes:
    """One client -> server frame: a single msgpack map with a ``type`` key."""
    assert "type" in message, message
    return msgspec.msgpack.encode(message)


def decode_server_frame(frame: bytes) -> List[Message]:
    """One server -> client frame: a msgpack array of message maps."""
    decoded = msgspec.msgpack.decode(frame)
    if isinstance(decoded, dict):  # client_api_version=0 servers send single messages
        decoded = [decoded]
    assert isinstance(decoded, list), type(decoded)
    return decoded


def viewer_camera_message(
    wxyz: Sequence[float],
    position: Sequence[float],
    fov: float,
    aspect: float,
    look_at: Optional[Sequence[float]] = None,
    up_direction: Optional[Sequence[float]] = None,
) -> Message:
    """A ``ViewerCameraMessage`` as the web client sends it (T_world_camera, OpenCV axes, vertical fov in rad).

    ``look_at`` defaults to one unit along the camera's +Z and ``up_direction`` to the camera's -Y, which is what
    viser itself derives from a pose."""
    R = quat_wxyz_to_matrix(wxyz)
    pos = np.asarray(position, dtype=np.float64)
    if look_at is None:
        look_at = pos + R[:, 2]
    if up_direction is None:
        up_direction = -R[:, 1]
    return {
        "type": "ViewerCameraMessage",
        "wxyz": [float(v) for v in wxyz],
        "position": [float(v) for v in pos],
        "fov": float(fov),
        "aspect": float(aspect),
        "look_at": [float(v) for v in look_at],
        "up_direction": [float(v) for v in up_direction],
    }


def quat_wxyz_to_matrix(wxyz: Sequence[float]) -> np.ndarray:
    w, x, y, z = (float(v) for v in wxyz)
    n = math.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


@dataclass
class Frustum:
    """A camera frustum scene node (nerfstudio draws one per training camera)."""

    name: str
    fov: float  # what nerfstudio passes: 2 * atan(cx / fx), i.e. the HORIZONTAL fov for a centred principal point
    aspect: float  # cx / cy
    wxyz: Optional[Sequence[float]] = None
    position: Optional[Sequence[float]] = None
    image_media_type: Optional[str] = None
    image_binary: Optional[bytes] = None  # nerfstudio attaches the training image, resized to 100 px high

    def thumbnail(self) -> Optional[np.ndarray]:
        """The frustum's image as [H, W, 3] uint8, if it has one."""
        if self.image_binary is None:
            return None
        return decode_image_bytes(self.image_binary, self.image_media_type)

    @property
    def posed(self) -> bool:
        return self.wxyz is not None and self.position is not None

    def camera_message(self) -> Message:
        """A viewer camera looking through this frustum (same pose; vertical fov derived from the horizontal)."""
        assert self.posed, self.name
        vertical_fov = 2.0 * math.atan(math.tan(self.fov / 2.0) / self.aspect)
        return viewer_camera_message(self.wxyz, self.position, vertical_fov, self.aspect)


@dataclass
class DecodedImage:
    media_type: str
    rgb: np.ndarray  # [H, W, 3] uint8
    encoded_size: int
    received_at: float


def decode_image_bytes(data: bytes, media_type: Optional[str]) -> np.ndarray:
    """JPEG / PNG bytes -> [H, W, 3] uint8; checks that the bytes are what ``media_type`` says."""
    from PIL import Image

    expected_format = {"image/jpeg": "JPEG", "image/png": "PNG"}.get(media_type or "")
    assert expected_format is not None, f"unexpected media type {media_type!r}"
    with Image.open(io.BytesIO(data)) as image:
        assert image.format == expected_format, (image.format, media_type)
        return np.asarray(image.convert("RGB"))


def decode_background_image(message: Message) -> DecodedImage:
    assert message["type"] == "BackgroundImageMessage", message["type"]
    data, media_type = message["rgb_bytes"], message["media_type"]
    return DecodedImage(media_type, decode_image_bytes(data, media_type), len(data), time.monotonic())


class ViserProtocolClient:
    """Speaks viser's websocket protocol; keeps the scene state it needs (frustums) and a log of messages."""

    def __init__(self, websocket: ClientConnection) -> None:
        self.websocket = websocket
        self.frustums: Dict[str, Frustum] = {}
        self.type_counts: Dict[str, int] = {}
        self._pending: List[Message] = []

    @classmethod
    @contextlib.asynccontextmanager
    async def connect(cls, url: str, open_timeout_s: float = 30.0):
        async with connect(
            url,
            open_timeout=open_timeout_s,
            close_timeout=2,
            max_size=None,  # the initial state (frustum thumbnails) can exceed websockets' 1 MiB default
            ping_interval=None,
        ) as websocket:
            yield cls(websocket)

    async def send(self, message: Message) -> None:
        await self.websocket.send(encode_client_message(message))

    async def send_camera(self, message: Message) -> None:
        assert message["type"] == "ViewerCameraMessage"
        await self.send(message)

    def _observe(self, message: Message) -> None:
        kind = message.get("type", "?")
        self.type_counts[kind] = self.type_counts.get(kind, 0) + 1
        if kind == "CameraFrustumMessage":
            self.frustums[message["name"]] = Frustum(
                message["name"],
                float(message["fov"]),
                float(message["aspect"]),
                image_media_type=message.get("image_media_type"),
                image_binary=message.get("image_binary"),
            )
        elif kind in ("SetOrientationMessage", "SetPositionMessage") and message["name"] in self.frustums:
            frustum = self.frustums[message["name"]]
            if kind == "SetOrientationMessage":
                frustum.wxyz = tuple(message["wxyz"])
            else:
                frustum.position = tuple(message["position"])
        elif kind == "RemoveSceneNodeMessage":
            self.frustums.pop(message["name"], None)

    async def next_message(self) -> Message:
        while not self._pending:
            frame = await self.websocket.recv()
            assert isinstance(frame, bytes), f"viser sends binary frames, got {type(frame)}"
            self._pending.extend(decode_server_frame(frame))
        message = self._pending.pop(0)
        self._observe(message)
        return message

    async def wait_for(self, predicate: Callable[[Message], bool], timeout_s: float) -> Message:
        """The next message that satisfies ``predicate`` (all messages on the way are observed)."""

        async def loop() -> Message:
            while True:
                message = await self.next_message()
                if predicate(message):
                    return message

        return await asyncio.wait_for(loop(), timeout_s)

    async def wait_until(self, condition: Callable[[], bool], timeout_s: float) -> None:
        """Read messages until ``condition()`` holds (checked before each message)."""

        async def loop() -> None:
            while not condition():
                await self.next_message()

        await asyncio.wait_for(loop(), timeout_s)

    async def drain(self, quiet_s: float, max_s: float) -> int:
        """Read whatever arrives until nothing came for ``quiet_s`` (or ``max_s`` passed); return the count."""
        deadline = time.monotonic() + max_s
        count = 0
        while time.monotonic() < deadline:
            try:
                await asyncio.wait_for(self.next_message(), min(quiet_s, max(deadline - time.monotonic(), 0.01)))
            except asyncio.TimeoutError:
                break
            count += 1
        return count

    def posed_frustums(self) -> List[Frustum]:
        return [f for _, f in sorted(self.frustums.items()) if f.posed]

    async def next_frame(self, timeout_s: float) -> DecodedImage:
        message = await self.wait_for(lambda m: m.get("type") == "BackgroundImageMessage", timeout_s)
        return decode_background_image(message)
