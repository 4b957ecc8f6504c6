"""UR5e constants shared by the simulated cell and the real-robot runtime.

Kinematics and link masses/centres of mass are Universal Robots' published "DH parameters for calculations of
kinematics and dynamics" (e-Series, software 5.x). Frames follow the controller's DH convention: the base frame is
the one the controller reports ``actual_TCP_pose`` in, which is the ROS ``base_link`` frame rotated 180 degrees
about z. Link ``i`` frame is DH frame ``i`` (after joint ``i``), and each centre of mass is given in it.

UR publishes no inertia tensors for the UR5e ("negligible due to their smaller size"), so the simulation derives
them from solid cylinders around the links (see ``sim.world``).

Speed and acceleration limits are the ones the ur_rtde client enforces on ``moveJ`` arguments
(``UR_JOINT_VELOCITY_MAX``, ``UR_JOINT_ACCELERATION_MAX``); the joint speed matches the UR5e data sheet
(180 deg/s on every joint). Torque limits are the e-Series joint sizes (size 3: 150 N m, size 1: 28 N m).
"""

from __future__ import annotations

import math

import numpy as np

# ---------------------------------------------------------------------------------------------- kinematics (DH)

#: DH ``d`` per joint (m).
DH_D_M = np.array([0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996])
#: DH ``a`` per joint (m). UR's "a" is Wikipedia's "r".
DH_A_M = np.array([0.0, -0.425, -0.3922, 0.0, 0.0, 0.0])
#: DH ``alpha`` per joint (rad).
DH_ALPHA_RAD = np.array([math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0])

NUM_JOINTS = 6

#: Joint names as the ROS driver and the MuJoCo model name them, base first.
JOINT_NAMES = (
    "shoulder_pan",
    "shoulder_lift",
    "elbow",
    "wrist_1",
    "wrist_2",
    "wrist_3",
)

#: Link names (DH link ``i`` moves with joint ``i``).
LINK_NAMES = ("shoulder_link", "upper_arm_link", "forearm_link", "wrist_1_link", "wrist_2_link", "wrist_3_link")

# ---------------------------------------------------------------------------------------------- joint limits

_TWO_PI = 2.0 * math.pi
#: (6, 2) lower/upper position limits (rad): +-2 pi on every joint, the elbow +-pi (it would hit itself beyond).
JOINT_LIMITS_RAD = np.array([[-_TWO_PI, _TWO_PI]] * 6)
JOINT_LIMITS_RAD[2] = [-math.pi, math.pi]
#: Maximum joint speed (rad/s), every joint.
MAX_JOINT_SPEED_RAD_S = np.full(NUM_JOINTS, 3.14)
#: Maximum joint acceleration (rad/s^2), every joint (the ur_rtde client's argument limit).
MAX_JOINT_ACCEL_RAD_S2 = np.full(NUM_JOINTS, 40.0)
#: Maximum joint torque (N m): size-3 joints for base, shoulder, elbow; size-1 joints for the wrists.
MAX_JOINT_TORQUE_NM = np.array([150.0, 150.0, 150.0, 28.0, 28.0, 28.0])
#: Tool-speed and tool-acceleration limits the ur_rtde client enforces on moveL (m/s, m/s^2).
MAX_TOOL_SPEED_M_S = 3.0
MAX_TOOL_ACCEL_M_S2 = 150.0

#: Home configuration (rad): the arm upright-bent "L" pose that URSim starts in.
HOME_Q = np.array([0.0, -math.pi / 2, math.pi / 2, -math.pi / 2, -math.pi / 2, 0.0])

# ---------------------------------------------------------------------------------------------- dynamics

