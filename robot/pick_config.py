"""``PickerConfig``: the settings of the pick cycle (``robot.picker``), the ``[picker]`` section of a cell file."""

from __future__ import annotations

from dataclasses import dataclass

from sygrid.errors import ConfigError

#: ``PickerConfig.nudge_contact``: the force-limited press (any cell) or position control only (simulated cells).
NUDGE_CONTACTS = ("force_limited", "position")


@dataclass(frozen=True)
class PickerConfig:
    """Settings of the cycle. Speeds in m/s (straight lines) and rad/s (joint moves); None: the robot's default.

    approach_speed_m_s: pre-grasp -> grasp and grasp -> lift; transit_linear_speed_m_s: lift -> pre-grasp.
    approach_max_force_n: the pre-grasp -> grasp line is a guarded move: where the TCP force passes this [N] the arm
    stops, backs out to the lift and the attempt fails "contact" (a finger met a part that lies elsewhere than
    estimated). Below the controller's force limit (150 N on a UR5e), so that such a contact ends before a
    protective stop, and above what a light part pushed aside reads; None: unguarded. final_approach_m /
    final_approach_speed_m_s: the last stretch of that line (metres short of the grasp) runs at this slower speed:
    the guard stops the arm within v^2 / (2 a) + v * (one control tick) of where the force passed it, so a finger
    meeting a stiff part at the approach speed overshoots by millimetres and presses it past the controller's
    limit (a protective stop), where at the final speed it stops within a fraction of a millimetre.
    final_approach_contact_detection: the last stretch also runs under the controller's own contact detection
    (``URRobot.move_l(stop_on_contact=True)``), which stops the arm on the tick a contact shows rather than after a
    round trip through this process (whose reaction a loaded computer delays by tens of milliseconds) and moves it
    back to where the contact began.
    transit_speed_rad_s: joint moves (to the lift, to the place pose). grip_force_n: closing force (None: the
    gripper's default). max_attempts_per_cycle: planned grasps tried in one cycle before looking again.
    slip_width_tolerance_m: after lifting, an opening smaller than the narrowest width the part can be held at
    (``hold_any_width``; else the planned grasp width) less this means the part slipped out; hold_any_width: a part
    held at another of its widths than the planned one is held (False: only near the planned width; the fingers
    closing on a nut's faces instead of its flats then drop it back into the bin as "slipped"); slip_settle_s: how
    long the gripper may report no object (its fingers settling) before the part counts as lost.
    still_there_distance_m: a part of the same model this close to a picked one in the next frame means the pick
    failed. max_failures_per_part / exclusion_distance_m: after this many failed attempts on parts of one model
    within this distance of each other, parts there are no longer planned (checked on the poses planned from,
    refined ones included).
    open_tolerance_m / open_timeout_s: the fingers must reach a commanded opening less this within this time (a
    gripper may report "stopped" while its fingers still move); release_tries: how often the gripper is opened at
    the place pose before the part counts as stuck. release_drop_m: at the place pose the arm goes this far straight
    down along the tool's approach before letting go, guarded by ``approach_max_force_n`` (it stops where the held
    part meets what already lies in the tray), and back up after: a part let go lower bounces less, and off the
    tray less often (0: let go at the place pose; the place pose less this must still clear the tray's rim).
    reconnect_timeout_s: how long recovery keeps trying to reach a controller that does not answer (a network link
    that is down). max_nudges / max_nudges_per_part: nudges per run (0: never nudge) and per location (within
    ``exclusion_distance_m``); a nudge is not a failed cycle.
    min_unseen_area_m2: with no part estimated in the bin, a bin whose depth shows at least this much of it covered
    (something above the floor, ``PlannerLike.pile_area_m2``) holds parts the detector does not find or whose
    estimates land outside it: the run stops with "parts_unseen", not "bin_empty". 1 cm2 is a third of a nut's top
    seen from above. relooks: frames taken again in a cycle where the camera sees parts but the verification
    refused every pose (stereo noise and masks change from frame to frame; then the run stops with
    "parts_unseen"), or refused some and nothing else is safe to pick or to nudge (then "nothing_safe").
    look_while_placing: the next cycle's first frame is taken at the place pose with the part still held (the
    observe pose: the camera's view of the bin is clear) and perceived while the arm lets go, so that the cycle
    waits only for what is left of it; False: every frame is taken at the start of its cycle.
    nudge_contact: how a nudge touches its part. "force_limited": straight down from ``nudge_approach_m`` above the
    planned press until the controller detects the contact (``move_until_contact`` at ``nudge_contact_speed_m_s``,
    at most ``nudge_overtravel_m`` past the planned press), then the drag in force mode pressing with
    ``nudge_press_force_n``; a robot without force-limited motion refuses nudges. "position": straight lines to
    the planned press (``press_depth_m`` into the part's estimated top) and the drag, under position control only
    (simulated cells; a hardware cell file refuses it).
    min_held_width_m: fingers that stopped at least this far apart hold something, even when the gripper reports no
    object, and fingers closer than this after lifting hold nothing. A gripper detects an object when its fingers
    stop short of the commanded position by more than a tolerance, so a thin sheet squeezed between the pads can
    read "no object" while fingers closed on air read 0 (the simulated gripper's pads squeeze the 2 mm sheet of an
    L-bracket to as little as one register count, 0.33 mm). The default, under one count, suits a gripper whose
    empty close reads exactly closed, as the simulated one does; on hardware, ``sygrid calibrate gripper`` makes
    closed on air read 0, and the cell raises this to the calibration's hold threshold (``robot.cell_setup``).
    """

    max_cycles: int = 50
    max_attempts_per_cycle: int = 3
    max_failed_cycles: int = 3
    approach_speed_m_s: float | None = 0.25
    transit_linear_speed_m_s: float | None = 0.5
    approach_accel_m_s2: float | None = 1.2
    approach_max_force_n: float | None = 30.0
    final_approach_m: float = 0.03
    final_approach_speed_m_s: float = 0.05
    final_approach_contact_detection: bool = True
    transit_speed_rad_s: float | None = 2.0
    transit_accel_rad_s2: float | None = 3.0
    grip_force_n: float | None = None
    slip_width_tolerance_m: float = 0.004
    hold_any_width: bool = True
    slip_settle_s: float = 0.5
    still_there_distance_m: float = 0.01
    max_failures_per_part: int = 2
    exclusion_distance_m: float = 0.015
    open_tolerance_m: float = 0.003
    open_timeout_s: float = 2.0
    release_tries: int = 2
    release_drop_m: float = 0.0
    reconnect_timeout_s: float = 30.0
    max_nudges: int = 8
    max_nudges_per_part: int = 2
    min_unseen_area_m2: float = 1e-4
    relooks: int = 2
    look_while_placing: bool = True
    min_held_width_m: float = 0.00025
    nudge_contact: str = "force_limited"
    nudge_press_force_n: float = 25.0
    nudge_contact_speed_m_s: float = 0.01
    nudge_approach_m: float = 0.015
    nudge_overtravel_m: float = 0.01

    def __post_init__(self) -> None:
        for name in (
            "max_cycles",
            "max_attempts_per_cycle",
            "max_failed_cycles",
            "max_failures_per_part",
            "release_tries",
            "max_nudges_per_part",
        ):
            if not (isinstance(getattr(self, name), int) and getattr(self, name) >= 1):
                raise ConfigError(f"PickerConfig.{name} must be an integer >= 1, got {getattr(self, name)!r}")
        for name in ("hold_any_width", "final_approach_contact_detection", "look_while_placing"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(f"PickerConfig.{name} must be true or false, got {getattr(self, name)!r}")
        for name in ("max_nudges", "relooks"):
            if not (isinstance(getattr(self, name), int) and getattr(self, name) >= 0):
                raise ConfigError(f"PickerConfig.{name} must be an integer >= 0, got {getattr(self, name)!r}")
        for name in (
            "slip_width_tolerance_m", "still_there_distance_m", "exclusion_distance_m", "open_tolerance_m",
            "open_timeout_s", "slip_settle_s", "reconnect_timeout_s", "min_unseen_area_m2", "min_held_width_m",
            "release_drop_m",
        ):  # fmt: skip
            if not getattr(self, name) >= 0:
                raise ConfigError(f"PickerConfig.{name} must be >= 0, got {getattr(self, name)!r}")
        if self.approach_max_force_n is not None and not self.approach_max_force_n > 0:
            raise ConfigError(
                f"PickerConfig.approach_max_force_n must be > 0 or absent, got {self.approach_max_force_n!r}"
            )
        if not self.final_approach_m >= 0:
            raise ConfigError(f"PickerConfig.final_approach_m must be >= 0, got {self.final_approach_m!r}")
        if not self.final_approach_speed_m_s > 0:
            raise ConfigError(
                f"PickerConfig.final_approach_speed_m_s must be > 0, got {self.final_approach_speed_m_s!r}"
            )
        if self.nudge_contact not in NUDGE_CONTACTS:
            raise ConfigError(f"PickerConfig.nudge_contact must be one of {NUDGE_CONTACTS}, got {self.nudge_contact!r}")
        for name in ("nudge_press_force_n", "nudge_contact_speed_m_s", "nudge_approach_m", "nudge_overtravel_m"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"PickerConfig.{name} must be > 0, got {getattr(self, name)!r}")
