"""CSV logs on real clocks: coarse stamps, the log's own rate, resampling said aloud."""

from dataclasses import replace

import numpy as np
import pytest

from tests.data.test_data_safety import _rtde_csv
from twinrl_data.errors import DataError, DataWarning
from twinrl_data.importers import RTDE_MAP, ColumnMap, import_csv


def _log(tmp_path, stamps) -> str:
    lines = _rtde_csv(len(stamps), np.random.default_rng(0)).splitlines()
    rows = [line.split(" ") for line in lines[1:]]
    for row, stamp in zip(rows, stamps, strict=True):
        row[0] = f"{stamp:.6f}"
    path = tmp_path / "log.csv"
    path.write_text("\n".join([lines[0], *(" ".join(r) for r in rows)]) + "\n")
    return path


def test_coarse_stamps_are_refused_with_the_count_and_the_rate_keeps_every_row(tmp_path):
    t = np.arange(500) / 125.0
    path = _log(tmp_path, 1_700_000_000 + np.floor(t))  # a PC clock in whole seconds
    with pytest.raises(DataError, match=r"496 of 500 rows repeat .* every 1 s.*\(rate: 125\)"):
        import_csv(path)
    episode = import_csv(path, replace(RTDE_MAP, rate=125.0))
    assert len(episode) == 500 and episode.meta.fps == 125.0


def test_stamps_that_go_back_are_refused(tmp_path):
    t = np.arange(200) / 125.0
    t[100:] -= 0.5  # a clock set back mid-log
    with pytest.raises(DataError, match="1 rows go back in time"):
        import_csv(_log(tmp_path, t))


def test_the_log_is_imported_at_its_own_rate_and_resampling_says_what_it_loses(tmp_path):
    path = _log(tmp_path, np.arange(500) / 125.0)
    episode = import_csv(path)
    assert len(episode) == 500 and episode.meta.fps == 125.0
    with pytest.warns(DataWarning, match=r"from 125 Hz to 10 Hz \(500 rows became 40 steps\)"):
        slow = import_csv(path, fps=10.0)
    assert len(slow) == 40


def test_a_column_map_may_give_the_rate_instead_of_a_time_column(tmp_path):
    path = _log(tmp_path, np.arange(300) / 125.0)
    (tmp_path / "map.yaml").write_text(
        "rate: 125\n"
        f"commanded: {RTDE_MAP.commanded}\nmeasured: {RTDE_MAP.measured}\ntcp: {RTDE_MAP.tcp}\n"
    )
    episode = import_csv(path, ColumnMap.load(tmp_path / "map.yaml"))
    assert len(episode) == 300 and episode.meta.fps == 125.0
    (tmp_path / "bad.yaml").write_text(f"commanded: {RTDE_MAP.commanded}\nmeasured: [a]\n")
    with pytest.raises(DataError, match=r"missing key\(s\) \['time \(or rate\)'\]"):
        ColumnMap.load(tmp_path / "bad.yaml")
    with pytest.raises(DataError, match="rate must be a sample rate"):
        replace(RTDE_MAP, rate=float("nan"))


def test_rows_that_repeat_the_row_before_exactly_are_dropped_and_said(tmp_path):
    stamps = np.arange(400) / 125.0
    path = _log(tmp_path, stamps)
    lines = path.read_text().splitlines()
    repeated = [lines[0]] + [
        row for i, row in enumerate(lines[1:]) for _ in range(1 + (i % 7 == 3))
    ]
    path.write_text("\n".join(repeated) + "\n")
    said = r"dropped 57 of 457 rows that repeat the row before exactly and 0"
    with pytest.warns(DataWarning, match=said):
        episode = import_csv(path)
    assert len(episode) == 400 and episode.meta.fps == 125.0


def test_a_row_with_the_last_packages_stamp_and_new_values_takes_the_stamp_between(tmp_path):
    """ur_rtde's recorder, reading while a package arrives, may write the new package's
    values under the last one's stamp; the next row is then two periods on, or three when
    the recorder missed a package too (seen in CI). No sample is lost: the row takes the
    stamp it lacks."""
    stamps = np.arange(300) / 500.0
    stamps[200:] += 1 / 500.0  # a package the recorder missed, right after a torn row
    torn = [40, 150, 199]
    stamps[torn] = stamps[[39, 149, 198]]
    path = _log(tmp_path, np.round(stamps, 6))
    with pytest.warns(DataWarning, match=r"gave 3 the stamp between"):
        episode = import_csv(path)
    assert episode.meta.fps == 500.0 and len(episode) == 301  # the missed one interpolated
    # A genuine coarse clock (stamps repeating without the skip) is still refused.
    coarse = np.floor(np.arange(300) / 250.0 * 100) / 100
    with pytest.raises(DataError, match="repeat the stamp"):
        import_csv(_log(tmp_path, coarse))
