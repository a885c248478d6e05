"""Each effect edits the model as documented; the dynamic ones change a tracked trajectory."""

import mujoco
import numpy as np
import pytest

from twinrl_sim.build import compile_scene
from twinrl_sim.cell import Cell
from twinrl_sim.effects import EFFECTS, load_effects, validate_effects
from twinrl_sim.replay import replay
from twinrl_sim.tasks import TaskConfig, make_task

TASK = make_task("pick_place")
CONFIG = TaskConfig(object=(0.45, -0.2, 0.3), target=(0.5, -0.05, 0.0))
ARM = ("shoulder_pan", "shoulder_lift", "elbow", "wrist_1", "wrist_2", "wrist_3")


def model_with(effects: dict) -> mujoco.MjModel:
    return compile_scene(TASK.scene, extra_effects=effects).model


NOMINAL = model_with({})


def test_the_library_has_exactly_the_documented_effects_and_parameters():
    assert {name: set(d.params) for name, d in EFFECTS.items()} == {
        "actuator_delay": {"seconds"},
        "joint_friction": {"coulomb"},
        "joint_damping": {"viscous"},
        "joint_armature": {"inertia"},
        "servo_gain": {"scale"},
        "servo_lead": {"seconds"},
        "payload": {"mass", "cog"},
        "link_mass": {"scale"},
        "link_com": {"shift"},
        "torque_offset": {"torque"},
        "object_mass": {"scale"},
        "object_friction": {"sliding"},
        "table_height": {"offset"},
        "joint_offset": {"radians"},
        "tool_offset": {"xyz"},
        "base_offset": {"xyz"},
        "camera_pose": {"camera", "xyz", "rpy"},
        "appearance": {"light_scale", "table_tint"},
        "gripper_force": {"scale"},
    }
    assert all(d.doc for d in EFFECTS.values())


def test_actuator_delay_sets_a_history_buffer():
    model = model_with({"actuator_delay": {"seconds": 0.02}})
    for name in ARM:
        assert model.actuator_delay[model.actuator(name).id] == pytest.approx(0.02)
        assert model.actuator_history[model.actuator(name).id, 0] >= 10


def test_joint_friction_and_damping_add_to_the_nominal():
    coulomb = [1.0, 2.0, 3.0, 0.1, 0.2, 0.3]
    model = model_with(
        {"joint_friction": {"coulomb": coulomb}, "joint_damping": {"viscous": [5.0] * 6}}
    )
    for name, value in zip(ARM, coulomb, strict=True):
        assert model.joint(name).frictionloss[0] == pytest.approx(value)
        assert model.joint(name).damping[0] == pytest.approx(NOMINAL.joint(name).damping[0] + 5.0)


def test_joint_armature_adds_rotor_inertia_to_the_nominal():
    inertia = [0.0, 0.0, 0.0, 0.15, 0.0, 0.04]
    model = model_with({"joint_armature": {"inertia": inertia}})
    for name, value in zip(ARM, inertia, strict=True):
        nominal = NOMINAL.dof_armature[NOMINAL.joint(name).dofadr[0]]
        assert model.dof_armature[model.joint(name).dofadr[0]] == pytest.approx(nominal + value)


def test_servo_gain_scales_stiffness():
    model = model_with({"servo_gain": {"scale": [2.0, 1, 1, 1, 1, 0.5]}})
    assert (
        model.actuator("shoulder_pan").gainprm[0] == 2 * NOMINAL.actuator("shoulder_pan").gainprm[0]
    )
    assert (
        model.actuator("shoulder_pan").biasprm[1] == 2 * NOMINAL.actuator("shoulder_pan").biasprm[1]
    )
    assert model.actuator("wrist_3").gainprm[0] == 0.5 * NOMINAL.actuator("wrist_3").gainprm[0]


