"""Fit a camera's mounting error (the ``camera_pose`` effect) from logged images.

A camera pose changes nothing the arm or the objects do, only what the camera sees, so
it is fitted on its own residuals: frames sampled from the episodes are rendered in
the twin at the *measured* state (arm joints, gripper opening, object and fixture
poses) and compared with the logged images. Both are compared as grey images
box-averaged to :data:`IMAGE_SIZE` pixels and standardised (zero mean, unit spread),
so that a real camera's exposure and a lighting difference do not count as
misplacement.

The fit is ``mujoco.sysid``'s: one :class:`sysid.Parameter` (offset xyz in the
camera's frame, roll/pitch/yaw) whose modifier applies the effect to a copy of the
twin's ``MjSpec``; :func:`sysid.optimize` on the image residual; and
:func:`sysid.calculate_intervals`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields

import mujoco
import numpy as np
from mujoco import sysid

from twinrl_data import schema as contract
from twinrl_sim.build import build_mjspec
from twinrl_sim.effects import apply_camera_pose, apply_effects
from twinrl_sim.gap.identify import least_squares
from twinrl_sim.gap.windows import place_measured
from twinrl_sim.layout import CellLayout
from twinrl_sim.robots import gripper as gripper_lib
from twinrl_sim.spec import SceneSpec

IMAGE_SIZE = 32  # px: compared images are box-averaged to this size
SHIFT_SCALE = 0.01  # m per optimiser unit (xyz)
TURN_SCALE = 0.01  # rad per optimiser unit (roll, pitch, yaw)
# A photometric fit is local: mounting errors beyond these (a re-mounted camera) need
# the camera re-calibrated, not a twin correction.
SHIFT_RANGE = 0.1  # m
TURN_RANGE = 0.2  # rad
FD_STEP = 0.2  # optimiser units: 2 mm / 2 mrad, above the renders' 8-bit quantisation
MAX_ITERS = 15
FRAMES_PER_EPISODE = 6


@dataclass
class Frames:
    """Logged images of one camera with the measured state they were taken in."""

    camera: str
    images: np.ndarray  # (n, S, S[, 3]) compared form (see :func:`compared`, :func:`colours`)
    size: tuple[int, int]  # logged (height, width)
    q: np.ndarray  # (n, n_arm) measured joints
    opening: np.ndarray  # (n,) gripper opening (m)
    objects: list[str]  # objects whose poses are in ``poses`` (scene order)
    poses: np.ndarray  # (n, n_objects, 7) measured object poses
    episode: np.ndarray  # (n,) episode index

    def __len__(self) -> int:
        return len(self.images)

    def subset(self, index: np.ndarray) -> Frames:
        arrays = {
            f.name: getattr(self, f.name)[index]
            for f in fields(self)
            if f.name in ("images", "q", "opening", "poses", "episode")
        }
        return Frames(self.camera, size=self.size, objects=self.objects, **arrays)


def logged_cameras(episodes: Sequence[contract.Episode], layout: CellLayout) -> list[str]:
    """The cell's cameras that every episode logs images of."""
    return [c for c in layout.cameras if all(c in e.images for e in episodes)]


