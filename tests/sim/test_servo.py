"""The arm's servo models: holding servos lag and saturate on a fast 125 Hz target
stream, tracking ones (servoJ-like: interpolated, velocity feed-forward) follow it; the
batched replay and the cell step them alike; the gap workflow names a hidden lead."""

import mujoco
import numpy as np
import pytest
from mujoco.rollout import Rollout

from tests.sim.test_gap_diagnose import _record, _within
from twinrl_sim.build import compile_scene
from twinrl_sim.cell import Cell
from twinrl_sim.gap.diagnose import diagnose
from twinrl_sim.servo import TRACKING_STIFFNESS, servo_lead, tracking_setpoints
from twinrl_sim.spec import PhysicsSpec
from twinrl_sim.tasks import make_task
from twinrl_sim.windowed import Starts, WindowedReplay

SCENE = make_task("pick_place").scene
TORQUE_LIMITS = np.array([150.0, 150.0, 150.0, 28.0, 28.0, 28.0])


def _cell(servo: str, hz: float = 125.0, lead: float | None = None) -> Cell:
    physics = SCENE.physics.model_copy(
        update={"servo": servo, "control_hz": hz, "servo_lead": lead}
    )
    return Cell(compile_scene(SCENE.model_copy(update={"physics": physics})))


def _stream(cell: Cell, seconds: float = 2.0, amplitude: float = 0.3) -> np.ndarray:
    """Joint targets swinging every joint at up to 1.5 rad/s (0.8 Hz), at the cell's rate."""
    t = np.arange(1, round(seconds / cell.control_dt)) * cell.control_dt
    swing = amplitude * np.sin(2 * np.pi * 0.8 * t)[:, None] * [1, 0.5, 0.5, 1, 1, 1]
    return np.array(cell.layout.home_qpos) + swing


