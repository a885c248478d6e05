"""Stage III: target-driven resets, the simulated operator and intervention flagging,
real-RL resume, and the whole pipeline at smoke scale."""

import json
import re
import shutil
from dataclasses import replace

import numpy as np
import pytest
import torch

from tests.conftest import tiny_state_policy
from tests.test_cli import twinrl as run_cli
from twinrl_data.mcap_log import read_episode
from twinrl_data.session import Session
from twinrl_learn.agent import Agent
from twinrl_learn.mining import Target
from twinrl_learn.policy import Policy
from twinrl_learn.real_rl import RealRL, RealRLSettings, ResetPlanner
from twinrl_learn.real_rl_progress import load_evaluations
from twinrl_learn.settings import RLConfig
from twinrl_learn.studies.pipeline import run_demo
from twinrl_learn.studies.presets import METHOD_TABLE, PRESETS
from twinrl_learn.studies.settings import StagesSettings
from twinrl_learn.studies.stages import measure_stages
from twinrl_robot.backends import open_robot
from twinrl_robot.operator import OperatorRule, SimulatedOperator
from twinrl_robot.wrappers import OperatorTakeover
from twinrl_sim.tasks import make_task
from twinrl_sim.tasks.expert import GRIPPER_CLOSED


@pytest.fixture(scope="module")
def demos(tmp_path_factory):
    return tiny_state_policy(tmp_path_factory.mktemp("real_rl"), seed=5, steps=20)


def test_resets_follow_the_targets_by_score_and_mix_in_uniform_draws():
    task = make_task("pick_place")
    rng = np.random.default_rng(0)
    configs = [task.sample_config(rng, "OOD") for _ in range(2)]
    targets = [
        Target(config=c.to_dict(), region="OOD", x=0, y=0, estimated_success=0.3, score=score)
        for c, score in zip(configs, (3.0, 1.0), strict=True)
    ]
    draws = [ResetPlanner(task, targets, ratio=1.0).next(rng) for _ in range(400)]
    assert {origin for _, _, origin in draws} == {"target"}
    first = np.mean([config == configs[0] for config, _, _ in draws])
    assert first == pytest.approx(0.75, abs=0.07)  # in proportion to the score

    mixed = [ResetPlanner(task, targets, ratio=0.3).next(rng) for _ in range(400)]
    share = np.mean([origin == "target" for _, _, origin in mixed])
    assert share == pytest.approx(0.3, abs=0.07)
    uniform = [(c, r) for c, r, origin in mixed if origin == "uniform"]
    assert {r for _, r in uniform} == {"ID", "OOD"}
    assert all(c not in configs for c, _ in uniform)
    assert {o for _, _, o in (ResetPlanner(task, [], 1.0).next(rng) for _ in range(20))} == {
        "uniform"
    }


def _operated_episode(task, operator, policy_action, heights=None):
    """Run one plant episode with ``operator`` watching (through the takeover wrapper);
    which steps it acted on (and, into ``heights``, the TCP height at each step)."""
    robot = OperatorTakeover(open_robot("plant", task, seed=0), operator, task)
    config = task.sample_config(np.random.default_rng(1), "ID")
    obs = robot.reset(config)
    acting = []
    tcp_z = robot.names["observation.state"].index("tcp.z")
    for _ in range(task.max_steps):
        if heights is not None:
            heights.append(float(obs["observation.state"][tcp_z]))
        acting.append(robot.act(policy_action(obs)).intervention)
        obs = robot.observe()
        if robot.privileged.success:
            break
    robot.close()
    return acting, robot.privileged.success


def test_the_operator_takes_over_a_stalled_arm_after_its_delay_and_hands_back():
    task = make_task("pick_place")
    rule = OperatorRule(patience=5, delay=2, noise=0.0)
    operator = SimulatedOperator(rule, seed=0)
    acting, _ = _operated_episode(task, operator, lambda obs: np.zeros(7, np.float32))
    first = acting.index(True)
    assert first == rule.patience + rule.delay  # noticed after patience, acted after delay
    assert not any(acting[:first])
    handed_back = first + acting[first:].index(False)
    assert handed_back > first + rule.min_control
    assert operator.takeovers >= 1


