"""The ``twinrl`` command line: help, the first commands, and one-line errors."""

import contextlib
import io
import json
import os
import subprocess
import sys
import warnings
from pathlib import Path

import pytest
from typer.testing import CliRunner

from twinrl_learn.cli import app, main

runner = CliRunner()


def twinrl_process(*args: str, cwd=None, stdin: str = "") -> subprocess.CompletedProcess:
    """Run the real entry point in a fresh interpreter, for what only a process shows
    (its start-up, what it imports, how it ends)."""
    return subprocess.run(
        [sys.executable, "-m", "twinrl_learn", *args],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=cwd,
        input=stdin,
    )


def twinrl(
    *args: str, cwd: str | Path | None = None, stdin: str = ""
) -> subprocess.CompletedProcess:
    """The entry point called in this process, as ``python -m twinrl_learn`` calls it
    (the same ``main``: one-line errors, exit statuses): a fresh interpreter's start-up
    (up to 14 s here, most of it lerobot's imports) would cost more than most commands
    tested. A bug's traceback is raised here rather than printed."""
    out, err = io.StringIO(), io.StringIO()
    argv, here, show, stdin_was = sys.argv, os.getcwd(), warnings.showwarning, sys.stdin
    sys.argv = ["twinrl", *args]
    sys.stdin = io.StringIO(stdin)
    os.chdir(cwd or here)
    code: int | str | None = 0
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            main()
    except SystemExit as stop:
        code = stop.code
    finally:
        sys.argv, warnings.showwarning, sys.stdin = argv, show, stdin_was
        os.chdir(here)
    if isinstance(code, str):  # as the interpreter does with sys.exit("...")
        err.write(code + "\n")
    status = code if isinstance(code, int) else (0 if code is None else 1)
    return subprocess.CompletedProcess(list(args), status, out.getvalue(), err.getvalue())


def test_help_lists_every_command():
    result = runner.invoke(app, ["--help"])
    assert result.exit_code == 0 and "sim" in result.output
    result = runner.invoke(app, ["sim", "--help"])
    for command in ("show", "expert", "effects"):
        assert command in result.output


# What a command loads only when it runs: the command list and every --help stay quick.
HEAVY_MODULES = ("torch", "lerobot", "scipy", "rerun", "mujoco.sysid", "pycolmap", "open3d", "ray")


def test_help_loads_no_heavy_module():
    probe = (
        "import sys; from twinrl_learn.cli import app; from typer.main import get_command; "
        "get_command(app); "
        f"print(','.join(m for m in {HEAVY_MODULES!r} if m in sys.modules))"
    )
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "", f"building the CLI loaded {result.stdout.strip()}"
    help_text = twinrl("--help")
    assert help_text.returncode == 0 and "locate" in help_text.stdout


def test_expert_json_has_the_documented_shape():
    result = twinrl("sim", "expert", "pick_place", "--episodes", "2", "--region", "OOD", "--json")
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert report["task"] == "pick_place" and report["world"] == "twin"
    assert report["episodes"] == 2 and set(report["success_rate"]) == {"OOD"}


def test_expert_table_in_both_worlds():
    result = twinrl(
        "sim", "expert", "insert_hexagon", "--episodes", "2", "--world", "twin", "--world", "plant"
    )
    assert result.returncode == 0, result.stderr
    for word in ("twin", "plant", "ID success", "OOD success"):
        assert word in result.stdout


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["sim", "expert", "pick_plce"], "did you mean 'pick_place'"),
        (["sim", "expert", "pick_place", "--region", "MID"], "--region must be one of"),
        (["sim", "expert", "pick_place", "--world", "mars"], "--world must be one of"),
        (
            ["sim", "expert", "pick_place", "--effects", "nope.yaml", "--world", "plant"],
            "does not exist",
        ),
        (["sim", "show", "pick_place", "--config", "{bad json"], "--config must be JSON"),
    ],
)
def test_bad_input_gives_one_line_and_exit_2(args, message):
    result = twinrl(*args)
    assert result.returncode == 2
    lines = [line for line in result.stderr.strip().splitlines() if line.strip()]
    assert message in result.stderr and len(lines) <= 3  # one message, maybe soft-wrapped
    assert "Traceback" not in result.stderr


def test_show_writes_a_png_and_never_overwrites(tmp_path):
    out = tmp_path / "cell.png"
    config = json.dumps({"object": [0.4, 0.2, 0.5], "target": [0.5, 0.1, 0.0]})
    result = twinrl(
        "sim", "show", "pick_place", "--config", config, "--size", "96", "--out", str(out)
    )
    assert result.returncode == 0, result.stderr
    assert out.stat().st_size > 1000
    before = out.read_bytes()
    again = twinrl("sim", "show", "pick_place", "--out", str(out))
    assert again.returncode == 2 and "already exists" in again.stderr
    assert out.read_bytes() == before


def test_effects_lists_the_library():
    result = runner.invoke(app, ["sim", "effects"])
    assert result.exit_code == 0
    assert "actuator_delay" in result.output and "gripper_force" in result.output


