"""The 8-beam LIDAR of seed 001 section 3.2: one range per 45 degrees, each on its own topic.

The seed sends 0, 45, ..., 315 degrees (robot frame, counter-clockwise from straight ahead) on
eight separate topics, so on the wire each beam can be late, lost or held back independently;
``beam_topic`` gives the topic names both ends must agree on.
"""

from __future__ import annotations

from typing import Final

import numpy as np

from arpz.mission.kinematics import Pose
from arpz.mission.world import FloatArray, World

#: Beam angles in the robot frame: 0 ahead, 90 left, 180 behind, 270 right.
BEAM_ANGLES_DEG: Final = (0, 45, 90, 135, 180, 225, 270, 315)

#: The range of a SLAMTEC A2M8 (the LIDAR of seed 001); a beam that hits nothing reads this.
DEFAULT_MAX_RANGE_M: Final = 12.0

_TOPIC_PREFIX = "lidar_"


def beam_topic(beam_deg: int) -> str:
    """``lidar_0`` ... ``lidar_315``: the sensor topic carrying one beam."""
    if beam_deg not in BEAM_ANGLES_DEG:
        raise ValueError(f"no beam at {beam_deg} degrees; beams: {BEAM_ANGLES_DEG}")
    return f"{_TOPIC_PREFIX}{beam_deg}"


def beam_of_topic(topic: str) -> int | None:
    """The beam angle a topic carries, or None if the topic is not a LIDAR beam."""
    if not topic.startswith(_TOPIC_PREFIX):
        return None
    suffix = topic[len(_TOPIC_PREFIX) :]
    if not suffix.isdigit() or int(suffix) not in BEAM_ANGLES_DEG:
        return None
    return int(suffix)


class Lidar:
    """Ray-casts the beams from a pose; optional Gaussian noise from a seeded generator.

    Noise is added to hits only: a beam that sees nothing keeps reading exactly the maximum range,
    as a real scanner reports "no return" rather than a noisy far value.
    """

    def __init__(
        self,
        world: World,
        *,
        max_range_m: float = DEFAULT_MAX_RANGE_M,
        noise_std_m: float = 0.0,
        seed: int | None = None,
        beams_deg: tuple[int, ...] = BEAM_ANGLES_DEG,
    ) -> None:
        if max_range_m <= 0.0:
            raise ValueError(f"max_range_m must be > 0, got {max_range_m}")
        if noise_std_m < 0.0:
            raise ValueError(f"noise_std_m must be >= 0, got {noise_std_m}")
        self.world = world
        self.max_range_m = max_range_m
        self.noise_std_m = noise_std_m
        self.beams_deg = beams_deg
        self._beams_rad = np.radians(np.array(beams_deg, dtype=np.float64))
        self._rng = np.random.default_rng(seed)

    def true_ranges_m(self, pose: Pose) -> FloatArray:
        """Noise-free ranges in ``beams_deg`` order: what the judge compares readings with."""
        return self.world.ray_ranges_m(
            pose.x_m, pose.y_m, self._beams_rad + pose.theta_rad, self.max_range_m
        )

    def scan(self, pose: Pose) -> FloatArray:
        """One reading per beam in ``beams_deg`` order, noisy if ``noise_std_m > 0``."""
        ranges = self.true_ranges_m(pose)
        if self.noise_std_m > 0.0:
            hits = ranges < self.max_range_m
            noisy = ranges + self._rng.normal(0.0, self.noise_std_m, size=ranges.shape)
            ranges = np.where(hits, np.clip(noisy, 0.0, self.max_range_m), ranges)
        return ranges

    def readings(self, pose: Pose) -> dict[str, float]:
        """``{"lidar_0": range_m, ...}``: one scan as the values to publish on the beam topics."""
        return {
            beam_topic(deg): float(r)
            for deg, r in zip(self.beams_deg, self.scan(pose), strict=True)
        }


def beam_endpoints(
    pose: Pose, ranges_m: FloatArray | list[float], beams_deg: tuple[int, ...] = BEAM_ANGLES_DEG
) -> FloatArray:
    """World-frame end points (K x 2) of the beams from ``pose``: for drawing the rays."""
    angles = np.radians(np.array(beams_deg, dtype=np.float64)) + pose.theta_rad
    ranges = np.asarray(ranges_m, dtype=np.float64)
    return np.stack(
        [pose.x_m + ranges * np.cos(angles), pose.y_m + ranges * np.sin(angles)], axis=-1
    )
