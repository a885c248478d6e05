"""RL parts: replay buffers, the actor objective, twin RL resume, failure mining."""

import json

import numpy as np
import pytest
import torch

from tests.conftest import tiny_state_policy
from tests.test_cli import twinrl as run_cli
from twinrl_data.mcap_log import read_episode
from twinrl_data.schema import Episode, EpisodeMeta
from twinrl_data.session import Session
from twinrl_learn.agent import Agent
from twinrl_learn.mining import estimate_cell, load_targets, select_targets
from twinrl_learn.policy import Policy
from twinrl_learn.replay import MixedSampler, ReplayBuffer, RewardSettings, discounted_returns
from twinrl_learn.settings import RLConfig
from twinrl_learn.twin_rl import TwinRLSettings, run_twin_rl
from twinrl_sim.spec import load_spec, save_spec
from twinrl_sim.tasks import make_task


def synthetic_episode(length: int, success: bool, source: str = "twin_rl", offset: float = 0.0):
    steps = np.arange(length, dtype=np.float32)
    outcome = np.zeros(length, bool)
    outcome[-1] = success
    return Episode(
        meta=EpisodeMeta(task="pick_place", source=source, world="twin", success=success),
        data={
            "observation.state": (steps[:, None] + offset) * np.ones((1, 3), np.float32),
            "observation.environment_state": np.zeros((length, 2), np.float32),
            "action": steps[:, None] * np.ones((1, 7), np.float32),
            "next.success": outcome,
            "intervention": np.zeros(length, bool),
        },
    )


@pytest.fixture(scope="module")
def demos(tmp_path_factory):
    """Two recorded expert demos as a dataset and a tiny state policy trained on them."""
    return tiny_state_policy(tmp_path_factory.mktemp("rl"), seed=3, steps=30)


def test_chunked_transitions_sum_rewards_and_stop_at_success():
    rewards = RewardSettings(success=10.0, step=-1.0)
    buffer = ReplayBuffer(rewards=rewards)
    buffer.add(synthetic_episode(5, success=True))
    buffer.add(synthetic_episode(6, success=False, offset=100))
    gamma = 0.5
    starts = buffer.valid_starts(chunk=3, gamma=gamma)
    # success episode: every start has a known outcome; timeout: only those 3+ from the end
    assert starts.tolist() == [0, 1, 2, 3, 4, 5, 6, 7]
    batch = buffer.transitions(np.array([0, 3, 5]), chunk=3, gamma=gamma)
    assert batch.reward[0] == pytest.approx(-1 - 0.5 - 0.25)
    assert batch.discount[0] == pytest.approx(0.125)
    assert batch.next_state[0, 0] == 3
    assert batch.reward[1] == pytest.approx(-1 + 0.5 * 10)  # steps 3, 4 then success
    assert batch.discount[1] == 0
    np.testing.assert_array_equal(batch.actions[1, :, 0], [3, 4, 4])  # last action repeated
    assert batch.next_state[2, 0] == 103
    assert batch.mc_return[0] == pytest.approx(
        discounted_returns(np.array([-1, -1, -1, -1, 10.0]), 0.5)[0]
    )
    assert not batch.demo.any()


def test_a_takeover_ends_the_policys_stretch_with_its_reward():
    episode = synthetic_episode(8, success=True)
    episode.data["intervention"][[3, 4]] = True  # the operator holds steps 3-4, hands back
    gamma = 0.5
    for takeover, ends in ((-2.0, True), (None, False)):
        buffer = ReplayBuffer(rewards=RewardSettings(success=10.0, step=-1.0, takeover=takeover))
        buffer.add(episode)
        batch = buffer.transitions(np.array([1, 3, 5]), chunk=3, gamma=gamma)
        if ends:  # steps 1, 2 and the takeover: terminal, the operator's actions not in it
            assert batch.reward[0] == pytest.approx(-1 + 0.5 * (-1 - 2))
            assert batch.discount[0] == 0
            np.testing.assert_array_equal(batch.actions[0, :, 0], [1, 2, 2])
            assert batch.mc_return[0] == pytest.approx(batch.reward[0])
        else:  # the stretch runs on into the operator's steps
            assert batch.reward[0] == pytest.approx(-1 - 0.5 - 0.25)
            assert batch.discount[0] == pytest.approx(0.125)
            np.testing.assert_array_equal(batch.actions[0, :, 0], [1, 2, 3])
        # The operator's stretch and the policy's after the hand-back run to the success.
        assert batch.reward[1] == pytest.approx(-1 - 0.5 - 0.25) and batch.discount[1] > 0
        assert batch.reward[2] == pytest.approx(-1 - 0.5 + 0.25 * 10) and batch.discount[2] == 0
        assert buffer.valid_starts(3, gamma).tolist() == list(range(8))


