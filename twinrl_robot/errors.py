"""The errors of robots, their wrappers and loops: every one says what is wrong and how to
fix it."""

from twinrl_data.errors import TwinrlError


class RobotError(TwinrlError):
    """A robot, an action, a trajectory or a setting cannot be used as given."""


class PrivilegedStateError(RobotError):
    """Code that needs a simulation's hidden state was given a robot without it."""
