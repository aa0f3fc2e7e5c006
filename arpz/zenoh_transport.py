"""Compatibility: the Zenoh session now lives in ``arpz.transport.zenoh``.

Kept so that ``from arpz.zenoh_transport import ZenohTransport`` keeps working; new code imports
``arpz.transport.zenoh``.
"""

from arpz.transport.zenoh import ZenohTransport

__all__ = ["ZenohTransport"]
