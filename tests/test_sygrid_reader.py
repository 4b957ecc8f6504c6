"""The published SyGRID ``gt.pickle`` reader: conversion to metres and masks, and refusal of code-carrying pickles."""

from __future__ import annotations

import os
import pickle

import numpy as np
import pytest

from sygrid.errors import ConfigError
from sygrid.readers import load_sygrid_pickle, safe_load_pickle

W, H = 64, 48
K = [80.0, 0.0, 31.5, 0.0, 80.0, 23.5, 0.0, 0.0, 1.0]


def _corners_mm(centre_mm, half_mm):
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=float)
    return (np.asarray(centre_mm) + signs * np.asarray(half_mm)).tolist()


def _published_labels() -> dict:
    """Two images in the published layout; image 1 has an instance split in two polygons."""
    square = [[10, 10], [19, 10], [19, 19], [10, 19]]
    return {
        "000000.png": {
            "cam_K": K,
            "objects": [
                {
                    "obj_id": 3,
                    "inst_id": 0,
                    "R": [0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0],
                    "t": [10.0, -20.0, 600.0],
                    "bbox": [10, 10, 10, 10],
                    "3d-bbox": _corners_mm([0.0, 0.0, 600.0], [30.0, 30.0, 10.0]),
                    "segmentation": [square],
                    "mask_visib": 50.0,
                }
            ],
        },
        "000001.png": {
            "cam_K": np.asarray(K),  # numpy arrays are allowed too
            "objects": [
                {
                    "obj_id": np.int64(5),
                    "inst_id": 0,
                    "R": np.eye(3).reshape(-1),
                    "t": np.array([0.0, 0.0, 500.0]),
                    "bbox": [2, 2, 40, 6],
                    "3d-bbox": _corners_mm([0.0, 0.0, 500.0], [5.0, 5.0, 5.0]),
                    "segmentation": [[[2, 2], [11, 2], [11, 7], [2, 7]], [[30, 2], [41, 2], [41, 7], [30, 7]]],
                    "mask_visib": 100,
                }
            ],
        },
    }


def test_published_pickle_loads_in_metres_with_masks(tmp_path):
    path = tmp_path / "gt.pickle"
    path.write_bytes(pickle.dumps(_published_labels(), protocol=2))
    images = load_sygrid_pickle(path, W, H)
    assert list(images) == ["000000.png", "000001.png"]
    first, second = images["000000.png"], images["000001.png"]
    assert first.image_id == 0 and second.image_id == 1
    assert first.intrinsics.fx == 80.0 and first.intrinsics.width == W
    inst = first.instances[0]
    assert inst.obj_id == 3
    np.testing.assert_allclose(inst.T_camera_obj[:3, 3], [0.01, -0.02, 0.6])  # metres
    np.testing.assert_allclose(inst.T_camera_obj[:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]])
    expected = np.zeros((H, W), bool)
    expected[10:20, 10:20] = True
    np.testing.assert_array_equal(inst.mask_visib, expected)
    assert inst.mask_full is None
    assert inst.px_count_visib == 100 and inst.visib_fract == 0.5 and inst.px_count_all == 200
    assert inst.bbox_visib == (10, 10, 10, 10)
    assert inst.bbox_obj == (27, 19, 10, 10)  # near corners (z = 590 mm): u in 31.5 +- 4.07, v in 23.5 +- 4.07
    split = second.instances[0]
    assert split.obj_id == 5 and split.px_count_visib == 10 * 6 + 12 * 6 and split.visib_fract == 1.0


def test_code_carrying_pickle_is_refused_without_running(tmp_path):
    marker = tmp_path / "pwned"

    class Evil:
        def __reduce__(self):
            return (os.system, (f"echo pwned > {marker}",))

    path = tmp_path / "gt.pickle"
    path.write_bytes(pickle.dumps({"000000.png": {"cam_K": K, "objects": [Evil()]}}))
    with pytest.raises(ConfigError, match=r"gt\.pickle: refused to load the global '(posix|nt|os)\.system'"):
        load_sygrid_pickle(path, W, H)
    assert not marker.exists()


def test_other_classes_and_garbage_are_refused(tmp_path):
    path = tmp_path / "objs.pickle"
    path.write_bytes(pickle.dumps({"x": ConfigError("boom")}))
    with pytest.raises(ConfigError, match=r"refused to load the global 'sygrid\.errors\.ConfigError'"):
        safe_load_pickle(path)
    path.write_bytes(b"\x80\x02c_codecs\nencode\nX\x01\x00\x00\x00xX\x04\x00\x00\x00zlib\x86R.")
    with pytest.raises(ConfigError, match="refused codec 'zlib'"):
        safe_load_pickle(path)
    path.write_bytes(b"not a pickle")
    with pytest.raises(ConfigError, match=r"objs\.pickle: not a readable pickle"):
        safe_load_pickle(path)
    path.write_bytes(pickle.dumps({"000000.png": {"objects": []}}))
    with pytest.raises(ConfigError, match=r"\['000000.png'\]: missing field 'cam_K'"):
        load_sygrid_pickle(path, W, H)
