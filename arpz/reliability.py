"""Compatibility: the reliable channel's public names now live in ``arpz.channel``.

Kept so that ``from arpz.reliability import Writer, Reader, QosProfile`` (docs/api.md before the
layers moved into folders) keeps working; new code imports ``arpz.channel``.
"""

from arpz.channel import *  # noqa: F403
from arpz.channel import __all__  # noqa: F401
