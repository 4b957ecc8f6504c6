"""Hardware-facing runtime: the UR5e, the gripper, hand-eye calibration, the grasp planner and the pick cycle.

Import the modules themselves (nothing is imported here, so ``import robot`` stays cheap and needs no ur_rtde):

- ``robot.ur``: ``URRobot`` over ur_rtde (connect, recover, checked motion with 4x4 poses); ``robot.ur_config``
  (``URConfig``, ``WorkspaceBox``, the pre-send checks), ``robot.ur_errors``, ``robot.ur_connection`` (the clients,
  reconnect, recovery), ``robot.ur_motion`` (a motion in flight, watched), ``robot.ur_force`` (force-limited
  motion: move until contact, a move in force mode), ``robot.ur_probe`` (bounded reachability).
- ``robot.gripper``: ``Gripper``, the Robotiq URCap socket and digital-output kinds, ``make_gripper``.
- ``robot.calibration`` (pose set, capture, file), ``robot.hand_eye`` (the solver), ``robot.charuco``: eye-to-hand
  hand-eye calibration with a ChArUco board.
- ``robot.grasp_planner`` (``GraspPlanner``), with its settings (``robot.grasp_config``), results
  (``robot.grasp_plan``), scene (``robot.grasp_scene``), collision checks (``robot.grasp_collision``), waypoints and IK
  (``robot.grasp_waypoints``); the grasp candidates (``robot.grasp_candidates``, ``robot.grasp_set``,
  ``robot.grasp_cache``) and the gripper's boxes (``robot.grasp_geometry``).
- ``robot.nudge``: pushing a part off a wall or a neighbour with the closed fingers.
- ``robot.picker``: the pick cycle as a state machine (``Picker``), with its settings (``robot.pick_config``), the
  interfaces it calls (``robot.pick_protocols``), its records and outcomes (``robot.pick_report``), and its helpers
  for the fingers (``robot.pick_fingers``), the arm's moves (``robot.pick_arm``) and per-part memory
  (``robot.pick_memory``).
- ``robot.cell_setup``: a cell file (TOML) read into the settings of every part above.
"""
