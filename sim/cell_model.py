"""The static cell as an MjSpec: options, table, bin, tray, the UR5e placed from its DH parameters with its
gripper, and the cameras. ``sim.world.CellWorld`` compiles it and adds the parts."""

from __future__ import annotations

import mujoco
import numpy as np

from sim import gripper_model
from sim.cell_config import BoardPlate, CellConfig
from sygrid.mjspec import add_camera, add_open_box, quat_wxyz
from sygrid.robots import ur5e
from sygrid.robots.kinematics import dh_transforms

ARM_BODY_NAMES = ur5e.LINK_NAMES
FLANGE_SITE = "flange"
OVERHEAD_CAMERA = "overhead"
WRIST_CAMERA = "wrist"
CALIBRATION_BOARD = "calibration_board"  #: the plate's geom, texture and material, and a site at its image frame
_ENV_FRICTION = (0.5, 0.005, 0.0001)
_ARM_RGBA = (0.75, 0.76, 0.78, 1.0)
_JOINT_ARMATURE = (0.1, 0.1, 0.1, 0.05, 0.05, 0.05)  # reflected rotor inertia, kg m^2
_JOINT_DAMPING = (1.0, 1.0, 1.0, 0.2, 0.2, 0.2)  # N m s/rad (compensated by the controller)


def build_cell_spec(config: CellConfig) -> tuple[mujoco.MjSpec, gripper_model.GripperNames]:
    """The MjSpec of the cell without parts: options, table, bin, tray, the arm with its gripper, cameras."""
    spec = mujoco.MjSpec()
    spec.modelname = "sygrid_cell"
    spec.compiler.degree = False  # joint ranges in radians
    spec.option.timestep = config.timestep_s
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    spec.option.cone = mujoco.mjtCone.mjCONE_ELLIPTIC  # with impratio: grasps hold without creeping
    spec.option.impratio = 10.0
    spec.stat.extent = 2.0  # fixes the clip planes: znear 0.02 m, zfar 100 m whatever parts are added
    spec.stat.center = [-0.3, 0.0, 0.3]
    spec.visual.map.znear = 0.01
    spec.visual.quality.offsamples = 0
    max_w = max(config.camera_intrinsics.width, config.wrist_camera_intrinsics.width, 1280)
    max_h = max(config.camera_intrinsics.height, config.wrist_camera_intrinsics.height, 960)
    spec.visual.global_.offwidth, spec.visual.global_.offheight = max_w, max_h
    spec.visual.headlight.ambient, spec.visual.headlight.diffuse = [0.25] * 3, [0.3] * 3
    spec.worldbody.add_light(
        name="top", pos=[-0.3, 0.0, 2.0], dir=[0, 0, -1], diffuse=[0.45, 0.45, 0.45], castshadow=False
    )
    spec.worldbody.add_geom(
        name="floor",
        type=mujoco.mjtGeom.mjGEOM_PLANE,
        size=[3, 3, 0.1],
        pos=[0, 0, -config.table_height_m],
        rgba=[0.35, 0.35, 0.38, 1],
    )
    solref = [2.0 * config.timestep_s, 1.0]
    table = spec.worldbody.add_body(name="table")
    tx, ty = config.table_size_xy_m
    table.add_geom(
        name="table_top",
        type=mujoco.mjtGeom.mjGEOM_BOX,
        rgba=[0.55, 0.45, 0.35, 1],
        pos=[*config.table_center_xy_m, -config.table_height_m / 2],
        size=[tx / 2, ty / 2, config.table_height_m / 2],
        friction=list(_ENV_FRICTION),
        solref=solref,
    )
    env_friction = list(_ENV_FRICTION)
    add_open_box(
        spec.worldbody, "bin", config.T_world_bin, config.bin_inner_size_m, config.bin_wall_thickness_m,
        config.bin_floor_thickness_m, solref, env_friction, rgba=(0.2, 0.35, 0.6, 1.0),
    )  # fmt: skip
    add_open_box(
        spec.worldbody, "tray", config.T_world_tray, config.tray_inner_size_m, config.tray_wall_thickness_m,
        config.tray_floor_thickness_m, solref, env_friction, rgba=(0.3, 0.55, 0.3, 1.0),
    )  # fmt: skip
    flange = _add_arm(spec, config.T_world_base)
    names = gripper_model.add_gripper(spec, flange, solref)
    if config.calibration_board is not None:
        _add_board_plate(spec, flange, config.calibration_board)
    add_camera(spec.worldbody, OVERHEAD_CAMERA, config.T_world_camera, config.camera_intrinsics)
    if config.wrist_camera:
        add_camera(flange, WRIST_CAMERA, config.T_flange_wrist_camera, config.wrist_camera_intrinsics)
    return spec, names


