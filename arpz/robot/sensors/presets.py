"""The sensor sets of seed 001's machines (section 3.1, Fig. 8)."""

from __future__ import annotations

from arpz.core.config import SensorConfig

PRESETS: dict[str, tuple[str, ...]] = {
    "machine1": ("lidar", "light", "flame", "dht11", "imu", "pir"),
    "machine2": ("flame", "pir", "ultrasonic", "dht11", "light"),
    "machine3": ("flame", "pir", "ultrasonic", "dht11", "light"),
}


def preset_sensors(preset: str, rate_hz: float = 10.0) -> list[SensorConfig]:
    """One simulated sensor per kind of the preset, named after its kind."""
    if preset not in PRESETS:
        known = ", ".join(sorted(PRESETS))
        raise ValueError(f"unknown preset {preset!r}: use one of {known}")
    return [SensorConfig(name=kind, kind=kind, rate_hz=rate_hz) for kind in PRESETS[preset]]  # type: ignore[arg-type]
