"""Pick-and-place: put the banana on the plate (the paper's Pick-and-Place analogue)."""

from __future__ import annotations

import math

import numpy as np

from twinrl_sim.cell import Cell
from twinrl_sim.planar import planar_distance
from twinrl_sim.tasks.base import Progress, Task, TaskConfig, Tracker
from twinrl_sim.tasks.expert import (
    ObsView,
    ScriptedExpert,
    pick_phases,
    place_phases,
    sample_grasps,
)

PLATE_RADIUS_OK = 0.05  # banana centre within this distance of the plate centre (m)


class PickPlace(Task):
    name = "pick_place"
    instruction = "put the banana on the plate"
    object_name = "banana"
    target_name = "plate"
    max_steps = 100
    min_separation = 0.16
    target_yaw = (0.0, 0.0)

    def evaluate(self, cell: Cell, tracker: Tracker) -> Progress:
        banana, _ = cell.object_pose(self.object_name)
        plate, _ = cell.object_pose(self.target_name)
        rest = cell.table_top + self.scene.object(self.object_name).pos[2]
        plate_top = 2 * self.scene.object(self.target_name).pos[2]
        tcp, _ = cell.tcp_pose()
        on_plate = (
            planar_distance(banana, plate) < PLATE_RADIUS_OK and banana[2] < rest + plate_top + 0.01
        )
        released = cell.gripper_opening > 0.045
        lifted = banana[2] > rest + 0.02
        return Progress(
            success=bool(on_plate and released),
            terms={
                "reach": 1.0 - math.tanh(5.0 * float(np.linalg.norm(tcp - banana))),
                "grasp": float(lifted),
                "place": (1.0 - math.tanh(5.0 * planar_distance(banana, plate)))
                * float(lifted or on_plate),
            },
        )

    def goal_poses(self, cell: Cell, config: TaskConfig) -> list[tuple[np.ndarray, float]]:
        plate, _ = cell.object_pose(self.target_name)
        height = (
            self.scene.object(self.target_name).pos[2] + self.scene.object(self.object_name).pos[2]
        )
        return [(plate + [0.0, 0.0, height + 0.004], config.object[2])]

    def expert(self, config: TaskConfig, rng: np.random.Generator) -> ScriptedExpert:
        def grasp(view: ObsView) -> tuple[np.ndarray, float]:
            pos, yaw = view.position(self.object_name), view.yaw(self.object_name)
            tool_yaw, shift = sample_grasps(
                rng, yaw, self.grasp_period, self.grasp_yaw_offset, 0.02, view.tool_yaw
            )[0]
            axis = np.array([math.cos(yaw), math.sin(yaw), 0.0])
            return pos + shift * axis, tool_yaw

        # Body origins rest at half their height above what they stand on.
        plate_half = self.scene.object(self.target_name).pos[2]
        banana_half = self.scene.object(self.object_name).pos[2]

        def placement(view: ObsView, memory: dict) -> tuple[np.ndarray, float]:
            plate = view.position(self.target_name)
            drop = 0.004
            return plate + [0.0, 0.0, plate_half + banana_half + drop], view.yaw(self.object_name)

        return ScriptedExpert(
            self.scene, pick_phases(self.object_name, grasp) + place_phases(placement)
        )
