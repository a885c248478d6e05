"""The live view of a recording: Rerun, spawned, connected to, or saved to a file.

Per episode it shows the **reset guidance** (the configuration to set up, rendered
from the twin, and the objects' outlines where they should go drawn over the live
camera of the same name, when the twin has that camera), then every step's camera
images, the cell in 3D (the twin's arm, gripper, table and objects posed by the live
joints, gripper opening and, where the cell measures them, object poses) with the TCP's
path, what the robot touches (the twin's contacts of the live configuration:
:mod:`twinrl_data.contact_view`) and, where object poses are measured, the object in
hand (:class:`twinrl_data.grasp_view.LiveGrasp`), joint positions and targets, the
gripper's opening, the action and who chose it.

Every Rerun call runs in a process of its own (:mod:`twinrl_robot.live_view_writer`):
a viewer that stops reading blocks rerun's calls for good, and in the recorder's
process the view's close then never returned. Here a thread of the view hands the
writer the newest step (the episode records every one) with the live cameras as JPEG
previews at most :data:`PREVIEW_WIDTH` wide; while the writer lags, older steps are skipped, and a
writer that does not finish within :data:`CLOSE_TIMEOUT` of the view closing is
stopped, with a warning.
"""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import Mapping
from multiprocessing.connection import Connection
from typing import Any

import cv2
import numpy as np

from twinrl_data.schema import ENVIRONMENT_STATE, STATE, WRENCH, image_field
from twinrl_data.web_view import die_with_parent
from twinrl_robot.errors import RobotError
from twinrl_robot.live_view_writer import Preview, StepView, ViewSpec
from twinrl_robot.robot import Sent
from twinrl_sim.tasks import Task, TaskConfig

PREVIEW_WIDTH = 320  # px, the live cameras' previews at most
PREVIEW_QUALITY = 80  # JPEG quality of the previews
START_TIMEOUT = 120.0  # s for the writer to open the view (imports, the twin, rerun)
CLOSE_TIMEOUT = 10.0  # s for the writer to send what it was handed and close
MAX_WAITING = 16  # messages held for a lagging writer before the oldest are dropped


def preview_stride(width: int) -> int:
    """Every how many pixels a live camera ``width`` px wide is previewed."""
    return -(-width // PREVIEW_WIDTH)


def preview(image: np.ndarray) -> Preview:
    """A live camera's image (RGB) as a JPEG preview, :func:`preview_stride` downscaled."""
    stride = preview_stride(image.shape[1])
    small = np.ascontiguousarray(image[::stride, ::stride, ::-1])  # RGB to OpenCV's BGR
    ok, jpeg = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, PREVIEW_QUALITY])
    if not ok:
        raise ValueError(f"a {image.shape} camera image could not be encoded as JPEG")
    return Preview(jpeg.tobytes(), image.shape[1] / stride)


