"""The contracts: what every layer above agrees on, with no I/O, no zenoh and no rerun in it.

Messages and keys (``messages``, ``keys``, ``frames``), the configs (``config``), the transport
contract (``transport``), the reliable channel's sans-IO protocol machines and QoS (``protocol``),
the ROS 2 message types (``rosmsg``) and the small shared pieces (``errors``, ``percentiles``,
``endpoints``, ``link_sizes``, ``traffic``, ``throttled_log``, ``version``). Import-linter keeps
everything here free of the layers above (pyproject.toml, docs/architecture.md).
"""
