"""6D pose: the RoI geometry shared by training and runtime (allocentric rotation, SITE, PnP decoding), the
symmetric losses, a smoke training run that exports an ONNX model, and the onnxruntime estimator on it."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper

from perception.pose import PoseEstimator
from perception.results import Detection
from sygrid.camera import CameraIntrinsics, project_points
from sygrid.errors import ModelError
from sygrid.objects.parts import builtin_part
from sygrid.pose_geometry import (
    POSE_METADATA_KEY,
    POSE_ONNX_FORMAT,
    allocentric_to_egocentric,
    bop_bbox_to_xyxy,
    decode_direct,
    decode_pnp,
    egocentric_to_allocentric,
    matrix_to_rot6d,
    normalise_xyz,
    ray_rotation,
    roi_grid,
    rot6d_to_matrix,
    site_decode,
    site_encode,
    square_roi,
)
from sygrid.transforms import make_T, random_rotation, rotation_about, rotation_angle_deg
from sygrid.writers import load_bop_item

K = np.array([[600.0, 0.0, 319.5], [0.0, 600.0, 239.5], [0.0, 0.0, 1.0]])
INTRINSICS = CameraIntrinsics.from_K(K, 640, 480)


# ------------------------------------------------------------------------------------- allocentric rotation
def test_on_the_optical_axis_allocentric_equals_egocentric():
    R = random_rotation(np.random.default_rng(0))
    t = np.array([0.0, 0.0, 0.7])
    np.testing.assert_allclose(egocentric_to_allocentric(R, t), R, atol=1e-12)
    np.testing.assert_allclose(allocentric_to_egocentric(R, t), R, atol=1e-12)


def test_ray_rotation_hand_case_and_round_trip():
    # t in the x-z plane at 30 degrees off-axis: the rotation is 30 degrees about +y.
    t = np.array([np.sin(np.radians(30)), 0.0, np.cos(np.radians(30))]) * 0.8
    np.testing.assert_allclose(ray_rotation(t), rotation_about(np.array([0.0, 1.0, 0.0]), np.radians(30)), atol=1e-12)
    rng = np.random.default_rng(1)
    for _ in range(20):
        t = np.array([*rng.uniform(-0.3, 0.3, 2), rng.uniform(0.3, 1.0)])
        R = random_rotation(rng)
        np.testing.assert_allclose(ray_rotation(t) @ [0, 0, np.linalg.norm(t)], t, atol=1e-12)
        R_allo = egocentric_to_allocentric(R, t)
        np.testing.assert_allclose(allocentric_to_egocentric(R_allo, t), R, atol=1e-12)
        assert abs(np.linalg.det(R_allo) - 1.0) < 1e-12


def test_rot6d_round_trip_and_gram_schmidt():
    R = random_rotation(np.random.default_rng(2))
    np.testing.assert_allclose(rot6d_to_matrix(matrix_to_rot6d(R)), R, atol=1e-12)
    # scaled, non-orthogonal columns still give the same rotation
    x = matrix_to_rot6d(R)
    noisy = np.concatenate([3.0 * x[:3], 0.5 * x[3:] + 0.2 * x[:3]])
    np.testing.assert_allclose(rot6d_to_matrix(noisy), R, atol=1e-12)


# ----------------------------------------------------------------------------------------------- SITE
def test_site_hand_case():
    # f = 600: the origin projects to (319.5 + 600 * 0.05 / 0.6, 239.5 - 600 * 0.02 / 0.6) = (369.5, 219.5).
    t = np.array([0.05, -0.02, 0.6])
    site = site_encode(t, np.array([369.5, 219.5]), 60.0, K, 0.05)
    np.testing.assert_allclose(site, [0.0, 0.0, 0.6 * 60.0 / (600.0 * 0.05)], atol=1e-12)
    site = site_encode(t, np.array([359.5, 229.5]), 40.0, K, 0.05)
    np.testing.assert_allclose(site, [0.25, -0.25, 0.6 * 40.0 / (600.0 * 0.05)], atol=1e-12)


def test_site_round_trip():
    rng = np.random.default_rng(3)
    for _ in range(20):
        t = np.array([*rng.uniform(-0.2, 0.2, 2), rng.uniform(0.4, 1.0)])
        centre, size = rng.uniform(100, 500, 2), rng.uniform(20, 150)
        np.testing.assert_allclose(site_decode(site_encode(t, centre, size, K, 0.03), centre, size, K, 0.03), t)


def test_direct_decode_inverts_the_training_targets():
    T = make_T(random_rotation(np.random.default_rng(4)), [0.04, 0.03, 0.65])
    centre, size = np.array([360.0, 270.0]), 48.0
    rot6d = matrix_to_rot6d(egocentric_to_allocentric(T[:3, :3], T[:3, 3]))
    site = site_encode(T[:3, 3], centre, size, K, 0.02)
    np.testing.assert_allclose(decode_direct(rot6d, site, centre, size, K, 0.02), T, atol=1e-12)


# ----------------------------------------------------------------------------------------------- PnP
def _exact_xyz_map(name: str, T: np.ndarray, out_size: int = 32):
    """The exact normalised XYZ map and mask of a built-in part at pose T, on the RoI of its projected box."""
    from sygrid.train.pose.data import CoordinateRenderer

    model = builtin_part(name)
    uv = project_points(K, model.mesh.vertices @ T[:3, :3].T + T[:3, 3])
    centre, size = square_roi(np.concatenate([uv.min(0), uv.max(0)]))
    points = CoordinateRenderer({model.obj_id: model}).render(model.obj_id, T, K, roi_grid(centre, size, out_size))
    hit = np.isfinite(points[..., 0])
    xyz = np.where(hit[..., None], normalise_xyz(np.nan_to_num(points), model.bounds_m), 0.0)
    return xyz.transpose(2, 0, 1), hit.astype(np.float32), centre, size, model


@pytest.mark.parametrize(
    ("name", "R"),
    [
        ("l_bracket", rotation_about(np.array([1.0, 0.3, 0.2]), 2.1)),  # a 3-D point set
        ("washer", rotation_about(np.array([0.2, 1.0, 0.0]), 0.3)),  # nearly all points on one plane
    ],
)
def test_pnp_recovers_the_pose_from_an_exact_xyz_map(name, R):
    T = make_T(R, [0.03, -0.02, 0.6])
    xyz, mask, centre, size, model = _exact_xyz_map(name, T)
    assert mask.sum() > 100
    sol = decode_pnp(xyz, mask, centre, size, K, model.bounds_m)
    assert sol is not None and sol.n_inliers == sol.n_points == int(mask.sum())
    assert rotation_angle_deg(sol.T_camera_object[:3, :3], R) < 1e-3 * 180 / np.pi  # 1e-3 rad
    assert np.linalg.norm(sol.T_camera_object[:3, 3] - T[:3, 3]) < 1e-3 * model.diameter_m
    np.testing.assert_allclose(sol.T_camera_object, T, atol=1e-3)


def test_pnp_refuses_too_few_points():
    xyz, mask, centre, size, model = _exact_xyz_map("l_bracket", make_T(t=[0.0, 0.0, 0.6]))
    few = np.zeros_like(mask)
    few[np.nonzero(mask)[0][:4], np.nonzero(mask)[1][:4]] = 1.0
    assert decode_pnp(xyz, few, centre, size, K, model.bounds_m) is None


# ------------------------------------------------------------------------------------------- losses
def _tables(names):
    from sygrid.train.pose.objects import build_tables

    models = {builtin_part(n).obj_id: builtin_part(n) for n in names}
    return build_tables(models, num_regions=16, sym_steps=36), models


def test_symmetric_losses_vanish_for_a_symmetric_equivalent():
    torch = pytest.importorskip("torch")
    from sygrid.train.pose.losses import PoseLoss

    tables, _ = _tables(["hex_nut", "washer", "l_bracket"])
    loss = PoseLoss(tables)
    rng = np.random.default_rng(5)
    p_gt, xyz_sym, xyz_plain, p_sym_all, R_gt, R_sym, cls = [], [], [], [], [], [], []
    for name, k in (("hex_nut", 3), ("washer", 40), ("l_bracket", 1)):
        c = tables.class_index(builtin_part(name).obj_id)
        S = tables.sym_T[c, k]  # a symmetry other than the identity
        assert tables.sym_valid[c, k] and not np.allclose(S, np.eye(4))
        p = np.asarray(builtin_part(name).mesh.sample(64, seed=int(rng.integers(1 << 30))))  # (64, 3) [m]
        p_sym = (p - S[:3, 3]) @ S[:3, :3]  # S^-1 p: what the pose T @ S shows at the same pixels
        p_gt.append(p.T.reshape(3, 8, 8))
        p_sym_all.append(p_sym)
        xyz_sym.append(normalise_xyz(p_sym, tables.bounds_m[c]).T.reshape(3, 8, 8))
        xyz_plain.append(normalise_xyz(p, tables.bounds_m[c]).T.reshape(3, 8, 8))
        R = random_rotation(rng)
        R_gt.append(R)
        R_sym.append(R @ S[:3, :3])
        cls.append(c)

    def f(a):
        return torch.as_tensor(np.stack(a), dtype=torch.float32)

    cls_t, visible = torch.tensor(cls), torch.ones(3, 8, 8)
    l_xyz, p_best = loss.symmetric_xyz(f(xyz_sym), f(p_gt), visible, cls_t)
    assert float(l_xyz.max()) < 1e-5
    np.testing.assert_allclose(p_best.numpy(), np.stack(p_sym_all), atol=1e-6)  # the equivalent it matched
    l_rot = loss.rotation_pm(f([matrix_to_rot6d(R) for R in R_sym]), f(R_gt), cls_t)
    assert float(l_rot.max()) < 1e-5
    # the same predictions against the plain targets are far off: the minimum is what makes the losses vanish
    assert np.abs(np.stack(xyz_sym) - np.stack(xyz_plain)).mean() > 0.05
    for c, R, R_s in zip(cls, R_gt, R_sym, strict=True):  # point matching without the symmetries, in diameters
        pts = tables.points_m[c] / tables.diameters_m[c]
        assert np.abs(pts @ R_s.T - pts @ R.T).sum(1).mean() > 0.1


# ------------------------------------------------------------------------------- training and runtime
def test_pose_defaults_are_the_shipped_model():
    """The command line, a training run and the network share one set of architecture defaults: the shipped
    model's (its metadata gives the sizes, its first convolution the width)."""
    import argparse

    from sygrid.train.pose.command import add_arguments
    from sygrid.train.pose.config import PoseNetConfig, TrainConfig

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    args = parser.parse_args(["--data", "d", "--out", "o"])
    config = TrainConfig(data_dir=args.data, out_dir=args.out, input_size=args.input_size,
                         output_stride=args.output_stride, width=args.width)  # fmt: skip
    assert config == TrainConfig(data_dir=Path("d"), out_dir=Path("o"))
    assert config.net_config(7) == PoseNetConfig(num_classes=7)
    shipped = onnx.load(str(Path(__file__).resolve().parents[1] / "models" / "builtin" / "pose.onnx"))
    info = json.loads({p.key: p.value for p in shipped.metadata_props}[POSE_METADATA_KEY])
    stem = next(n for n in shipped.graph.node if n.op_type == "Conv")
    (weight,) = [i for i in shipped.graph.initializer if i.name == stem.input[1]]
    net = PoseNetConfig(num_classes=len(info["obj_ids"]))
    assert (net.input_size, net.output_size, net.num_regions) == (
        info["input_size"],
        info["output_size"],
        info["num_regions"],
    )
    assert net.width == weight.dims[0]


