"""Excitation: safe joint motions that make a cell's dynamics identifiable.

Each episode moves every arm joint along a multi-sine about the home pose (harmonics of
``1 / duration`` with random phases, amplitudes falling as ``1 / k`` so that speed
stays bounded), faded in and out so that it starts and ends at rest. Before anything
moves, the whole trajectory is checked against the joint speed limit, the joint ranges
and, through the twin's forward kinematics, against the workspace box (with a margin
above the table); amplitudes are halved until it fits. Any arm works: the built-in UR5e
uses amplitudes tuned per joint, a robot MJCF named in a scene spec a common one capped
by each joint's range. Episodes are logged with source ``excitation``:
measured joints, velocities, TCP pose, joint torques (``observation.effort``) and the
joint targets sent, at the control rate. This is the data ``twinrl gap diagnose``
identifies effects from.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from twinrl_data.errors import SettingError
from twinrl_data.recorder import Recorder
from twinrl_data.session import Session
from twinrl_robot.backends import open_robot
from twinrl_robot.cell_file import CellFile
from twinrl_robot.errors import RobotError
from twinrl_robot.loop import JointCommand, run_episode
from twinrl_sim.build import CompiledScene, compile_scene
from twinrl_sim.control import quat_conj, quat_mul, quat_to_rotvec
from twinrl_sim.kinematics import TcpKinematics
from twinrl_sim.robots.ur5e import JOINT_SPEED_LIMIT
from twinrl_sim.spec import SceneSpec
from twinrl_sim.tasks import Task, TaskConfig, make_task

# Peak amplitude (rad) of each UR joint's multi-sine before scaling: the wrists move
# most, the shoulder lift least (it carries the whole arm over the table).
BASE_AMPLITUDE = (0.5, 0.25, 0.35, 0.6, 0.6, 0.9)
# Any other arm (a robot MJCF named in the spec): this peak per joint, at most a quarter
# of the joint's range, before the same safety checks scale it down.
CUSTOM_AMPLITUDE = 0.4
LIMIT_MARGIN = 0.05  # rad kept clear of each limited joint's range


@dataclass(frozen=True)
class ExcitationSettings:
    """Shape and safety limits of the excitation trajectories."""

    duration: float = 10.0  # s per episode
    harmonics: int = 4  # sines per joint (frequencies k / duration)
    amplitude: float = 1.0  # scales BASE_AMPLITUDE
    fade: float = 1.0  # s of fade-in and fade-out
    speed_fraction: float = 0.5  # of the joint speed limit
    margin: float = 0.05  # m inside the workspace box (and above the table)

    def __post_init__(self) -> None:
        if self.duration <= 2 * self.fade:
            raise SettingError("duration", f"must exceed twice the fade ({2 * self.fade} s)")
        if self.harmonics < 1:
            raise RobotError(f"harmonics must be at least 1, got {self.harmonics}")
        if not 0 < self.amplitude <= 2:
            raise SettingError("amplitude", f"must be in (0, 2], got {self.amplitude}")


def joint_ranges(scene: CompiledScene) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper limit (rad) of each arm joint; +-inf where it is unlimited."""
    model = scene.model
    ids = [model.joint(j).id for j in scene.layout.arm_joints]
    limited = model.jnt_limited[ids].astype(bool)
    low = np.where(limited, model.jnt_range[ids, 0], -np.inf)
    high = np.where(limited, model.jnt_range[ids, 1], np.inf)
    return low, high


def base_amplitude(scene: CompiledScene) -> np.ndarray:
    """Peak multi-sine amplitude (rad) per arm joint before ``settings.amplitude``."""
    if scene.spec.robot.is_builtin:
        return np.asarray(BASE_AMPLITUDE, float)
    low, high = joint_ranges(scene)
    return np.minimum(CUSTOM_AMPLITUDE, (high - low) / 4)


def multisine(
    home: np.ndarray,
    settings: ExcitationSettings,
    rate: float,
    rng: np.random.Generator,
    amplitude: np.ndarray | None = None,
) -> np.ndarray:
    """Joint targets (T, n) at ``rate`` Hz: home plus faded multi-sines, random phases.

    ``amplitude`` is the peak per joint before ``settings.amplitude`` (default: the UR's).
    """
    t = np.arange(round(settings.duration * rate) + 1) / rate
    k = np.arange(1, settings.harmonics + 1)
    freqs = k / settings.duration
    phases = rng.uniform(0, 2 * math.pi, (len(home), len(k)))
    weights = (1.0 / k) / np.sum(1.0 / k)
    base = np.asarray(BASE_AMPLITUDE if amplitude is None else amplitude, float)
    amplitude = base * settings.amplitude
    waves = np.sin(2 * math.pi * freqs[None, None] * t[:, None, None] + phases[None])
    offsets = (waves * weights).sum(-1) * amplitude
    ramp = np.clip(np.minimum(t, settings.duration - t) / settings.fade, 0, 1)
    fade = 0.5 - 0.5 * np.cos(math.pi * ramp)  # smooth 0 -> 1 -> 0
    return home + offsets * fade[:, None]


