"""The one place robot backends are chosen: :func:`open_robot`.

Every caller that acts in a cell (experts, evaluation, excitation, real RL, recording)
opens its robot here and is typed against :class:`~twinrl_robot.robot.Robot`. A
backend comes wrapped in what it always needs: the safety limits, and for the plant its
sensor noise; the caller stacks the rest (an operator's takeover, the grasp hold).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from twinrl_robot.errors import RobotError
from twinrl_robot.plant import hidden_effects
from twinrl_robot.robot import Robot
from twinrl_robot.simulated import SimulatedCell
from twinrl_robot.wrappers import NoiseLevels, PrivilegedObservation, SafetyLimits, SensorNoise
from twinrl_sim.tasks import Task, make_task

WORLDS: tuple[str, ...] = ("twin", "plant")


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
            expert needs.
    """
    if world not in WORLDS:
        raise RobotError(
            f"unknown robot '{world}': use one of {', '.join(WORLDS)} (a real arm needs its "
            "driver behind twinrl_robot.Robot)"
        )
    if world == "twin" and effects is not None:
        raise RobotError("effects apply to the plant only; the twin runs its own scene spec")
    task = make_task(task) if isinstance(task, str) else task
    hidden = hidden_effects(effects) if world == "plant" else None
    robot: Robot = SimulatedCell(task, effects=hidden, cameras=cameras, effort=effort, world=world)
    if object_poses:
        robot = PrivilegedObservation(robot)
    if world == "plant":
        robot = SensorNoise(robot, noise or NoiseLevels(), seed)
    return SafetyLimits(robot)
