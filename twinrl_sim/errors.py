"""The errors of the twin: every one says what is wrong and how to fix it."""

from twinrl_data.errors import TwinrlError


class TwinError(TwinrlError):
    """A scene spec, an effect, a task setting, a log to replay or a video cannot be used
    as given by the twin."""
