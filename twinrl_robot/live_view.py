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
One blueprint lays it out: cameras and guidance, the scene, the plots. Each step is
logged by a thread of the view's own, the newest step when it lags (the episode records
every one), and the live cameras go as JPEG previews at most :data:`PREVIEW_WIDTH` wide:
logging two full 640x480 images, the plots and the cell's poses in the control loop's
thread cost it milliseconds a step.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Mapping
from pathlib import Path

import cv2
import mujoco
import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from twinrl_data.contact_view import CONTACT_COLOR, CONTACT_RADIUS
from twinrl_data.grasp_view import ARROW_M_PER_N, FORCE_COLOR, HELD_COLOR, LiveGrasp
from twinrl_data.mcap_log import pose_groups
from twinrl_data.schema import (
    ENVIRONMENT_STATE,
    GRIPPER_CLOSED,
    GRIPPER_OPENING,
    STATE,
    WRENCH,
    image_field,
)
from twinrl_data.view import log_cell_geometry, log_cell_poses
from twinrl_robot.robot import Sent
from twinrl_sim.build import compile_scene
from twinrl_sim.cell import Cell
from twinrl_sim.cell_view import TwinCell
from twinrl_sim.errors import TwinError
from twinrl_sim.tasks import Task, TaskConfig

OUTLINE_COLOUR = [255, 200, 0]
GUIDE_WIDTH = 480  # px of the twin's guidance renders
PREVIEW_WIDTH = 320  # px, the live cameras' previews at most
PREVIEW_QUALITY = 80  # JPEG quality of the previews