class LiveView:
    """A Rerun recording of the session as it is recorded (see the module docstring).

    ``target``: ``"spawn"`` (start a viewer), a ``rerun+http://`` URL (connect to a
    running one), or a ``.rrd`` path (save, to open later).
    """

    def __init__(
        self,
        target: str,
        task: Task,
        cameras: tuple[str, ...],
        state_names: list[str],
        name: str = "twinrl record",
        environment_names: list[str] | tuple[str, ...] = (),
    ) -> None:
        self.cameras = cameras
        spec = ViewSpec(
            target, task.name, task.scene, tuple(cameras), list(state_names),
            list(environment_names), name,
        )  # fmt: skip
        self._process, self._messages, self._replies = _start_writer()
        try:
            self._messages.send(spec)
            if not self._replies.poll(START_TIMEOUT):
                raise RobotError(f"the live view did not open within {START_TIMEOUT:.0f} s")
            reply = self._replies.recv()
            if reply[0] != "ready":
                raise RobotError(f"the live view could not open {target}: {reply[1]}")
        except (EOFError, OSError) as err:
            self._stop_writer()
            raise RobotError(f"the live view's process ended as it opened: {err}") from err
        except BaseException:
            self._stop_writer()
            raise
        self._waiting: deque[tuple[Any, ...]] = deque()
        self._dropped = 0
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._closing = False
        self._thread = threading.Thread(target=self._run, name="live-view", daemon=True)
        self._thread.start()

    def guidance(
        self, episode: int, config: TaskConfig, observation: Mapping[str, np.ndarray]
    ) -> None:
        """Show where the next episode starts: the twin's renders, the outlines over the
        live cameras the twin also has (``observation``: the cell at its start pose)."""
        self._hand(("guidance", episode, config, observation))

    def live(self, observation: Mapping[str, np.ndarray]) -> None:
        """The cameras now (while the person sets the cell up)."""
        self._hand(("live", observation), newest=True)

    def step(self, observation: Mapping[str, np.ndarray], sent: Sent) -> None:
        """Hand a step to the view (it shows the newest it has not shown)."""
        self._hand(("step", observation, sent), newest=True)

    def note(self, text: str) -> None:
        self._hand(("note", text))

    def close(self) -> None:
        """Show what was handed, then close the view; a writer that has not finished
        within :data:`CLOSE_TIMEOUT` (its viewer stopped reading) is stopped."""
        self._hand(("close",))
        self._closing = True
        self._wake.set()
        deadline = time.monotonic() + CLOSE_TIMEOUT
        self._thread.join(CLOSE_TIMEOUT)
        try:
            self._process.wait(max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            logging.getLogger(__name__).warning(
                "the live view did not finish within %.0f s of the session's end (its viewer "
                "stopped taking data); it was stopped and misses the last steps (the "
                "episodes are recorded whole)",
                CLOSE_TIMEOUT,
            )
        self._stop_writer()
        self._thread.join()

    def _hand(self, message: tuple[Any, ...], newest: bool = False) -> None:
        """Queue ``message`` for the writer; ``newest`` replaces a waiting one of its kind
        at the end of the queue (the view shows the newest step, not every one)."""
        with self._lock:
            if newest and self._waiting and self._waiting[-1][0] == message[0]:
                self._waiting[-1] = message
            else:
                self._waiting.append(message)
            while len(self._waiting) > MAX_WAITING:  # the writer is stuck: keep the newest
                self._waiting.popleft()
                self._dropped += 1
        self._wake.set()

    def _run(self) -> None:
        """The view's thread: send the writer each waiting message, previews encoded."""
        warned = False
        while True:
            self._wake.wait()
            self._wake.clear()
            while True:
                with self._lock:
                    if not self._waiting:
                        break
                    message = self._waiting.popleft()
                try:
                    self._messages.send(self._wire(message))
                except (OSError, ValueError):  # the writer is gone: drop what is left
                    with self._lock:
                        self._waiting.clear()
                    return
                except Exception as err:  # a view must not stop the recording
                    if not warned:
                        logging.getLogger(__name__).warning("the live view failed: %s", err)
                    warned = True
                if message[0] == "close":
                    return
            if self._closing and not self._waiting:
                return

    def _wire(self, message: tuple[Any, ...]) -> tuple[Any, ...]:
        """``message`` as the writer takes it: observations as previews and arrays."""
        kind = message[0]
        if kind == "guidance":
            _, episode, config, observation = message
            return kind, episode, config, self._previews(observation)
        if kind == "live":
            return kind, self._previews(message[1])
        if kind == "step":
            _, observation, sent = message
            environment, wrench = observation.get(ENVIRONMENT_STATE), observation.get(WRENCH)
            return kind, StepView(
                previews=self._previews(observation),
                state=np.asarray(observation[STATE]),
                environment=None if environment is None else np.asarray(environment),
                wrench=None if wrench is None else np.asarray(wrench),
                action=np.asarray(sent.action),
                joint_target=np.asarray(sent.joint_target),
                intervention=bool(sent.intervention),
            )
        return message

    def _previews(self, observation: Mapping[str, np.ndarray]) -> dict[str, Preview]:
        shown = {c: observation.get(image_field(c)) for c in self.cameras}
        return {c: preview(np.asarray(image)) for c, image in shown.items() if image is not None}

    def _stop_writer(self) -> None:
        if self._process.poll() is None:
            self._process.kill()
            self._process.wait()
        self._messages.close()
        self._replies.close()


def _start_writer() -> tuple[subprocess.Popen, Connection, Connection]:
    """The writer's process and the two ends of its pipes this process keeps."""
    message_read, message_write = os.pipe()
    reply_read, reply_write = os.pipe()
    try:
        process = subprocess.Popen(
            [sys.executable, "-m", "twinrl_robot.live_view_writer",
             str(message_read), str(reply_write)],
            pass_fds=(message_read, reply_write),
            stdin=subprocess.DEVNULL,
            preexec_fn=die_with_parent(),
        )  # fmt: skip
    except BaseException:
        for fd in (message_read, message_write, reply_read, reply_write):
            os.close(fd)
        raise
    os.close(message_read)
    os.close(reply_write)
    return (
        process,
        Connection(message_write, readable=False),
        Connection(reply_read, writable=False),
    )
