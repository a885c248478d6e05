"""``twinrl data`` and ``twinrl view`` end to end, through the entry point's ``main``."""

import json

from tests.data.conftest import write_episode
from tests.test_cli import twinrl


def test_record_index_query_export_view(tmp_path):
    run = twinrl(
        "sim",
        "expert",
        "insert_hexagon",
        "--episodes",
        "1",
        "--world",
        "twin",
        "--world",
        "plant",
        "--out",
        "session",
        cwd=tmp_path,
    )
    assert run.returncode == 0, run.stderr
    assert "recorded 4 episodes" in run.stdout
    assert twinrl("data", "index", "session", cwd=tmp_path).returncode == 0
    rows = json.loads(twinrl("data", "query", "--world", "plant", "--json", cwd=tmp_path).stdout)
    assert len(rows) == 2 and {r["source"] for r in rows} == {"teleop"}
    curated = twinrl("data", "curate", "--source", "twin_demo", "--to", "demos", cwd=tmp_path)
    assert curated.returncode == 0, curated.stderr
    assert "2 episodes" in curated.stdout
    saved = twinrl("view", "session#0", "session#2", "--save", "pair.rrd", cwd=tmp_path)
    assert saved.returncode == 0, saved.stderr
    assert (tmp_path / "pair.rrd").stat().st_size > 10_000
    again = twinrl("view", "demos", "--save", "pair.rrd", cwd=tmp_path)
    assert again.returncode == 2 and "already exists" in again.stderr


def test_recover_and_import(tmp_path):
    path = tmp_path / "ep.mcap"
    write_episode(path, length=15)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[:-2000])
    run = twinrl("data", "recover", str(cut))
    assert run.returncode == 0, run.stderr
    assert "kept" in run.stdout and "truncated" in run.stdout
    exported = twinrl("data", "export", str(path), "--to", str(tmp_path / "ds"))
    assert exported.returncode == 0, exported.stderr
    imported = twinrl("data", "import", str(tmp_path / "ds"), "--to", str(tmp_path / "back"))
    assert imported.returncode == 0, imported.stderr
    assert "1 episodes imported" in imported.stdout


def test_data_errors_are_one_line(tmp_path):
    (tmp_path / "junk.mcap").write_text("junk")
    cases = [
        (["data", "recover", str(tmp_path / "junk.mcap")], "not an MCAP file"),
        (["data", "index", str(tmp_path / "missing")], "does not exist"),
        (
            ["data", "query", "--catalog", str(tmp_path / "none.parquet")],
            "does not exist; build it",
        ),
        (["data", "export", str(tmp_path), "--to", str(tmp_path / "x")], "is not a session folder"),
        (["data", "import", str(tmp_path), "--to", str(tmp_path / "y")], "is not a LeRobotDataset"),
        (
            ["view", str(tmp_path / "junk.mcap"), "--save", str(tmp_path / "v.rrd")],
            "not an MCAP file",
        ),
    ]
    for args, message in cases:
        run = twinrl(*args)
        assert run.returncode == 2, (args, run.stderr)
        assert message in run.stderr and "Traceback" not in run.stderr
