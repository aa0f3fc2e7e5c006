"""ROS 2 (rclpy) counterparts of arpz.experiment's runs: the same applications and
measurements over the ROS 2 RMW installed (Fast DDS by default), for side-by-side figures."""
