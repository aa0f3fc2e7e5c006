"""The hallway mission planner of seed 001 section 3.2, as pure logic (no Zenoh, no clock).

The planner sees only what reaches the CEDDP: per robot, the latest value of each LIDAR beam topic
and when it was taken. Robot 1, the leader, follows the corridor and turns at corners on its own
8 ranges; robots 2 and 3 watch ahead for obstacles in their lanes; when both are clear every
robot gets the leader's velocity, so the fleet moves in parallel (seed 001 Figure 17), and a
follower seen out of its lane gets a turn rate on top of it to get back.

Like the robots of the seed, the planner trusts the data it is given. That is the point: when the
network delivers beams too rarely or too late, it turns late or stops for obstacles that are not
there, and the judge (``arpz.mission.judge``) says so. The safety rules: data older than
``max_age_s`` stops the fleet rather than steer it (docs/simulation.md, "Staleness"); a robot
closer than ``clearance_m`` to something ahead or at 45 degrees stops it too; and a follower is
steered back into its lane from its own side beams when it is not where the leader's velocity
alone would keep it (docs/simulation.md, "Formation"): a robot that missed commands the others
executed (its link died, its process froze) breaks the formation, and without that a follower
drives on with the wrong heading into a wall.
"""

from __future__ import annotations

import math
from typing import Literal

import msgspec
import numpy as np

from arpz.mission.lidar import BEAM_ANGLES_DEG, DEFAULT_MAX_RANGE_M, beam_of_topic, beam_topic
from arpz.mission.missed import CatchUp, Missed, MissedCommands
from arpz.mission.vocabulary import STOP, EventKind, MissionEvent, VelocityCommand
from arpz.mission.world import World

Phase = Literal["waiting", "following", "turning", "home"]
Hold = Literal["stale", "obstacle"]

#: The leader's beams the corridor follower reads (180, straight behind, is never used).
LEADER_BEAMS_DEG = (0, 45, 90, 135, 225, 270, 315)
#: The side beams that give a robot's heading and offset in its corridor (45/90/135 left,
#: 315/270/225 right).
SIDE_BEAMS_DEG = (45, 90, 135, 225, 270, 315)


