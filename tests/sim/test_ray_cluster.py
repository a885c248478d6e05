"""The executor on Ray: embedded Ray listens on loopback only; on a two-node cluster jobs
come back in order, the first failure is raised as it was, `expand` keeps the same
demonstrations as the process pool, mining and the gap diagnosis find what one process
finds, and twin RL with its environments in shards on the nodes is the same run, for the
same seed (the pipeline's runs there: test_pipeline_on_ray.py)."""

import json
import sys
import time

import numpy as np
import psutil
import pytest
import ray
import torch
from typer.testing import CliRunner

from tests.conftest import tiny_state_policy
from tests.data.test_executor import chatty  # the same chatty job on Ray as on processes
from tests.learn.test_rl import twin_rl_outcome
from tests.sim.test_gap_diagnose import SCENE, _record
from tests.sim.test_gap_search import HIDDEN, outcome
from twinrl_data import ray_executor
from twinrl_data.executor import make_executor
from twinrl_data.mcap_log import read_episode
from twinrl_data.ray_executor import RayExecutor
from twinrl_data.session import Session
from twinrl_learn.cli import app, main
from twinrl_learn.mining import mine
from twinrl_learn.runners import ExpertRunner
from twinrl_learn.settings import RLConfig, TwinRLSettings
from twinrl_learn.twin_rl import run_twin_rl
from twinrl_sim.expand import expand
from twinrl_sim.gap.diagnose import diagnose

LOOPBACK = {"127.0.0.1", "::ffff:127.0.0.1", "::1"}


pytestmark = pytest.mark.usefixtures("ray_environment")


def node_of(n):
    time.sleep(0.3)  # long enough that two jobs overlap, so each node takes one
    return n * n, ray.get_runtime_context().get_node_id()


def test_embedded_ray_listens_on_loopback_only_and_runs_no_dashboard():
    with make_executor(2, cluster="local") as executor:
        assert isinstance(executor, RayExecutor) and executor.workers == 2
        assert [r for r, _ in executor.map(node_of, range(3))] == [0, 1, 4]
        processes = [psutil.Process(), *psutil.Process().children(recursive=True)]
        listening = [
            (" ".join(p.cmdline()[:2]), c.laddr.ip)  # the program (or the script it runs)
            for p in processes
            for c in p.net_connections(kind="inet")
            if c.status == psutil.CONN_LISTEN
        ]
        assert any("gcs_server" in program for program, _ in listening)
        assert {ip for _, ip in listening} <= LOOPBACK, listening
        # Its dashboard process serves no HTTP, hence no job API to submit code through.
        assert not [ip for program, ip in listening if program.endswith("dashboard/dashboard.py")]
    assert not ray.is_initialized()


def test_jobs_spread_over_the_nodes_in_order_and_the_first_failure_is_raised_as_it_was(
    cluster, monkeypatch
):
    monkeypatch.setattr(ray_executor, "_warned_unauthenticated", False)
    with pytest.warns(UserWarning, match="without token authentication") as warned:
        executor = make_executor(None, cluster=cluster.address)
    with executor:
        assert executor.workers == 2  # a CPU each on two nodes
        results = executor.map(node_of, range(4))
        heard = []
        assert executor.run(chatty, [0, 1, 2], heard.append) == [100, 101, 102]
        with pytest.raises(ArithmeticError, match="job 3 cannot") as failure:
            executor.run(chatty, [3, 4], heard.append)
    assert [r for r, _ in results] == [0, 1, 4, 9]
    assert len({node for _, node in results}) == 2
    assert sorted(heard)[:3] == [f"job {n} starts" for n in range(3)]
    assert type(failure.value) is ArithmeticError
    assert len(warned) == 1
    with make_executor(1, cluster=cluster.address):  # warned once per process
        pass
    assert not ray.is_initialized()


