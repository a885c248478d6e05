"""The emulator's cameras: the plant rendered and served as MJPEG over HTTP.

``GET /<camera>`` answers a ``multipart/x-mixed-replace`` stream of JPEG frames at the
camera's rate, which OpenCV (and so the driver's
:class:`~twinrl_robot.ur.cameras.OpenCVCamera`) opens like an IP camera. Frames are
rendered from a copy of the physics state, so rendering never holds the servo loop.
"""

from __future__ import annotations

import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import cv2
import mujoco
import numpy as np

from twinrl_robot.ur.emulator.arm import EmulatedArm

BOUNDARY = "twinrlframe"


class CameraServer(ThreadingHTTPServer):
    """Serves each of ``cameras`` (name -> (width, height, fps)) at ``/<name>``."""

    daemon_threads = True
    allow_reuse_address = True

    def __init__(
        self, address: tuple[str, int], arm: EmulatedArm, cameras: dict[str, tuple[int, int, float]]
    ) -> None:
        self.arm, self.cameras = arm, cameras
        self.running = True
        self._render_lock = threading.Lock()  # one GL context, one renderer at a time
        self._renderers: dict[tuple[int, int], mujoco.Renderer] = {}
        self._data = mujoco.MjData(arm.cell.model)
        super().__init__(address, _StreamHandler)

    def render(self, camera: str, width: int, height: int) -> bytes:
        """One JPEG of ``camera`` at the arm's current state."""
        model = self.arm.cell.model
        with self._render_lock:
            with self.arm.lock:
                source = self.arm.cell.data
                self._data.qpos[:] = source.qpos
                self._data.mocap_pos[:] = source.mocap_pos
                self._data.mocap_quat[:] = source.mocap_quat
            mujoco.mj_forward(model, self._data)
            renderer = self._renderers.get((width, height))
            if renderer is None:
                renderer = mujoco.Renderer(model, height=height, width=width)
                self._renderers[(width, height)] = renderer
            renderer.update_scene(self._data, camera=camera)
            rgb = renderer.render()
        ok, jpeg = cv2.imencode(".jpg", np.ascontiguousarray(rgb[..., ::-1]))
        return jpeg.tobytes() if ok else b""


class _StreamHandler(BaseHTTPRequestHandler):
    server: CameraServer

    def log_message(self, format: str, *args: object) -> None:
        return None

    def do_GET(self) -> None:
        name = self.path.strip("/")
        if name not in self.server.cameras:
            self.send_error(404, f"no camera {name!r}; this cell has {sorted(self.server.cameras)}")
            return
        width, height, fps = self.server.cameras[name]
        self.send_response(200)
        self.send_header("Content-Type", f"multipart/x-mixed-replace; boundary={BOUNDARY}")
        self.send_header("Cache-Control", "no-cache")
        self.end_headers()
        period = 1.0 / fps
        next_frame = time.monotonic()
        try:
            while self.server.running:
                jpeg = self.server.render(name, width, height)
                self.wfile.write(
                    f"--{BOUNDARY}\r\nContent-Type: image/jpeg\r\n"
                    f"Content-Length: {len(jpeg)}\r\n\r\n".encode()
                )
                self.wfile.write(jpeg + b"\r\n")
                self.wfile.flush()
                next_frame += period
                time.sleep(max(0.0, next_frame - time.monotonic()))
        except (BrokenPipeError, ConnectionResetError):
            return