def test_buffers_are_sampled_in_the_configured_ratio():
    demo = ReplayBuffer(episodes=[synthetic_episode(20, True, source="teleop")])
    online = ReplayBuffer(episodes=[synthetic_episode(20, False, offset=100)])
    rng = np.random.default_rng(0)
    sampler = MixedSampler([demo, online], [0.25, 0.75])
    batch, origin = sampler.sample(64, rng, chunk=2, gamma=0.9)
    assert (origin == 0).sum() == 16 and (origin == 1).sum() == 48
    np.testing.assert_array_equal(batch.demo, origin == 0)
    assert (batch.state[origin == 1, 0] >= 100).all()
    empty = MixedSampler([demo, ReplayBuffer()], [0.5, 0.5])
    _, origin = empty.sample(10, rng, chunk=1, gamma=0.9)
    assert (origin == 0).all()  # an empty buffer gives its share to the others
    with pytest.raises(ValueError, match="non-negative"):
        MixedSampler([demo], [-1.0])


def test_buffer_is_saved_and_loaded_as_a_dataset(demos, tmp_path):
    dataset, _ = demos
    buffer = ReplayBuffer.from_datasets([dataset])
    buffer.save(tmp_path / "copy")
    again = ReplayBuffer.from_datasets([tmp_path / "copy"])
    assert again.num_steps == buffer.num_steps
    rows = np.arange(buffer.num_steps - 1)
    a = buffer.transitions(rows, chunk=1, gamma=0.9)
    b = again.transitions(rows, chunk=1, gamma=0.9)
    np.testing.assert_array_equal(a.state, b.state)
    np.testing.assert_array_equal(a.actions, b.actions)
    assert a.demo.all()  # teleop-like expert demos are imitation data
    with pytest.raises(ValueError, match="empty"):
        ReplayBuffer().save(tmp_path / "none")


def test_actor_objective_reduces_to_bc_and_to_pure_q(demos):
    dataset, sft = demos
    buffer = ReplayBuffer.from_datasets([dataset])
    batch = buffer.sample(32, np.random.default_rng(0), chunk=4, gamma=0.98)
    demo_rows = torch.from_numpy(batch.demo)

    def gradients(beta, eta):
        agent = Agent(Policy.from_pretrained(sft), RLConfig(beta=beta, eta=eta, seed=1))
        torch.manual_seed(5)
        t = agent._tensors(batch)
        loss, _ = agent.actor_loss(t, demo_rows)
        return agent, t, loss

    # The BC limit is SFT's loss: imitation of the demo rows under SFT's augmentation.
    agent, t, loss = gradients(beta=1.0, eta=0.0)
    policy, generator = agent.policy, torch.Generator().manual_seed(1)
    augmented = policy.augment(t["obs"], generator)
    assert not torch.equal(augmented["env"], t["obs"]["env"])
    assert loss.item() == pytest.approx(policy.imitation_loss(augmented, t["actions"]).item())
    agent, t, loss = gradients(beta=0.0, eta=1.0)
    torch.manual_seed(5)
    actions, _ = agent.policy.rsample(t["obs"])
    q = agent.critic(agent.policy.critic_inputs(t["obs"]), actions).min(0).values
    assert loss.item() == pytest.approx((-(q / q.abs().mean())).mean().item(), rel=1e-5)


