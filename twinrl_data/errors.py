"""The project's errors: every one says what is wrong and how to fix it.

Messages speak of the library's own terms. A setting a message names is written in
backticks (```force```), so that the command line can name it by its flag instead
(``--force``; see :func:`twinrl_data.settings_cli.describe`).

:class:`TwinrlError` is the root; each package raises its own subclasses. They derive
from ``ValueError`` because every one of them is a value the caller passed (a file, a
setting, a robot) that cannot be used as given.
"""


class TwinrlError(ValueError):
    """Something the caller gave twinrl cannot be used as given."""


class DataError(TwinrlError):
    """A log, dataset or catalog cannot be used as given."""


class McapError(DataError):
    """An MCAP file is missing, not MCAP, truncated or not an episode log."""


class UsageError(TwinrlError):
    """A command was given options it cannot use together, or a value it cannot read."""


class SettingError(TwinrlError):
    """A setting (a field of a settings record) has a value it cannot take.

    The message names the setting as the record does (``plant_steps must be at least
    1``); the command line, which derives its options from the same records, names it by
    its flag instead (``--plant-steps must be at least 1``).
    """

    def __init__(self, setting: str, problem: str) -> None:
        super().__init__(f"{setting} {problem}")
        self.setting, self.problem = setting, problem


class DataWarning(UserWarning):
    """Something read is not quite as it should be, yet what can be read was read (a
    session whose manifest disagrees with its files, an episode left unfinished)."""
