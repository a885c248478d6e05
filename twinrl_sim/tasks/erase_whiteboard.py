"""Erase a whiteboard: grasp the eraser and wipe the marks off the board.

The marks are a grid of points on the board, tracked explicitly: a mark is wiped when
the eraser's felt (its bottom face) is flat on the board within :data:`CONTACT_GAP` and
the mark lies under it. Success: at least :data:`SUCCESS_FRACTION` of the marks wiped.
Marks are drawn into camera images as dark dots until wiped, so a vision policy sees
them.
"""

from __future__ import annotations

import math
from typing import ClassVar

import mujoco
import numpy as np

from twinrl_sim.cell import Cell
from twinrl_sim.planar import yaw_of
from twinrl_sim.tasks.base import Progress, Region, Task, TaskConfig, Tracker
from twinrl_sim.tasks.expert import (
    ObsView,
    Phase,
    ScriptedExpert,
    nearest_equivalent,
    pick_phases,
    place_goal,
    remember_grasp,
    sample_grasps,
)

SUCCESS_FRACTION = 0.9
CONTACT_GAP = 0.003  # m between felt and board for a mark to be wiped
MARK_GRID = (6, 4)  # marks along the board's x and y
MARK_AREA = (0.12, 0.07)  # m, centred on the board
MARK_RADIUS = 0.007
WIPE_ROWS = (-0.012, 0.012)  # eraser centre offsets across the marks (board y, m)
GRASP_BELOW_CENTRE = 0.008  # m: TCP below the eraser's centre when grasping
WIPE_RUN = 0.075  # eraser centre travels from -WIPE_RUN to +WIPE_RUN along board x (m)


def mark_positions() -> np.ndarray:
    """Board-frame (x, y) of every mark, shape (n, 2)."""
    xs = np.linspace(-MARK_AREA[0] / 2, MARK_AREA[0] / 2, MARK_GRID[0])
    ys = np.linspace(-MARK_AREA[1] / 2, MARK_AREA[1] / 2, MARK_GRID[1])
    return np.array([(x, y) for x in xs for y in ys])


def _rotate(yaw: float, xy: np.ndarray) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return xy @ np.array([[c, s], [-s, c]])


class WipeTracker(Tracker):
    """Which marks are wiped so far; draws the remaining ones into rendered frames."""

    def __init__(self, task: EraseWhiteboard, cell: Cell, config: TaskConfig) -> None:
        super().__init__(task, cell, config)
        self.marks = mark_positions()
        self.wiped = np.zeros(len(self.marks), dtype=bool)
        self._board_half_height = task.scene.object(task.target_name).pos[2]
        eraser = task.scene.object(task.object_name)
        self._eraser_half = np.array(eraser.geoms[0].size)
        cell.decorations.append(self._draw)

    def mark_world(self) -> np.ndarray:
        """World xyz of every mark (on the board's top face)."""
        board, quat = self.cell.object_pose(self.task.target_name)
        xy = board[:2] + _rotate(yaw_of(quat), self.marks)
        z = np.full((len(xy), 1), board[2] + self._board_half_height)
        return np.hstack([xy, z])

    def update(self) -> Progress:
        eraser, quat = self.cell.object_pose(self.task.object_name)
        rot = np.zeros(9)
        mujoco.mju_quat2Mat(rot, quat)
        rot = rot.reshape(3, 3)
        marks = self.mark_world()
        flat = rot[2, 2] > math.cos(math.radians(10))
        felt = eraser[2] - self._eraser_half[2]
        if flat and felt - marks[0, 2] < CONTACT_GAP:
            local = (marks - eraser) @ rot  # mark coordinates in the eraser frame
            under = (np.abs(local[:, 0]) <= self._eraser_half[0]) & (
                np.abs(local[:, 1]) <= self._eraser_half[1]
            )
            self.wiped |= under
        return self.task.evaluate(self.cell, self)

    @property
    def fraction(self) -> float:
        return float(self.wiped.mean())

    def _draw(self, scene: mujoco.MjvScene) -> None:
        for point in self.mark_world()[~self.wiped]:
            if scene.ngeom >= scene.maxgeom:
                return
            mujoco.mjv_initGeom(
                scene.geoms[scene.ngeom],
                mujoco.mjtGeom.mjGEOM_CYLINDER,
                np.array([MARK_RADIUS, 0.0005, 0.0]),
                point + [0.0, 0.0, 0.0006],
                np.eye(3).ravel(),
                np.array([0.15, 0.15, 0.6, 1.0], dtype=np.float32),
            )
            scene.ngeom += 1