def colours(images: np.ndarray) -> np.ndarray:
    """(n, H, W, 3) uint8 -> (n, S, S, 3) colour in [0, 1], box-averaged to
    :data:`IMAGE_SIZE` (what the ``appearance`` fit compares)."""
    n, h, w, _ = images.shape
    fy, fx = max(1, h // IMAGE_SIZE), max(1, w // IMAGE_SIZE)
    cropped = images[:, : h - h % fy, : w - w % fx].astype(np.float32) / 255
    return cropped.reshape(n, h // fy, fy, w // fx, fx, 3).mean(axis=(2, 4))


def compared(images: np.ndarray) -> np.ndarray:
    """(n, H, W, 3) uint8 -> (n, S, S) grey, box-averaged to :data:`IMAGE_SIZE`,
    standardised per image (what the ``camera_pose`` fit compares)."""
    grey = colours(images) @ np.array([0.299, 0.587, 0.114], np.float32)
    centred = grey - grey.mean(axis=(1, 2), keepdims=True)
    return centred / (centred.std(axis=(1, 2), keepdims=True) + 1e-6)


def sample_frames(
    episodes: Sequence[contract.Episode],
    layout: CellLayout,
    objects: Sequence[str],
    camera: str,
    per_episode: int = FRAMES_PER_EPISODE,
    form: Callable[[np.ndarray], np.ndarray] = compared,
) -> Frames:
    """``per_episode`` frames spread over each episode's rows, images in ``form``."""
    parts: dict[str, list] = {k: [] for k in ("images", "q", "opening", "poses", "episode")}
    size = (0, 0)
    for e_index, episode in enumerate(episodes):
        col = {n: i for i, n in enumerate(episode.meta.names[contract.STATE])}
        state = episode.data[contract.STATE].astype(float)
        rows = np.linspace(0, len(state) - 1, min(per_episode, len(state))).round().astype(int)
        logged = episode.images[camera]
        size = logged.shape[1:3]
        parts["images"].append(form(logged[rows]))
        parts["q"].append(state[rows][:, [col[f"q.{j}"] for j in layout.arm_joints]])
        opening = (
            state[rows, col["gripper.opening"]]
            if "gripper.opening" in col
            else np.full(len(rows), 2 * gripper_lib.STROKE)
        )
        parts["opening"].append(opening)
        env_names = episode.meta.names.get(contract.ENVIRONMENT_STATE, [])
        poses = np.zeros((len(rows), len(objects), 7))
        for k, name in enumerate(objects):
            if f"{name}.x" in env_names:
                start = env_names.index(f"{name}.x")
                poses[:, k] = episode.data[contract.ENVIRONMENT_STATE][rows, start : start + 7]
            else:
                poses[:, k, 3] = np.nan  # not logged: left where the scene puts it
        parts["poses"].append(poses)
        parts["episode"].append(np.full(len(rows), e_index))
    arrays = {k: np.concatenate(v) for k, v in parts.items()}
    return Frames(camera, size=size, objects=list(objects), **arrays)


def render_measured(
    model: mujoco.MjModel,
    data: mujoco.MjData,
    renderer: mujoco.Renderer,
    layout: CellLayout,
    frames: Frames,
) -> np.ndarray:
    """(n, H, W, 3) uint8: ``frames``' camera rendering the twin at each frame's
    measured state (arm joints, gripper opening, object and fixture poses)."""
    camera = model.camera(frames.camera).id
    arm = [model.joint(j).qposadr[0] for j in layout.arm_joints]
    images = np.empty((len(frames), *frames.size, 3), np.uint8)
    for i in range(len(frames)):
        mujoco.mj_resetData(model, data)
        place_measured(model, data, layout, frames.objects, frames.poses[i], frames.opening[i])
        data.qpos[arm] = frames.q[i]
        mujoco.mj_forward(model, data)
        renderer.update_scene(data, camera=camera)
        images[i] = renderer.render()
    return images


class CameraFit:
    """The twin of ``scene`` (plus ``fixed`` effects) rendering ``frames`` with the
    camera's mounting error adjustable: a ``mujoco.sysid`` residual over all frames."""

    def __init__(
        self,
        scene: SceneSpec,
        frames: Frames,
        noise: float,
        *,
        fixed: dict[str, dict] | None = None,
    ) -> None:
        self.frames = frames
        self.noise = noise
        self.spec, self.layout = build_mjspec(scene)
        if fixed:
            apply_effects(self.spec, self.layout, fixed)
        self.model = self.spec.copy().compile()
        self.data = mujoco.MjData(self.model)
        self.camera_id = self.model.camera(frames.camera).id
        height, width = frames.size
        self.renderer = mujoco.Renderer(self.model, height=height, width=width)
        high = np.r_[[SHIFT_RANGE / SHIFT_SCALE] * 3, [TURN_RANGE / TURN_SCALE] * 3]
        self.params = sysid.ParameterDict()
        self.params.add(
            sysid.Parameter(
                "camera_pose",
                nominal=np.zeros(6),
                min_value=-high,
                max_value=high,
                modifier=lambda spec, p: apply_camera_pose(
                    spec, self.layout, frames.camera, *self._physical(p.value)
                ),
            )
        )

    @staticmethod
    def _physical(x: np.ndarray) -> tuple[list[float], list[float]]:
        x = np.asarray(x, float)
        return (x[:3] * SHIFT_SCALE).tolist(), (x[3:] * TURN_SCALE).tolist()

    def effect_at(self, x: np.ndarray) -> dict:
        """The camera_pose effect at ``x`` in effects-file form."""
        xyz, rpy = self._physical(x)
        return {"camera": self.frames.camera, "xyz": xyz, "rpy": rpy}

    def interval_at(self, half_width: np.ndarray) -> dict:
        xyz, rpy = self._physical(half_width)
        return {"xyz": xyz, "rpy": rpy}

    def render(self, x: np.ndarray) -> np.ndarray:
        """The frames as the twin's camera sees them at ``x``: (n, S, S) compared form."""
        params = self.params.copy()
        params.update_from_vector(np.asarray(x, float))
        moved = sysid.apply_param_modifiers_spec(params, self.spec.copy()).compile()
        self.model.cam_pos[self.camera_id] = moved.cam_pos[self.camera_id]
        self.model.cam_quat[self.camera_id] = moved.cam_quat[self.camera_id]
        return compared(
            render_measured(self.model, self.data, self.renderer, self.layout, self.frames)
        )

    def residuals(self, x: np.ndarray | None = None) -> np.ndarray:
        """(n, S, S) residuals in image-noise units at ``x`` (default: no effect)."""
        x = np.zeros(6) if x is None else x
        return (self.frames.images - self.render(x)).astype(np.float64) / self.noise

    def _residual_fn(self, x: np.ndarray, _params: sysid.ParameterDict):
        """sysid's residual signature; the finite-difference Jacobian passes its points
        as the columns of ``x``."""
        x = np.asarray(x, float)
        if x.ndim == 1:
            return [self.residuals(x).ravel()], None, None
        return [np.stack([self.residuals(c).ravel() for c in x.T], axis=1)], None, None

    def fit(self) -> tuple[np.ndarray, np.ndarray, int]:
        """Least-squares fit: (x, 95 % half-widths, iterations) in optimiser units."""
        params, result, iterations = least_squares(
            self.params, self._residual_fn, eps=FD_STEP, xtol=1e-3, max_iters=MAX_ITERS
        )
        x = params.as_vector()
        _, half_width = sysid.calculate_intervals([self.residuals(x).ravel()], result.jac)
        return x, np.asarray(half_width), iterations

    def close(self) -> None:
        self.renderer.close()
