"""The catalog: index sessions and datasets, query with filters and SQL, curate."""

import pytest

from tests.data.conftest import make_meta, make_step
from twinrl_data.catalog import build_index, flatten_config, load_selected, query
from twinrl_data.errors import DataError
from twinrl_data.lerobot_io import export_dataset
from twinrl_data.session import Session


def record_session(path, specs):
    import numpy as np

    session = Session.create(path)
    for i, (source, world, region, success, length) in enumerate(specs):
        rng = np.random.default_rng(i)
        with session.record(make_meta(source=source, world=world, region=region)) as log:
            for t in range(length):
                step = make_step(t, length, rng, cameras=())
                step["next.success"] = success and t == length - 1
                log.append(step)
    return session


@pytest.fixture
def session(tmp_path):
    return record_session(
        tmp_path / "session",
        [
            ("twin_demo", "twin", "ID", True, 6),
            ("twin_demo", "twin", "OOD", False, 9),
            ("teleop", "plant", "ID", True, 7),
        ],
    )


def test_index_and_filters(session, tmp_path):
    catalog = tmp_path / "catalog.parquet"
    report = build_index([session.path], catalog)
    assert (report.indexed, report.total) == (3, 3)
    assert query(catalog).num_rows == 3
    assert query(catalog, world="twin").num_rows == 2
    assert query(catalog, world="twin", success=False).column("length").to_pylist() == [9]
    assert query(catalog, where="length >= 7 AND region = 'ID'").column("source").to_pylist() == [
        "teleop"
    ]
    row = query(catalog, source="teleop").to_pylist()[0]
    assert (
        row["config_object_0"] == pytest.approx(0.4) and row["num_interventions"] == 2
    )  # t = 5, 6
    assert row["return"] == pytest.approx(-0.05 * 6 + 10)
    counts = query(
        catalog, sql="SELECT world, count(*) AS n FROM episodes GROUP BY world ORDER BY world"
    )
    assert counts.to_pylist() == [{"world": "plant", "n": 1}, {"world": "twin", "n": 2}]


def test_reindexing_updates_instead_of_duplicating(session, tmp_path):
    catalog = tmp_path / "catalog.parquet"
    build_index([session.path], catalog)
    assert build_index([session.path], catalog).total == 3
    more = record_session(tmp_path / "more", [("eval", "twin", "OOD", True, 5)])
    assert build_index([more.path], catalog).total == 4


def test_datasets_are_indexed_and_curated(session, tmp_path):
    catalog = tmp_path / "catalog.parquet"
    build_index([session.path], catalog)
    selected = query(catalog, world="twin")
    result = export_dataset(load_selected(selected), tmp_path / "curated")
    assert result.episodes == 2
    build_index([tmp_path / "curated"], catalog)
    rows = query(catalog, where="kind = 'lerobot'").to_pylist()
    assert sorted(r["region"] for r in rows) == ["ID", "OOD"]
    assert {r["dataset_index"] for r in rows} == {0, 1}
    assert [len(e) for e in load_selected(query(catalog, where="kind = 'lerobot'"))] == [6, 9]


def test_bad_queries_name_the_problem(session, tmp_path):
    catalog = tmp_path / "catalog.parquet"
    build_index([session.path], catalog)
    with pytest.raises(
        DataError, match="unknown catalog column 'lenght' \\(did you mean 'length'\\?\\)"
    ):
        query(catalog, where="lenght > 3")
    with pytest.raises(DataError, match="query failed"):
        query(catalog, where="length >>> 3")
    with pytest.raises(DataError, match="does not exist; build it"):
        query(tmp_path / "none.parquet")
    with pytest.raises(DataError, match="does not exist"):
        build_index([tmp_path / "missing"], catalog)


def test_flatten_config():
    assert flatten_config({"object": [1, 2, 3], "speed": 0.5, "name": "x"}) == {
        "config_object_0": 1.0,
        "config_object_1": 2.0,
        "config_object_2": 3.0,
        "config_speed": 0.5,
    }


def test_an_episode_that_ended_early_is_marked_in_the_catalog(tmp_path):
    import numpy as np

    from twinrl_data.recorder import Recorder

    session = Session.create(tmp_path / "session")
    recorder = Recorder(session)
    rng = np.random.default_rng(0)
    for reason in (None, "the arm is in a protective stop"):
        recorder.start_episode(make_meta(source="teleop", world="real", region="ID"))
        for t in range(4):
            recorder.add_frame(make_step(t, 4, rng, cameras=()))
        recorder.save_episode(success=False, aborted=reason)
    catalog = tmp_path / "catalog.parquet"
    build_index([session.path], catalog)
    assert query(catalog, where="aborted IS NULL").num_rows == 1
    (row,) = query(catalog, where="aborted IS NOT NULL").to_pylist()
    assert row["aborted"] == "the arm is in a protective stop" and row["length"] == 4