class EraseWhiteboard(Task):
    name = "erase_whiteboard"
    instruction = "wipe the marks off the whiteboard with the eraser"
    object_name = "eraser"
    target_name = "whiteboard"
    max_steps = 120
    min_separation = 0.2
    target_yaw = (-0.3, 0.3)
    tracker_class = WipeTracker
    # A near miss stops part of the way along the first row: marks left unwiped.
    near_miss = ("wipe_out", 0.3, 0.8)
    # The board is large: keep it where the eraser can sweep all of it (the robot's
    # wrist cannot press flat on the table closer than about 0.25 m from the base).
    regions: ClassVar[dict[str, Region]] = {
        "ID": Region("ID", x=(0.36, 0.60), y=(-0.40, -0.04)),
        "OOD": Region("OOD", x=(0.36, 0.60), y=(0.04, 0.40)),
    }

    @classmethod
    def default_config(cls) -> dict:
        config = super().default_config()
        config["dense_weights"] = {"reach": 1.0, "grasp": 1.0, "wipe": 3.0}
        return config

    def evaluate(self, cell: Cell, tracker: Tracker) -> Progress:
        assert isinstance(tracker, WipeTracker)
        eraser, _ = cell.object_pose(self.object_name)
        tcp, _ = cell.tcp_pose()
        rest = cell.table_top + self.scene.object(self.object_name).pos[2]
        return Progress(
            success=tracker.fraction >= SUCCESS_FRACTION,
            terms={
                "reach": 1.0 - math.tanh(5.0 * float(np.linalg.norm(tcp - eraser))),
                "grasp": float(eraser[2] > rest + 0.02),
                "wipe": tracker.fraction,
            },
        )

    def goal_poses(self, cell: Cell, config: TaskConfig) -> list[tuple[np.ndarray, float]]:
        """The eraser's path over the marks: two passes, felt flat on the board."""
        board, board_quat = cell.object_pose(self.target_name)
        board_yaw = yaw_of(board_quat)
        yaw = nearest_equivalent(board_yaw + math.pi / 2, math.pi, config.object[2])
        height = (
            board[2]
            + self.scene.object(self.target_name).pos[2]
            + self.scene.object(self.object_name).pos[2]
            - 0.001
        )
        row_a, row_b = WIPE_ROWS
        path = [(-WIPE_RUN, row_a), (WIPE_RUN, row_a), (WIPE_RUN, row_b), (-WIPE_RUN, row_b)]
        poses = []
        for x, y in path:
            xy = board[:2] + _rotate(board_yaw, np.array([[x, y]]))[0]
            poses.append((np.array([xy[0], xy[1], height]), yaw))
        return poses

    @property
    def releases_object(self) -> bool:
        return False

    def expert(self, config: TaskConfig, rng: np.random.Generator) -> ScriptedExpert:
        eraser_half_height = self.scene.object(self.object_name).pos[2]
        board_half_height = self.scene.object(self.target_name).pos[2]

        def grasp(view: ObsView) -> tuple[np.ndarray, float]:
            pos, yaw = view.position(self.object_name), view.yaw(self.object_name)
            tool_yaw, shift = sample_grasps(
                rng, yaw, self.grasp_period, self.grasp_yaw_offset, 0.01, view.tool_yaw
            )[0]
            # Low on the sides: pads straddle the eraser's centre so it cannot roll.
            low = np.array([0.0, 0.0, -GRASP_BELOW_CENTRE])
            return pos + shift * np.array([math.cos(yaw), math.sin(yaw), 0.0]) + low, tool_yaw

        def wipe_pose(view: ObsView, memory: dict, x: float, y: float, lift: float):
            board, board_quat = view.pose(self.target_name)
            board_yaw = yaw_of(board_quat)
            if "wipe_yaw" not in memory:
                memory["wipe_yaw"] = nearest_equivalent(
                    board_yaw + math.pi / 2, math.pi, view.yaw(self.object_name)
                )
            xy = board[:2] + _rotate(board_yaw, np.array([[x, y]]))[0]
            height = board[2] + board_half_height + eraser_half_height - 0.001 + lift
            return place_goal(np.array([xy[0], xy[1], height]), memory["wipe_yaw"], memory)

        def waypoint(x: float, y: float, lift: float = 0.0):
            return lambda view, memory: wipe_pose(view, memory, x, y, lift)

        (row_a, row_b) = WIPE_ROWS
        phases = pick_phases(self.object_name, grasp) + [
            Phase(
                "transport",
                waypoint(-WIPE_RUN, row_a, 0.05),
                gripper=1.0,
                tolerance=0.01,
                on_exit=remember_grasp(self.object_name),
            ),
            Phase("touch", waypoint(-WIPE_RUN, row_a), gripper=1.0, speed=0.015),
            Phase("wipe_out", waypoint(WIPE_RUN, row_a), gripper=1.0, speed=0.02, tolerance=0.006),
            Phase("shift", waypoint(WIPE_RUN, row_b), gripper=1.0, speed=0.02, tolerance=0.006),
            Phase(
                "wipe_back", waypoint(-WIPE_RUN, row_b), gripper=1.0, speed=0.02, tolerance=0.006
            ),
            Phase("lift_off", waypoint(-WIPE_RUN, row_b, 0.08), gripper=1.0, tolerance=0.01),
        ]
        return ScriptedExpert(self.scene, phases)
