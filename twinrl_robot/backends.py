"""The one place robot backends are chosen: :func:`open_robot`.

Every caller that acts in a cell (experts, evaluation, excitation, real RL, recording)
opens its robot here and is typed against :class:`~twinrl_robot.robot.Robot`. A
backend comes wrapped in what it always needs: the safety limits, and for the plant its
sensor noise; the caller stacks the rest (an operator's takeover, the grasp hold).
``real`` is a UR arm described by a cell file (:mod:`twinrl_robot.ur`), on a real
controller or on the emulator (``emulated``: its harness sets each configuration up and
lends the plant's ground truth, which a real cell does not have).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from twinrl_data.errors import SettingError
from twinrl_robot.cell_file import CellFile, load_cell
from twinrl_robot.errors import RobotError
from twinrl_robot.plant import hidden_effects
from twinrl_robot.robot import Robot
from twinrl_robot.simulated import SimulatedCell
from twinrl_robot.wrappers import NoiseLevels, PrivilegedObservation, SafetyLimits, SensorNoise
from twinrl_sim.cell import environment_names
from twinrl_sim.tasks import Task, make_task

WORLDS: tuple[str, ...] = ("twin", "plant", "real")
ROBOTS: dict[str, str] = {"ur": "real", "plant": "plant", "twin": "twin"}
"""The commands' ``--robot`` names, each with the world it opens."""


def open_robot(
    world: str,
    task: str | Task,
    *,
    effects: dict[str, dict[str, Any]] | str | Path | None = None,
    noise: NoiseLevels | None = None,
    seed: int | None = None,
    cameras: tuple[str, ...] = (),
    effort: bool = False,
    object_poses: bool = True,
    cell: CellFile | str | Path | None = None,
    emulated: bool = False,
) -> Robot:
    """Open ``task``'s cell as a robot.

    Args:
        world: ``plant`` (the stand-in for the real cell: hidden effects, noisy sensors)
            or ``twin`` (the scene spec itself, exact readings).
        task: a task name or instance (a task on another cell: ``make_task(name, scene)``).
        effects: the plant's hidden effects (see :func:`twinrl_robot.plant.hidden_effects`;
            ``None``: the built-in plant); the twin takes none.
        noise: the plant's sensor noise (``None``: the default levels), seeded by ``seed``.
        cameras: cameras rendered into each observation.
        effort: report joint torques (``observation.effort``).
        object_poses: add the objects' poses from the simulation's ground truth
            (``observation.environment_state``), as a state policy or the scripted
            expert needs (a real cell has none: refused unless ``emulated``).
        cell: the cell file of a ``real`` robot.
        emulated: the ``real`` cell is the emulator (``twinrl robot emulate``).
    """
    if world not in WORLDS:
        raise RobotError(f"unknown robot '{world}': use one of {', '.join(WORLDS)}")
    task = make_task(task) if isinstance(task, str) else task
    if world == "real":
        if cell is None:
            raise SettingError("cell", "a real robot needs its cell file")
        if effects is not None:
            raise RobotError("effects apply to the plant only; a real cell has its own physics")
        cell = cell if isinstance(cell, CellFile) else load_cell(cell)
        real: Robot = _open_real(task, cell, cameras, effort, emulated)
        if object_poses:
            real = PrivilegedObservation(real)
        limits = cell.safety
        return SafetyLimits(real, limits.max_step_translation, limits.max_step_rotation)
    if cell is not None or emulated:
        raise RobotError(f"a cell file describes a real robot; the {world} takes none")
    if world == "twin" and effects is not None:
        raise RobotError("effects apply to the plant only; the twin runs its own scene spec")
    hidden = hidden_effects(effects) if world == "plant" else None
    robot: Robot = SimulatedCell(task, effects=hidden, cameras=cameras, effort=effort, world=world)
    if object_poses:
        robot = PrivilegedObservation(robot)
    if world == "plant":
        robot = SensorNoise(robot, noise or NoiseLevels(), seed)
    return SafetyLimits(robot)


def recorded_cameras(world: str, cell: CellFile | str | Path | None) -> tuple[str, ...]:
    """The cameras an episode of ``world`` records: the simulated cell's two, or every
    camera of a real cell's file."""
    if world != "real" or cell is None:
        return ("front", "wrist")
    cell = cell if isinstance(cell, CellFile) else load_cell(cell)
    return tuple(camera.name for camera in cell.cameras)


def _open_real(
    task: Task, cell: CellFile, cameras: tuple[str, ...], effort: bool, emulated: bool
) -> Robot:
    from twinrl_robot.ur.hardware import open_arm

    if not emulated:
        return open_arm(cell, task, cameras=cameras, effort=effort)
    from twinrl_robot.ur.emulator.harness import EmulatedTruth, HarnessClient

    try:
        harness = HarnessClient(cell.arm.host)
    except OSError as err:
        raise RobotError(
            f"no emulator answers at {cell.arm.host} ({err.strerror or err}); start one with "
            "'twinrl robot emulate CELL' or leave out `emulated` for a real arm"
        ) from None
    names = environment_names(tuple(o.name for o in task.scene.objects))
    return open_arm(
        cell,
        task,
        cameras=cameras,
        effort=effort,
        arrange=harness.arrange,
        privileged=EmulatedTruth(harness, names),
    )
