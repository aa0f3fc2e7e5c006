"""The robot side of arpz: sensing through a local cache, actuation, presence."""