@pytest.mark.filterwarnings("ignore:this Ray cluster runs without token authentication")
def test_expand_on_the_cluster_keeps_the_demos_of_the_process_pool(cluster, tmp_path):
    pool = expand(
        "pick_place", id_count=2, ood_count=1, seed=5, images=False, workers=2,
        out=tmp_path / "pool", export=False,
    )  # fmt: skip
    args = ["expand", "pick_place", "--id", "2", "--ood", "1", "--seed", "5", "--no-images"]
    result = CliRunner().invoke(
        app, [*args, "--cluster", cluster.address, "--out", str(tmp_path / "ray")]
    )
    assert result.exit_code == 0, result.output
    on_ray = json.loads((tmp_path / "ray" / "expand.json").read_text())
    assert on_ray["kept"] == pool.kept and on_ray["attempts"] == pool.attempts

    def episodes(out):
        paths = Session(out / "session").episode_paths()
        return sorted((read_episode(p) for p in paths), key=lambda e: json.dumps(e.meta.config))

    for ours, theirs in zip(episodes(tmp_path / "ray"), episodes(tmp_path / "pool"), strict=True):
        assert ours.meta.config == theirs.meta.config
        np.testing.assert_array_equal(ours.data["action"], theirs.data["action"])
        np.testing.assert_array_equal(
            ours.data["observation.state"], theirs.data["observation.state"]
        )


@pytest.mark.filterwarnings("ignore:this Ray cluster runs without token authentication")
def test_mining_on_the_cluster_finds_what_one_process_finds(cluster, tmp_path):
    settings = dict(grid=(3, 3), episodes=1, seed=2, tau=1.0)
    alone = mine(ExpertRunner(), "pick_place", out=tmp_path / "alone.json", **settings)
    spread = mine(
        ExpertRunner(), "pick_place", out=tmp_path / "ray.json", workers=None,
        cluster=cluster.address, **settings,
    )  # fmt: skip
    assert spread == alone and alone["episodes"] > 1

    def episodes(name):
        return [read_episode(p) for p in Session(tmp_path / name / "session").episode_paths()]

    for ours, theirs in zip(episodes("ray"), episodes("alone"), strict=True):
        assert ours.meta.config == theirs.meta.config
        np.testing.assert_array_equal(ours.data["action"], theirs.data["action"])