#: Link masses (kg), links 1..6.
LINK_MASSES_KG = np.array([3.761, 8.058, 2.846, 1.37, 1.3, 0.365])
#: (6, 3) centres of mass (m), link ``i`` in DH frame ``i``.
LINK_COMS_M = np.array(
    [
        [0.0, -0.02561, 0.00193],
        [0.2125, 0.0, 0.11336],
        [0.15, 0.0, 0.0265],
        [0.0, -0.0018, 0.01634],
        [0.0, 0.0018, 0.01634],
        [0.0, 0.0, -0.001159],
    ]
)
#: Mass of the base housing (kg); it does not move, so it matters only for display and for a mobile base.
BASE_MASS_KG = 4.0
#: Rated payload (kg).
PAYLOAD_MAX_KG = 5.0
#: Reach from the base axis to the flange centre (m), data sheet.
REACH_M = 0.85


# ---------------------------------------------------------------------------------------------- link geometry

#: Simple collision/display geometry: per body, cylinders ``(from_xyz, to_xyz, radius)`` in metres. Body ``0`` is the
#: fixed base housing (base frame); body ``i`` (1..6) is link ``i`` in its *joint frame*: DH frame ``i-1`` rotated
#: by ``q_i`` about its z axis, so that joint ``i`` turns about the body's z axis through its origin, and DH frame
#: ``i`` sits at ``Tz(d_i) Tx(a_i) Rx(alpha_i)`` in it. Sizes follow the UR5e's outline drawing (housings about
#: 120 mm across, upper-arm tube offset 138 mm and forearm tube 7 mm along the shoulder axis); good enough for
#: collisions with the cell, not for a photo.
LINK_CYLINDERS_M: tuple[tuple[tuple[tuple[float, float, float], tuple[float, float, float], float], ...], ...] = (
    (((0.0, 0.0, 0.0), (0.0, 0.0, 0.086), 0.075),),
    (
        ((0.0, 0.0, 0.086), (0.0, 0.0, 0.16), 0.06),
        ((0.0, 0.07, 0.1625), (0.0, -0.085, 0.1625), 0.06),
    ),
    (
        ((0.0, 0.0, 0.085), (0.0, 0.0, 0.19), 0.06),
        ((-0.05, 0.0, 0.138), (-0.375, 0.0, 0.138), 0.045),
        ((-0.425, 0.0, 0.09), (-0.425, 0.0, 0.185), 0.05),
    ),
    (
        ((0.0, 0.0, -0.035), (0.0, 0.0, 0.09), 0.047),
        ((-0.045, 0.0, 0.007), (-0.35, 0.0, 0.007), 0.035),
    ),
    (((0.0, 0.0, -0.035), (0.0, 0.0, 0.09), 0.04),),
    (((0.0, 0.0, -0.04), (0.0, 0.0, 0.055), 0.04),),
    (
        ((0.0, 0.0, -0.045), (0.0, 0.0, 0.085), 0.04),
        ((0.0, 0.0, 0.085), (0.0, 0.0, 0.0996), 0.0315),
    ),
)
#: Axis (in the joint frame) of the solid cylinder each link's inertia is modelled as, with its radius and length (m).
LINK_INERTIA_CYLINDERS = (
    ("z", 0.06, 0.15),
    ("x", 0.054, 0.425),
    ("x", 0.04, 0.392),
    ("z", 0.045, 0.12),
    ("z", 0.045, 0.12),
    ("z", 0.04, 0.08),
)


def joint_index(name: str) -> int:
    """Index (0..5) of a joint by its name; the error lists the valid names."""
    try:
        return JOINT_NAMES.index(name)
    except ValueError:
        raise ValueError(f"unknown UR5e joint {name!r}; valid names: {list(JOINT_NAMES)}") from None


for _array in (
    DH_D_M, DH_A_M, DH_ALPHA_RAD, JOINT_LIMITS_RAD, MAX_JOINT_SPEED_RAD_S, MAX_JOINT_ACCEL_RAD_S2,
    MAX_JOINT_TORQUE_NM, HOME_Q, LINK_MASSES_KG, LINK_COMS_M,
):  # fmt: skip
    _array.flags.writeable = False  # shared constants: a caller that needs to change one must copy it
