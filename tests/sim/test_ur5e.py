"""The built-in UR5e: kinematics against the published DH parameters, home pose, limits."""

import mujoco
import numpy as np

from twinrl_sim.build import compile_scene
from twinrl_sim.robots import ur5e
from twinrl_sim.spec import parse_spec


def test_flange_pose_matches_published_dh_within_a_millimetre(rng):
    """FK of the compiled model equals the DH chain at random joint angles."""
    scene = compile_scene(parse_spec({"name": "fk"}))
    model, data = scene.model, mujoco.MjData(scene.model)
    flange = model.body(scene.layout.flange_body).id
    adr = [model.joint(j).qposadr[0] for j in scene.layout.arm_joints]
    for _ in range(200):
        q = rng.uniform(-np.pi, np.pi, 6)
        data.qpos[adr] = q
        mujoco.mj_kinematics(model, data)
        expected = ur5e.UR5E_DH.forward(q)
        assert np.linalg.norm(data.xpos[flange] - expected[:3, 3]) < 1e-3
        np.testing.assert_allclose(data.xmat[flange].reshape(3, 3), expected[:3, :3], atol=1e-6)


def test_dh_chain_reaches_published_zero_pose():
    """At zero angles the flange is at (a2 + a3, -(d4 + d6), d1 - d5), as UR documents."""
    pose = ur5e.UR5E_DH.forward(np.zeros(6))
    np.testing.assert_allclose(pose[:3, 3], [-0.8172, -0.2329, 0.0628], atol=1e-4)


def test_masses_limits_and_servos_come_from_the_tables():
    scene = compile_scene(parse_spec({"name": "dyn"}))
    model = scene.model
    for i, name in enumerate(scene.layout.arm_joints):
        body = model.body(f"link{i + 1}")
        assert body.mass[0] == ur5e.LINK_MASSES[i]
        np.testing.assert_allclose(model.joint(name).range, ur5e.JOINT_LIMITS[i])
        act = model.actuator(name)
        assert act.gainprm[0] == ur5e.SERVO_KP[i]
        np.testing.assert_allclose(
            act.forcerange, [-ur5e.JOINT_TORQUE_LIMITS[i], ur5e.JOINT_TORQUE_LIMITS[i]]
        )


def test_home_pose_puts_the_tool_above_the_table_pointing_down():
    scene = compile_scene(parse_spec({"name": "home"}))
    model, data = scene.model, mujoco.MjData(scene.model)
    adr = [model.joint(j).qposadr[0] for j in scene.layout.arm_joints]
    data.qpos[adr] = scene.layout.home_qpos
    mujoco.mj_kinematics(model, data)
    tcp = model.site(scene.layout.tcp_site).id
    np.testing.assert_allclose(data.site_xpos[tcp], [0.45, 0.0, 0.30], atol=1e-3)
    assert data.site_xmat[tcp].reshape(3, 3)[2, 2] < -0.999
