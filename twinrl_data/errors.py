"""The errors twinrl_data raises: every one says what is wrong and how to fix it."""


class DataError(ValueError):
    """A log, dataset or catalog cannot be used as given."""


class McapError(DataError):
    """An MCAP file is missing, not MCAP, truncated or not an episode log."""