def _add_arm(spec: mujoco.MjSpec, T_world_base: np.ndarray) -> mujoco.MjsBody:
    """The UR5e: a static base and six links placed from the DH parameters; returns the flange body.

    Link ``i``'s body frame is its joint frame (DH frame ``i-1`` turned by ``q_i``), so joint ``i`` is a hinge about
    the body's z axis, and the next body sits at ``Tz(d_i) Tx(a_i) Rx(alpha_i)``. The flange body is DH frame 6.
    """
    base = spec.worldbody.add_body(
        name="robot_base", pos=T_world_base[:3, 3].tolist(), quat=quat_wxyz(T_world_base[:3, :3]).tolist()
    )
    _add_cylinders(base, "robot_base", ur5e.LINK_CYLINDERS_M[0], (0.2, 0.45, 0.75, 1.0))
    offsets = dh_transforms(np.zeros(6))  # A_i at q_i = 0: the fixed part Tz(d_i) Tx(a_i) Rx(alpha_i)
    parent, T_parent_body = base, np.eye(4)
    for i, (link, joint) in enumerate(zip(ur5e.LINK_NAMES, ur5e.JOINT_NAMES, strict=True)):
        body = parent.add_body(
            name=link, pos=T_parent_body[:3, 3].tolist(), quat=quat_wxyz(T_parent_body[:3, :3]).tolist()
        )
        lo, hi = ur5e.JOINT_LIMITS_RAD[i]
        body.add_joint(
            name=joint,
            type=mujoco.mjtJoint.mjJNT_HINGE,
            axis=[0, 0, 1],
            range=[lo, hi],
            limited=mujoco.mjtLimited.mjLIMITED_TRUE,
            armature=_JOINT_ARMATURE[i],
            damping=_JOINT_DAMPING[i],
        )
        body.explicitinertial = True
        body.mass = float(ur5e.LINK_MASSES_KG[i])
        body.ipos = (offsets[i] @ np.append(ur5e.LINK_COMS_M[i], 1.0))[:3].tolist()  # CoM: DH frame i -> body
        body.inertia = _cylinder_inertia(float(ur5e.LINK_MASSES_KG[i]), *ur5e.LINK_INERTIA_CYLINDERS[i]).tolist()
        _add_cylinders(body, link, ur5e.LINK_CYLINDERS_M[i + 1], _ARM_RGBA)
        torque = float(ur5e.MAX_JOINT_TORQUE_NM[i])
        motor = spec.add_actuator(name=joint, trntype=mujoco.mjtTrn.mjTRN_JOINT, target=joint)
        motor.set_to_motor()
        motor.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
        motor.ctrlrange = [-torque, torque]
        parent, T_parent_body = body, offsets[i]
    flange = parent.add_body(
        name="flange", pos=T_parent_body[:3, 3].tolist(), quat=quat_wxyz(T_parent_body[:3, :3]).tolist()
    )
    flange.add_site(name=FLANGE_SITE, size=[0.005, 0, 0])
    # Self-collision: neighbours two apart along the chain overlap by construction (compact wrist); skip them.
    chain = ["robot_base", *ur5e.LINK_NAMES, "gripper"]
    for a in range(len(chain) - 2):
        spec.add_exclude(bodyname1=chain[a], bodyname2=chain[a + 2])
    return flange


# A box's +z face shows a 2D texture (texrepeat 1 1, texuniform false) once, image columns along the box's +x and
# image rows along its -y (checked by detecting a rendered ChArUco board); its -z face shows the image mirrored. So
# the printed face is the box's +z face and the plate's image frame (z into the plate) is the box frame turned by
# diag(1, -1, -1).
_R_PLATE_BOX = np.diag([1.0, -1.0, -1.0])


def _add_board_plate(spec: mujoco.MjSpec, flange: mujoco.MjsBody, plate: BoardPlate) -> None:
    """The calibration plate on the flange body: a thin textured box, visual only (no mass, no contacts)."""
    h, w = plate.image.shape[:2]
    texture = spec.add_texture(name=CALIBRATION_BOARD, type=mujoco.mjtTexture.mjTEXTURE_2D, width=w, height=h)
    texture.nchannel = 3
    texture.data = np.ascontiguousarray(plate.image).tobytes()
    material = spec.add_material(name=CALIBRATION_BOARD, texuniform=False, texrepeat=[1.0, 1.0])
    material.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = CALIBRATION_BOARD
    material.specular, material.shininess = 0.0, 0.0  # matte print: no highlight that washes the pattern out
    sx, sy = plate.size_xy_m
    T_plate_box = np.eye(4)
    T_plate_box[:3, :3] = _R_PLATE_BOX
    T_plate_box[:3, 3] = [sx / 2, sy / 2, plate.thickness_m / 2]  # printed face in the plate's z = 0 plane
    T_flange_box = plate.T_flange_plate @ T_plate_box
    flange.add_geom(
        name=CALIBRATION_BOARD,
        type=mujoco.mjtGeom.mjGEOM_BOX,
        size=[sx / 2, sy / 2, plate.thickness_m / 2],
        pos=T_flange_box[:3, 3].tolist(),
        quat=quat_wxyz(T_flange_box[:3, :3]).tolist(),
        material=CALIBRATION_BOARD,
        rgba=[1.0, 1.0, 1.0, 1.0],
        contype=0,
        conaffinity=0,
        mass=0.0,
    )
    flange.add_site(
        name=CALIBRATION_BOARD,
        pos=plate.T_flange_plate[:3, 3].tolist(),
        quat=quat_wxyz(plate.T_flange_plate[:3, :3]).tolist(),
        size=[0.002, 0, 0],
    )


def _add_cylinders(body: mujoco.MjsBody, name: str, cylinders: tuple, rgba: tuple[float, ...]) -> None:
    for k, (p0, p1, radius) in enumerate(cylinders):
        body.add_geom(
            name=f"{name}_geom{k}",
            type=mujoco.mjtGeom.mjGEOM_CYLINDER,
            fromto=[*p0, *p1],
            size=[radius, 0, 0],
            rgba=rgba,
            mass=0,
        )


def _cylinder_inertia(mass: float, axis: str, radius: float, length: float) -> np.ndarray:
    """Principal moments (kg m^2) of a solid cylinder along ``axis`` in the body frame."""
    along = 0.5 * mass * radius**2
    across = mass * (3 * radius**2 + length**2) / 12.0
    return np.array([along if a == axis else across for a in "xyz"])