def safe_trajectory(
    task: Task, settings: ExcitationSettings, rng: np.random.Generator, scene: CompiledScene
) -> np.ndarray:
    """A multi-sine that keeps the TCP inside the workspace box, every limited joint
    ``LIMIT_MARGIN`` inside its range and joint speeds below ``speed_fraction`` of the
    limit (amplitude halved until it does)."""
    fk = TcpKinematics(scene)
    ws = task.scene.workspace
    low = np.array(ws.low) + settings.margin
    high = np.array(ws.high) - settings.margin
    low[2] = max(low[2], settings.margin)
    q_low, q_high = joint_ranges(scene)
    q_low, q_high = q_low + LIMIT_MARGIN, q_high - LIMIT_MARGIN
    rate = task.scene.physics.control_hz
    home = np.asarray(scene.layout.home_qpos, float)
    amplitude = base_amplitude(scene)
    seed = rng.integers(2**31)
    for halvings in range(8):
        shaped = replace(settings, amplitude=settings.amplitude / 2**halvings)
        targets = multisine(home, shaped, rate, np.random.default_rng(seed), amplitude)
        speed = np.abs(np.diff(targets, axis=0)).max() * rate
        if speed > settings.speed_fraction * JOINT_SPEED_LIMIT:
            continue
        if (targets < q_low).any() or (targets > q_high).any():
            continue
        tcp = np.array([fk(q)[0] for q in targets])
        if (tcp >= low).all() and (tcp <= high).all():
            return targets
    raise RobotError(
        "no safe excitation found (workspace box, joint limits or speed); lower "
        "`amplitude`, enlarge the workspace box or move the home pose away from the limits"
    )


class TrajectorySource:
    """Joint targets sent one per control step (the first is the start pose), with the
    gripper open; records the end-effector motion each step amounts to."""

    def __init__(self, targets: np.ndarray, actions: np.ndarray) -> None:
        self.targets, self.actions = targets, actions
        self._step = 0

    def reset(self, task: Task, config: TaskConfig) -> None:
        self._step = 0

    def act(self, observation: dict[str, np.ndarray]) -> JointCommand:
        t = self._step
        self._step += 1
        return JointCommand(self.targets[t + 1], 0.0, self.actions[t])

    def interrupted(self) -> None:
        """Nobody takes the controls from an excitation."""


def _tcp_actions(targets: np.ndarray, fk: Callable) -> np.ndarray:
    """Commanded end-effector motion per step (the contract's action), from the targets."""
    poses = [fk(q) for q in targets]
    actions = []
    for (p0, q0), (p1, q1) in itertools.pairwise(poses):
        turn = quat_to_rotvec(quat_mul(q1, quat_conj(q0)))
        actions.append(np.concatenate([p1 - p0, turn, [0.0]]))
    return np.asarray(actions, np.float32)


def run_excitation(
    task: str,
    *,
    scene: SceneSpec | None = None,
    world: str = "twin",
    episodes: int = 4,
    effects: dict | str | Path | None = None,
    settings: ExcitationSettings = ExcitationSettings(),
    seed: int = 0,
    session: Session,
    on_episode: Callable[[int], None] | None = None,
    cell: CellFile | str | Path | None = None,
    emulated: bool = False,
) -> list[Path]:
    """Record ``episodes`` excitation episodes into ``session``: ``task``'s built-in cell,
    or ``scene`` (any cell spec, e.g. with a custom robot MJCF) with the task's objects
    placed as the task places them; in the ``real`` world, on the arm of ``cell`` (the
    joint guard clips every target to the cell's safety limits)."""
    if episodes < 1:
        raise SettingError("episodes", f"must be at least 1, got {episodes}")
    spec_task = make_task(task, scene)
    robot = open_robot(
        world,
        spec_task,
        effects=effects,
        seed=seed,
        effort=True,
        object_poses=world != "real" or emulated,  # a real cell has no object poses
        cell=cell,
        emulated=emulated,
    )
    scene = compile_scene(spec_task.scene)
    fk = TcpKinematics(scene)
    rng = np.random.default_rng(seed)
    recorder = Recorder(session)
    paths = []
    try:
        for index in range(episodes):
            config = spec_task.sample_config(rng, "ID")
            targets = safe_trajectory(spec_task, settings, rng, scene)
            meta = spec_task.episode_meta(
                source="excitation",
                world=world,
                names=robot.names,
                config=config,
                policy=f"multisine:{settings.harmonics}x{settings.duration:g}s",
                instruction="excitation",
            )
            outcome = run_episode(
                robot,
                TrajectorySource(targets, _tcp_actions(targets, fk)),
                spec_task,
                config,
                judge=None,
                max_steps=len(targets) - 1,
                recorder=recorder,
                meta=meta,
            )
            paths.append(outcome.path)
            if on_episode is not None:
                on_episode(index)
    finally:
        robot.close()
    return paths
