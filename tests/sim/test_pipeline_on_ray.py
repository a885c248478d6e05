"""The pipeline's real-RL runs as Ray tasks on a two-node cluster end as on one machine
(a file of its own: two smoke pipelines, so that the parallel suite balances it)."""

import shutil
from dataclasses import replace

import pytest

from twinrl_learn.studies.pipeline import run_demo
from twinrl_learn.studies.presets import PRESETS

# The smoke preset with half its plant steps: its four real-RL runs are most of its time.
SHORT = replace(PRESETS["smoke"], plant_steps=50)

pytestmark = pytest.mark.usefixtures("ray_environment")


@pytest.mark.slow  # a short smoke pipeline and its real-RL runs again, about a minute
@pytest.mark.filterwarnings("ignore:this Ray cluster runs without token authentication")
def test_the_pipelines_real_rl_runs_resumed_on_the_cluster_end_as_on_one_machine(cluster, tmp_path):
    """A short smoke pipeline on worker processes; its real-RL runs removed and the pipeline
    resumed on the cluster, which runs them as Ray tasks: the same report."""
    out = tmp_path / "demo"
    alone = run_demo("pick_place", SHORT, out, device="cpu", log=lambda _: None)
    shutil.rmtree(out / "real_rl")
    said: list[str] = []
    spread = run_demo(
        "pick_place", SHORT, out, resume=True, cluster=cluster.address, device="cpu",
        log=said.append,
    )  # fmt: skip
    assert spread == alone
    assert any("real RL" in m for m in said)  # the runs' lines reach the log from the nodes
