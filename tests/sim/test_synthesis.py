"""Demo synthesis: antipodal grasps, collision-free plans, re-targeting geometry, expand."""

import json
import math

import numpy as np
import pytest

from twinrl_data.mcap_log import read_episode
from twinrl_data.session import Session
from twinrl_robot.scripted import run_scripted_expert
from twinrl_sim.augment import PlanarMotion, commanded_path, keyframes, retarget
from twinrl_sim.build import compile_scene
from twinrl_sim.cell import Cell
from twinrl_sim.env import TwinEnv
from twinrl_sim.expand import expand
from twinrl_sim.grasping import sample_antipodal_grasps
from twinrl_sim.planar import wrap_angle, yaw_of
from twinrl_sim.planner import (
    APPROACH,
    DETOUR_RADIUS,
    MISS_HEIGHT,
    CollisionChecker,
    object_pose_from_tcp,
    plan_demo,
    tcp_from_object,
)
from twinrl_sim.randomize import randomize_scene
from twinrl_sim.spec import ObjectSpec
from twinrl_sim.tasks import TaskConfig, make_task
from twinrl_sim.tasks.pick_place import PickPlace


@pytest.mark.parametrize("name", ["pick_place", "insert_hexagon", "insert_triple_column"])
def test_grasps_are_antipodal_and_fit_the_gripper(name, rng):
    task = make_task(name)
    cell = Cell(compile_scene(task.scene))
    task.start(cell, task.sample_config(rng, "ID"))
    grasps = sample_antipodal_grasps(cell, task.object_name, rng)
    assert len(grasps) >= 3
    assert all(0 < g.width <= 0.08 and g.quality >= math.cos(math.radians(12)) for g in grasps)
    assert [g.score for g in grasps] == sorted((g.score for g in grasps), reverse=True)
    if name == "insert_hexagon":  # a parallel grasp closes on two flat faces: 30 deg + k * 60 deg
        offsets = [((g.yaw - math.pi / 6) % (math.pi / 3)) for g in grasps[:3]]
        assert all(min(o, math.pi / 3 - o) < math.radians(12) for o in offsets)
        assert grasps[0].width == pytest.approx(2 * 0.024 * math.cos(math.pi / 6), abs=2e-3)


def test_grasp_frame_round_trip():
    grasp = sample_antipodal_grasps(*_started("pick_place"), np.random.default_rng(0))[0]
    tcp, yaw = tcp_from_object(np.array([0.4, 0.1, 0.02]), 0.7, grasp)
    obj, _ = object_pose_from_tcp(tcp, yaw, grasp)
    np.testing.assert_allclose(obj, [0.4, 0.1, 0.02], atol=1e-12)


def _started(name):
    task = make_task(name)
    cell = Cell(compile_scene(task.scene))
    task.start(cell, task.sample_config(np.random.default_rng(0), "ID"))
    return cell, task.object_name


def test_plans_are_collision_free_and_succeed(rng):
    env = TwinEnv("insert_hexagon")
    config = env.task.sample_config(rng, "OOD")
    plan = plan_demo(env.task, env.cell, config, np.random.default_rng(1))
    assert plan is not None
    checker = CollisionChecker(env.cell, env.task.object_name)
    lift, above = plan.waypoints[3], plan.waypoints[4]
    for s in np.linspace(0, 1, 15):  # the transport segment, object held
        point = lift.position + s * (above.position - lift.position)
        assert not checker.collides(
            point, lift.yaw + s * (above.yaw - lift.yaw), plan.grasp, plan.grasp.width
        )
    env.reset(options={"config": config})
    for action in plan.actions:
        *_, terminated, _, info = env.step(action)
        if terminated:
            break
    assert info["success"]


