"""The live view's writer: the process that makes every Rerun call of a live view.

:class:`~twinrl_robot.live_view.LiveView` starts it (``python -m
twinrl_robot.live_view_writer READ_FD REPLY_FD``) and hands it, over a pipe, the view's
:class:`ViewSpec`, then one message per thing to show. Rerun's calls run here and
nowhere near the control loop: a gRPC sink whose viewer stops reading blocks ``log``
and ``flush`` (without end, in rerun 0.33), which in the recorder's process kept the
recording from ever closing. Here it blocks only this process, which the view stops when it
closes. The process runs at a lower priority (:data:`NICENESS`): a view that lags shows
the newest step, a control loop that lags is late.

Messages (tuples; previews are :class:`Preview`):

- ``("guidance", episode, config, previews)``: the twin's render of the next
  configuration from its cameras, the objects' outlines drawn over the live previews;
- ``("live", previews)``: the cameras now;
- ``("step", StepView)``: one control step;
- ``("note", text)``;
- ``("close",)``: flush and end.
"""

from __future__ import annotations

import logging
import os
import signal
import sys
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path

import mujoco
import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from twinrl_data.contact_view import CONTACT_COLOR, CONTACT_RADIUS
from twinrl_data.grasp_view import ARROW_M_PER_N, FORCE_COLOR, HELD_COLOR, LiveGrasp
from twinrl_data.mcap_log import pose_groups
from twinrl_data.schema import GRIPPER_CLOSED, GRIPPER_OPENING
from twinrl_data.view import log_cell_geometry, log_cell_poses
from twinrl_sim.build import compile_scene
from twinrl_sim.cell import Cell
from twinrl_sim.cell_view import TwinCell
from twinrl_sim.errors import TwinError
from twinrl_sim.spec import SceneSpec
from twinrl_sim.tasks import Task, TaskConfig, make_task

OUTLINE_COLOUR = [255, 200, 0]
GUIDE_WIDTH = 480  # px of the twin's guidance renders
FLUSH_TIMEOUT = 5.0  # s the writer waits for its sink when it closes
NICENESS = 10  # the writer yields the processor to the control loop and the recorder


@dataclass(frozen=True)
class ViewSpec:
    """What the writer needs to open the view (sent first)."""

    target: str  # "spawn", a rerun+http:// URL, or an .rrd path
    task: str
    scene: SceneSpec
    cameras: tuple[str, ...]
    state_names: list[str]
    environment_names: list[str]
    name: str


@dataclass(frozen=True)
class Preview:
    """A live camera's JPEG preview and the width (px, of the full image over the
    preview's stride) the twin's outlines are scaled to."""

    jpeg: bytes
    width: float


@dataclass(frozen=True)
class StepView:
    """What the view shows of one control step."""

    previews: dict[str, Preview]
    state: np.ndarray
    environment: np.ndarray | None
    wrench: np.ndarray | None
    action: np.ndarray
    joint_target: np.ndarray
    intervention: bool


class TwinGuide:
    """Renders a task configuration from the twin's cameras, with each object's outline."""

    def __init__(self, task: Task) -> None:
        self.task = task
        self.cell = Cell(compile_scene(task.scene))
        model = self.cell.model
        roots = {model.body(o.name).id for o in task.scene.objects}
        self._object_geoms = np.isin(model.body_rootid[model.geom_bodyid], list(roots))

    @property
    def cameras(self) -> tuple[str, ...]:
        return tuple(self.cell.layout.cameras)

    def render(self, config: TaskConfig, camera: str) -> tuple[np.ndarray, list[np.ndarray]]:
        """The twin's picture of ``config`` from ``camera`` and the objects' outlines in
        it (each an (n, 2) array of pixel x, y), at :data:`GUIDE_WIDTH` px wide."""
        from skimage.measure import find_contours

        self.task.start(self.cell, config)
        model = self.cell.model
        cam = model.camera(camera)
        width, height = (int(v) for v in model.cam_resolution[cam.id])
        scale = GUIDE_WIDTH / width
        size = (GUIDE_WIDTH, max(1, round(height * scale)))
        image = self.cell.render(camera, width=size[0], height=size[1])
        with mujoco.Renderer(model, height=size[1], width=size[0]) as renderer:
            renderer.enable_segmentation_rendering()
            renderer.update_scene(self.cell.data, camera=cam.id)
            segmentation = renderer.render()
        ids, kinds = segmentation[..., 0], segmentation[..., 1]
        is_geom = kinds == int(mujoco.mjtObj.mjOBJ_GEOM)
        mask = is_geom & self._object_geoms[np.clip(ids, 0, model.ngeom - 1)]
        outlines = [c[:, ::-1] for c in find_contours(mask.astype(float), 0.5) if len(c) > 8]
        return image, outlines

    def close(self) -> None:
        self.cell.close()


