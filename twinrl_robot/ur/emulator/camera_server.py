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
    """Serves each of ``cameras`` (name -> (width, height, fps)) at ``/<name>``.

    One thread renders every camera at its rate (an OpenGL context belongs to one thread)
    and keeps each camera's newest JPEG; each client's thread sends the frames as they come.
    """

    daemon_threads = True
    allow_reuse_address = True

    def __init__(
        self, address: tuple[str, int], arm: EmulatedArm, cameras: dict[str, tuple[int, int, float]]
    ) -> None:
        self.arm, self.cameras = arm, cameras
        self.running = True
        self.frames: dict[str, tuple[int, bytes]] = {}  # camera -> (frame number, JPEG)
        self.new_frame = threading.Condition()
        self._data = mujoco.MjData(arm.cell.model)
        super().__init__(address, _StreamHandler)
        threading.Thread(target=self._render_loop, name="cameras", daemon=True).start()

    def _render_loop(self) -> None:
        model = self.arm.cell.model
        renderers = {
            name: mujoco.Renderer(model, height=h, width=w)
            for name, (w, h, _) in self.cameras.items()
        }
        due = dict.fromkeys(self.cameras, time.monotonic())
        try:
            while self.running:
                name = min(due, key=due.__getitem__)
                time.sleep(max(0.0, due[name] - time.monotonic()))
                jpeg = self._render(renderers[name], name)
                with self.new_frame:
                    number = self.frames.get(name, (0, b""))[0] + 1
                    self.frames[name] = (number, jpeg)
                    self.new_frame.notify_all()
                due[name] = max(due[name] + 1.0 / self.cameras[name][2], time.monotonic())
        finally:
            for renderer in renderers.values():
                renderer.close()

    def next_frame(self, camera: str, after: int) -> tuple[int, bytes]:
        """The camera's first frame numbered above ``after`` (waits up to a second)."""
        with self.new_frame:
            self.new_frame.wait_for(
                lambda: self.frames.get(camera, (0, b""))[0] > after or not self.running,
                timeout=1.0,
            )
            return self.frames.get(camera, (after, b""))

    def _render(self, renderer: mujoco.Renderer, camera: str) -> bytes:
        """One JPEG of ``camera``, rendered from a copy of the arm's current state."""
        with self.arm.lock:
            source = self.arm.cell.data
            self._data.qpos[:] = source.qpos
            self._data.mocap_pos[:] = source.mocap_pos
            self._data.mocap_quat[:] = source.mocap_quat
        mujoco.mj_forward(self.arm.cell.model, self._data)
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
        self.send_response(200)
        self.send_header("Content-Type", f"multipart/x-mixed-replace; boundary={BOUNDARY}")
        self.send_header("Cache-Control", "no-cache")
        self.end_headers()
        sent = 0
        server = self.server
        try:
            while server.running:
                sent, jpeg = server.next_frame(name, after=sent)
                if not jpeg:
                    continue
                self.wfile.write(
                    f"--{BOUNDARY}\r\nContent-Type: image/jpeg\r\n"
                    f"Content-Length: {len(jpeg)}\r\n\r\n".encode()
                )
                self.wfile.write(jpeg + b"\r\n")
                self.wfile.flush()
        except (BrokenPipeError, ConnectionResetError):
            return
