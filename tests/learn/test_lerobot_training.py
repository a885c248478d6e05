"""lerobot's own policies trained by lerobot's trainer on twinrl's datasets (Table I's
external anchor): the dataset they learn from, the trainer's run, the checkpoint acting
through the adapter on any machine."""

import json

import pytest

from tests.conftest import record_demos, stage1_smoke
from twinrl_learn.errors import LearnError
from twinrl_learn.evaluate import evaluate
from twinrl_learn.lerobot_training import (
    NOT_IN_EVERY_SOURCE,
    NOT_SEEN_BY_A_CELL,
    LeRobotTraining,
    policy_dataset,
    train_lerobot_policy,
)
from twinrl_learn.runners import LeRobotRunner, load_runner


def _info(root):
    return json.loads((root / "meta" / "info.json").read_text())


@pytest.fixture(scope="module")
def sources(tmp_path_factory):
    """Plant demos (they log the arm's effort) and twin demos (they log the policy's own
    action): both log the object poses."""
    base = tmp_path_factory.mktemp("sources")
    return (
        record_demos(base / "plant", episodes=2, seed=3, world="plant"),
        record_demos(base / "twin", episodes=1, seed=3),
    )


def test_the_policys_dataset_holds_every_frame_and_nothing_a_cell_cannot_see(sources, tmp_path):
    plant, twin = sources
    assert "observation.environment_state" in _info(plant)["features"]
    assert "observation.effort" in _info(plant)["features"]
    assert "action.policy" in _info(twin)["features"]

    out = policy_dataset([plant, twin], tmp_path / "mix")

    info = _info(out)
    for column in NOT_SEEN_BY_A_CELL + NOT_IN_EVERY_SOURCE:
        assert column not in info["features"]
    for column in ("observation.state", "action", "observation.images.front"):
        assert column in info["features"]
    for count in ("total_episodes", "total_frames"):
        assert info[count] == _info(plant)[count] + _info(twin)[count] > 0
    # The sources are left as they were, and no scratch copy is left beside the result.
    assert "observation.environment_state" in _info(plant)["features"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mix"]
    with pytest.raises(LearnError, match="exists; choose another folder"):
        policy_dataset([plant], out)


def test_a_lerobot_policy_is_refused_before_anything_runs_when_not_trained_here():
    with pytest.raises(LearnError, match="'diffusion' is not trained here; use one of act"):
        LeRobotTraining(policy="diffusion")
    with pytest.raises(LearnError, match="at least 1 step"):
        LeRobotTraining(steps=0)


@pytest.mark.slow
def test_act_trains_with_lerobots_trainer_and_a_gpu_checkpoint_acts_on_the_cpu(sources, tmp_path):
    dataset = policy_dataset(list(sources), tmp_path / "mix")
    checkpoint = train_lerobot_policy(
        dataset, tmp_path / "act", LeRobotTraining(steps=2, batch_size=2, device="cpu")
    )
    assert (checkpoint / "model.safetensors").is_file()
    trained = checkpoint.parent / "training_state" / "training_step.json"
    assert json.loads(trained.read_text())["step"] == 2
    assert "End of training" in (tmp_path / "act.log").read_text()
    # As if trained on a GPU: the saved processors name a device this machine lacks.
    for name in ("config.json", "policy_preprocessor.json"):
        path = checkpoint / name
        path.write_text(path.read_text().replace('"device": "cpu"', '"device": "cuda"'))
    assert '"cuda"' in (checkpoint / "policy_preprocessor.json").read_text()
    runner = load_runner(checkpoint, device="cpu")
    assert isinstance(runner, LeRobotRunner) and runner.cameras == ("front", "wrist")
    assert "observation.environment_state" not in runner.input_features
    report = evaluate(runner, "pick_place", grid=(1, 2), out=tmp_path / "eval")
    assert report.episodes == 2  # two steps of training fail, but it runs end to end
    # A trainer that stops says where its log is, in one line.
    with pytest.raises(LearnError, match=r"stopped \(exit [1-9]\d*\).*last lines are in"):
        train_lerobot_policy(tmp_path / "missing", tmp_path / "broken", LeRobotTraining(steps=1))


@pytest.mark.long  # four minutes alone on 2 cores: beyond CI's time (make test-long)
@pytest.mark.slow
def test_table_i_trains_lerobots_act_on_a_mix_and_evaluates_it_like_every_row(
    tmp_path, monkeypatch
):
    from twinrl_learn.studies import table1

    monkeypatch.setattr(table1, "MIXES", ((30, 60),))  # one row of the table
    out = tmp_path / "stage1"
    act = ["--policies", "act", "--act-steps", "1", "--grid", "2x2", "--episodes", "1"]
    rows = stage1_smoke(out, *act)
    assert [(r["policy"], r["twin_id"], r["twin_ood"]) for r in rows] == [("act", 30, 60)]
    table = (out / "table1.md").read_text()
    assert "| pick_place | ACT, lerobot's (images) | 30 | 60 |" in table
    assert "(1 steps, batch 16), reads the cameras and the arm's state" in table
    task = out / "pick_place"
    learnt = _info(task / "act_real_id30_ood60_dataset")
    assert "observation.environment_state" not in learnt["features"]
    sources = [task / "real", task / "twin_id_3", task / "twin_ood_6"]
    assert learnt["total_episodes"] == sum(_info(s)["total_episodes"] for s in sources)
    assert (task / "act_real_id30_ood60_eval" / "heatmap.png").is_file()
