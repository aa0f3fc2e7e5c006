"""A lab's own robot code for arpz: GPS and battery drivers, a dock planner, a base actuator.

What a team writes to run its robots on arpz (docs/nodes.md); the configs beside this package
(`robot.toml`, `ceddp.toml`) name these classes, and `msg/` holds the lab's own message type.
"""
