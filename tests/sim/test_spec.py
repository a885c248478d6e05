"""Scene specs: validation errors say what is wrong and where; digests; custom robots."""

import copy
import json
from pathlib import Path

import numpy as np
import pytest

from twinrl_sim.build import compile_scene
from twinrl_sim.errors import TwinError
from twinrl_sim.spec import SpecError, load_spec, parse_spec, save_spec
from twinrl_sim.tasks import TASKS, make_task

BANANA = {
    "name": "banana",
    "role": "manipulated",
    "mass": 0.1,
    "geoms": [{"type": "capsule", "size": [0.02, 0.06]}],
}


def test_every_builtin_scene_compiles():
    for name in TASKS:
        scene = make_task(name).scene
        assert compile_scene(scene).model.nbody > 10


def test_unknown_key_is_named_with_the_nearest_valid_key():
    with pytest.raises(
        SpecError, match=r"unknown key 'table.frcition' \(did you mean 'friction'\?\)"
    ):
        parse_spec({"name": "x", "table": {"frcition": 0.5}})


def test_out_of_range_values_are_reported_with_their_location():
    with pytest.raises(SpecError, match=r"objects.0.mass: .*greater than 0"):
        parse_spec({"name": "x", "objects": [{**BANANA, "mass": -1.0}]})
    with pytest.raises(SpecError, match=r"physics.timestep"):
        parse_spec({"name": "x", "physics": {"timestep": 0.5}})


def test_all_problems_are_reported_in_one_message():
    with pytest.raises(SpecError) as err:
        parse_spec({"name": "x", "table": {"size": [-1, 1]}, "bogus": 1})
    message = str(err.value)
    assert "table.size" in message and "unknown key 'bogus'" in message


def test_semantic_errors():
    with pytest.raises(SpecError, match="needs a mass"):
        parse_spec({"name": "x", "objects": [{**BANANA, "mass": None}]})
    with pytest.raises(SpecError, match="duplicate object name"):
        parse_spec({"name": "x", "objects": [BANANA, BANANA]})
    with pytest.raises(SpecError, match="needs 3 size"):
        parse_spec(
            {"name": "x", "objects": [{**BANANA, "geoms": [{"type": "box", "size": [0.1]}]}]}
        )
    with pytest.raises(SpecError, match="not a whole number"):
        parse_spec({"name": "x", "physics": {"timestep": 0.003, "control_hz": 10}})


def test_effects_are_validated_by_name_parameter_and_bounds():
    with pytest.raises(
        SpecError, match="unknown effect 'joint_fricton'.*did you mean 'joint_friction'"
    ):
        parse_spec({"name": "x", "effects": {"joint_fricton": {"coulomb": [1] * 6}}})
    with pytest.raises(SpecError, match="payload.mass: 50.0 is outside"):
        parse_spec({"name": "x", "effects": {"payload": {"mass": 50}}})
    with pytest.raises(SpecError, match="unknown parameter 'secs'.*did you mean 'seconds'"):
        parse_spec({"name": "x", "effects": {"actuator_delay": {"secs": 0.1}}})
    with pytest.raises(SpecError, match="needs 6 values"):
        compile_scene(parse_spec({"name": "x", "effects": {"joint_friction": {"coulomb": [1, 2]}}}))


def test_bad_files_fail_with_one_clear_line(tmp_path):
    with pytest.raises(SpecError, match="does not exist"):
        load_spec(tmp_path / "missing.yaml")
    broken = tmp_path / "broken.yaml"
    broken.write_text("name: [unclosed")
    with pytest.raises(SpecError, match="not valid YAML"):
        load_spec(broken)


def test_digest_is_stable_and_tracks_content(tmp_path):
    scene = make_task("pick_place").scene
    again = load_spec(Path(__file__).parents[2] / "twinrl_sim/scenes/pick_place.yaml")
    assert scene.digest == again.digest
    assert scene.with_effects({"payload": {"mass": 0.5}}).digest != scene.digest
    path = save_spec(scene, tmp_path / "cell.yaml")
    assert load_spec(path).digest == scene.digest
    with pytest.raises(SpecError, match="already exists"):
        save_spec(scene, path)


ARM_MJCF = """
<mujoco>
  <worldbody>
    <body name="arm_base">
      <joint name="j1" axis="0 0 1"/>
      <geom type="capsule" fromto="0 0 0 0 0 0.3" size="0.04"/>
      <body name="arm_upper" pos="0 0 0.3">
        <joint name="j2" axis="0 1 0"/>
        <geom type="capsule" fromto="0 0 0 0.4 0 0" size="0.03"/>
        <body name="arm_tool" pos="0.4 0 0" quat="0 1 0 0">
          <joint name="j3" axis="0 0 1"/>
          <geom type="cylinder" size="0.03 0.02"/>
        </body>
      </body>
    </body>
  </worldbody>
  <actuator>
    <position name="a1" joint="j1" kp="500"/>
    <position name="a2" joint="j2" kp="500"/>
    <position name="a3" joint="j3" kp="100"/>
  </actuator>
</mujoco>
"""