@pytest.mark.filterwarnings("ignore:this Ray cluster runs without token authentication")
def test_a_gap_diagnosis_on_the_cluster_finds_what_one_process_finds(cluster, tmp_path):
    episodes = _record(tmp_path / "s", HIDDEN, episodes=3)
    allowed = ["payload", "base_offset", "table_height", "joint_damping", "servo_gain"]
    alone = diagnose(episodes, SCENE, allowed=allowed)
    args = ["gap", "diagnose", str(tmp_path / "s"), "--twin", "pick_place"]
    result = CliRunner().invoke(
        app,
        [*args, "--effects-allowed", ",".join(allowed), "--cluster", cluster.address,
         "--out", str(tmp_path / "ray")],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    report = json.loads((tmp_path / "ray" / "gap_report.json").read_text())
    fields = ("effect", "params", "heldout_error", "bic", "screened")
    on_ray = [[tuple(r[f] for f in fields) for r in rnd] for rnd in report["rounds"]]
    assert on_ray == outcome(alone)[0]
    assert report["selected"] == alone.selected
    assert [s["effect"] for s in alone.selected] == ["payload"]


@pytest.mark.filterwarnings("ignore:this Ray cluster runs without token authentication")
def test_twin_rl_with_its_environments_on_the_nodes_is_the_same_run(cluster, tmp_path):
    dataset, sft = tiny_state_policy(tmp_path / "sft", seed=3, steps=30)
    torch.set_num_threads(1)

    def run(out, cluster_address):
        return run_twin_rl(
            TwinRLSettings(
                task="pick_place", init=str(sft), out=str(out), demos=[str(dataset)],
                envs=2, steps=100, cluster=cluster_address,
                rl=RLConfig(offline_steps=4, batch_size=16, utd=0.05),
            )
        )  # fmt: skip

    alone, spread = run(tmp_path / "alone", ""), run(tmp_path / "ray", cluster.address)
    (weights, episodes), (their_weights, their_episodes) = map(twin_rl_outcome, (alone, spread))
    assert episodes == their_episodes and len(episodes) >= 2
    for key, value in weights.items():
        torch.testing.assert_close(value, their_weights[key], rtol=0, atol=0)


@pytest.mark.parametrize("value", ["bogus", "ray:/head:10001", "head:0", "ray://head"])
def test_a_bad_cluster_is_one_line_and_leaves_nothing(tmp_path, value, monkeypatch, capsys):
    out = tmp_path / "out"
    args = ["expand", "pick_place", "--id", "1", "--ood", "0", "--cluster", value]
    monkeypatch.setattr(sys, "argv", ["twinrl", *args, "--out", str(out)])
    with pytest.raises(SystemExit) as stopped:
        main()
    error = capsys.readouterr().err.strip()
    assert stopped.value.code == 2 and len(error.splitlines()) == 1
    assert "--cluster must be none, local, auto, HOST:PORT or ray://HOST:PORT" in error
    assert error.endswith(f"got '{value}'") and not out.exists()


@pytest.mark.slow
def test_real_rl_with_its_learner_on_a_node_loses_no_episode_when_the_learner_dies(
    cluster, tmp_path
):
    """The learner as a Ray actor on the cluster: killed after the first episode, the
    robot goes on, a learner comes back and holds every episode of the actor."""
    import os
    import signal

    from twinrl_learn.real_rl import RealRL
    from twinrl_learn.settings import RealRLSettings

    dataset, sft = tiny_state_policy(tmp_path / "sft", seed=4, steps=20)
    said: list[str] = []
    real = RealRL.start(
        RealRLSettings(
            task="pick_place", init=str(sft), out=str(tmp_path / "run"), demos=[str(dataset)],
            plant_steps=300, eval_every=0, eval_grid=(1, 1), refresh_every=0,
            show_resets=False, operator=None, learner=cluster.address,
            rl=RLConfig.for_method("twinrl", offline_steps=3, batch_size=16, seed=2),
        ),
        on_notice=said.append,
    )  # fmt: skip

    def on_episode(record, real) -> None:
        if len(real.run_state.history) == 1:
            os.kill(real.learner.learner_pid(), signal.SIGKILL)

    real.run(on_episode=on_episode)
    actor = [p.name for p in Session(tmp_path / "run" / "session").episode_paths()]
    learner = Session(tmp_path / "run" / "learner" / "session").episode_paths()
    assert len(actor) >= 3 and [p.name for p in learner] == actor
    assert any("the learner is lost" in m for m in said)
    assert any("a learner is back" in m for m in said)


def test_an_actor_that_needs_a_gpu_the_cluster_lacks_is_refused_not_left_waiting(cluster):
    from twinrl_data.errors import TwinrlError

    with RayExecutor(1, address=cluster.address) as executor:
        assert executor.gpus() == 0
        with pytest.raises(TwinrlError, match="fewer than 1 GPU"):
            executor.actors(dict, [{}], gpus=1)


def test_a_ray_actor_that_does_not_answer_in_time_is_stopped_and_taken_for_lost(cluster):
    from tests.data.test_executor import Sleeper
    from twinrl_data.actors import ActorLost

    with RayExecutor(1, address=cluster.address) as executor:
        actors = executor.actors(Sleeper, [{}])
        assert actors.call("nap", [(0.1,)], timeout_s=60) == [0.1]
        started = time.monotonic()
        with pytest.raises(ActorLost, match=r"did not answer nap within 1 s; it was stopped"):
            actors.call("nap", [(120.0,)], timeout_s=1)
        assert time.monotonic() - started < 60
        with pytest.raises(ActorLost, match="stopped"):
            actors.call("nap", [(0.0,)])
        actors.close()
