"""arpz: Aggregated Robot Processing on Eclipse Zenoh.

Robots (``python -m arpz.robot``) sense and act; the CEDDP server (``python -m arpz.ceddp``) is the
Zenoh router, de-duplicates readings (cache control), plans, tunes QoS and draws a Rerun dashboard.
"""

from arpz.core.errors import ArpzError, ConfigError
from arpz.core.transport import TransportError

__version__ = "0.1.0"

#: the root of every error arpz raises on purpose, and the two a deployment meets first; the
#: rest of the public API lives in the package it belongs to (docs/api.md)
__all__ = ["ArpzError", "ConfigError", "TransportError", "__version__"]
