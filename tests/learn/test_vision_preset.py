"""The `quick-vision` pipeline preset: what each of its stages is given instead of the
plant's privileged state, and the twin it runs its twin work in."""

import json
from dataclasses import replace

import pytest

from twinrl_data.errors import SettingError
from twinrl_data.mcap_log import read_episode
from twinrl_data.session import Session
from twinrl_learn.reward_classifier import RewardClassifier
from twinrl_learn.settings import RealRLSettings, TwinRLSettings
from twinrl_learn.studies.layout import stage1_paths
from twinrl_learn.studies.pipeline import RealRLJob, real_rl_settings
from twinrl_learn.studies.presets import METHOD_TABLE, PRESETS, Preset
from twinrl_sim.spec import save_spec
from twinrl_sim.tasks import make_task

LOOK = {"light_scale": 0.8, "table_tint": [0.04, 0.02, -0.03]}


def _look(path):
    """A fitted look stands in as the task's own scene with a darker light."""
    scene = make_task("pick_place").scene
    save_spec(scene.with_effects({"appearance": LOOK}), path)
    return path


def test_only_the_vision_preset_reads_nothing_privileged():
    assert not PRESETS["quick-vision"].privileged
    for name in ("smoke", "quick", "paper"):
        assert PRESETS[name].privileged, name
    vision = PRESETS["quick-vision"]
    # Leaving either of the real cell's stand-ins out makes it privileged again.
    assert replace(vision, classifier_episodes=0, success_frames=1).privileged
    assert replace(vision, operator_sees=False).privileged


def test_a_preset_refuses_perception_it_cannot_use():
    with pytest.raises(SettingError, match="serves the vla policy"):
        replace(PRESETS["quick"], perception=10)
    with pytest.raises(SettingError, match="give `perception` episodes"):
        replace(PRESETS["quick-vision"], perception=0)
    with pytest.raises(SettingError, match="success_frames is the classifier's"):
        replace(PRESETS["quick-vision"], classifier_episodes=0)


def test_every_real_rl_run_of_the_vision_preset_sees_and_judges_as_a_cell_does(tmp_path):
    stage1 = stage1_paths(tmp_path / "stage1", "vla")
    stage1["look"].parent.mkdir(parents=True)
    _look(stage1["look"])
    p: Preset = PRESETS["quick-vision"]
    for method in METHOD_TABLE:
        job = RealRLJob(
            "pick_place", p, method, 0, tmp_path / method.slug, stage1,
            tmp_path / "stage2", tmp_path / "targets.json",
        )  # fmt: skip
        settings = real_rl_settings(job)
        assert settings.success == "classifier", method.name
        assert settings.success_frames == 3  # a lone false positive ends no episode
        # Stage I's classifier trained again with Stage II's rollouts (the policy's own).
        assert settings.classifier == str(tmp_path / "stage2" / "success_classifier")
        assert settings.operator_sees == str(stage1["estimator"])
        assert settings.twin == str(stage1["look"])  # re-mined in the fitted look
    # The privileged presets keep the plant's truth and an operator who reads it.
    job = replace(job, p=PRESETS["quick"])
    settings = real_rl_settings(job)
    assert (settings.success, settings.classifier, settings.operator_sees, settings.twin) == (
        "truth", None, None, None
    )  # fmt: skip
    assert settings.success_frames == 1


def test_twin_rl_and_real_rl_name_the_twin_they_run_in(tmp_path):
    with pytest.raises(SettingError, match="twin"):
        TwinRLSettings(task="pick_place", init="x", out=str(tmp_path), twin="no_such.yaml")
    with pytest.raises(SettingError, match="twin"):
        RealRLSettings(task="pick_place", init="x", out=str(tmp_path), twin="no_such.yaml")
    with pytest.raises(SettingError, match="cell file's twin"):
        RealRLSettings(
            task="pick_place", init="x", out=str(tmp_path), robot="ur", cell="cell.yaml",
            twin=str(_look(tmp_path / "look.yaml")), success="key",
        )  # fmt: skip
    # A look of another task's cell is refused before anything runs.
    with pytest.raises(SettingError, match="pick the `task` it is built for"):
        TwinRLSettings(
            task="insert_hexagon", init="x", out=str(tmp_path), twin=str(tmp_path / "look.yaml")
        )


def test_twin_rl_runs_in_the_twin_it_is_given(tmp_path):
    """Stage II in the fitted look: its environments render that look."""
    from tests.conftest import tiny_state_policy
    from twinrl_learn.settings import RLConfig
    from twinrl_learn.twin_rl import run_twin_rl

    dataset, sft = tiny_state_policy(tmp_path / "sft", seed=3, steps=10)
    seen = []
    import twinrl_learn.twin_rl as twin_rl

    original = twin_rl.BatchEnv

    class Recording(original):
        def __init__(self, task, *args, **kwargs):
            seen.append(task.scene.effects)
            super().__init__(task, *args, **kwargs)

    twin_rl.BatchEnv = Recording
    try:
        run_twin_rl(
            TwinRLSettings(
                task="pick_place", init=str(sft), out=str(tmp_path / "run"), demos=[str(dataset)],
                envs=1, steps=5, twin=str(_look(tmp_path / "look.yaml")),
                rl=RLConfig.for_method("twinrl", offline_steps=1, batch_size=8),
            )
        )  # fmt: skip
    finally:
        twin_rl.BatchEnv = original
    assert [effects["appearance"] for effects in seen] == [LOOK]


def test_the_twin_classifier_learns_success_from_labelled_twin_episodes(tmp_path):
    """Stage I's classifier: twin episodes with near misses and held successes, labelled
    by the twin itself; it loads as real RL loads it."""
    from twinrl_learn.studies.table1 import train_twin_classifier

    folder = train_twin_classifier("pick_place", tmp_path, None, 3, seed=0, device="cpu", steps=20)
    episodes = [read_episode(p) for p in Session(tmp_path / "success_session").episode_paths()]
    assert len(episodes) == 6 and {e.meta.world for e in episodes} == {"twin"}
    assert any(e.meta.success for e in episodes)
    classifier = RewardClassifier.load(folder)
    assert classifier.task == "pick_place"
    # After Stage II it learns again from those episodes and the twin-RL rollouts.
    from twinrl_learn.studies.table1 import fit_twin_classifier

    rollouts = Session.create(tmp_path / "rollouts")
    for episode in episodes[:2]:
        rollouts.add(episode)
    again = fit_twin_classifier(
        [tmp_path / "success_session", tmp_path / "rollouts"], tmp_path / "again", seed=0,
        device="cpu", steps=20,
    )  # fmt: skip
    metrics = json.loads((again / "metrics.json").read_text())
    assert metrics["fitted_episodes"] + metrics["heldout_episodes"] == 8
    assert RewardClassifier.load(again).task == "pick_place"
