"""How the twin's arm servos follow a stream of joint targets, and what they feed forward.

Two models of following, chosen by the scene (``physics.servo``) or by the
``servo_lead`` effect:

- **hold** (the default): each target is the servos' setpoint for its whole control
  period. At 10 Hz this is what the twin's tasks were tuned with.
- **track**, as a UR's ``servoJ`` does: at every physics step the setpoint moves along
  the line from the previous target to the new one, and leads it by ``lead`` seconds of
  its speed (velocity feed-forward). A position servo lags its setpoint by damping /
  stiffness times the speed; a lead of that size cancels the lag, so the arm follows the
  targets within a fraction of a milliradian at any speed, as a real arm does. Its
  position loop is :data:`TRACKING_STIFFNESS` times stiffer than the holding servo's, as
  a UR's joint controller is: an arm that brakes past a target it stopped on returns in
  a few milliseconds instead of creeping back over tens. The lead is a property of the
  compiled model (the custom numeric :data:`LEAD_NUMERIC`), so the gap workflow fits it
  like any other effect.

And what the servos know of the arm (``physics.feedforward``):

- **model** (the default where the servos track): a UR's joint controllers feed forward
  the arm's dynamic model with the payload set on the controller, so they hold any load
  they know of without sagging, and the torques they log (``target_moment``) are the
  model's. The twin's servos do the same with the twin's own model: the weight of
  every body the arm carries (its links, the gripper, a ``payload`` or ``link_mass``
  effect) is compensated through the arm's actuators (MuJoCo's actuator gravity
  compensation), so it shows in the joint torques and not in the tracking. What the
  arm does not carry (a grasped object) still loads the position loop. The inertial and
  Coriolis terms are left to the position loop: at a tracking servo's stiffness they
  cost a fraction of a milliradian.
- **none** (the default where the servos hold): the built-in arm's links and gripper
  are weightless to the servos (compensated outside them, as the tasks were tuned) and
  absent from the logged torques; a ``payload`` sags them by its weight over their
  stiffness.
"""

from __future__ import annotations

import mujoco
import numpy as np

from twinrl_sim.layout import CellLayout

LEAD_NUMERIC = "twinrl_servo_lead"  # s; present: the servos track, absent: they hold
FEEDFORWARD_NUMERIC = "twinrl_servo_feedforward"  # present: the servos feed the model forward
TRACKING_STIFFNESS = 4.0  # a tracking servo's position gain over the holding servo's


def scale_stiffness(actuator: mujoco.MjsActuator, factor: float) -> None:
    """Multiply a position servo's stiffness (its gain and the matching bias) by
    ``factor``."""
    gain, bias = list(actuator.gainprm), list(actuator.biasprm)
    gain[0] *= factor
    bias[1] *= factor
    actuator.gainprm, actuator.biasprm = gain, bias


def full_lead(spec: mujoco.MjSpec, layout: CellLayout) -> float:
    """The lead that cancels the lag of the arm's servos once they track: the median over
    its joints of the (holding) joint damping / the tracking stiffness (s)."""
    ratios = []
    for joint, actuator in zip(layout.arm_joints, layout.arm_actuators, strict=True):
        stiffness = TRACKING_STIFFNESS * float(spec.actuator(actuator).gainprm[0])
        damping = float(np.atleast_1d(spec.joint(joint).damping)[0])
        if stiffness > 0:
            ratios.append(damping / stiffness)
    return float(np.median(ratios)) if ratios else 0.0


def spec_lead(spec: mujoco.MjSpec) -> float | None:
    """The lead ``spec``'s servos track with (s), or None where they hold."""
    numeric = next((n for n in spec.numerics if n.name == LEAD_NUMERIC), None)
    return None if numeric is None else float(numeric.data[0])


def set_lead(spec: mujoco.MjSpec, layout: CellLayout, seconds: float) -> None:
    """Make the arm's servos track their targets with ``seconds`` of lead.

    A holding servo's damping is the joint's (passive, so it drags at any speed); a
    tracking servo damps the speed error instead, so its damping moves into the
    actuator, where the lead's setpoint speed cancels it: moving fast costs no torque
    beyond what the arm's inertia and friction take, as on a real arm. The position gain
    becomes :data:`TRACKING_STIFFNESS` times the holding servo's."""
    numeric = next((n for n in spec.numerics if n.name == LEAD_NUMERIC), None)
    if numeric is not None:
        numeric.data = [float(seconds)]
        return
    for joint_name, actuator_name in zip(layout.arm_joints, layout.arm_actuators, strict=True):
        joint, actuator = spec.joint(joint_name), spec.actuator(actuator_name)
        damping = float(np.atleast_1d(joint.damping)[0])
        scale_stiffness(actuator, TRACKING_STIFFNESS)
        bias = list(actuator.biasprm)
        bias[2] -= damping
        actuator.biasprm = bias
        joint.damping = [0.0] * len(np.atleast_1d(joint.damping))
    spec.add_numeric(name=LEAD_NUMERIC, data=[float(seconds)], size=1)


def set_feedforward(spec: mujoco.MjSpec, layout: CellLayout) -> None:
    """Make the arm's servos feed forward the weight of everything the arm carries.

    Every body below the arm's first joint is gravity-compensated, and the compensation
    is routed through the arm joints' actuators (``actuatorgravcomp``), so that it is
    part of the joint torques the twin logs. Bodies added later to the arm (a payload)
    follow :func:`feeds_forward`."""
    if feeds_forward(spec):
        return
    first = spec.joint(layout.arm_joints[0]).parent
    for body in [first, *first.find_all(mujoco.mjtObj.mjOBJ_BODY)]:
        body.gravcomp = 1.0
    for name in layout.arm_joints:
        spec.joint(name).actgravcomp = True
    spec.add_numeric(name=FEEDFORWARD_NUMERIC, data=[1.0], size=1)


def feeds_forward(spec: mujoco.MjSpec) -> bool:
    """Whether ``spec``'s arm servos feed forward the model of what the arm carries."""
    return any(n.name == FEEDFORWARD_NUMERIC for n in spec.numerics)


def servo_lead(model: mujoco.MjModel) -> float | None:
    """The tracking servos' lead (s), or None where the servos hold each target."""
    index = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_NUMERIC, LEAD_NUMERIC)
    if index < 0:
        return None
    return float(model.numeric_data[model.numeric_adr[index]])


def tracking_setpoints(
    previous: np.ndarray, targets: np.ndarray, substeps: int, period: float, lead: float
) -> np.ndarray:
    """The setpoints of tracking servos at every physics step.

    Args:
        previous: (n, n_arm) the targets in force before the first period.
        targets: (n, W, n_arm) one target per control period.
        substeps: physics steps per control period.
        period: the control period (s).
        lead: velocity feed-forward (s).

    Returns:
        (n, W * substeps, n_arm): the setpoint held during each physics step; the last
        of each period is the period's target (plus the lead).
    """
    before = np.concatenate([previous[:, None], targets[:, :-1]], axis=1)
    change = targets - before
    fraction = np.arange(1, substeps + 1) / substeps
    setpoints = before[:, :, None] + change[:, :, None] * fraction[None, None, :, None]
    setpoints += lead * (change / period)[:, :, None]
    n, rows, _, joints = setpoints.shape
    return setpoints.reshape(n, rows * substeps, joints)
