"""A UR controller emulator speaking the real protocols, backed by the plant's physics
(see :mod:`.emulator`)."""

from twinrl_robot.ur.emulator.emulator import Emulator as Emulator
from twinrl_robot.ur.emulator.emulator import Ports as Ports
from twinrl_robot.ur.emulator.emulator import free_loopback_host as free_loopback_host