def test_a_detour_strays_beside_the_object_and_comes_back_to_the_same_grasp():
    env = TwinEnv("pick_place")
    config = env.task.sample_config(np.random.default_rng(3), "OOD")
    straight = plan_demo(env.task, env.cell, config, np.random.default_rng(1))
    plan = plan_demo(
        env.task, env.cell, config, np.random.default_rng(1), detour=np.random.default_rng(2)
    )
    assert straight is not None and plan is not None
    stray, approach = plan.waypoints[0], plan.waypoints[1]
    # The detour is drawn apart: after it, the same grasp and the same waypoints.
    assert len(plan.waypoints) == len(straight.waypoints) + 1
    for mine, theirs in zip(plan.waypoints[1:], straight.waypoints, strict=True):
        np.testing.assert_array_equal(mine.position, theirs.position)
    object_pos, _ = env.cell.object_pose(env.task.object_name)
    beside = np.linalg.norm(stray.position[:2] - object_pos[:2])
    assert DETOUR_RADIUS[0] <= beside <= DETOUR_RADIUS[1]
    assert stray.position[2] >= approach.position[2] >= object_pos[2] + APPROACH / 2
    checker = CollisionChecker(env.cell, env.task.object_name)
    home, home_quat = env.cell.tcp_pose()
    for a, ya, b, yb in [
        (home, yaw_of(home_quat), stray.position, stray.yaw),
        (stray.position, stray.yaw, approach.position, approach.yaw),
    ]:
        for s in np.linspace(0, 1, 15):
            assert not checker.collides(a + s * (b - a), ya + s * (yb - ya), None, 0.08)
    env.reset(options={"config": config})
    closest = np.inf
    for action in plan.actions:
        *_, terminated, _, info = env.step(action)
        closest = min(closest, np.linalg.norm(env.cell.tcp_pose()[0] - stray.position))
        if terminated:
            break
    assert info["success"] and closest < 0.02  # it went there, and still did the task
    assert len(plan.actions) > len(straight.actions)


def test_a_closed_handed_detour_shuts_the_fingers_on_nothing_and_opens_them_to_grasp():
    """Closed empty fingers far from the object (for a pose estimator): the same stray and
    grasp as the open-handed detour, the fingers shut there and open on the way back."""
    env = TwinEnv("pick_place")
    config = env.task.sample_config(np.random.default_rng(3), "OOD")
    open_handed = plan_demo(
        env.task, env.cell, config, np.random.default_rng(1), detour=np.random.default_rng(2)
    )
    plan = plan_demo(
        env.task,
        env.cell,
        config,
        np.random.default_rng(1),
        detour=np.random.default_rng(2),
        closed_detour=True,
    )
    assert open_handed is not None and plan is not None
    for mine, theirs in zip(plan.waypoints, open_handed.waypoints, strict=True):
        np.testing.assert_array_equal(mine.position, theirs.position)
    assert plan.waypoints[0].gripper == 1.0 and open_handed.waypoints[0].gripper == 0.0
    env.reset(options={"config": config})
    stray = plan.waypoints[0].position
    object_start = env.cell.object_pose(env.task.object_name)[0]
    shut_away = False
    for action in plan.actions:
        *_, terminated, _, info = env.step(action)
        tcp = env.cell.tcp_pose()[0]
        if np.linalg.norm(tcp - stray) < 0.02 and env.cell.gripper_opening < 0.01:
            shut_away = np.linalg.norm(tcp[:2] - object_start[:2]) >= DETOUR_RADIUS[0] - 0.01
        if terminated:
            break
    assert shut_away and info["success"]


def test_a_missed_grasp_closes_empty_above_the_object_then_grasps_as_planned():
    """The first close is above the banana: the fingers shut on nothing and it stays on
    the table; then the arm opens and does the straight plan's grasp."""
    env = TwinEnv("pick_place")
    config = env.task.sample_config(np.random.default_rng(4), "ID")
    straight = plan_demo(env.task, env.cell, config, np.random.default_rng(1))
    plan = plan_demo(
        env.task, env.cell, config, np.random.default_rng(1), miss=np.random.default_rng(5)
    )
    assert straight is not None and plan is not None
    assert len(plan.waypoints) == len(straight.waypoints) + 4
    high, grasp = plan.waypoints[1], straight.waypoints[1]
    assert MISS_HEIGHT[0] <= high.position[2] - grasp.position[2] <= MISS_HEIGHT[1]
    for mine, theirs in zip(plan.waypoints[5:], straight.waypoints[1:], strict=True):
        np.testing.assert_array_equal(mine.position, theirs.position)
    env.reset(options={"config": config})
    resting = env.cell.object_pose(env.task.object_name)[0][2]
    closes = np.flatnonzero(np.diff((plan.actions[:, 6] > 0.5).astype(int)) == 1) + 1
    assert len(closes) == 2
    for t, action in enumerate(plan.actions):
        _, _, terminated, _, info = env.step(action)
        if t == closes[1] - 1:  # just before the second close: the first held nothing
            assert env.cell.object_pose(env.task.object_name)[0][2] == pytest.approx(
                resting, abs=0.003
            )
            assert env.cell.gripper_opening > 0.05
        if closes[0] + 8 <= t < closes[0] + 10:  # the first close has shut on nothing
            assert env.cell.gripper_opening < 0.01
        if terminated:
            break
    assert info["success"]