def preview_stride(width: int) -> int:
    """Every how many pixels a live camera ``width`` px wide is previewed."""
    return -(-width // PREVIEW_WIDTH)


def preview(image: np.ndarray) -> rr.EncodedImage:
    """A live camera's image (RGB) as a JPEG preview, :func:`preview_stride` downscaled."""
    stride = preview_stride(image.shape[1])
    small = np.ascontiguousarray(image[::stride, ::stride, ::-1])  # RGB to OpenCV's BGR
    ok, jpeg = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, PREVIEW_QUALITY])
    if not ok:
        raise ValueError(f"a {image.shape} camera image could not be encoded as JPEG")
    return rr.EncodedImage(contents=jpeg.tobytes(), media_type="image/jpeg")


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
        self.stream = rr.RecordingStream(name)
        self.guide = TwinGuide(task)
        try:
            self.cell: TwinCell | None = TwinCell(
                self.guide.cell.scene, state_names, environment_names
            )
        except TwinError:  # the arm logs no joint positions the twin can pose: no 3D
            self.cell = None
        self.cameras = cameras
        self._joints = [(i, n) for i, n in enumerate(state_names) if n.startswith("q.")]
        self._tcp = [i for i, n in enumerate(state_names) if n.startswith("tcp.")][:3]
        names = state_names
        self._opening = names.index(GRIPPER_OPENING) if GRIPPER_OPENING in names else None
        self._objects = pose_groups(list(environment_names))
        self._grasp = LiveGrasp()
        blueprint = self._blueprint()
        if target == "spawn":
            self.stream.spawn(default_blueprint=blueprint)
        elif target.endswith(".rrd"):
            self.stream.save(str(Path(target)), default_blueprint=blueprint)
        else:
            self.stream.connect_grpc(target, default_blueprint=blueprint)
        self._path: list[list[float]] = []
        self._step = 0
        if self.cell is not None:
            log_cell_geometry(self.cell, "world/cell", self.stream)
        self._newest: tuple[Mapping[str, np.ndarray], Sent] | None = None
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._closing = False
        self._thread = threading.Thread(target=self._run, name="live-view", daemon=True)
        self._thread.start()

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

    def guidance(
        self,
        episode: int,
        config: TaskConfig,
        observation: Mapping[str, np.ndarray],
    ) -> None:
        """Show where the next episode starts: the twin's renders, the outlines over the
        live cameras the twin also has (``observation``: the cell at its start pose)."""
        self.stream.set_time("step", sequence=self._step)
        self._path = []
        self.note(f"episode {episode}: set up {config.to_dict()}")
        for camera in self.guide.cameras:
            if self.cameras and camera not in self.cameras:
                continue
            image, outlines = self.guide.render(config, camera)
            rr.log(f"guidance/{camera}", rr.Image(image), recording=self.stream)
            rr.log(
                f"guidance/{camera}/outline",
                rr.LineStrips2D(outlines, colors=[OUTLINE_COLOUR]),
                recording=self.stream,
            )
            live = observation.get(image_field(camera))
            if live is not None:  # the twin's camera at the live preview's size
                scale = live.shape[1] / preview_stride(live.shape[1]) / image.shape[1]
                rr.log(
                    f"cameras/{camera}/target",
                    rr.LineStrips2D([o * scale for o in outlines], colors=[OUTLINE_COLOUR]),
                    recording=self.stream,
                )
        self.live(observation)

    def live(self, observation: Mapping[str, np.ndarray]) -> None:
        """The cameras now (while the person sets the cell up)."""
        for camera in self.cameras:
            image = observation.get(image_field(camera))
            if image is not None:
                self.stream.log(f"cameras/{camera}", preview(image))

    def step(self, observation: Mapping[str, np.ndarray], sent: Sent) -> None:
        """Hand a step to the view's thread (it logs the newest it has not logged)."""
        with self._lock:
            self._newest = (observation, sent)
        self._wake.set()

    def _run(self) -> None:
        warned = False
        while True:
            self._wake.wait()
            self._wake.clear()
            with self._lock:
                newest, self._newest = self._newest, None
            if newest is not None:
                try:
                    self._log_step(*newest)
                except Exception as err:  # a view must not stop the recording
                    if not warned:
                        logging.getLogger(__name__).warning("the live view failed: %s", err)
                    warned = True
            if self._closing and self._newest is None:
                return

    def _log_step(self, observation: Mapping[str, np.ndarray], sent: Sent) -> None:
        self._step += 1
        self.stream.set_time("step", sequence=self._step)
        self.live(observation)
        log = self.stream.log
        state = observation[STATE]
        for j, (i, name) in enumerate(self._joints):
            log(f"signals/joints/{name}", rr.Scalars(float(state[i])))
            if j < len(sent.joint_target):
                log(f"signals/joints/{name}_target", rr.Scalars(float(sent.joint_target[j])))
        for j, value in enumerate(sent.action):
            log(f"signals/actions/{j}", rr.Scalars(float(value)))
        log("signals/intervention", rr.Scalars(float(sent.intervention)))
        if self._opening is not None:
            log("signals/grasp/opening", rr.Scalars(100.0 * float(state[self._opening])))
            log("signals/grasp/command", rr.Scalars(float(sent.action[-1])))
        tcp = [float(state[i]) for i in self._tcp]
        if len(tcp) == 3:
            self._path.append(tcp)
            log("world/tcp_path", rr.LineStrips3D([self._path]))
        wrench = observation.get(WRENCH)
        if wrench is not None:  # a cell that measures it: the force at the tool
            force = np.asarray(wrench[:3], float)
            for axis, value in zip("xyz", force, strict=True):
                log(f"signals/force/{axis}", rr.Scalars(float(value)))
            if len(tcp) == 3:
                arrow = rr.Arrows3D(
                    origins=[tcp], vectors=[force * ARROW_M_PER_N], colors=[FORCE_COLOR],
                    labels=[f"{np.linalg.norm(force):.0f} N"],
                )  # fmt: skip
                log("world/tcp_force", arrow)
        environment = observation.get(ENVIRONMENT_STATE)
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
                                      bool(sent.action[-1] >= GRIPPER_CLOSED), np.array(tcp),
                                      objects)  # fmt: skip
            at = [objects[held]] if held else []
            log("world/in_hand", rr.Points3D(at, labels=["in hand"] * len(at),
                                             colors=[HELD_COLOR], radii=0.02))  # fmt: skip

    def note(self, text: str) -> None:
        self.stream.log("events", rr.TextLog(text))

    def close(self) -> None:
        self._closing = True
        self._wake.set()
        self._thread.join()
        self.guide.close()
        self.stream.flush()
        self.stream.disconnect()
