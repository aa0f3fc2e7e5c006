"""The everyday tools of a fleet (docs/tools.md): topic introspection, MCAP record and play, and
the doctor. They join a running fleet's router as clients, like any robot or ROS 2 tool would."""