class ViewWriter:
    """The Rerun recording of a live view (see the module docstring)."""

    def __init__(self, spec: ViewSpec) -> None:
        self.stream = rr.RecordingStream(spec.name)
        self.guide = TwinGuide(make_task(spec.task, spec.scene))
        try:
            self.cell: TwinCell | None = TwinCell(
                self.guide.cell.scene, spec.state_names, spec.environment_names
            )
        except TwinError:  # the arm logs no joint positions the twin can pose: no 3D
            self.cell = None
        self.cameras = spec.cameras
        names = spec.state_names
        self._joints = [(i, n) for i, n in enumerate(names) if n.startswith("q.")]
        self._tcp = [i for i, n in enumerate(names) if n.startswith("tcp.")][:3]
        self._opening = names.index(GRIPPER_OPENING) if GRIPPER_OPENING in names else None
        self._objects = pose_groups(list(spec.environment_names))
        self._grasp = LiveGrasp()
        blueprint = self._blueprint()
        if spec.target == "spawn":
            self.stream.spawn(default_blueprint=blueprint)
        elif spec.target.endswith(".rrd"):
            self.stream.save(str(Path(spec.target)), default_blueprint=blueprint)
        else:
            self.stream.connect_grpc(spec.target, default_blueprint=blueprint)
        self._path: list[list[float]] = []
        self._step = 0
        if self.cell is not None:
            log_cell_geometry(self.cell, "world/cell", self.stream)

    def _blueprint(self) -> rrb.Blueprint:
        views = [rrb.Spatial2DView(origin=f"cameras/{c}", name=f"{c} (live)") for c in self.cameras]
        views += [
            rrb.Spatial2DView(origin=f"guidance/{c}", name=f"{c}: set up like this")
            for c in self.guide.cameras
            if c in self.cameras or not self.cameras
        ]
        plots = rrb.Vertical(
            rrb.TimeSeriesView(origin="signals/joints", name="joints and targets (rad)"),
            rrb.TimeSeriesView(origin="signals/grasp", name="gripper opening (cm), command"),
            rrb.TimeSeriesView(origin="signals/force", name="force at the tool (N)"),
            rrb.TimeSeriesView(origin="signals/actions", name="action"),
            rrb.TimeSeriesView(origin="signals/intervention", name="person in control"),
        )
        columns = [rrb.Spatial3DView(origin="world", name="the cell and the TCP path"), plots]
        if views:
            columns.insert(0, rrb.Vertical(*views))
        return rrb.Blueprint(rrb.Horizontal(*columns), rrb.TimePanel(expanded=False))

    def guidance(self, episode: int, config: TaskConfig, previews: dict[str, Preview]) -> None:
        """Where the next episode starts: the twin's renders, the outlines over the live
        previews of the cameras the twin also has."""
        self.stream.set_time("step", sequence=self._step)
        self._path = []
        self.note(f"episode {episode}: set up {config.to_dict()}")
        for camera in self.guide.cameras:
            if self.cameras and camera not in self.cameras:
                continue
            image, outlines = self.guide.render(config, camera)
            self.stream.log(f"guidance/{camera}", rr.Image(image))
            self.stream.log(
                f"guidance/{camera}/outline", rr.LineStrips2D(outlines, colors=[OUTLINE_COLOUR])
            )
            live = previews.get(camera)
            if live is not None:  # the twin's camera at the live preview's size
                scale = live.width / image.shape[1]
                self.stream.log(
                    f"cameras/{camera}/target",
                    rr.LineStrips2D([o * scale for o in outlines], colors=[OUTLINE_COLOUR]),
                )
        self.live(previews)

    def live(self, previews: dict[str, Preview]) -> None:
        """The cameras now."""
        for camera, shown in previews.items():
            image = rr.EncodedImage(contents=shown.jpeg, media_type="image/jpeg")
            self.stream.log(f"cameras/{camera}", image)

    def step(self, step: StepView) -> None:
        """One control step: cameras, signals, the TCP's path, the cell posed, contacts,
        the object in hand."""
        self._step += 1
        self.stream.set_time("step", sequence=self._step)
        self.live(step.previews)
        log = self.stream.log
        state, action = step.state, step.action
        for j, (i, name) in enumerate(self._joints):
            log(f"signals/joints/{name}", rr.Scalars(float(state[i])))
            if j < len(step.joint_target):
                log(f"signals/joints/{name}_target", rr.Scalars(float(step.joint_target[j])))
        for j, value in enumerate(action):
            log(f"signals/actions/{j}", rr.Scalars(float(value)))
        log("signals/intervention", rr.Scalars(float(step.intervention)))
        if self._opening is not None:
            log("signals/grasp/opening", rr.Scalars(100.0 * float(state[self._opening])))
            log("signals/grasp/command", rr.Scalars(float(action[-1])))
        tcp = [float(state[i]) for i in self._tcp]
        if len(tcp) == 3:
            self._path.append(tcp)
            log("world/tcp_path", rr.LineStrips3D([self._path]))
        if step.wrench is not None:  # a cell that measures it: the force at the tool
            force = np.asarray(step.wrench[:3], float)
            for axis, value in zip("xyz", force, strict=True):
                log(f"signals/force/{axis}", rr.Scalars(float(value)))
            if len(tcp) == 3:
                arrow = rr.Arrows3D(
                    origins=[tcp], vectors=[force * ARROW_M_PER_N], colors=[FORCE_COLOR],
                    labels=[f"{np.linalg.norm(force):.0f} N"],
                )  # fmt: skip
                log("world/tcp_force", arrow)
        environment = step.environment
        if self.cell is not None:
            log_cell_poses(self.cell, "world/cell", state, environment, self.stream)
            touching = self.cell.contacts(state, environment)
            log("world/contacts", rr.Points3D(
                [c.position for c in touching], labels=[c.label for c in touching],
                colors=[CONTACT_COLOR], radii=CONTACT_RADIUS,
            ))  # fmt: skip
        if self._opening is not None and len(tcp) == 3 and environment is not None:
            objects = {name: environment[idx[:3]] for name, idx in self._objects.items()}
            held = self._grasp.update(float(state[self._opening]),
                                      bool(action[-1] >= GRIPPER_CLOSED), np.array(tcp),
                                      objects)  # fmt: skip
            at = [objects[held]] if held else []
            log("world/in_hand", rr.Points3D(at, labels=["in hand"] * len(at),
                                             colors=[HELD_COLOR], radii=0.02))  # fmt: skip

    def note(self, text: str) -> None:
        self.stream.log("events", rr.TextLog(text))

    def close(self) -> None:
        self.guide.close()
        self.stream.flush(timeout_sec=FLUSH_TIMEOUT)
        self.stream.disconnect()


def serve(messages: Connection, replies: Connection) -> None:
    """Open the view from the first message, then show each message until ``close`` or
    until the view's process is gone (its end of the pipe closed)."""
    spec = messages.recv()
    try:
        writer = ViewWriter(spec)
    except Exception as err:  # said to the view, which raises it in its process
        replies.send(("error", f"{type(err).__name__}: {err}"))
        return
    replies.send(("ready",))
    warned = False
    while True:
        try:
            kind, *body = messages.recv()
        except EOFError:
            break
        if kind == "close":
            break
        try:
            getattr(writer, kind)(*body)
        except Exception as err:  # a view must not stop the recording
            if not warned:
                logging.getLogger(__name__).warning("the live view failed: %s", err)
            warned = True
    writer.close()


if __name__ == "__main__":
    os.nice(NICENESS)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # a terminal's Ctrl-C is the view's to act on
    serve(
        Connection(int(sys.argv[1]), writable=False), Connection(int(sys.argv[2]), readable=False)
    )