def test_any_robot_mjcf_can_replace_the_builtin_arm(tmp_path):
    (tmp_path / "arm.xml").write_text(ARM_MJCF)
    spec_file = tmp_path / "cell.yaml"
    spec_file.write_text(
        "name: custom\nrobot:\n  mjcf: arm.xml\n  joints: [j1, j2, j3]\n"
        "  actuators: [a1, a2, a3]\n  flange_body: arm_tool\n  home_qpos: [0, 0.3, 0]\n"
    )
    scene = compile_scene(load_spec(spec_file))
    assert scene.layout.arm_joints == ("j1", "j2", "j3")
    assert scene.layout.gripper_actuator == "gripper"
    assert np.isfinite(scene.model.body("arm_tool").mass[0])


def test_builtin_arm_without_gripper_uses_the_flange_as_tool_point():
    scene = compile_scene(parse_spec({"name": "bare", "robot": {"gripper": "none"}}))
    assert scene.layout.gripper_actuator is None
    assert scene.model.site(scene.layout.tcp_site).bodyid[0] == scene.model.body("flange").id


def test_custom_robot_with_wrong_names_says_which(tmp_path):
    (tmp_path / "arm.xml").write_text(ARM_MJCF)
    data = {
        "name": "custom",
        "robot": {
            "mjcf": str(tmp_path / "arm.xml"),
            "joints": ["j1", "jX"],
            "actuators": ["a1", "a2"],
            "flange_body": "arm_tool",
        },
    }
    with pytest.raises(SpecError, match="lacks joint 'jX'"):
        compile_scene(parse_spec(data))


def number_paths(node, path=()):
    """Paths to every number of a parsed spec's dict."""
    if isinstance(node, dict):
        for key, value in node.items():
            yield from number_paths(value, (*path, key))
    elif isinstance(node, list | tuple):
        for index, value in enumerate(node):
            yield from number_paths(value, (*path, index))
    elif isinstance(node, int | float) and not isinstance(node, bool):
        yield path


def replaced(data, path, value):
    """A deep copy of ``data`` with the value at ``path`` replaced."""
    changed = copy.deepcopy(data)
    node = changed
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    return changed


@pytest.mark.parametrize("task", ["pick_place", "insert_hexagon"])
def test_no_damaged_number_compiles_into_a_scene_that_diverges(task):
    """Seeded fuzzing: one number of a built-in scene replaced by NaN, an infinity, a huge
    value, a negative, zero or a wrong type. Each spec is refused with the project's
    error, or compiles and simulates to finite states."""
    from twinrl_sim.cell import Cell

    data = json.loads(make_task(task).scene.model_dump_json())
    paths = list(number_paths(data))
    rng = np.random.default_rng(11)
    values = [float("nan"), float("inf"), -float("inf"), 1e300, -1e300, -1.0, 0.0, 1e6, "x", []]
    refused = accepted = 0
    for _ in range(200):
        path = paths[int(rng.integers(len(paths)))]
        value = values[int(rng.integers(len(values)))]
        try:
            scene = parse_spec(replaced(data, path, value))
            cell = Cell(compile_scene(scene))
        except TwinError:
            refused += 1
            continue
        home = np.array(cell.layout.home_qpos)
        cell.reset_robot()
        for _ in range(5):
            cell.send(home, 0.0)
        assert np.isfinite(cell.state_vector()).all(), f"{path} = {value!r} diverged"
        cell.close()
        accepted += 1
    assert refused + accepted == 200 and refused > 50 and accepted > 10, (refused, accepted)


def test_a_real_cells_file_names_its_twin_as_its_arm_runs_it(tmp_path):
    """`--twin` may be a real cell's file: its twin (built-in or a scene file beside it),
    with servos that track and feed the arm's model forward, as a UR's controller does."""
    from twinrl_sim.tasks import twin_scene

    cell = {"name": "lab", "twin": "pick_place", "arm": {"model": "ur5e", "host": "10.0.0.2"}}
    (tmp_path / "cell.yaml").write_text(json.dumps(cell))
    scene = twin_scene(str(tmp_path / "cell.yaml"))
    assert scene.name == make_task("pick_place").scene.name
    assert scene.physics.servo == "track" and scene.physics.feeds_forward
    save_spec(make_task("insert_hexagon").scene, tmp_path / "mine.yaml")
    (tmp_path / "cell.yaml").write_text(json.dumps({**cell, "twin": "mine.yaml"}))
    assert twin_scene(str(tmp_path / "cell.yaml")).name == make_task("insert_hexagon").scene.name
    (tmp_path / "cell.yaml").write_text(json.dumps({**cell, "twin": "missing.yaml"}))
    with pytest.raises(SpecError, match="missing.yaml does not exist"):
        twin_scene(str(tmp_path / "cell.yaml"))