def test_the_operator_takes_over_a_grasp_that_closes_off_the_object():
    task = make_task("pick_place")
    rule = OperatorRule(patience=50, delay=2, noise=0.0, funnel=0.015)
    close_at_once = np.array([0, 0, 0, 0, 0, 0, 1], np.float32)  # far above the banana
    acting, _ = _operated_episode(task, SimulatedOperator(rule, seed=0), lambda obs: close_at_once)
    first = acting.index(True)
    # The fingers move on the first closed step; the operator sees it on the next
    # observation and acts after its delay, long before the stall rule's patience.
    assert 1 <= first - rule.delay <= 3

    # The expert's own grasp lies inside the funnel: as the policy it is never corrected.
    expert = task.expert(
        task.sample_config(np.random.default_rng(1), "ID"), np.random.default_rng(2)
    )
    acting, success = _operated_episode(task, SimulatedOperator(rule, seed=0), expert.act)
    assert success and not any(acting)

    # funnel = 0 switches the rule off: the stall rule alone acts, after its patience.
    quiet = OperatorRule(patience=50, delay=2, noise=0.0, funnel=0.0)
    acting, _ = _operated_episode(task, SimulatedOperator(quiet, seed=0), lambda obs: close_at_once)
    assert acting.index(True) >= quiet.patience


def test_the_operator_corrects_a_grasp_beside_the_object_without_backing_off():
    task = make_task("pick_place")
    config = task.sample_config(np.random.default_rng(1), "ID")
    yaw = float(config.object[2])
    across = 0.03 * np.array([-np.sin(yaw), np.cos(yaw), 0.0])

    def grasp_beside(obs):
        # The expert, told the banana lies 3 cm across from where it is: it closes the
        # fingers beside it, where the funnel rule takes over.
        seen = dict(obs)
        seen["observation.environment_state"] = obs["observation.environment_state"].copy()
        seen["observation.environment_state"][:3] += across
        return expert.act(seen)

    tops, held = {}, {}
    for correct_within in (0.06, 0.0):
        expert = task.expert(config, np.random.default_rng(2))
        rule = OperatorRule(patience=50, delay=2, noise=0.0, correct_within=correct_within)
        operator, heights = SimulatedOperator(rule, seed=0), []
        acting, _ = _operated_episode(task, operator, grasp_beside, heights)
        first = acting.index(True)
        low = heights[first]
        assert low < 0.05  # taken over at the grasp, beside the banana
        grasped = next(t for t in range(first, len(acting)) if not acting[t])  # handed back
        tops[correct_within] = max(heights[first:grasped]) - low
        held[correct_within] = grasped - first
    assert tops[0.06] < 0.02  # corrected where it was
    assert tops[0.0] > 0.08  # backed off to the approach pose first
    assert held[0.06] < held[0.0]  # and the grasp is done sooner


def real_settings(demos, out, **overrides):
    dataset, sft = demos
    options = {
        "task": "pick_place",
        "init": str(sft),
        "out": str(out),
        "demos": [str(dataset)],
        "plant_steps": 60,
        "eval_every": 0,
        "eval_grid": (2, 2),
        "refresh_every": 0,
        "operator": OperatorRule(patience=3, delay=1),
        "rl": RLConfig.for_method("twinrl", offline_steps=2, batch_size=16, seed=1),
    }
    return RealRLSettings(**(options | overrides))