def test_expand_with_detours_marks_them_and_refuses_what_cannot_stray(tmp_path):
    from typer.testing import CliRunner

    from twinrl_learn.cli import app

    args = ["expand", "pick_place", "--id", "1", "--ood", "1", "--workers", "1", "--no-images"]
    result = CliRunner().invoke(app, [*args, "--detours", "1", "--out", str(tmp_path / "d")])
    assert result.exit_code == 0, result.output
    assert "2 of the kept demos stray first" in result.output
    saved = json.loads((tmp_path / "d" / "expand.json").read_text())
    assert saved["detoured"] == {"ID": 1, "OOD": 1}
    paths = Session(tmp_path / "d" / "session").episode_paths()
    assert {read_episode(p).meta.policy for p in paths} == {"synthesis:plan+detour"}
    result = CliRunner().invoke(app, [*args, "--misses", "1", "--out", str(tmp_path / "m")])
    assert result.exit_code == 0, result.output
    assert "2 of the kept demos miss their first grasp" in result.output
    assert json.loads((tmp_path / "m" / "expand.json").read_text())["missed"] == {"ID": 1, "OOD": 1}
    closed = ["--detours", "1", "--closed-detours", "1", "--out", str(tmp_path / "c")]
    result = CliRunner().invoke(app, [*args, *closed])
    assert result.exit_code == 0, result.output
    assert "2 of the kept demos stray first (2 with closed fingers)" in result.output
    assert json.loads((tmp_path / "c" / "expand.json").read_text())["closed"] == {"ID": 1, "OOD": 1}
    paths = Session(tmp_path / "c" / "session").episode_paths()
    assert {read_episode(p).meta.policy for p in paths} == {"synthesis:plan+detour+closed"}
    for detours, closed_detours, method, message in [
        (1.5, 0.0, "plan", "from 0 to 1"),
        (0.5, 0.0, "augment", "applies to `method` plan"),
        (0.0, 0.5, "plan", "share of the detours"),
    ]:
        with pytest.raises(ValueError, match=message):
            expand(
                "pick_place",
                id_count=1,
                ood_count=0,
                out=tmp_path / "x",
                method=method,
                from_demo=paths[0] if method == "augment" else None,
                detours=detours,
                closed_detours=closed_detours,
            )
        assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("degrees", [-88, -84, -80, 80, 84, 88])
def test_plans_turn_the_wrist_the_way_the_nominal_grasp_does(degrees):
    """Near a right angle either half-turn equivalent of a grasp needs a similar turn;
    planned demos must turn as the object's heading says (as the expert does), or demos
    of neighbouring configurations disagree and a policy imitating both stops halfway."""
    task = make_task("pick_place")
    cell = Cell(compile_scene(task.scene))
    heading = math.radians(degrees)
    config = TaskConfig(object=(0.45, -0.3, heading), target=(0.45, -0.05, 0.0))
    for seed in range(3):
        plan = plan_demo(task, cell, config, np.random.default_rng(seed))
        assert plan is not None
        tool_yaw = heading + plan.grasp.yaw  # the grasp's yaw is relative to the heading
        assert abs(tool_yaw - heading) < math.radians(35), (degrees, seed, math.degrees(tool_yaw))


