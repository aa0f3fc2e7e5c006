"""Compatibility: the typed TOML configs now live in ``arpz.core.config``.

Kept so that ``from arpz.config import RobotConfig, CeddpConfig, load_toml`` keeps working; new
code imports ``arpz.core.config``.
"""

from arpz.core.config import *  # noqa: F403
