"""Behaviour stacked over a robot, one wrapper each (see :mod:`.base`)."""

from twinrl_robot.wrappers.base import ActionWrapper as ActionWrapper
from twinrl_robot.wrappers.base import ObservationWrapper as ObservationWrapper
from twinrl_robot.wrappers.base import RobotWrapper as RobotWrapper
from twinrl_robot.wrappers.base import layers as layers
from twinrl_robot.wrappers.base import random_states as random_states
from twinrl_robot.wrappers.base import restore_random_states as restore_random_states
from twinrl_robot.wrappers.grasp_hold import GraspHold as GraspHold
from twinrl_robot.wrappers.grasp_hold import HoldRule as HoldRule
from twinrl_robot.wrappers.noise import NoiseLevels as NoiseLevels
from twinrl_robot.wrappers.noise import SensorNoise as SensorNoise
from twinrl_robot.wrappers.privileged import PrivilegedObservation as PrivilegedObservation
from twinrl_robot.wrappers.safety import SafetyLimits as SafetyLimits
from twinrl_robot.wrappers.takeover import OperatorTakeover as OperatorTakeover