def test_train_and_eval_commands(tmp_path):
    run = twinrl(
        "sim", "expert", "pick_place", "--episodes", "1", "--out", str(tmp_path / "session")
    )
    assert run.returncode == 0, run.stderr
    assert (
        twinrl("data", "export", str(tmp_path / "session"), "--to", str(tmp_path / "ds")).returncode
        == 0
    )

    def sft(*options):
        return twinrl(
            "train", "sft", "--dataset", str(tmp_path / "ds"), "--policy", "state",
            "--out", str(tmp_path / "policy"), *options,
        )  # fmt: skip

    trained = sft("--steps", "20")
    assert trained.returncode == 0, trained.stderr
    assert "20 steps" in trained.stdout
    evaluated = twinrl(
        "eval",
        str(tmp_path / "policy"),
        "--task",
        "pick_place",
        "--grid",
        "1x2",
        "--open-loop",
        "--no-grasp-hold",
        "--out",
        str(tmp_path / "eval"),
    )
    assert evaluated.returncode == 0, evaluated.stderr
    assert (tmp_path / "eval" / "heatmap.png").is_file() and "ID" in evaluated.stdout
    policy_name = json.loads((tmp_path / "eval" / "eval.json").read_text())["policy"]
    assert policy_name == "twinrl:policy:open-loop:no-hold"
    again = sft("--resume")  # no --steps: the run's own 20, not the default
    assert again.returncode == 0, again.stderr
    assert "20 steps" in again.stdout
    resumed = sft("--steps", "30", "--resume")
    assert resumed.returncode == 0, resumed.stderr
    assert "30 steps" in resumed.stdout


STARTED = ["--task", "pick_place", "--init", "p", "--out", "x"]  # a run's first options


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["train", "sft", "--dataset", "nowhere", "--out", "x"], "is not a LeRobotDataset"),
        (
            ["train", "sft", "--dataset", "nowhere", "--out", "x", "--inputs", "sideways"],
            "--inputs must be one of absolute, relative",
        ),
        (
            ["train", "sft", "--dataset", "nowhere", "--out", "x", "--image-size", "96"],
            "--image-size must be one of 64, 128, got 96",
        ),
        (
            ["train", "sft", "--dataset", "nowhere", "--out", "x", "--lr-schedule", "linear"],
            "--lr-schedule must be one of cosine, constant",
        ),
        (["eval", "nowhere", "--task", "pick_place", "--out", "x"], "is not a policy checkpoint"),
        (
            ["eval", "expert", "--task", "pick_place", "--grid", "8by8", "--out", "x"],
            "--grid must look like",
        ),
        (
            ["eval", "expert", "--task", "pick_place", "--open-loop", "--out", "x"],
            "--open-loop applies to a twinrl checkpoint",
        ),
        (
            ["eval", "expert", "--task", "pick_place", "--no-grasp-hold", "--out", "x"],
            "--grasp-hold applies to a twinrl checkpoint",
        ),
        (
            ["eval", "expert", "--task", "pick_place", "--binary-gripper", "--out", "x"],
            "--binary-gripper applies to a twinrl checkpoint",
        ),
        (["expand", "pick_place", "--out", "x", "--randomize", "fog"], "unknown randomisation"),
        (["expand", "pick_place", "--out", "x", "--method", "augment"], "needs --from-demo"),
        (
            ["bench", "stage1", "--out", "x", "--inputs", "sideways"],
            "--inputs must be one of absolute, relative, got 'sideways'",
        ),
        (
            ["bench", "stage1", "--out", "x", "--perception", "-1"],
            "--perception must be >= 0, got -1",
        ),
        (
            ["bench", "stage1", "--out", "x", "--policies", "diffusion"],
            "--policies has diffusion; use state, vla, act",
        ),
        (["bench", "stage1", "--out", "x", "--act-steps", "0"], "--act-steps must be at least 1"),
        (
            [
                "train",
                "sft",
                "--dataset",
                ".",
                "--out",
                "x",
                "--policy",
                "state",
                "--perception",
                "est",
            ],
            "--perception serves the vla policy",
        ),
        (
            ["train", "perception", "--dataset", ".", "--out", "x", "--steps", "0"],
            "--steps must be at least 1, got 0",
        ),
        # Options derived from the run's settings: the settings' checks name the flag.
        (
            ["train", "real-rl", "--task", "pick_place", "--out", "x", "--plant-steps", "0"],
            "--plant-steps must be at least 1, got 0",
        ),
        (
            ["train", "real-rl", "--task", "pick_place", "--out", "x", "--eval-grid", "4"],
            "--eval-grid must look like 8x8",
        ),
        (
            ["train", "real-rl", "--task", "pick_place", "--out", "x", "--method", "sarsa"],
            "--method must be one of twinrl, conrft, hil-serl",
        ),
        (["train", "real-rl", "--task", "pick_place", "--out", "x"], "--init is needed"),
        (
            ["train", "real-rl", *STARTED, "--no-operator", "--operator-sees", "e"],
            "--operator-sees is the simulated operator's eyes",
        ),
        (
            ["train", "twin-rl", *STARTED, "--workers", "0"],
            "--workers must be at least 1, got 0",
        ),
        (
            ["train", "twin-rl", "--task", "pick_place", "--out", "x", "--envs", "0"],
            "--envs must be at least 1, got 0",
        ),
    ],
)
def test_stage1_bad_input(args, message, tmp_path):
    result = twinrl(*args, cwd=tmp_path)
    assert result.returncode == 2, result.stderr
    assert message in result.stderr and "Traceback" not in result.stderr
    assert not (tmp_path / "x").exists()  # nothing written


def test_only_the_projects_errors_become_one_line(monkeypatch, capsys):
    """Bad input (a project error) is one red line and status 2; a bug keeps its traceback."""
    import twinrl_learn.cli as cli
    from twinrl_data.errors import DataError

    def failing(error):
        def command():
            raise error

        return command

    monkeypatch.setattr(sys, "argv", ["twinrl"])
    monkeypatch.setattr(cli, "app", failing(DataError("the session is damaged; recover it")))
    with pytest.raises(SystemExit) as stopped:
        cli.main()
    assert stopped.value.code == 2
    assert "error: the session is damaged; recover it" in capsys.readouterr().err
    monkeypatch.setattr(cli, "app", failing(ValueError("an internal slip")))
    with pytest.raises(ValueError, match="an internal slip"):
        cli.main()
