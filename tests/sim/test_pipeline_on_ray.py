"""The pipeline's real-RL runs as Ray tasks on a two-node cluster end as on one machine
(a file of its own: two smoke pipelines, so that the parallel suite balances it)."""

import shutil

import pytest

from twinrl_learn.studies.pipeline import run_demo

pytestmark = pytest.mark.usefixtures("ray_environment")


@pytest.mark.slow  # two smoke pipelines' real-RL runs, about 90 s
@pytest.mark.filterwarnings("ignore:this Ray cluster runs without token authentication")
def test_the_pipelines_real_rl_runs_resumed_on_the_cluster_end_as_on_one_machine(cluster, tmp_path):
    """A smoke pipeline on worker processes; its real-RL runs removed and the pipeline
    resumed on the cluster, which runs them as Ray tasks: the same report."""
    out = tmp_path / "demo"
    alone = run_demo("pick_place", "smoke", out, device="cpu", log=lambda _: None)
    shutil.rmtree(out / "real_rl")
    said: list[str] = []
    spread = run_demo(
        "pick_place", "smoke", out, resume=True, cluster=cluster.address, device="cpu",
        log=said.append,
    )  # fmt: skip
    assert spread == alone
    assert any("real RL" in m for m in said)  # the runs' lines reach the log from the nodes