def test_hil_serl_warms_its_critic_before_the_actor_moves_and_then_moves_it_every_other_update(
    demos,
):
    """HiL-SERL's recipe: the critic alone learns through the offline phase, then the
    actor steps once per ``critic_per_actor`` updates, from a temperature of 0.01."""
    dataset, sft = demos
    config = RLConfig.for_method("hil-serl", offline_steps=2, batch_size=16, seed=1)
    assert (config.critic_warmup, config.critic_per_actor, config.utd) == (2, 2, 2.0)
    assert config.beta == 0 and config.cql_alpha == 0
    agent = Agent(Policy.from_pretrained(sft), config)
    assert agent.alpha.item() == pytest.approx(0.01)
    buffer = ReplayBuffer.from_datasets([dataset])
    rng = np.random.default_rng(0)
    moved, critic_moved = [], []

    def changed(before, module):
        return any(not torch.equal(b, p) for b, p in zip(before, module.parameters(), strict=True))

    for _ in range(6):
        actor = [p.detach().clone() for p in agent.policy.parameters()]
        critic = [p.detach().clone() for p in agent.critic.parameters()]
        agent.update(buffer.sample(16, rng, chunk=4, gamma=0.98))
        moved.append(changed(actor, agent.policy))
        critic_moved.append(changed(critic, agent.critic))
    assert moved == [False, False, True, False, True, False]
    assert all(critic_moved)
    # An explicit warm-up wins over the offline phase's length; bad values are refused.
    assert RLConfig.for_method("hil-serl", offline_steps=5, critic_warmup=1).critic_warmup == 1
    with pytest.raises(ValueError, match="critic_per_actor"):
        RLConfig(critic_per_actor=0)
    with pytest.raises(ValueError, match="temperature_init"):
        RLConfig(temperature_init=0)


def test_twin_rl_logs_rollouts_and_resumes_exactly(demos, tmp_path):
    dataset, sft = demos
    torch.set_num_threads(1)
    rl = RLConfig(offline_steps=4, batch_size=16, utd=0.05)

    def settings(out, steps):
        return TwinRLSettings(
            task="pick_place", init=str(sft), out=str(out), demos=[str(dataset)],
            envs=2, steps=steps, rl=rl, failures=1,
        )  # fmt: skip

    straight = run_twin_rl(settings(tmp_path / "straight", 2 * 200))
    run_twin_rl(settings(tmp_path / "split", 200))
    resumed = run_twin_rl(settings(tmp_path / "split", 2 * 200), resume=True)
    assert straight.agent.env_steps == resumed.agent.env_steps
    assert straight.agent.updates == resumed.agent.updates > 4
    for key, value in straight.agent.state_dict()["critic"].items():
        torch.testing.assert_close(value, resumed.agent.state_dict()["critic"][key], rtol=0, atol=0)
    for key, value in straight.agent.policy.state_dict().items():
        torch.testing.assert_close(value, resumed.agent.policy.state_dict()[key], rtol=0, atol=0)
    entries = Session(tmp_path / "split" / "session").entries
    assert len(entries) == 4 and {e["source"] for e in entries} == {"twin_rl"}
    assert (tmp_path / "split" / "curve.png").stat().st_size > 1000
    assert (tmp_path / "split" / "twin_buffer" / "meta" / "info.json").is_file()  # 1 failure
    assert Policy.from_pretrained(tmp_path / "split" / "agent").config.chunk == 4
    with pytest.raises(ValueError, match="already holds a run"):
        run_twin_rl(settings(tmp_path / "split", 400))


def twin_rl_outcome(run) -> tuple:
    """What a twin RL run did: its weights and every episode's actions, in order."""
    episodes = [read_episode(p) for p in run.session.episode_paths()]
    return (
        {k: v.clone() for k, v in run.agent.policy.state_dict().items()},
        [(e.meta.config, e.data["action"].tolist(), e.meta.success) for e in episodes],
    )


def test_twin_rl_with_its_environments_in_shards_is_the_same_run(demos, tmp_path):
    """Three environments split over two worker processes: the same episodes, updates
    and weights as in one process."""
    dataset, sft = demos
    torch.set_num_threads(1)
    rl = RLConfig(offline_steps=4, batch_size=16, utd=0.05)

    def run(out, workers):
        return run_twin_rl(
            TwinRLSettings(
                task="pick_place", init=str(sft), out=str(out), demos=[str(dataset)],
                envs=3, steps=150, rl=rl, workers=workers,
            )
        )  # fmt: skip

    alone, apart = run(tmp_path / "alone", 1), run(tmp_path / "apart", 2)
    (weights, episodes), (their_weights, their_episodes) = map(twin_rl_outcome, (alone, apart))
    assert episodes == their_episodes and len(episodes) >= 3
    assert alone.agent.updates == apart.agent.updates > 4
    for key, value in weights.items():
        torch.testing.assert_close(value, their_weights[key], rtol=0, atol=0)


