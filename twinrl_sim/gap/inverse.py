"""Inverse dynamics of the measured motion against the measured joint torques.

Forward replay asks "given the commands, does the twin move as the robot did?"; inverse
dynamics asks the converse: "given how the robot moved, does the twin need the torques
the robot's servos reported?" (``mujoco.mj_inverse`` on the measured joint positions,
velocities and accelerations, the accelerations by central differences of the
velocities). A missing payload shows as a torque bias under gravity, missing friction as
torque that flips with the direction of motion, a wrong inertia as a gain, while servo
effects (delay, gain) barely do: the two views together narrow down the cause.

The arm is evaluated alone, with contacts off: a held object's load is not in the
twin's inverse dynamics, so it shows in the ``grasp_transport`` phase.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import mujoco
import numpy as np

from twinrl_data import schema as contract
from twinrl_sim.build import CompiledScene, compile_scene
from twinrl_sim.effects import torque_offset
from twinrl_sim.errors import TwinError
from twinrl_sim.spec import SceneSpec

PREFIX = "tau_id."  # signal names of the comparison: tau_id.<joint>


@dataclass(frozen=True)
class InverseDynamics:
    """Measured joint torques and the twin's inverse dynamics of the measured motion."""

    names: list[str]  # tau_id.<joint>
    measured: np.ndarray  # (T, n_arm) N m
    predicted: np.ndarray  # (T, n_arm) N m


def inverse_model(scene: SceneSpec, effects: dict | None = None) -> CompiledScene:
    """The twin (plus ``effects``) compiled for inverse dynamics: contacts off."""
    compiled = compile_scene(scene, extra_effects=effects or None)
    compiled.model.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONTACT
    return compiled


def inverse_dynamics(episode: contract.Episode, twin: CompiledScene) -> InverseDynamics | None:
    """The comparison for one episode against ``twin`` (from :func:`inverse_model`), or
    ``None`` when the episode logs no joint torques or lacks arm joint velocities."""
    arm = twin.layout.arm_joints
    names = episode.meta.names
    if contract.EFFORT not in episode.data:
        return None
    if names.get(contract.EFFORT) != contract.effort_names(arm):
        raise TwinError(
            f"episode {episode.meta.episode_id} logs torques of {names.get(contract.EFFORT)}, "
            f"not of the twin's arm joints {list(arm)}"
        )
    state_names = names.get(contract.STATE, [])
    wanted = [f"q.{j}" for j in arm] + [f"qd.{j}" for j in arm]
    if not set(wanted) <= set(state_names):
        return None
    state = episode.data[contract.STATE].astype(float)
    columns = [state_names.index(n) for n in wanted]
    q, qd = state[:, columns[: len(arm)]], state[:, columns[len(arm) :]]
    qdd = np.gradient(qd, axis=0) * episode.meta.fps if len(qd) > 1 else np.zeros_like(qd)
    model = twin.model
    data = mujoco.MjData(model)
    qpos = [model.joint(j).qposadr[0] for j in arm]
    dof = [model.joint(j).dofadr[0] for j in arm]
    predicted = np.empty_like(q)
    offset = torque_offset(model, len(arm))  # logged, not acted on
    for t in range(len(q)):
        mujoco.mj_resetData(model, data)
        data.qpos[qpos], data.qvel[dof], data.qacc[dof] = q[t], qd[t], qdd[t]
        mujoco.mj_inverse(model, data)
        predicted[t] = data.qfrc_inverse[dof] + offset
    measured = episode.data[contract.EFFORT].astype(float)
    return InverseDynamics([f"{PREFIX}{j}" for j in arm], measured, predicted)


def inverse_dynamics_gap(
    episodes: Sequence[contract.Episode], scene: SceneSpec, effects: dict | None = None
) -> dict[str, float]:
    """RMS (N m) of measured minus inverse-dynamics torque per joint over ``episodes``
    (empty when none logs torques)."""
    twin = inverse_model(scene, effects)
    results = [r for e in episodes if (r := inverse_dynamics(e, twin))]
    if not results:
        return {}
    error = np.concatenate([r.measured - r.predicted for r in results])
    return dict(zip(results[0].names, np.sqrt(np.mean(error**2, axis=0)).tolist(), strict=True))
