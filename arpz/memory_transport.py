"""Compatibility: the in-process bus now lives in ``arpz.transport.memory``.

Kept so that ``from arpz.memory_transport import MemoryBus, MemoryTransport`` keeps working; new
code imports ``arpz.transport.memory``.
"""

from arpz.transport.memory import MemoryBus, MemoryTransport

__all__ = ["MemoryBus", "MemoryTransport"]
