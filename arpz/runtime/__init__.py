"""What every long-running arpz process shares: start-up, logging, signals and the common
command-line options (``startup``), used by the robot, the CEDDP, the bridge and the tools."""