@pytest.fixture(scope="module")
def trained(tiny_dataset: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    pytest.importorskip("torch")
    from sygrid.train.pose.config import TrainConfig
    from sygrid.train.pose.train import train

    out = tmp_path_factory.mktemp("pose_run")
    config = TrainConfig(
        data_dir=tiny_dataset, out_dir=out, epochs=1, batch_size=4, input_size=32, output_stride=4, width=8,
        num_regions=8, max_iters=3, threads=2, progress=False, checkpoint_every=2, val_max=6,
    )  # fmt: skip
    result = train(config)
    assert result.iterations == 3 and result.export_max_diff <= 1e-4
    return out


def test_smoke_training_writes_checkpoints_log_and_onnx(trained: Path):
    for name in ("last.pt", "best.pt", "pose.onnx", "train_log.json"):
        assert (trained / name).is_file(), name
    log = json.loads((trained / "train_log.json").read_text())
    assert [e["iteration"] for e in log["entries"]][-1] == 3
    assert all(np.isfinite(e["loss"]["loss"]) for e in log["entries"])
    meta = {p.key: p.value for p in onnx.load(str(trained / "pose.onnx")).metadata_props}
    info = json.loads(meta[POSE_METADATA_KEY])
    assert info["format"] == POSE_ONNX_FORMAT and info["input_size"] == 32 and info["output_size"] == 8
    assert info["obj_ids"] == [1, 3, 4]  # hex_nut, washer, l_bracket
    np.testing.assert_allclose(info["objects"]["3"]["bounds_m"], builtin_part("washer").bounds_m, atol=1e-6)


def test_training_resumes_from_last_checkpoint(trained: Path, tiny_dataset: Path, tmp_path: Path):
    from sygrid.errors import ConfigError
    from sygrid.train.pose.config import TrainConfig
    from sygrid.train.pose.train import train

    base = dict(data_dir=tiny_dataset, epochs=1, batch_size=4, input_size=32, output_stride=4, width=8,
                num_regions=8, threads=2, progress=False, val_max=6, checkpoint_every=2)  # fmt: skip
    with pytest.raises(ConfigError, match="--resume"):
        train(TrainConfig(out_dir=trained, max_iters=3, **base))
    run = tmp_path / "run"
    run.mkdir()
    (run / "last.pt").write_bytes((trained / "last.pt").read_bytes())
    result = train(TrainConfig(out_dir=run, max_iters=5, **base), resume=True)
    log = json.loads((run / "train_log.json").read_text())
    assert result.iterations == 5
    assert [e["iteration"] for e in log["entries"]] == [2, 3, 4, 5]  # 2 and 3 from the resumed run's history
    assert log["runs"] == [{"start_iteration": 0, "epochs": 1}, {"start_iteration": 3, "epochs": 1}]


def test_estimator_runs_the_exported_model(trained: Path, tiny_dataset: Path):
    est = PoseEstimator(trained / "pose.onnx", models={1: builtin_part("hex_nut")})
    split = "val_pbr" if (tiny_dataset / "bop" / "val_pbr").is_dir() else "train_pbr"
    scene = tiny_dataset / "bop" / split / "000000"
    image_id = int(min(json.loads((scene / "scene_gt.json").read_text()), key=int))
    ann, rgb, _ = load_bop_item(tiny_dataset / "bop", 0, image_id, split)
    dets = [
        Detection(est.obj_ids.index(i.obj_id), i.obj_id, 0.9, bop_bbox_to_xyxy(i.bbox_visib))
        for i in ann.instances
        if i.px_count_visib > 0
    ]
    assert dets
    for method in ("direct", "pnp"):
        poses = est.estimate(rgb, dets, ann.intrinsics, method=method)
        assert len(poses) == len(dets)  # an untrained network still gives a pose in front of the camera or none
        for pose, det in zip(poses, dets, strict=True):
            assert pose.detection is det and pose.T_camera_object.shape == (4, 4)
            assert np.all(np.isfinite(pose.T_camera_object)) and 0.0 <= pose.score <= 1.0
            assert pose.method in ("direct", "pnp")
    assert est.estimate(rgb, [], ann.intrinsics) == []
    with pytest.raises(ValueError, match="rgb: expected a uint8 array of shape"):
        est.estimate(rgb[:-1], dets, ann.intrinsics)
    with pytest.raises(ValueError, match="method"):
        est.estimate(rgb, dets, ann.intrinsics, method="icp")


def test_estimator_rejects_a_model_made_for_another_mesh(trained: Path):
    with pytest.raises(ModelError, match="different mesh"):
        PoseEstimator(trained / "pose.onnx", models={1: builtin_part("hex_bolt")})


# ------------------------------------------------------------------------------------------ bad models
def test_missing_and_corrupt_model_files(tmp_path: Path):
    with pytest.raises(ModelError, match="not found"):
        PoseEstimator(tmp_path / "nope.onnx")
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"\x08\x07garbage" * 10)
    with pytest.raises(ModelError, match="not a loadable ONNX model"):
        PoseEstimator(bad)


