"""The reliable channel's protocol with no I/O in it: wire format, QoS profiles, and the writer
and reader state machines (docs/reliability.md).

Everything here is a pure function of its inputs and a ``Clock``: messages in, ``Action`` lists
out. ``arpz.channel`` drives these machines over a ``arpz.core.transport.Transport``; the unit
tests drive them over an in-memory lossy bus. Nothing here imports zenoh, rerun or cvxpy.
"""