def test_real_rl_flags_interventions_and_feeds_them_to_the_demo_buffer(demos, tmp_path):
    # No --targets: the resets stay uniform, and nothing is mined however often a
    # refresh is asked for.
    real = RealRL.start(real_settings(demos, tmp_path / "run", refresh_every=1))
    recorded_demos = len(real.run_state.demo.episodes)
    run = real.run()
    session = Session(tmp_path / "run" / "session")
    episodes = [read_episode(p) for p in session.episode_paths()]
    assert sum(len(e) for e in episodes) == run.agent.env_steps >= 60
    helped = [e for e in episodes if e.meta.num_interventions]
    assert helped, "the operator never took over an untrained policy"
    for episode in episodes:
        assert (episode.meta.source, episode.meta.world) == ("real_rl", "plant")
        flags = episode.data["intervention"]
        assert int(flags.sum()) == episode.meta.num_interventions
        # The policy's steps execute what it proposed, save the arm's motion held while
        # the gripper closes.
        executed = episode.data["action"][~flags]
        proposed = episode.data["action.policy"][~flags]
        held = ~executed[:, :6].any(axis=1) & proposed[:, :6].any(axis=1)
        np.testing.assert_array_equal(executed[~held], proposed[~held])
        np.testing.assert_array_equal(executed[:, 6], proposed[:, 6])
        assert (proposed[held, 6] >= GRIPPER_CLOSED).all()
    assert len(run.demo.episodes) == recorded_demos + len(helped)
    assert len(run.online.episodes) == len(episodes) - len(helped)
    points = load_evaluations(tmp_path / "run")
    assert [p.plant_steps for p in points] == [0, run.agent.env_steps]
    assert list((tmp_path / "run").glob("live-*.rrd"))

    # Resume with a longer budget: counters, history and evaluations carry on.
    more = real_settings(demos, tmp_path / "run", plant_steps=120, refresh_every=1)
    resumed = RealRL.resume(more)
    assert resumed.run_state.agent.env_steps == run.agent.env_steps
    assert len(resumed.run_state.history) == len(run.history)
    resumed.run()
    assert resumed.run_state.agent.env_steps >= 120
    assert len(load_evaluations(tmp_path / "run")) == 3
    assert len(resumed.run_state.history) >= 2 and not (tmp_path / "run" / "mining").exists()
    assert set(resumed.run_state.extra["reset_origins"]) == {"uniform"}