def test_an_obstacle_raises_the_transport_height():
    """A tall wall between object and plate: the planner must go over it."""
    base = PickPlace.default_scene()
    wall = ObjectSpec(
        name="wall",
        role="fixture",
        pos=(0.45, -0.2, 0.1),
        geoms=[{"type": "box", "size": [0.1, 0.01, 0.1]}],
    )
    scene = base.model_copy(update={"objects": [*base.objects, wall]})
    task = PickPlace(scene)
    cell = Cell(compile_scene(scene))
    config = TaskConfig(object=(0.45, -0.32, 0.0), target=(0.45, -0.08, 0.0))
    low = plan_demo(PickPlace(), Cell(compile_scene(base)), config, np.random.default_rng(0))
    high = plan_demo(task, cell, config, np.random.default_rng(0))
    assert low is not None and high is not None
    assert high.transport_height > low.transport_height
    top = max(w.position[2] for w in high.waypoints)
    assert top > 0.2 + 0.02  # over the wall


def test_retargeted_paths_keep_their_pose_relative_to_object_and_target(tmp_path):
    session = Session.create(tmp_path / "demo")
    run_scripted_expert("pick_place", world="twin", episodes=1, regions=("ID",), session=session)
    demo = read_episode(session.episode_paths()[0])
    source = TaskConfig.from_dict(demo.meta.config)
    target = TaskConfig(object=(0.5, 0.2, source.object[2] + 0.4), target=(0.35, 0.3, 0.2))
    actions = retarget(demo, source, target, extend_steps=0)
    original, _ = commanded_path(demo)
    start = original[0]
    new = start + np.vstack([np.zeros(3), np.cumsum(actions[:, :3], axis=0)])
    grasp, handover = keyframes(demo, releases_object=True)
    np.testing.assert_allclose(
        new[grasp],
        PlanarMotion.between(source.object, target.object).apply(original[grasp]),
        atol=1e-6,
    )
    np.testing.assert_allclose(
        new[handover],
        PlanarMotion.between(source.target, target.target).apply(original[handover]),
        atol=1e-6,
    )
    np.testing.assert_array_equal(actions[:, 6], demo.data["action"][:, 6])
    same = retarget(demo, source, source, extend_steps=0)
    np.testing.assert_allclose(same, demo.data["action"], atol=1e-6)


def test_a_retargeted_demo_turns_the_wrist_toward_the_targets_nominal_grasp(tmp_path):
    """Turning the object by more than a right angle: the wrist turns the same way (to
    the target's nominal grasp yaw), not by the shorter equivalent the other way."""
    session = Session.create(tmp_path / "demo")
    run_scripted_expert("pick_place", world="twin", episodes=1, regions=("ID",), session=session)
    demo = read_episode(session.episode_paths()[0])
    source = TaskConfig.from_dict(demo.meta.config)
    heading = -1.4 if source.object[2] > 0 else 1.4  # across the right angle from the source
    target = TaskConfig(object=(0.45, -0.3, heading), target=source.target)
    actions = retarget(demo, source, target, extend_steps=0)
    _, quats = commanded_path(demo)
    grasp, _ = keyframes(demo, releases_object=True)
    source_offset = wrap_angle(yaw_of(quats[grasp]) - source.object[2], math.pi)
    turn = np.sum(actions[:grasp, 5])  # a top-down tool turns about the vertical only
    new_grasp_yaw = yaw_of(quats[0]) + turn
    assert new_grasp_yaw == pytest.approx(heading + source_offset, abs=1e-3)


def test_randomisation_is_seeded_and_recorded():
    scene = make_task("pick_place").scene
    a, record_a = randomize_scene(
        scene, np.random.default_rng(4), ("lighting", "colors", "textures", "camera")
    )
    b, record_b = randomize_scene(
        scene, np.random.default_rng(4), ("lighting", "colors", "textures", "camera")
    )
    assert a == b and record_a == record_b
    assert a.digest != scene.digest and set(record_a) == {
        "lighting",
        "colors",
        "textures",
        "camera",
    }
    with pytest.raises(ValueError, match="unknown randomisation 'fog'"):
        randomize_scene(scene, np.random.default_rng(0), ("fog",))


