"""The twin's one replay engine: windows that restart from given states and re-send
held commands.

A window is a start (the twin's physics state and inputs at one moment) and the arm
joint targets and gripper commands of the next ``W`` control periods, each held for a
control period as a robot holds it. All windows of all models (the parameter points of
a fit) run as one batched ``mujoco.rollout`` call, and the physics state at the end of
every control period comes back.

The arm's servos hold each target for its period or track the targets (interpolated,
with velocity feed-forward), as each model says (:mod:`twinrl_sim.servo`).

Its users compare the same prediction: :func:`twinrl_sim.replay.replay` runs one window
from a task configuration's reset; the gap workflow's localisation
(:mod:`twinrl_sim.gap.shooting`) and identification (:mod:`twinrl_sim.gap.identify`)
run windows restarted from what was measured (:mod:`twinrl_sim.gap.windows`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import mujoco
import numpy as np
from mujoco.rollout import Rollout

from twinrl_sim.errors import TwinError
from twinrl_sim.layout import CellLayout
from twinrl_sim.servo import servo_lead, tracking_setpoints

STATE = mujoco.mjtState.mjSTATE_FULLPHYSICS
# What a window's rollout sets at every physics step: the servo and gripper commands,
# and the poses of mocap bodies (targets and fixtures: inputs, not physics state).
INPUTS = int(
    mujoco.mjtState.mjSTATE_CTRL
    | mujoco.mjtState.mjSTATE_MOCAP_POS
    | mujoco.mjtState.mjSTATE_MOCAP_QUAT
)


def control_substeps(model: mujoco.MjModel, fps: float) -> int:
    """Physics steps per control period at ``fps``; a rate the twin cannot step is refused."""
    steps = 1.0 / (fps * model.opt.timestep)
    if abs(steps - round(steps)) > 1e-6 or round(steps) < 1:
        raise TwinError(
            f"a control rate of {fps:g} Hz is not a whole number of the twin's "
            f"{model.opt.timestep:g} s physics steps; resample the log to a rate that "
            f"divides {1 / model.opt.timestep:g} Hz"
        )
    return round(steps)


@dataclass(frozen=True)
class Starts:
    """Where ``n`` windows begin: physics states (:data:`STATE`) and inputs (:data:`INPUTS`).

    Tracking servos (:mod:`twinrl_sim.servo`) move from the targets in force before the
    start, ``previous``; None: the arm's commands in ``inputs`` (a reset holds the pose)."""

    state: np.ndarray  # (n, state size)
    inputs: np.ndarray  # (n, inputs size)
    previous: np.ndarray | None = None  # (n, n_arm)

    @classmethod
    def capture(cls, model: mujoco.MjModel, data: mujoco.MjData) -> Starts:
        """The one start ``data`` is at."""
        state = np.empty((1, mujoco.mj_stateSize(model, STATE)))
        inputs = np.empty((1, mujoco.mj_stateSize(model, INPUTS)))
        mujoco.mj_getState(model, data, state[0], STATE)
        mujoco.mj_getState(model, data, inputs[0], INPUTS)
        return cls(state, inputs)


class WindowedReplay:
    """Batched replay of windows for a cell of ``layout`` at ``fps`` control steps per second."""

    def __init__(self, layout: CellLayout, fps: float, pool: Rollout | None = None) -> None:
        self.layout = layout
        self.fps = fps
        self.pool = pool or Rollout(nthread=2)

    def period_inputs(
        self,
        model: mujoco.MjModel,
        starts: Starts,
        targets: np.ndarray,
        gripper: np.ndarray,
    ) -> np.ndarray:
        """(n, W, inputs size): what each window holds during each control period, its
        targets (n, W, n_arm) and gripper commands (n, W), mocap bodies where they were
        at the start. ``ctrl`` comes first in the inputs (mjtState order)."""
        inputs = np.repeat(starts.inputs[:, None], targets.shape[1], axis=1)
        inputs[:, :, [model.actuator(a).id for a in self.layout.arm_actuators]] = targets
        if self.layout.gripper_actuator:
            inputs[:, :, model.actuator(self.layout.gripper_actuator).id] = gripper
        return inputs

    def rollout(
        self,
        models: Sequence[mujoco.MjModel],
        starts: Starts,
        targets: np.ndarray,
        gripper: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Every window under every model (which share one structure): the physics state
        at the end of each control period, (len(models), n, W, state size), and the
        inputs in force at the end of each period, (len(models), n, W, inputs size; see
        :meth:`restore`). Each model's servos hold or track the targets as it says
        (:func:`twinrl_sim.servo.servo_lead`)."""
        targets = np.asarray(targets, float)
        n, rows = targets.shape[:2]
        held = self.period_inputs(models[0], starts, targets, np.asarray(gripper, float))
        substeps = control_substeps(models[0], self.fps)
        held_steps = np.repeat(held, substeps, axis=1)
        leads = [servo_lead(model) for model in models]
        if all(lead is None for lead in leads):
            controls = np.tile(held_steps, (len(models), 1, 1))
            ends = np.broadcast_to(held, (len(models), *held.shape))
        else:
            arm = [models[0].actuator(a).id for a in self.layout.arm_actuators]
            previous = starts.inputs[:, arm] if starts.previous is None else starts.previous
            per_model = []
            for lead in leads:
                steps = held_steps.copy()
                if lead is not None:
                    steps[:, :, arm] = tracking_setpoints(
                        previous, targets, substeps, 1.0 / self.fps, lead
                    )
                per_model.append(steps)
            controls = np.concatenate(per_model)
            ends = controls[:, substeps - 1 :: substeps].reshape(len(models), n, rows, -1)
        state, _ = self.pool.rollout(
            [m for m in models for _ in range(n)],
            [mujoco.MjData(models[0]) for _ in range(max(self.pool.nthread, 1))],
            np.tile(starts.state, (len(models), 1)),
            controls,
            control_spec=INPUTS,
        )
        ticks = state[:, substeps - 1 :: substeps]
        return ticks.reshape(len(models), n, rows, -1), ends

    @staticmethod
    def restore(
        model: mujoco.MjModel, data: mujoco.MjData, tick: np.ndarray, held: np.ndarray
    ) -> None:
        """Put ``data`` at a control period's end: its physics state ``tick`` and the
        inputs ``held`` during it, derived quantities (site poses, actuator forces)
        included."""
        mujoco.mj_setState(model, data, tick, STATE)
        mujoco.mj_setState(model, data, held, INPUTS)
        mujoco.mj_forward(model, data)