def _follow(cell: Cell, targets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per step: the worst joint's tracking error (rad) and the torques (N m)."""
    cell.reset_robot()
    cell.finish_reset()
    errors, torques = [], []
    for target in targets:
        cell.send(target, 0.0)
        errors.append(np.abs(cell.arm_q - target).max())
        torques.append(cell.joint_torques())
    return np.array(errors), np.array(torques)


def test_tracking_servos_follow_a_fast_stream_that_holding_ones_saturate_on():
    hold, track = _cell("hold"), _cell("track")
    assert servo_lead(hold.model) is None
    # damping / the tracking stiffness of the UR5e's servos
    assert track.servo_lead == pytest.approx(0.05 / TRACKING_STIFFNESS)
    targets = _stream(hold)
    settled = slice(round(0.3 / hold.control_dt), None)
    hold_error, hold_torque = _follow(hold, targets)
    track_error, track_torque = _follow(track, targets)
    # Holding servos drag their damping at full speed: the wrists hit their torque limit.
    assert hold_error[settled].max() > 0.1
    assert np.isclose(np.abs(hold_torque).max(axis=0), TORQUE_LIMITS).any()
    # Tracking ones lag only by what the arm's inertia takes, well inside the limits.
    assert track_error[settled].max() < 0.006
    assert np.all(np.abs(track_torque[settled]).max(axis=0) < 0.6 * TORQUE_LIMITS)
    # No lead: the setpoint still moves smoothly, the lag comes back.
    unled_error, _ = _follow(_cell("track", lead=0.0), targets)
    assert unled_error[settled].max() > 5 * track_error[settled].max()


def test_setpoints_move_from_target_to_target_and_lead_by_their_speed():
    previous = np.zeros((1, 2))
    targets = np.array([[[0.1, -0.2], [0.3, -0.2]]])
    setpoints = tracking_setpoints(previous, targets, substeps=4, period=0.04, lead=0.02)
    assert setpoints.shape == (1, 8, 2)
    speed = np.array([[2.5, -5.0], [5.0, 0.0]])  # rad/s in each period
    expected_first = [0.025, 0.05, 0.075, 0.1] + 0.02 * speed[0, 0]
    assert np.allclose(setpoints[0, :4, 0], expected_first)
    assert np.allclose(setpoints[0, 7], targets[0, 1] + 0.02 * speed[1])


def test_the_batched_replay_steps_tracking_servos_as_the_cell_does():
    cell = _cell("track")
    targets = _stream(cell, seconds=0.6)
    cell.reset_robot()
    cell.finish_reset()
    starts = Starts.capture(cell.model, cell.data)
    with Rollout(nthread=1) as pool:
        engine = WindowedReplay(cell.layout, 125.0, pool)
        ticks, ends = engine.rollout(
            [cell.model], starts, targets[None], np.zeros((1, len(targets)))
        )
    replayed = mujoco.MjData(cell.model)
    engine.restore(cell.model, replayed, ticks[0, 0, -1], ends[0, 0, -1])
    for target in targets:
        cell.send(target, 0.0)
    assert np.allclose(replayed.qpos[cell.arm_qpos], cell.arm_q, atol=1e-9)
    assert np.allclose(replayed.qfrc_actuator[cell.arm_dof], cell.joint_torques(), atol=1e-6)


def test_a_servo_the_twin_does_not_have_or_a_lead_out_of_range_is_refused():
    physics = SCENE.physics.model_dump()
    with pytest.raises(ValueError, match="servo_lead"):
        PhysicsSpec.model_validate({**physics, "servo": "track", "servo_lead": 2.0})
    with pytest.raises(ValueError, match="servo"):
        PhysicsSpec.model_validate({**physics, "servo": "servoj"})


def test_the_gap_workflow_names_a_hidden_servo_lead(tmp_path):
    # The plant's servos track with a lead the twin (holding its targets) lacks.
    episodes = _record(tmp_path / "s", {"servo_lead": {"seconds": 0.05}})
    diagnosis = diagnose(episodes, SCENE, allowed=["servo_lead", "actuator_delay", "payload"])
    assert diagnosis.selected and diagnosis.selected[0]["effect"] == "servo_lead"
    fitted = diagnosis.effects["servo_lead"]["seconds"]
    assert _within(fitted, 0.05, diagnosis.selected[0]["ci"]["seconds"]), fitted
    assert diagnosis.heldout_reduction >= 0.7


def _held(servo: str, feedforward: str | None, effects: dict | None = None) -> Cell:
    physics = SCENE.physics.model_copy(
        update={"servo": servo, "control_hz": 125.0, "feedforward": feedforward}
    )
    cell = Cell(compile_scene(SCENE.model_copy(update={"physics": physics}), extra_effects=effects))
    cell.reset_robot()
    cell.finish_reset()
    home = np.array(cell.layout.home_qpos)
    for _ in range(60):
        cell.send(home, 0.0)
    return cell


def test_servos_that_feed_the_model_forward_carry_a_load_and_log_its_weight():
    load = {"payload": {"mass": 2.5, "cog": [0.04, 0.0, 0.08]}}
    bare, loaded = _held("track", None), _held("track", None, load)
    home = np.array(bare.layout.home_qpos)
    # A UR's joints track within a fraction of a milliradian while carrying their load.
    assert np.abs(loaded.arm_q - home).max() < 2e-4
    # The logged torques are the model's: the load's weight through the arm's Jacobian.
    model, data = loaded.model, mujoco.MjData(loaded.model)
    data.qpos[:] = loaded.data.qpos
    mujoco.mj_forward(model, data)
    body = model.body("effect_payload").id
    jac = np.zeros((3, model.nv))
    mujoco.mj_jacBodyCom(model, data, jac, None, body)
    weight = -jac[:, loaded.arm_dof].T @ (model.body_mass[body] * model.opt.gravity)
    assert loaded.joint_torques() - bare.joint_torques() == pytest.approx(weight, abs=0.05)
    # The arm's own weight is in them too, as in a UR's target_moment.
    assert np.abs(bare.joint_torques()[1:3]).min() > 10.0
    # Servos without the model hold the arm's links but sag under what they carry.
    plain = _held("track", "none", load)
    assert np.abs(plain.arm_q - home).max() > 5e-4
    assert np.abs(_held("track", "none").joint_torques()).max() < 0.05


def test_a_grasped_object_is_not_in_the_servos_model():
    """What the arm holds but does not carry as part of itself still loads the
    position loop: only the arm, its tool and its payload are compensated."""
    cell = _held("track", None)
    first = cell.model.jnt_bodyid[cell.model.joint(cell.layout.arm_joints[0]).id]
    carried = {b for b in range(cell.model.nbody) if cell.model.body_gravcomp[b] == 1.0}
    assert first in carried
    for name in cell.layout.manipulated:
        assert cell.model.body(name).id not in carried