class PlannerSettings(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """What the planner knows of the world and how it drives; ``for_world`` fills the map part."""

    leader: str = "robot1"
    followers: tuple[str, ...] = ("robot2", "robot3")
    #: Corridor width, for centring on one wall when the other side opens (near a corner).
    corridor_width_m: float = 4.0
    #: Direction of every corner: "right" for a clockwise loop.
    turn: Literal["right", "left"] = "right"
    corners: int = 4
    #: The leader's front range at its home pose: after the last corner it stops there.
    home_front_m: float = 10.0
    #: Each follower's front range at its home pose (``for_world``): once the leader is home, a
    #: follower short of its own mark drives on to it (at most ``home_reach_m``), so that one
    #: left behind by a robot that drove on without commands still stops at home. A follower
    #: not named here stops with the leader.
    home_fronts_m: dict[str, float] = msgspec.field(default_factory=dict)
    home_reach_m: float = 2.0
    cruise_speed_m_s: float = 0.8
    turn_radius_m: float = 1.0
    #: A follower reading closer than this on an obstacle beam stops the fleet.
    obstacle_range_m: float = 1.0
    #: ... and it must read this much further again before the fleet moves (no chattering).
    clear_margin_m: float = 0.2
    obstacle_beams_deg: tuple[int, ...] = (0,)
    #: Any robot (the leader too) reading closer than this on a clearance beam stops the fleet:
    #: the last guard against a robot heading into a wall at a slant its front beam does not
    #: see, as one whose formation broke would (nominal runs read 0.86 m or more on these).
    clearance_m: float = 0.45
    clearance_beams_deg: tuple[int, ...] = (0, 45, 315)
    #: Data older than this stops the fleet: set it to about 3 deadline periods of the beams.
    max_age_s: float = 0.3
    #: Commands a robot has not acknowledged for longer than this (``on_command_ack``) stop the
    #: fleet as stale data does: that robot may not be obeying (its commands are lost on the way
    #: while its readings still arrive, a downlink-only failure) and drives on its last command
    #: until its 0.5 s watchdog stops it, while the others would go on as planned. Four of the
    #: command writer's 0.1 s heartbeat periods: a robot acknowledges within one, and 0.4 s
    #: were never reached in the lab's lossy and bandwidth-limited missions (docs/simulation.md,
    #: "Commands acknowledged"). ``math.inf``: not watched.
    max_command_age_s: float = 0.4
    #: Acknowledgements up to this late are normal (the lab measured one 50 ms tick at most,
    #: on clean and 15 % lossy QUIC links); beyond, a robot is taken as hearing nothing since
    #: its oldest unacknowledged command, driving on the one before ...
    command_ack_slack_s: float = 0.15
    #: ... until its watchdog stops it after this long (the simulated body's
    #: ``command_timeout_s``, the robot's ``[watchdog]`` deadline for ``velocity``). When it
    #: acknowledges again, the heading that put it away from the plan's is turned back
    #: (``arpz.mission.missed``) at up to ``catch_up_rad_s``.
    command_timeout_s: float = 0.5
    catch_up_rad_s: float = 0.8
    max_range_m: float = DEFAULT_MAX_RANGE_M
    #: After a turn, the next corner counts only once the front has read this much beyond the
    #: turn point, on a reading taken after the turn: a pre-turn reading cannot trigger a new turn.
    rearm_margin_m: float = 1.0
    lateral_gain_rad_m: float = 0.6
    heading_gain_1_s: float = 1.5
    max_heading_correction_rad: float = 0.5
    max_omega_rad_s: float = 1.5
    #: How far the three beams on one side may disagree about the wall before that side is ignored
    #: (it then sees through an opening, not along a straight wall).
    wall_fit_tolerance_m: float = 0.15
    #: Home counts only while the leader is this parallel to the walls, so that a front beam
    #: slanting onto a side wall during a correction is not taken for the home mark ...
    home_alignment_rad: float = 0.1
    #: ... and only once, after the last corner, the front beam has read beyond the home mark or
    #: this long has passed since the turn ended: at a corner's exit the side beams can see two
    #: walls and pass a leader turned 16 degrees as parallel (the lab, over TCP in bursts).
    home_settle_s: float = 1.0
    #: While the fleet is held for stale data, a change of culprit is reported at most this often.
    stale_report_interval_s: float = 1.0
    #: Each follower's lane: its offset from the leader on the first leg, (ahead_m, left_m) in
    #: the leader's frame at home (``for_world`` takes it from the homes). It turns with the fleet
    #: at every corner. A follower without a lane here is only kept parallel to the leader.
    lanes_m: dict[str, tuple[float, float]] = msgspec.field(default_factory=dict)
    #: A follower further than this from its lane, or turned more than ``formation_tolerance_rad``
    #: away from the leader's heading (both seen from the side beams of the two robots), is
    #: steered back on top of the leader's velocity until it is within half of both again.
    lane_tolerance_m: float = 0.15
    formation_tolerance_rad: float = 0.06
    #: ... once it has been seen outside them this many times in a row (one odd scan is not
    #: enough) ...
    formation_ticks: int = 3
    #: ... seen on sides whose three beams fit one straight wall within this: stricter than
    #: ``wall_fit_tolerance_m``, as near a corner three beams can hit two walls and still fit a
    #: line well enough to centre the leader on, not to judge another robot's place by.
    formation_fit_tolerance_m: float = 0.05
    #: A lane is never taken closer than this to a wall (the robot's centre), whatever the
    #: leader's place: a follower is not steered towards a wall to keep its offset.
    lane_wall_margin_m: float = 0.6

    def __post_init__(self) -> None:
        def need(ok: bool, message: str) -> None:
            if not ok:
                raise ValueError(f"PlannerSettings: {message}")

        need(self.leader not in self.followers, f"leader {self.leader!r} is also a follower")
        need(len(set(self.followers)) == len(self.followers), "followers repeat a name")
        need(self.corners >= 1, f"corners must be >= 1, got {self.corners}")
        need(self.max_age_s > 0.0, f"max_age_s must be > 0, got {self.max_age_s}")
        need(
            self.max_command_age_s > 0.0,
            f"max_command_age_s must be > 0 (math.inf: not watched), got {self.max_command_age_s}",
        )
        need(self.cruise_speed_m_s > 0.0, "cruise_speed_m_s must be > 0")
        need(self.turn_radius_m > 0.0, "turn_radius_m must be > 0")
        need(
            0.0 < self.obstacle_range_m < self.turn_point_m,
            f"obstacle_range_m must be > 0 and below the turn point {self.turn_point_m:.2f} m",
        )
        need(
            self.turn_point_m + self.rearm_margin_m < self.max_range_m,
            f"turn point {self.turn_point_m:.2f} m + rearm_margin_m must be below max_range_m",
        )
        need(
            0.0 < self.home_front_m < self.max_range_m,
            f"home_front_m must be > 0 and below max_range_m {self.max_range_m} m "
            f"(got {self.home_front_m}): the leader cannot see its home mark",
        )
        for deg in (*self.obstacle_beams_deg, *self.clearance_beams_deg):
            need(deg in BEAM_ANGLES_DEG, f"obstacle beam {deg} is not one of {BEAM_ANGLES_DEG}")
        need(
            0.0 < self.clearance_m <= self.obstacle_range_m,
            f"clearance_m must be > 0 and at most obstacle_range_m {self.obstacle_range_m} m",
        )
        for robot in self.lanes_m:
            need(robot in self.followers, f"lanes_m names {robot!r}, which is not a follower")
        for robot, front_m in self.home_fronts_m.items():
            need(robot in self.followers, f"home_fronts_m names {robot!r}, not a follower")
            need(
                0.0 < front_m < self.max_range_m,
                f"home_fronts_m[{robot!r}] must be > 0 and below max_range_m, got {front_m}",
            )
        need(self.home_reach_m >= 0.0, "home_reach_m must be >= 0")
        need(self.home_settle_s >= 0.0, "home_settle_s must be >= 0")
        need(self.lane_tolerance_m > 0.0, "lane_tolerance_m must be > 0")
        need(self.formation_tolerance_rad > 0.0, "formation_tolerance_rad must be > 0")
        need(self.formation_ticks >= 1, "formation_ticks must be >= 1")
        need(self.command_ack_slack_s > 0.0, "command_ack_slack_s must be > 0")
        need(self.command_timeout_s > 0.0, "command_timeout_s must be > 0")
        need(self.catch_up_rad_s >= 0.0, "catch_up_rad_s must be >= 0 (0: no catch-up)")
        need(self.formation_fit_tolerance_m > 0.0, "formation_fit_tolerance_m must be > 0")
        need(
            0.0 <= self.lane_wall_margin_m < self.corridor_width_m / 2.0,
            "lane_wall_margin_m must be >= 0 and below half the corridor width",
        )

    @property
    def turn_point_m(self) -> float:
        """Front range at which a turn of ``turn_radius_m`` ends on the next corridor's middle."""
        return self.corridor_width_m / 2.0 + self.turn_radius_m

    @property
    def robots(self) -> tuple[str, ...]:
        return (self.leader, *self.followers)

    @classmethod
    def for_world(cls, world: World, **overrides: object) -> PlannerSettings:
        """Settings matching a map: fleet, corridor width, turn direction, the leader's home mark.

        ``home_front_m`` is what the leader's front beam reads at its home pose: the planner's
        only way to recognise home with a LIDAR and no map matching; ``home_fronts_m`` the same
        for each follower (where its front beam sees a wall within range). ``lanes_m`` is each
        follower's home offset from the leader, in the leader's frame at home.
        """
        max_range_m = overrides.get("max_range_m", DEFAULT_MAX_RANGE_M)
        if not isinstance(max_range_m, float | int):
            raise TypeError(f"max_range_m must be a number, got {max_range_m!r}")

        def front_at_home(robot: str) -> float:
            pose = world.homes[robot]
            ranges = world.ray_ranges_m(
                pose.x_m, pose.y_m, np.array([pose.theta_rad]), float(max_range_m)
            )
            return float(ranges[0])

        home = world.homes[world.leader]
        front_m = front_at_home(world.leader)
        ahead = (math.cos(home.theta_rad), math.sin(home.theta_rad))
        followers = [r for r in world.robots if r != world.leader]
        lanes: dict[str, tuple[float, float]] = {}
        for robot in followers:
            dx = world.homes[robot].x_m - home.x_m
            dy = world.homes[robot].y_m - home.y_m
            lanes[robot] = (dx * ahead[0] + dy * ahead[1], dy * ahead[0] - dx * ahead[1])
        fields: dict[str, object] = {
            "leader": world.leader,
            "followers": followers,
            "corridor_width_m": world.corridor_width_m,
            "turn": "right" if world.direction == "clockwise" else "left",
            "home_front_m": front_m,
            "home_fronts_m": {
                robot: mark
                for robot in followers
                if (mark := front_at_home(robot)) < float(max_range_m)
            },
            "lanes_m": lanes,
        }
        fields.update(overrides)
        return msgspec.convert(fields, type=cls)


class HallwayPlanner:
    """The CEDDP's planning component for the hallway mission.

    Feed it every beam value that passes cache control (``on_range`` / ``on_topic``) and call
    ``tick(now_s)`` at the command rate; send each returned command to that robot's actuation and
    ``pop_events()`` to the dashboard and the judge. All times are on one clock (``now_s`` and the
    stamps); nothing here reads a clock, so tests drive it with any numbers.
    """

    def __init__(self, settings: PlannerSettings) -> None:
        self.settings = settings
        self._latest: dict[tuple[str, int], tuple[float, float]] = {}
        self._events: list[MissionEvent] = []
        self._phase: Phase = "waiting"
        self._hold: Hold | None = None
        self._hold_since_s = 0.0
        self._corners_done = 0
        self._turned_rad = 0.0
        self._armed = True
        self._turn_end_s = -math.inf
        self._last_tick_s: float | None = None
        self._last_command = STOP
        #: the reading (robot, beam) the fleet is held for, or (robot, None): its commands
        self._stale_culprit: tuple[str, int | None] | None = None
        #: per robot, when the oldest command it has not acknowledged was sent (planner clock)
        self._unacked_since: dict[str, float] = {}
        #: what robots that heard no commands drove meanwhile, and turning them back
        self._missed = MissedCommands(
            settings.robots,
            slack_s=settings.command_ack_slack_s,
            timeout_s=settings.command_timeout_s,
        )
        self._catch_up = CatchUp(settings.catch_up_rad_s)
        #: once the leader is home: followers stopped at their own mark, and how far each drove
        self._homed: set[str] = set()
        self._home_driven_m: dict[str, float] = {}
        self._home_speed: dict[str, float] = {}
        self._stale_reported_s = -math.inf
        #: followers being steered back into their lane (entered outside the tolerances, left
        #: within half of them)
        self._off_lane: set[str] = set()
        #: per follower, consecutive ticks it was seen outside the tolerances (not yet steered)
        self._off_lane_ticks: dict[str, int] = {}

    @property
    def phase(self) -> Phase:
        return self._phase

    @property
    def hold(self) -> Hold | None:
        """Why the fleet is held still right now, if it is."""
        return self._hold

    @property
    def corners_done(self) -> int:
        return self._corners_done

    def on_range(self, robot: str, beam_deg: int, range_m: float, stamp_s: float) -> bool:
        """Take one beam value. ``stamp_s`` is when it was measured on the planner's clock (or, if
        clocks are not shared, when it arrived). Returns False if it was ignored: unknown robot,
        not a number, or older than the value already held (the network may reorder)."""
        if beam_deg not in BEAM_ANGLES_DEG:
            raise ValueError(f"no beam at {beam_deg} degrees; beams: {BEAM_ANGLES_DEG}")
        if robot not in self.settings.robots or math.isnan(range_m):
            return False
        key = (robot, beam_deg)
        held = self._latest.get(key)
        if held is not None and held[1] > stamp_s:
            return False
        self._latest[key] = (min(max(range_m, 0.0), self.settings.max_range_m), stamp_s)
        return True

    def on_topic(self, robot: str, topic: str, value: float, stamp_s: float) -> bool:
        """``on_range`` by topic name (``lidar_45``); other topics are ignored (returns False)."""
        beam_deg = beam_of_topic(topic)
        if beam_deg is None:
            return False
        return self.on_range(robot, beam_deg, float(value), stamp_s)

    def on_command_ack(self, robot: str, unacknowledged_since_s: float | None) -> None:
        """How far ``robot`` has acknowledged its commands: ``unacknowledged_since_s`` is when
        the oldest command it has not acknowledged was sent, on the planner's clock; None when
        it acknowledged every one (or nobody can tell). Older than ``max_command_age_s`` at a
        tick, the fleet is held as for stale data. The CEDDP takes it from the reliable
        channel's acknowledgements of each robot's velocity commands (``arpz.ceddp.downlink``),
        the offline loop from its model of them; a planner never told holds for readings only."""
        if unacknowledged_since_s is None:
            self._unacked_since.pop(robot, None)
        elif robot in self.settings.robots:
            self._unacked_since[robot] = unacknowledged_since_s

    def pop_events(self) -> list[MissionEvent]:
        events, self._events = self._events, []
        return events

    def tick(self, now_s: float) -> dict[str, VelocityCommand]:
        """Decide every robot's command for now: STOP for all, or the leader's velocity for all,
        with a turn rate added for a follower that is out of its lane (``lane_error``), and for
        a robot turned away from the plan while it heard no commands (``arpz.mission.missed``)."""
        elapsed_s = 0.0 if self._last_tick_s is None else now_s - self._last_tick_s
        if self._phase == "turning":
            # The turn is measured by what was commanded since the last tick (dead reckoning on
            # commands: the leader has no odometry on the wire, only its 8 ranges).
            self._turned_rad += abs(self._last_command.omega_rad_s) * elapsed_s
        self._catch_up.settle(elapsed_s)
        current = self._current_robots(now_s)
        for missed in self._missed.update(now_s, self._unacked_since, current.__contains__):
            self._owe(missed)
        self._last_tick_s = now_s
        if self._phase == "home":
            return self._homing(now_s, elapsed_s)
        command = self._decide(now_s)
        self._last_command = command
        commands = dict.fromkeys(self.settings.robots, command)
        limit = self.settings.max_omega_rad_s
        if command != STOP and self._phase == "following":
            for robot in self.settings.followers:
                omega_rad_s = self._formation_omega(robot, now_s)
                if omega_rad_s is not None:
                    omega_rad_s = min(max(command.omega_rad_s + omega_rad_s, -limit), limit)
                    commands[robot] = VelocityCommand(command.v_m_s, omega_rad_s)
        for robot in list(self._catch_up.owed):
            if robot in self._off_lane:  # the formation rule steers it, on what it measures
                self._catch_up.owed.pop(robot)
            # held or not (a robot turns on the spot), but only one that hears its commands
            elif robot in current and not self._missed.deaf(robot) and self.phase != "home":
                c = commands[robot]
                commands[robot] = VelocityCommand(
                    c.v_m_s, self._catch_up.add(robot, c.omega_rad_s, limit)
                )
        self._missed.sent(now_s, {r: c.omega_rad_s for r, c in commands.items()})
        return commands

    def _homing(self, now_s: float, elapsed_s: float) -> dict[str, VelocityCommand]:
        """The leader is home: a follower short of its own home mark (its front beam reads
        more) drives on to it in its lane, unless the fleet is held, or it has driven
        ``home_reach_m`` already, once parallel to the walls (turned on the spot until then);
        every other robot stops."""
        s = self.settings
        commands = dict.fromkeys(s.robots, STOP)
        for robot, v_m_s in self._home_speed.items():
            self._home_driven_m[robot] = self._home_driven_m.get(robot, 0.0) + v_m_s * elapsed_s
        self._home_speed = {}
        waiting = [r for r in s.home_fronts_m if r not in self._homed]
        if not waiting or self._held(now_s):
            return commands
        limit = s.max_omega_rad_s
        for robot in waiting:
            front_m, stamp_s = self._latest[(robot, 0)]
            mark_m = s.home_fronts_m[robot]
            driven_m = self._home_driven_m.get(robot, 0.0)
            if front_m > mark_m and driven_m < s.home_reach_m:
                corridor = self._corridor_estimate(robot, now_s)
                if corridor is None or abs(corridor[0]) > s.home_alignment_rad:
                    # not parallel to the walls: its front beam does not measure its way home;
                    # turned on the spot first (held still if its walls are not seen)
                    omega = 0.0 if corridor is None else -s.heading_gain_1_s * corridor[0]
                    commands[robot] = VelocityCommand(0.0, min(max(omega, -limit), limit))
                    continue
                steer = min(max(self._formation_omega(robot, now_s) or 0.0, -limit), limit)
                commands[robot] = VelocityCommand(s.cruise_speed_m_s, steer)
                self._home_speed[robot] = s.cruise_speed_m_s
                continue
            self._homed.add(robot)
            self._emit(
                now_s,
                "home",
                robot,
                f"{robot} lidar_0 reads {front_m:.2f} m (home mark {mark_m:.2f} m), "
                f"{driven_m:.2f} m after {s.leader}: {robot} stops",
                beam_deg=0,
                range_m=front_m,
                age_s=now_s - stamp_s,
            )
        return commands

    def _owe(self, missed: Missed) -> None:
        """A robot heard no commands and drove on its last one: turn it back to the plan's
        heading; the leader, whose heading the fleet is steered by, is matched by the
        followers instead, and a turn in progress counts what it turned."""
        s = self.settings
        error_rad = missed.error_rad
        if abs(error_rad) < math.radians(0.5):
            return
        if not s.catch_up_rad_s:
            who = "not turned back (catch_up_rad_s = 0)"
        elif missed.robot == s.leader:
            matching = [r for r in s.followers if r not in self._off_lane]
            for robot in matching:
                self._catch_up.owe(robot, error_rad)
            if self._phase == "turning":
                self._turned_rad += error_rad if s.turn == "left" else -error_rad
            who = f"{', '.join(matching) or 'no follower'} turned to match"
        elif missed.robot in self._off_lane:
            who = "left to the formation rule, which is steering it"
        else:
            self._catch_up.owe(missed.robot, -error_rad)
            who = "turned back"
        self._emit(
            missed.heard_s,
            "missed_commands",
            missed.robot,
            f"{missed.robot} heard no commands for {missed.heard_s - missed.since_s:.2f} s "
            f"and drove on its last one ({missed.drove_rad_s:+.2f} rad/s): "
            f"{math.degrees(error_rad):+.1f} deg from the plan, {who}",
            age_s=missed.heard_s - missed.since_s,
        )

    def _current_robots(self, now_s: float) -> set[str]:
        """Robots all of whose readings the fleet needs are at most ``command_ack_slack_s``
        old: what they measure reaches the CEDDP on time (a stalled uplink, which would delay
        their acknowledgements as well, makes them older than that long before ``max_age_s``)."""
        late = {
            robot
            for robot, deg in self._needed()
            if (held := self._latest.get((robot, deg))) is None
            or now_s - held[1] > self.settings.command_ack_slack_s
        }
        return set(self.settings.robots) - late

    def lane_error(self, robot: str, now_s: float) -> tuple[float, float] | None:
        """How far a follower is from its lane (m, positive: left of it) and how far it is turned
        from the leader's heading (rad, positive: to its left), from the side beams of both; None
        when either robot's side beams are older than ``max_age_s`` or fit no straight wall.

        Both headings are taken against the walls the robots see, which meet at right angles, so
        the difference is modulo a quarter turn: it does not matter which wall each one sees.
        """
        s = self.settings
        tolerance_m = s.formation_fit_tolerance_m
        lead = self._corridor_estimate(s.leader, now_s, tolerance_m)
        own = self._corridor_estimate(robot, now_s, tolerance_m)
        if lead is None or own is None:
            return None
        heading_rad = math.remainder(own[0] - lead[0], math.pi / 2.0)
        lane_m = self._lane_left_m(robot)
        if lane_m is None:
            return 0.0, heading_rad
        # offsets are from the centreline, left positive: the lane is the leader's offset plus
        # the follower's, kept clear of the walls
        limit_m = s.corridor_width_m / 2.0 - s.lane_wall_margin_m
        lane_at_m = min(max(lead[1] + lane_m, -limit_m), limit_m)
        return own[1] - lane_at_m, heading_rad

    def _lane_left_m(self, robot: str) -> float | None:
        """The follower's lane, left of the leader, on the leg the fleet is on now: the home
        offset turned a quarter turn per corner done (towards the turns)."""
        lane = self.settings.lanes_m.get(robot)
        if lane is None:
            return None
        ahead_m, left_m = lane
        for _ in range(self._corners_done % 4):
            # after a right turn the old "ahead" points left of the new heading; after a left
            # turn, right of it
            ahead_m, left_m = (
                (-left_m, ahead_m) if self.settings.turn == "right" else (left_m, -ahead_m)
            )
        return left_m

    def _formation_omega(self, robot: str, now_s: float) -> float | None:
        """The turn rate to add to the leader's for ``robot`` to get back into its lane, or None
        while it is in it (within the tolerances; once out, until within half of them) or its
        place is not known from fresh beams."""
        s = self.settings
        error = self.lane_error(robot, now_s)
        if error is None:
            return None
        offset_m, heading_rad = error
        lane = (
            "in its lane"
            if abs(offset_m) < 0.005
            else f"{abs(offset_m):.2f} m {'left' if offset_m > 0 else 'right'} of its lane"
        )
        where = f"{robot} is {lane}, turned {math.degrees(heading_rad):+.1f} deg from {s.leader}"
        if robot in self._off_lane:
            if (
                abs(offset_m) <= s.lane_tolerance_m / 2.0
                and abs(heading_rad) <= s.formation_tolerance_rad / 2.0
            ):
                self._off_lane.discard(robot)
                self._emit(now_s, "in_lane", robot, f"{where}: back in its lane")
                return None
        elif abs(offset_m) > s.lane_tolerance_m or abs(heading_rad) > s.formation_tolerance_rad:
            ticks = self._off_lane_ticks[robot] = self._off_lane_ticks.get(robot, 0) + 1
            if ticks < s.formation_ticks:
                return None
            self._off_lane.add(robot)
            self._off_lane_ticks[robot] = 0
            self._emit(now_s, "off_lane", robot, f"{where}: steered back")
        else:
            self._off_lane_ticks[robot] = 0
            return None
        limit = s.max_heading_correction_rad
        wanted_rad = min(max(-s.lateral_gain_rad_m * offset_m, -limit), limit)
        return s.heading_gain_1_s * (wanted_rad - heading_rad)

    def _decide(self, now_s: float) -> VelocityCommand:
        if self._phase == "home" or self._held(now_s):
            return STOP
        if self._phase == "waiting":
            self._phase = "following"
            self._emit(
                now_s, "started", self.settings.leader, "lanes clear, data fresh: fleet starts"
            )
        return self._navigate(now_s)

    def _held(self, now_s: float) -> bool:
        """Whether the fleet must stand still now (stale data, an obstacle), with the events."""
        s = self.settings
        stale = self._stalest(now_s)
        if stale is not None:
            robot, deg, age_s = stale
            culprit_changed = (
                self._hold == "stale"
                and (robot, deg) != self._stale_culprit
                and now_s - self._stale_reported_s >= s.stale_report_interval_s
            )
            if self._hold != "stale" or culprit_changed:
                if deg is None:
                    text = (
                        f"{robot} commands: unacknowledged for {age_s:.2f} s "
                        f"(max {s.max_command_age_s:.2f} s): fleet held"
                    )
                else:
                    what = "no reading yet" if math.isinf(age_s) else f"{age_s:.2f} s old"
                    text = (
                        f"{robot} {beam_topic(deg)}: {what} (max {s.max_age_s:.2f} s): fleet held"
                    )
                if self._hold != "stale":
                    self._enter_hold("stale", now_s)
                self._stale_culprit = (robot, deg)
                self._stale_reported_s = now_s
                self._emit(
                    now_s,
                    "stale_stop",
                    robot,
                    text,
                    beam_deg=deg,
                    age_s=None if math.isinf(age_s) else age_s,
                )
            return True
        if self._hold == "stale":
            commands = self._stale_culprit is not None and self._stale_culprit[1] is None
            why = "commands acknowledged again" if commands else "data fresh again"
            self._leave_hold(now_s, "resumed", why)

        blocked = self._closest_obstacle()
        if blocked is not None:
            robot, deg, range_m, limit_m = blocked
            if self._hold != "obstacle":
                self._enter_hold("obstacle", now_s)
                self._emit(
                    now_s,
                    "obstacle_stop",
                    robot,
                    f"{robot} {beam_topic(deg)} reads {range_m:.2f} m "
                    f"(< {limit_m:.2f} m): fleet stopped",
                    beam_deg=deg,
                    range_m=range_m,
                    age_s=now_s - self._stamp(robot, deg),
                )
            return True
        if self._hold == "obstacle":
            self._leave_hold(now_s, "clear", "all lanes clear ahead")
        return False

    def _navigate(self, now_s: float) -> VelocityCommand:
        """The leader's corridor following, corners and home, on fresh data with clear lanes."""
        s = self.settings
        if self._phase == "turning" and self._turned_rad >= math.pi / 2.0 - 1e-9:
            self._phase = "following"
            self._corners_done += 1
            self._armed = False
            self._turn_end_s = now_s
            self._emit(
                now_s,
                "turn_done",
                s.leader,
                f"corner {self._corners_done} done",
                corner=self._corners_done,
            )

        if self._phase == "following":
            front_m, front_stamp_s = self._latest[(s.leader, 0)]
            rearm_m = s.turn_point_m + s.rearm_margin_m
            if (
                self._corners_done >= s.corners
                and front_stamp_s < self._turn_end_s + s.home_settle_s
            ):
                # home counts once the leader has seen beyond its mark after the last corner,
                # or has had home_settle_s to straighten up: a front beam that slants onto a
                # wall near the corner's exit is not the end wall
                rearm_m = max(rearm_m, s.home_front_m)
            if not self._armed and front_stamp_s >= self._turn_end_s and front_m > rearm_m:
                self._armed = True
            corridor = self._corridor_estimate(s.leader, now_s)
            aligned = corridor is not None and abs(corridor[0]) <= s.home_alignment_rad
            if (
                self._armed
                and self._corners_done >= s.corners
                and front_m <= s.home_front_m
                and aligned
            ):
                self._phase = "home"
                self._emit(
                    now_s,
                    "home",
                    s.leader,
                    f"{s.leader} lidar_0 reads {front_m:.2f} m (home mark {s.home_front_m:.2f} m) "
                    f"after {self._corners_done} corners: fleet stops"
                    + (", followers short of theirs drive on to them" if s.home_fronts_m else ""),
                    beam_deg=0,
                    range_m=front_m,
                    age_s=now_s - front_stamp_s,
                )
                return STOP
            if self._armed and self._corners_done < s.corners and front_m <= s.turn_point_m:
                self._phase = "turning"
                self._turned_rad = 0.0
                self._emit(
                    now_s,
                    "turn_started",
                    s.leader,
                    f"corner {self._corners_done + 1}: {s.leader} lidar_0 reads {front_m:.2f} m "
                    f"(turn point {s.turn_point_m:.2f} m), {now_s - front_stamp_s:.2f} s old",
                    beam_deg=0,
                    range_m=front_m,
                    age_s=now_s - front_stamp_s,
                    corner=self._corners_done + 1,
                )

        if self._phase == "turning":
            sign = -1.0 if s.turn == "right" else 1.0
            return VelocityCommand(s.cruise_speed_m_s, sign * s.cruise_speed_m_s / s.turn_radius_m)
        return VelocityCommand(
            s.cruise_speed_m_s, self._centring_omega(self._corridor_estimate(s.leader, now_s))
        )

    def _stamp(self, robot: str, deg: int) -> float:
        return self._latest[(robot, deg)][1]

    def _needed(self) -> list[tuple[str, int]]:
        """The readings the fleet depends on: the leader's steering beams, every robot's
        obstacle and clearance beams."""
        s = self.settings
        needed = [(s.leader, deg) for deg in LEADER_BEAMS_DEG]
        for robot in s.robots:
            beams = (*s.obstacle_beams_deg, *s.clearance_beams_deg) if robot != s.leader else ()
            needed += [(robot, deg) for deg in dict.fromkeys(beams) if (robot, deg) not in needed]
        return needed

    def _stalest(self, now_s: float) -> tuple[str, int | None, float] | None:
        """The oldest reading the planner needs, if it is older than ``max_age_s``; else the
        robot whose commands have gone unacknowledged longest, if longer than
        ``max_command_age_s`` (beam None). Readings first: a robot cut off both ways is
        reported by its readings, as before commands were watched."""
        s = self.settings
        needed = self._needed()
        worst: tuple[str, int | None, float] | None = None
        for robot, deg in needed:
            held = self._latest.get((robot, deg))
            age_s = math.inf if held is None else now_s - held[1]
            if age_s > s.max_age_s and (worst is None or age_s > worst[2]):
                worst = (robot, deg, age_s)
        if worst is not None:
            return worst
        for robot, since_s in self._unacked_since.items():
            age_s = now_s - since_s
            if age_s > s.max_command_age_s and (worst is None or age_s > worst[2]):
                worst = (robot, None, age_s)
        return worst

    def _closest_obstacle(self) -> tuple[str, int, float, float] | None:
        """The closest reading inside its limit, with the limit: a follower's obstacle beam
        inside the obstacle range, any robot's clearance beam inside the clearance (each limit
        wider by the clear margin while already stopped)."""
        s = self.settings
        margin_m = s.clear_margin_m if self._hold == "obstacle" else 0.0
        closest: tuple[str, int, float, float] | None = None
        for robot in s.robots:
            limits = {deg: s.clearance_m for deg in s.clearance_beams_deg}
            if robot != s.leader:
                limits.update(dict.fromkeys(s.obstacle_beams_deg, s.obstacle_range_m))
            for deg, limit_m in limits.items():
                range_m = self._latest[(robot, deg)][0]
                if range_m < limit_m + margin_m and (closest is None or range_m < closest[2]):
                    closest = (robot, deg, range_m, limit_m)
        return closest

    def _sides(
        self, robot: str, now_s: float, tolerance_m: float
    ) -> tuple[tuple[float, float] | None, tuple[float, float] | None] | None:
        """The (angle, distance) of the wall on each side of a robot (``_wall``), None for the
        whole if any side beam is missing or older than ``max_age_s``."""
        ranges: dict[int, float] = {}
        for deg in SIDE_BEAMS_DEG:
            held = self._latest.get((robot, deg))
            if held is None or now_s - held[1] > self.settings.max_age_s:
                return None
            ranges[deg] = held[0]
        left = self._wall(ranges[45], ranges[90], ranges[135], tolerance_m)
        right = self._wall(ranges[315], ranges[270], ranges[225], tolerance_m)
        return left, right

    def _corridor_estimate(
        self, robot: str, now_s: float, tolerance_m: float | None = None
    ) -> tuple[float, float] | None:
        """A robot's (heading, offset) in the corridor from its side beams, None if unknown (or
        any of them is older than ``max_age_s``).

        Heading is positive when the robot points towards its left wall, offset when it is left
        of the centreline. Each side's three beams (45/90/135 on the left, 315/270/225 on the
        right) give that wall's angle and distance when they all hit one straight wall (within
        ``tolerance_m``, by default ``wall_fit_tolerance_m``); a side that disagrees with itself
        looks through an opening and is ignored.
        """
        s = self.settings
        sides = self._sides(
            robot, now_s, s.wall_fit_tolerance_m if tolerance_m is None else tolerance_m
        )
        if sides is None:
            return None
        left, right = sides
        if left is None and right is None:
            return None
        if left is not None and right is not None:
            heading_rad = (left[0] - right[0]) / 2.0
            offset_m = (right[1] - left[1]) / 2.0  # positive: left of the centreline
        elif left is not None:
            heading_rad = left[0]
            offset_m = s.corridor_width_m / 2.0 - left[1]
        else:
            assert right is not None
            heading_rad = -right[0]
            offset_m = right[1] - s.corridor_width_m / 2.0
        return heading_rad, offset_m

    def _centring_omega(self, corridor: tuple[float, float] | None) -> float:
        """Turn rate that steers the leader onto the centreline, parallel to the walls (with no
        usable wall on either side, the heading is held)."""
        s = self.settings
        if corridor is None:
            return 0.0
        heading_rad, offset_m = corridor
        limit = s.max_heading_correction_rad
        wanted_rad = min(max(-s.lateral_gain_rad_m * offset_m, -limit), limit)
        omega = s.heading_gain_1_s * (wanted_rad - heading_rad)
        return min(max(omega, -s.max_omega_rad_s), s.max_omega_rad_s)

    def _wall(
        self, ahead_m: float, abeam_m: float, behind_m: float, tolerance_m: float
    ) -> tuple[float, float] | None:
        """(angle towards the wall, perpendicular distance) from the 45/90/135-degree beams to one
        side, or None if they do not fit one straight wall.

        For a wall at distance d and a heading turned by psi towards it, the beam at 45 degrees
        reads d / sin(45 + psi) and the one at 135 reads d / sin(45 - psi), which gives
        tan(psi) = (behind - ahead) / (behind + ahead).
        """
        s = self.settings
        if max(ahead_m, abeam_m, behind_m) >= s.max_range_m or min(ahead_m, behind_m) <= 0.0:
            return None
        psi = math.atan((behind_m - ahead_m) / (behind_m + ahead_m))
        quarter = math.pi / 4.0
        d_abeam = abeam_m * math.cos(psi)
        d_ahead = ahead_m * math.sin(quarter + psi)
        d_behind = behind_m * math.sin(quarter - psi)
        if abs(d_ahead - d_abeam) > tolerance_m or abs(d_behind - d_abeam) > tolerance_m:
            return None
        if d_abeam > s.corridor_width_m:
            return None
        return psi, d_abeam

    def _enter_hold(self, hold: Hold, now_s: float) -> None:
        self._hold = hold
        self._hold_since_s = now_s

    def _leave_hold(self, now_s: float, kind: EventKind, why: str) -> None:
        held_s = now_s - self._hold_since_s
        self._hold = None
        self._emit(now_s, kind, self.settings.leader, f"{why} after {held_s:.2f} s: fleet moves")

    def _emit(
        self,
        t_s: float,
        kind: EventKind,
        robot: str,
        text: str,
        *,
        beam_deg: int | None = None,
        range_m: float | None = None,
        age_s: float | None = None,
        corner: int | None = None,
    ) -> None:
        self._events.append(
            MissionEvent(
                t_s=t_s,
                kind=kind,
                robot=robot,
                text=text,
                beam_deg=beam_deg,
                range_m=range_m,
                age_s=age_s,
                corner=corner,
            )
        )
