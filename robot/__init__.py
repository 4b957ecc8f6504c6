"""Hardware-facing runtime: the UR5e, the gripper, hand-eye calibration, the grasp planner and the pick cycle.

Import the modules themselves (nothing is imported here, so ``import robot`` stays cheap and needs no ur_rtde):

- ``robot.ur``: ``URRobot`` over ur_rtde (connect, recover, checked motion with 4x4 poses); ``robot.ur_config``
  (``URConfig``, ``WorkspaceBox``, the pre-send checks) and ``robot.ur_errors`` are re-exported by it.
- ``robot.gripper``: ``Gripper``, the Robotiq URCap socket and digital-output kinds, ``make_gripper``.
- ``robot.calibration`` (pose set, capture, file), ``robot.hand_eye`` (the solver), ``robot.charuco``: eye-to-hand
  hand-eye calibration with a ChArUco board.
- ``robot.grasp`` (the planner), ``robot.grasps``, ``robot.grasp_geometry``, ``robot.grasp_scene``: grasp candidates
  and planning.
"""
