"""The ROS 2 standard message types of arpz's sensor kinds, and exact conversion both ways
(docs/protocol.md "ROS 2 message types"). Pure data: no I/O, no zenoh."""