def test_payload_object_and_gripper_effects():
    payload = model_with({"payload": {"mass": 0.8}})
    assert payload.body("effect_payload").mass[0] == pytest.approx(0.8)
    assert payload.body_gravcomp[payload.body("effect_payload").id] == 0
    heavy = model_with({"object_mass": {"scale": 3.0}})
    assert heavy.body("banana").mass[0] == pytest.approx(3 * NOMINAL.body("banana").mass[0])
    slippery = model_with({"object_friction": {"sliding": 0.2}})
    assert slippery.geom("banana_geom0").friction[0] == pytest.approx(0.2)
    weak = model_with({"gripper_force": {"scale": 0.5}})
    np.testing.assert_allclose(
        weak.actuator("gripper").forcerange, 0.5 * NOMINAL.actuator("gripper").forcerange
    )


def test_payload_centre_of_gravity_and_the_arms_gravity_model():
    payload = model_with({"payload": {"mass": 2.0, "cog": [0.05, -0.02, 0.06]}})
    body = payload.body("effect_payload")
    assert payload.body_pos[body.id] == pytest.approx([0.05, -0.02, 0.06])
    heavier = model_with({"link_mass": {"scale": [1.0, 1.1, 0.9, 1.0, 1.0, 1.0]}})
    for name, scale in (("link2", 1.1), ("link3", 0.9), ("link4", 1.0)):
        nominal = NOMINAL.body(name)
        assert heavier.body(name).mass[0] == pytest.approx(scale * nominal.mass[0])
        assert heavier.body(name).inertia == pytest.approx(scale * nominal.inertia)
    moved = model_with({"link_com": {"shift": [0.0, 0.02, 0.0, 0.0, 0.0, 0.0]}})
    shift = moved.body("link2").ipos - NOMINAL.body("link2").ipos
    assert np.linalg.norm(shift) == pytest.approx(0.02)
    to_elbow = NOMINAL.body("link3").pos - NOMINAL.jnt_pos[NOMINAL.joint("shoulder_lift").id]
    assert shift @ to_elbow / np.linalg.norm(to_elbow) == pytest.approx(0.02, abs=1e-6)
    offsets = {"torque_offset": {"torque": [0.0, -2.5, 1.0, 0.0, 0.0, 0.0]}}
    np.testing.assert_array_equal(model_with(offsets).body_mass, NOMINAL.body_mass)  # logged only
    cell = Cell(compile_scene(TASK.scene, extra_effects=offsets))
    plain = Cell(compile_scene(TASK.scene))
    for each in (cell, plain):
        each.reset_robot()
        each.finish_reset()
    assert cell.joint_torques() - plain.joint_torques() == pytest.approx([0, -2.5, 1, 0, 0, 0])


def test_table_height_raises_the_table_and_what_rests_on_it():
    cell = Cell(compile_scene(TASK.scene, extra_effects={"table_height": {"offset": 0.03}}))
    nominal = Cell(compile_scene(TASK.scene))
    assert cell.table_top == pytest.approx(nominal.table_top + 0.03)
    TASK.start(cell, CONFIG)
    TASK.start(nominal, CONFIG)
    assert cell.object_pose("banana")[0][2] == pytest.approx(
        nominal.object_pose("banana")[0][2] + 0.03
    )


def test_joint_offset_makes_the_encoder_read_true_plus_offset():
    """With the same true arm pose, the offset model's joint reading is shifted."""
    offsets = [0.05, -0.03, 0.02, 0.0, 0.01, -0.04]
    model = model_with({"joint_offset": {"radians": offsets}})
    data, nominal_data = mujoco.MjData(model), mujoco.MjData(NOMINAL)
    q_true = np.array([2.5, -1.6, 1.7, -1.7, -1.5, -1.2])
    adr = [NOMINAL.joint(j).qposadr[0] for j in ARM]
    nominal_data.qpos[adr] = q_true
    data.qpos[adr] = q_true + offsets  # encoder reading
    mujoco.mj_kinematics(NOMINAL, nominal_data)
    mujoco.mj_kinematics(model, data)
    flange = NOMINAL.body("flange").id
    np.testing.assert_allclose(data.xpos[flange], nominal_data.xpos[flange], atol=1e-9)