def test_expand_writes_episodes_dataset_and_report(tmp_path):
    report = expand("pick_place", id_count=2, ood_count=1, out=tmp_path / "out", workers=1, seed=5)
    assert report.kept == {"ID": 2, "OOD": 1}
    session = Session(tmp_path / "out" / "session")
    episodes = [read_episode(p) for p in session.episode_paths()]
    assert {e.meta.source for e in episodes} == {"twin_demo"} and all(
        e.meta.success for e in episodes
    )
    assert sorted(e.meta.region for e in episodes) == ["ID", "ID", "OOD"]
    assert all(e.cameras == ["front", "wrist"] for e in episodes)
    saved = json.loads((tmp_path / "out" / "expand.json").read_text())
    assert (
        saved["yield"]["ID"] > 0 and (tmp_path / "out" / "dataset" / "meta" / "info.json").is_file()
    )
    # Two workers and no cameras (for a state policy): the same demonstrations.
    from typer.testing import CliRunner

    from twinrl_learn.cli import app

    args = ["expand", "pick_place", "--id", "2", "--ood", "1", "--seed", "5", "--workers", "2"]
    result = CliRunner().invoke(app, [*args, "--no-images", "--out", str(tmp_path / "again")])
    assert result.exit_code == 0, result.output
    again = sorted(
        (read_episode(p) for p in Session(tmp_path / "again" / "session").episode_paths()),
        key=lambda e: json.dumps(e.meta.config),
    )
    assert all(e.cameras == [] for e in again)
    by_config = sorted(episodes, key=lambda e: json.dumps(e.meta.config))
    for mine, theirs in zip(again, by_config, strict=True):
        assert mine.meta.config == theirs.meta.config
        np.testing.assert_array_equal(
            mine.data["observation.state"], theirs.data["observation.state"]
        )
    info = json.loads((tmp_path / "again" / "dataset" / "meta" / "info.json").read_text())
    assert not [k for k in info["features"] if k.startswith("observation.images")]
    with pytest.raises(ValueError, match="drop it or record images"):
        expand(
            "pick_place",
            id_count=1,
            ood_count=0,
            out=tmp_path / "y",
            randomize=("lighting",),
            images=False,
        )
    assert not (tmp_path / "y").exists()
    with pytest.raises(ValueError, match="not empty"):
        expand("pick_place", id_count=1, ood_count=0, out=tmp_path / "out")
    with pytest.raises(ValueError, match="needs `from_demo`"):
        expand("pick_place", id_count=1, ood_count=0, out=tmp_path / "x", method="augment")


def test_expand_in_a_fitted_twin_renders_with_its_look(tmp_path):
    from typer.testing import CliRunner

    from twinrl_learn.cli import app
    from twinrl_sim.spec import save_spec

    look = {"appearance": {"light_scale": 0.6, "table_tint": [0.1, 0.0, 0.0]}}
    fitted = make_task("pick_place").scene.with_effects(look)
    save_spec(fitted, tmp_path / "twin_fitted.yaml")
    runner = CliRunner()
    args = ["expand", "pick_place", "--id", "1", "--ood", "0", "--workers", "1", "--out"]
    twin = ["--twin", str(tmp_path / "twin_fitted.yaml")]
    result = runner.invoke(app, [*args, str(tmp_path / "fitted"), *twin])
    assert result.exit_code == 0, result.output
    assert runner.invoke(app, [*args, str(tmp_path / "nominal")]).exit_code == 0
    (mine,) = [read_episode(p) for p in Session(tmp_path / "fitted" / "session").episode_paths()]
    (nominal,) = [
        read_episode(p) for p in Session(tmp_path / "nominal" / "session").episode_paths()
    ]
    assert mine.meta.twin == fitted.digest != nominal.meta.twin
    assert mine.meta.config == nominal.meta.config  # same attempt, another look
    front, plain = mine.images["front"][0].astype(float), nominal.images["front"][0].astype(float)
    assert front.mean() < plain.mean() - 5  # the fitted cell's dimmer light
    wrong = runner.invoke(app, [*args, str(tmp_path / "w"), "--twin", "insert_hexagon"])
    assert wrong.exit_code != 0 and "twin insert_hexagon" in str(wrong.exception)
    assert not (tmp_path / "w").exists()
