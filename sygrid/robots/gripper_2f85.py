"""Dimensions of the two-finger parallel gripper the cell uses, a Robotiq 2F-85 look-alike: the one place for the
numbers that the simulated gripper (``sim.gripper_model``, MuJoCo geoms) and the grasp planner
(``robot.grasp_geometry.GripperGeometry``, collision boxes) both build from.

Frames: the flange frame (z out of the flange) and the TCP frame, ``TCP_OFFSET_M`` along the flange z axis, at the
centre of the pads (``GraspAnnotation``'s convention: z the approach direction, x the line between the pads). The
gripper is mirror-symmetric about the TCP's yz plane; per finger, from the inside out: a pad, then a finger link.
Lengths in metres; x sizes are along the line between the pads, y across the pads, z along the approach.
"""

from __future__ import annotations

from sygrid.transforms import make_T

#: Fully open width between the pads.
STROKE_M = 0.085
#: Grip force range (force on each pad) and finger speed range of the 2F-85 (Robotiq's specification).
FORCE_RANGE_N = (20.0, 235.0)
SPEED_RANGE_M_S = (0.02, 0.15)
#: The TCP (the pads' centre) along the flange z axis.
TCP_OFFSET_M = 0.145
#: The TCP in the flange frame (read-only).
T_FLANGE_TCP = make_T(t=(0.0, 0.0, TCP_OFFSET_M))
T_FLANGE_TCP.flags.writeable = False

#: Each pad: thickness (x, its inner face at half the opening), width (y) and length (z, centred on the TCP).
PAD_THICKNESS_M = 0.008
PAD_WIDTH_M = 0.022
PAD_LENGTH_M = 0.040

#: Each finger link, right behind its pad in x: thickness (x), width (y), and its z span in the TCP frame.
LINK_THICKNESS_M = 0.016
LINK_WIDTH_M = 0.022
LINK_Z_RANGE_M = (-0.043, 0.009)

#: The housing: half sizes in x and y about the TCP's z axis, and its z span in the TCP frame.
HOUSING_HALF_XY_M = (0.043, 0.031)
HOUSING_Z_RANGE_M = (-0.130, -0.030)

#: The coupling between the flange and the housing: a cylinder on the flange z axis from the flange face.
COUPLING_RADIUS_M = 0.0375
COUPLING_LENGTH_M = 0.015
