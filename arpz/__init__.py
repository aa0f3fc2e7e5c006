"""arpz: Aggregated Robot Processing on Eclipse Zenoh.

Robots (``python -m arpz.robot``) sense and act; the CEDDP server (``python -m arpz.ceddp``) is the
Zenoh router, de-duplicates readings (cache control), plans, tunes QoS and draws a Rerun dashboard.
"""

__version__ = "0.1.0"
