"""Sim in the loop: the stock ur_rtde client and the gripper socket pick a part that the generator's drop left in the
MuJoCo cell's bin. The part lifts with the arm by friction alone (the cell has no welds)."""

from __future__ import annotations

import json
import socket
import time

import numpy as np
import pytest

rtde_control = pytest.importorskip("rtde_control")

from sim.cell import build_cell_world  # noqa: E402
from sim.cell_config import CellConfig  # noqa: E402
from sim.controller import ControllerProcess  # noqa: E402
from sygrid.robots.gripper_2f85 import PAD_LENGTH_M, T_FLANGE_TCP  # noqa: E402
from sygrid.robots.kinematics import T_to_pose  # noqa: E402
from sygrid.scene import parse_scene  # noqa: E402
from sygrid.transforms import invert, make_T  # noqa: E402

HOST = "127.0.0.31"
SCENE = {"name": "one_nut", "objects": [{"builtin": "hex_nut", "count": 1}]}
CLEARANCE_M = 0.06  # from the part centre to every bin wall, so open fingers clear the walls
pytestmark = pytest.mark.timeout(120)


def _flat_part_away_from_walls() -> tuple[int, np.ndarray]:
    """The first seed whose nut lies flat, clear of the walls (the drop is deterministic, so the emulator's
    cell, built from the same scene and seed, has the part in the same place)."""
    scene = parse_scene(SCENE)
    for seed in range(20):
        world = build_cell_world(scene, seed=seed)
        T_world_obj = world.part_poses()[0]
        T_bin_obj = invert(world.T_world_bin) @ T_world_obj
        half = np.array(world.config.bin_inner_size_m[:2]) / 2 - CLEARANCE_M
        if abs(T_world_obj[2, 2]) > 0.99 and np.all(np.abs(T_bin_obj[:2, 3]) < half):
            return seed, T_world_obj
    raise AssertionError("no seed in 0..19 gives a flat nut away from the walls")


def _gripper(sock: socket.socket, line: str) -> str:
    sock.sendall((line + "\n").encode())
    return sock.recv(64).decode().strip()


def test_client_picks_a_dropped_part_and_it_lifts_by_friction(monkeypatch, tmp_path):
    monkeypatch.setenv("SYGRID_CACHE_DIR", str(tmp_path))  # the child process inherits it
    seed, T_world_obj = _flat_part_away_from_walls()
    scene_file = tmp_path / "one_nut.json"
    scene_file.write_text(json.dumps(SCENE))
    kwargs = {"parts_scene": str(scene_file), "parts_seed": seed}
    with ControllerProcess(HOST, backend="mujoco", backend_kwargs=kwargs) as cell:
        start = cell.part_poses()[0]
        np.testing.assert_allclose(start[:3, 3], T_world_obj[:3, 3], atol=2e-3)
        c = rtde_control.RTDEControlInterface(HOST)
        try:
            assert c.setTcp(T_to_pose(T_FLANGE_TCP))
            top_down = np.diag([1.0, -1.0, -1.0])  # tool z down, pads closing along world x
            # Pads reach half their length below the TCP: grasp the nut's upper part, pads clear of the bin floor.
            floor_z = CellConfig().T_world_bin[2, 3]  # the bin's inner floor in the default cell
            tcp_z = max(start[2, 3], floor_z + PAD_LENGTH_M / 2 + 0.002)
            grasp = make_T(top_down, [start[0, 3], start[1, 3], tcp_z])  # robot base = world origin here
            above = make_T(top_down, start[:3, 3] + [0, 0, 0.12])
            with socket.create_connection((HOST, 63352), timeout=2.0) as sock:
                for line in ("SET ACT 1", "SET GTO 1", "SET SPE 255", "SET FOR 150", "SET POS 130"):  # ~42 mm open
                    assert _gripper(sock, line) == "ack"
                assert c.moveL(T_to_pose(above).tolist(), 0.5, 1.0)
                assert c.moveL(T_to_pose(grasp).tolist(), 0.1, 0.5)
                assert _gripper(sock, "SET POS 255") == "ack"
                deadline, obj = time.monotonic() + 3.0, ""
                while time.monotonic() < deadline and obj != "OBJ 2":
                    time.sleep(0.05)
                    obj = _gripper(sock, "GET OBJ")
                assert obj == "OBJ 2", "the fingers should stop on the nut (object detected while closing)"
                assert c.moveL(T_to_pose(above).tolist(), 0.2, 0.5)
                time.sleep(0.2)
                lifted = cell.part_poses()[0]
                assert lifted[2, 3] - start[2, 3] > 0.10, "the nut rises with the gripper"
                assert _gripper(sock, "GET OBJ") == "OBJ 2"
        finally:
            c.stopScript()
            c.disconnect()