def test_real_rl_keeps_the_twin_agents_critic_when_asked(demos, tmp_path):
    twin_agent = Agent(Policy.from_pretrained(demos[1]), RLConfig(seed=11))
    twin_agent.save(tmp_path / "agent")
    saved = twin_agent.critic.state_dict()

    def critic_of(name, **overrides):
        settings = real_settings(demos, tmp_path / name, init=str(tmp_path / "agent"), **overrides)
        real = RealRL.start(settings)
        real.close()
        return real.run_state.agent.critic.state_dict()

    taken, fresh = critic_of("taken", keep_critic=True), critic_of("fresh")
    for key, value in saved.items():
        torch.testing.assert_close(taken[key], value, rtol=0, atol=0)
    assert any(not torch.equal(fresh[key], value) for key, value in saved.items())
    Agent(Policy.from_pretrained(demos[1]), RLConfig(hidden=32)).save(tmp_path / "narrow")
    with pytest.raises(ValueError, match="does not fit 2 critics of width 256"):
        RealRL.start(
            real_settings(demos, tmp_path / "c", init=str(tmp_path / "narrow"), keep_critic=True)
        )
    with pytest.raises(ValueError, match="keep_critic needs an RL agent as init"):
        RealRL.start(real_settings(demos, tmp_path / "c", keep_critic=True))  # an SFT policy
    assert not (tmp_path / "c").exists()
    result = run_cli(
        "train", "real-rl", "--task", "pick_place", "--out", str(tmp_path / "cli"),
        "--init", str(tmp_path / "agent"), "--keep-critic", "--takeover-reward", "-3",
        "--demos", str(demos[0]), "--plant-steps", "10", "--eval-every", "0",
        "--eval-grid", "2x2", "--eval-episodes", "2", "--refresh-every", "0",
        "--offline-steps", "1",
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert load_evaluations(tmp_path / "cli")[0].episodes == 2 * 4  # 2 per cell of 2x2
    config = RLConfig.load(tmp_path / "cli" / "agent")
    assert config.rewards.takeover == -3.0 and config.rewards.success == 10.0
    assert json.loads((tmp_path / "cli" / "settings.json").read_text())["keep_critic"]


def test_real_rl_refuses_bad_input(demos, tmp_path):
    with pytest.raises(ValueError, match="robot ur5e is not available"):
        real_settings(demos, tmp_path / "a", robot="ur5e")
    with pytest.raises(ValueError, match="target_ratio must be in"):
        real_settings(demos, tmp_path / "a", target_ratio=2.0)
    result = run_cli(
        "train", "real-rl", "--task", "pick_place", "--out", str(tmp_path / "b"),
        "--init", str(demos[1]), "--targets", str(tmp_path / "missing.json"),
    )  # fmt: skip
    assert result.returncode != 0
    assert "does not exist" in result.stderr and len(result.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "b").exists()


@pytest.fixture(scope="module")
def smoke_run(tmp_path_factory):
    """A whole pipeline run at smoke scale, and its report."""
    out = tmp_path_factory.mktemp("pipeline") / "demo"
    with pytest.raises(ValueError, match="inputs must be one of absolute, relative"):
        run_demo("pick_place", "smoke", out, inputs="sideways")
    assert not out.exists()
    return out, run_demo("pick_place", "smoke", out, inputs="relative", log=lambda _: None)


def test_the_whole_pipeline_runs_at_smoke_scale(smoke_run):
    out, report = smoke_run
    on_disk = json.loads((out / "report.json").read_text())
    assert on_disk == report
    assert (report["task"], report["preset"], report["policy"], report["inputs"]) == (
        "pick_place",
        "smoke",
        "state",
        "relative",
    )
    assert Policy.from_pretrained(out / "stage1" / "state_real_twin").config.inputs == "relative"
    assert set(report["methods"]) == {m.name for m in METHOD_TABLE}
    for summary in report["methods"].values():
        assert set(summary) == {
            "plant_minutes_to_95",
            "final_success",
            "interventions",
            "plant_steps",
            "seeds_kept_start",
        }
        assert set(summary["final_success"]) == {"ID", "OOD"}
        assert all(n in (0, 1) for n in summary["seeds_kept_start"].values())
        assert summary["plant_steps"] >= 100
    for name in ("report.md", "curves.png", "catalog.parquet", "representative.rrd"):
        assert (out / name).is_file(), name
    # TwinRL keeps imitating the twin demos its policy was fine-tuned on; ConRFT has none.
    # The imitating methods fine-tune gently; SAC keeps its usual actor learning rate.
    # Every method has the same operator, who corrects near-miss grasps where they are.
    for slug, demos, actor_lr in (
        ("twinrl", 2, 3e-5),
        ("twinrl_no_buffer", 2, 3e-5),
        ("conrft", 1, 3e-5),
        ("hil_serl", 1, 3e-4),
    ):
        settings = json.loads((out / "real_rl" / slug / "seed0" / "settings.json").read_text())
        assert len(settings["demos"]) == demos, slug
        assert settings["rl"]["actor_lr"] == actor_lr, slug
        assert settings["operator"]["correct_within"] == OperatorRule().correct_within > 0
    # The starting policies are measured on the runs' grid: Stage I's two, Stage II's.
    assert set(report["stages"]) == {"sft_real", "sft_real_twin", "twin_rl"}
    stage2_eval = json.loads((out / "stage2" / "plant_eval" / "eval.json").read_text())
    assert report["stages"]["twin_rl"] == {
        r: stage2_eval["success_rate"].get(r, 0.0) for r in ("ID", "OOD")
    }
    text = (out / "report.md").read_text()
    assert "![success against plant minutes](curves.png)" in text
    assert "| Stage II: twin RL (40 twin steps) |" in text
    for method in METHOD_TABLE:  # each run's evaluations, one row per method and seed
        rows = [line for line in text.splitlines() if line.startswith(f"| {method.name} | 0 |")]
        assert len(rows) == 1
        assert re.search(r"\d+ % \(\d+–\d+\) / \d+ % \(\d+–\d+\)", rows[0]), rows[0]
    # A run made before Stage II was evaluated gets the evaluation when resumed.
    shutil.rmtree(out / "stage2" / "plant_eval")
    assert (
        run_demo("pick_place", "smoke", out, inputs="relative", resume=True, log=lambda _: None)
        == report
    )
    # A finished pipeline is never overwritten by accident.
    with pytest.raises(ValueError, match="not empty"):
        run_demo("pick_place", "smoke", out)
    # Nor resumed as a different run: its stages would mix two kinds of policy.
    with pytest.raises(ValueError, match="is a run with `inputs` 'relative', not 'absolute'"):
        run_demo("pick_place", "smoke", out, resume=True)
    # A preset of one's own is a 'custom' run, never mixed with a named one.
    custom = replace(PRESETS["smoke"], plant_steps=200, inputs="relative")
    with pytest.raises(ValueError, match="is a run with `preset` 'smoke', not 'custom'"):
        run_demo("pick_place", custom, out, resume=True)


@pytest.mark.long  # ~80 s, beyond CI's time (make test-long)
def test_the_stages_are_measured_on_shared_configurations(smoke_run, tmp_path):
    out, _ = smoke_run
    run = tmp_path / "run"
    shutil.copytree(out, run)
    # Smoke-scale twin RL keeps no rollout; stand its real demos in as the twin buffer.
    shutil.copytree(run / "stage1" / "real", run / "stage2" / "twin_buffer")
    settings = StagesSettings(run=run, out=tmp_path / "stages", seeds=(0, 1), grid=(2, 2))
    heard = []
    result = measure_stages(settings, on_evaluation=lambda done, total, _: heard.append(done))
    policies = result["policies"]
    assert list(policies)[:5] == [
        "Stage I: SFT, real demos only",
        "Stage I: SFT, real + twin demos",
        "Stage II: twin RL",
        "Stage II + offline phase, with the twin buffer",
        "Stage II + offline phase, without the twin buffer",
    ]
    assert {"TwinRL, seed0 final", "TwinRL w/o twin buffer, seed0 final"} <= set(policies)
    assert heard == list(range(2 * len(policies)))
    for p in policies.values():
        assert len(p["per_seed"]) == 2 and set(p["mean"]) == {"ID", "OOD"}
    gain = result["twin_buffer_offline_gain"]
    with_, without = (
        policies[f"Stage II + offline phase, with{s} the twin buffer"] for s in ("", "out")
    )
    assert gain["mean"]["ID"] == pytest.approx(with_["mean"]["ID"] - without["mean"]["ID"])
    # Every policy met the same plant configurations in evaluation k.
    for k in (0, 1):
        starts = {
            json.dumps(read_episode(path).meta.config, sort_keys=True)
            for folder in (tmp_path / "stages" / "evaluations" / f"seed{k}").iterdir()
            for path in Session(folder / "session").episode_paths()[:1]
        }
        assert len(starts) == 1
    for name in ("stages.md", "stages.json", "stages.png"):
        assert (tmp_path / "stages" / name).is_file()
    # Side by side on two worker processes, each evaluation comes out as it did alone.
    apart = replace(settings, out=tmp_path / "apart", seeds=(1,), finals=False, workers=2)
    for label, measured in measure_stages(apart)["policies"].items():
        assert measured["per_seed"] == [policies[label]["per_seed"][1]], label
    # A finished study is not overwritten; a folder that is no pipeline run is refused.
    with pytest.raises(ValueError, match="not empty"):
        measure_stages(settings)
    result = run_cli("bench", "stages", str(tmp_path), "--out", str(tmp_path / "s2"))
    assert result.returncode == 2 and "is not a `twinrl demo` run folder" in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1 and not (tmp_path / "s2").exists()