def test_camera_pose_moves_and_turns_the_camera():
    model = model_with(
        {"camera_pose": {"camera": "front", "xyz": [0.01, 0.0, 0.0], "rpy": [0.0, 0.05, 0.0]}}
    )
    assert np.linalg.norm(model.cam_pos[0] - NOMINAL.cam_pos[0]) == pytest.approx(0.01)
    assert not np.allclose(model.cam_quat[0], NOMINAL.cam_quat[0])
    with pytest.raises(Exception, match="did you mean 'front'"):
        model_with({"camera_pose": {"camera": "fornt", "xyz": [0, 0, 0], "rpy": [0, 0, 0]}})


def test_appearance_dims_the_lights_and_tints_the_table():
    model = model_with({"appearance": {"light_scale": 0.5, "table_tint": [0.1, 0.0, -0.1]}})
    np.testing.assert_allclose(model.light_diffuse, 0.5 * NOMINAL.light_diffuse, atol=1e-6)
    table = NOMINAL.geom("table_top").id
    np.testing.assert_allclose(
        model.geom_rgba[table], NOMINAL.geom_rgba[table] + [0.1, 0.0, -0.1, 0.0], atol=1e-6
    )
    brighter = model_with({"appearance": {"light_scale": 3.0, "table_tint": [0, 0, 0]}})
    assert brighter.light_diffuse.max() == pytest.approx(1.0)  # capped at full intensity
    # A textured table's texture is tinted too.
    checker = TASK.scene.model_copy(
        update={"table": TASK.scene.table.model_copy(update={"texture": "checker"})}
    )
    plain = compile_scene(checker).model
    tinted = compile_scene(
        checker, extra_effects={"appearance": {"light_scale": 1.0, "table_tint": [0.2, 0, 0]}}
    ).model
    texture = plain.texture("table_texture").id
    adr, size = plain.tex_adr[texture], 3 * plain.tex_width[texture] * plain.tex_height[texture]
    red = lambda m: m.tex_data[adr : adr + size].reshape(-1, 3)[:, 0].astype(int)  # noqa: E731
    assert (red(tinted) - red(plain)).mean() > 20
    np.testing.assert_array_equal(model.body_mass, NOMINAL.body_mass)  # nothing physical


def tracked_trajectory(effects: dict) -> np.ndarray:
    """Joint positions while the arm follows a fixed fast swing of joint targets."""
    cell = Cell(compile_scene(TASK.scene, extra_effects=effects))
    home = np.array(cell.layout.home_qpos)
    t = np.arange(20)[:, None]
    targets = home + 0.25 * np.sin(2 * np.pi * t / 10.0) * np.array([1, 0.6, -0.6, 0.5, 0.5, 0.5])
    return replay(TASK, cell, CONFIG, targets).state[:, :6]


@pytest.mark.parametrize(
    "effect",
    [
        {"actuator_delay": {"seconds": 0.03}},
        {"joint_friction": {"coulomb": [8.0, 8.0, 6.0, 1.5, 1.5, 1.5]}},
        {"payload": {"mass": 2.0}},
    ],
    ids=["actuator_delay", "joint_friction", "payload"],
)
def test_dynamic_effects_measurably_change_a_tracked_joint_trajectory(effect):
    nominal = tracked_trajectory({})
    changed = tracked_trajectory(effect)
    assert np.abs(changed - nominal).max() > 2e-3  # rad: well above numerical noise
    np.testing.assert_array_equal(tracked_trajectory({}), nominal)


def test_effects_files_are_validated(tmp_path):
    path = tmp_path / "effects.yaml"
    path.write_text("payload: {mass: 0.3}\nactuator_delay: {seconds: 0.01}\n")
    assert load_effects(path) == {"payload": {"mass": 0.3}, "actuator_delay": {"seconds": 0.01}}
    path.write_text("payload: {mass: heavy}\n")
    with pytest.raises(ValueError, match="payload.mass: expected numbers"):
        load_effects(path)
    with pytest.raises(ValueError, match="expected one number per arm joint"):
        validate_effects({"joint_friction": {"coulomb": 1.0}})
    with pytest.raises(ValueError, match="payload: missing parameter"):
        validate_effects({"payload": {"cog": [0, 0, 0.1]}})  # the mass has no default
    with pytest.raises(ValueError, match="payload.cog: expected 3 numbers"):
        validate_effects({"payload": {"mass": 1.0, "cog": [0, 0.1]}})