def test_mining_prefers_failure_prone_informative_configurations():
    # A synthetic success map over the 4x4 grid: target y decides the true rate.
    rng = np.random.default_rng(0)
    from twinrl_learn.evaluate import grid_cells

    cells = grid_cells("pick_place", (4, 4))
    rate_of = {c.y: r for c, r in zip(cells[:4], [0.0, 0.5, 0.95, 1.0], strict=True)}
    outcomes = []
    for cell in cells:
        for _ in range(20):
            config = {"object": [0.5, 0.0, 0.0], "target": [cell.x, cell.y, 0.0]}
            outcomes.append((config, cell.region, bool(rng.random() < rate_of[cell.y])))
    estimates, targets = select_targets(outcomes, "pick_place", (4, 4), tau=0.8, k=6)
    assert len(estimates) == len(cells)
    columns = [round(t.y, 3) for t in targets]
    half, hopeless = round(cells[1].y, 3), round(cells[0].y, 3)
    per_column = sum(1 for c in cells if round(c.y, 3) == half)
    # the 50 % column outranks the hopeless one; the solved columns are never targets
    assert columns == [half] * per_column + [hopeless] * (6 - per_column)
    assert all(t.estimated_success < 0.8 for t in targets)
    scores = [t.score for t in targets]
    assert scores == sorted(scores, reverse=True)
    solved = estimate_cell(0, 0, "ID", 20, 20, 0.8)
    hopeless = estimate_cell(0, 0, "ID", 0, 20, 0.8)
    informative = estimate_cell(0, 0, "ID", 10, 20, 0.8)
    assert informative.score > hopeless.score > solved.score


def test_mine_and_twin_rl_commands(demos, tmp_path):
    dataset, sft = demos
    result = run_cli(
        "mine", "--task", "pick_place", "--policy", str(sft), "--grid", "2x2",
        "--episodes", "1", "--k", "3", "--out", str(tmp_path / "targets.json"),
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    targets = load_targets(tmp_path / "targets.json")
    data = json.loads((tmp_path / "targets.json").read_text())
    assert len(targets) <= 3 and len(data["cells"]) >= 2
    assert (tmp_path / "targets" / "heatmap.png").is_file()
    # Mining in a cell's own twin: its evaluation runs there (the episodes name its digest).
    scene = make_task("pick_place").scene
    cell_twin = scene.model_copy(
        update={"physics": scene.physics.model_copy(update={"servo": "track"})}
    )
    save_spec(cell_twin, tmp_path / "my_cell.yaml")
    in_cell = run_cli(
        "mine", "--task", "pick_place", "--policy", str(sft), "--grid", "2x2",
        "--episodes", "1", "--twin", str(tmp_path / "my_cell.yaml"),
        "--out", str(tmp_path / "cell_targets.json"),
    )  # fmt: skip
    assert in_cell.returncode == 0, in_cell.stderr
    mined = [read_episode(p, images=False).meta.twin for p in
             Session(tmp_path / "cell_targets" / "session").episode_paths()]  # fmt: skip
    assert mined and set(mined) == {load_spec(tmp_path / "my_cell.yaml").digest} != {scene.digest}
    again = run_cli(
        "mine",
        "--task",
        "pick_place",
        "--policy",
        str(sft),
        "--out",
        str(tmp_path / "targets.json"),
    )
    assert again.returncode == 2 and "exists" in again.stderr
    missing = run_cli("train", "twin-rl", "--task", "pick_place", "--out", str(tmp_path / "r"))
    assert missing.returncode == 2 and "--init" in missing.stderr
    wrong = run_cli(
        "train", "twin-rl", "--task", "pick_place", "--init", str(dataset),
        "--out", str(tmp_path / "r"),
    )  # fmt: skip
    assert wrong.returncode == 2 and "not a twinrl policy checkpoint" in wrong.stderr
    with pytest.raises(ValueError, match="does not exist"):
        load_targets(tmp_path / "nothing.json")