def _identity_model(path: Path, outputs: dict[str, list], metadata: dict | None) -> Path:
    """A tiny valid ONNX graph whose outputs have the given names and shapes (all computed from one input)."""
    inputs = [helper.make_tensor_value_info("image", TensorProto.FLOAT, ["B", 3, 32, 32]),
              helper.make_tensor_value_info("coord2d", TensorProto.FLOAT, ["B", 2, 8, 8]),
              helper.make_tensor_value_info("class_onehot", TensorProto.FLOAT, ["B", 1])]  # fmt: skip
    nodes = [helper.make_node("Identity", ["coord2d"], [name]) for name in outputs]
    outs = [helper.make_tensor_value_info(n, TensorProto.FLOAT, s) for n, s in outputs.items()]
    model = helper.make_model(
        helper.make_graph(nodes, "g", inputs, outs), opset_imports=[helper.make_opsetid("", 17)], ir_version=10
    )
    if metadata is not None:
        helper.set_model_props(model, {POSE_METADATA_KEY: json.dumps(metadata)})
    onnx.save(model, str(path))
    return path


def _metadata() -> dict:
    return {"format": POSE_ONNX_FORMAT, "input_size": 32, "output_size": 8, "pad_scale": 1.5, "num_regions": 2,
            "obj_ids": [1], "objects": {"1": {"bounds_m": [[-0.01] * 3, [0.01] * 3], "diameter_m": 0.03}}}  # fmt: skip


def test_models_without_metadata_or_with_other_outputs_are_refused(tmp_path: Path):
    outputs = {"xyz": ["B", 2, 8, 8]}
    with pytest.raises(ModelError, match="no 'sygrid_pose' metadata"):
        PoseEstimator(_identity_model(tmp_path / "a.onnx", outputs, None))
    with pytest.raises(ModelError, match=r"outputs .* do not match the pose contract"):
        PoseEstimator(_identity_model(tmp_path / "b.onnx", outputs, _metadata()))
    broken = {**_metadata(), "format": "something-else"}
    with pytest.raises(ModelError, match="invalid 'sygrid_pose' metadata"):
        PoseEstimator(_identity_model(tmp_path / "c.onnx", outputs, broken))
