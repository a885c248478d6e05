"""Whether the operator who sees (:class:`~twinrl_learn.seeing_operator.SeeingOperator`)
can do the task itself. In the plant, a policy that stalls (it holds the arm still, the
gripper open or closed) lets the operator take over after its patience, and the operator
drives the rest of the episode with the task's scripted expert. Side by side on the same
configurations: the operator judging and planning from a pose estimator's view, and the
same operator given the plant's truth. Reported per operator: successes per region, the
failed episodes in which the object never left the table (a grasp that missed or never
closed), and, for the seeing operator, the estimator's error on the object (median, mm:
in the table plane and in height, signed) over the steps it held the controls before it
first closed the gripper, where its plan of the grasp comes from. Usage::

    MUJOCO_GL=egl python bench/bench_operator_takeovers.py ESTIMATOR --episodes 8
    MUJOCO_GL=egl python bench/bench_operator_takeovers.py ESTIMATOR --gripper closed
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import numpy as np
import typer

from twinrl_data.schema import ENVIRONMENT_STATE
from twinrl_learn.perception.estimator import PoseEstimator
from twinrl_learn.seeing_operator import SeeingOperator
from twinrl_robot.backends import open_robot
from twinrl_robot.loop import privileged_success, run_episode
from twinrl_robot.operator import SimulatedOperator
from twinrl_robot.wrappers.takeover import OperatorTakeover
from twinrl_sim.tasks import REGION_NAMES, Task, TaskConfig, make_task

LIFTED = 0.03  # m above where it started: the object left the table
OPERATOR_SEED = 7


class Stall:
    """A policy that holds the arm still, its gripper ``closed`` or open."""

    def __init__(self, closed: bool) -> None:
        self.gripper = 1.0 if closed else 0.0

    def reset(self, task: Task, config: TaskConfig) -> None:
        pass

    def act(self, observation: dict[str, np.ndarray]) -> np.ndarray:
        return np.array([0, 0, 0, 0, 0, 0, self.gripper], np.float32)

    def interrupted(self) -> None:
        pass


class Watched:
    """An operator, and what the plant showed while it was asked each step: the object's
    height; for a seeing operator, what it saw against the truth while it held the
    controls before its first close."""

    def __init__(self, operator: SimulatedOperator, column: int) -> None:
        self.operator, self.column = operator, column
        self.judges_progress = operator.judges_progress
        self.heights: list[float] = []
        self.errors: list[np.ndarray] = []

    def reset(self, task: Task, config: TaskConfig) -> None:
        self.operator.reset(task, config)
        self.heights, self._closed = [], False

    def intervene(self, observation, progress):
        truth = np.asarray(observation[ENVIRONMENT_STATE][self.column : self.column + 3])
        self.heights.append(float(truth[2]))
        action = self.operator.intervene(observation, progress)
        seeing = isinstance(self.operator, SeeingOperator)
        if seeing and action is not None and not self._closed:
            self._closed = bool(action[6] >= 0.5)
            index = self.operator.task.scene.object_names.index(self.operator.task.object_name)
            self.errors.append(self.operator.last_seen[index, :3] - truth)
        return action


def drive(
    operator: SimulatedOperator,
    task: Task,
    configs: list[tuple[str, TaskConfig]],
    closed: bool,
    cameras: tuple[str, ...],
) -> tuple[dict[str, list[bool]], int, list[np.ndarray]]:
    """Successes per region, failures whose object never lifted, the seeing errors."""
    plant = open_robot("plant", task, seed=0, cameras=cameras, object_poses=True)
    names = plant.names[ENVIRONMENT_STATE]
    watched = Watched(operator, names.index(f"{task.object_name}.x"))
    robot = OperatorTakeover(plant, watched, task)
    successes: dict[str, list[bool]] = {r: [] for r in REGION_NAMES}
    never_lifted = 0
    try:
        for region, config in configs:
            result = run_episode(
                robot, Stall(closed), task, config, judge=privileged_success(robot)
            )
            successes[region].append(result.success)
            heights = np.asarray(watched.heights)
            never_lifted += not result.success and heights.max() - heights[0] < LIFTED
    finally:
        robot.close()
    return successes, never_lifted, watched.errors


def main(
    estimator: Annotated[Path, typer.Argument(help="Pose estimator folder.")],
    task: Annotated[str, typer.Option(help="Task the operator does.")] = "pick_place",
    episodes: Annotated[int, typer.Option(help="Configurations per region.")] = 8,
    gripper: Annotated[
        str, typer.Option(help="The stalling policy's gripper: open, closed.")
    ] = "open",
    seed: Annotated[int, typer.Option(help="Seed of the configurations.")] = 0,
) -> None:
    if gripper not in ("open", "closed"):
        raise typer.BadParameter(f"--gripper must be open or closed, got {gripper}")
    seeing = PoseEstimator.from_pretrained(estimator, "cpu")
    the_task = make_task(task)
    rng = np.random.default_rng(seed)
    configs = [(r, the_task.sample_config(rng, r)) for r in REGION_NAMES for _ in range(episodes)]
    cameras = tuple(seeing.config.cameras)
    print(
        f"{task}, the stalling policy's gripper {gripper}, {episodes} configurations per region\n"
    )
    print("| operator | " + " | ".join(REGION_NAMES) + " | failed, the object never lifted |")
    print("|---|" + "---|" * len(REGION_NAMES) + "---|")
    errors: list[np.ndarray] = []
    for label, operator in (
        (f"sees ({estimator.name})", SeeingOperator(seeing, seed=OPERATOR_SEED)),
        ("plant truth", SimulatedOperator(seed=OPERATOR_SEED)),
    ):
        successes, never_lifted, seen = drive(
            operator, the_task, configs, gripper == "closed", cameras
        )
        errors += seen
        rates = " | ".join(f"{sum(s)} of {len(s)}" for s in successes.values())
        print(f"| {label} | {rates} | {never_lifted} |")
    if errors:
        error = 1000 * np.asarray(errors)
        print(
            f"\nthe seeing operator's view of the {the_task.object_name} before its first close "
            f"({len(error)} steps): {np.median(np.linalg.norm(error[:, :2], axis=1)):.1f} mm "
            f"in the table plane, {np.median(error[:, 2]):+.1f} mm in height (median)"
        )


if __name__ == "__main__":
    typer.run(main)
