"""The ROS 2 bridge (docs/ros2.md): the fleet's topics as ROS 2 topics for nodes running
rmw_zenoh on the same router, and ROS 2 commands to the robots, speaking rmw_zenoh's wire
protocol. It runs inside the CEDDP (``[ros2]``) or on a machine of its own
(``python -m arpz.bridge``)."""
