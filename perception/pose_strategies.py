"""Pose strategies: how a part's pose is found from a detection, the frame's depth and (where used) the pose network.

A strategy is a source of hypotheses, optionally refined by ICP (``perception.icp``), and the verification
(``perception.verify``) chooses among them and gives the result its confidence:

- ``rgb``: the network's pose as it is (no depth in the fit);
- ``rgbd``: the network's rotation, the translation from depth (the visible model surface moved onto the centroid
  of the mask's depth points);
- ``depth``: no network: rotations that put the model's principal axes on the depth cloud's, every assignment of
  axes and signs that the part's symmetry does not make equivalent (``axis_rotations``), each translated as above;
- ``hybrid``: the ``depth`` hypotheses and the ``rgbd`` one (the network's rotation where the shape leaves the
  principal axes ambiguous);
- ``+icp`` on any of the depth-based ones: each hypothesis is moved along its viewing ray onto the observed surface
  and scored coarsely, the ``icp_hypotheses`` best are refined by ICP (the first to reach ``good_confidence`` ends
  it); short of that, the best fit turned about its own axes is tried (``_turns``), then slid along them
  (``_polish``);
- ``+search``: as ``+icp``, but every hypothesis is ranked by its verification after a short ICP (dearer, for
  parts whose coarse scores mislead, such as a bolt seen end-on or a bracket's legs).

Where the surface the part lies on is known (the bin's floor, else the plane found around the mask; the cleaned
observation's ``support``), every refined strategy (``+icp``, ``+search``) also offers its best fit put back on
that surface in the nearest stable pose and slid and turned in its plane (``perception.resting``): it replaces the
free fit when that needed a tilt of at most ``rest_max_tilt_deg`` and the verification rates it within
``rest_slack`` of the free fit (a free fit of a small part tilts and floats with the depth noise; a part leaning on
a neighbour is no stable pose and keeps its free fit). A best ICP fit short of ``good_confidence`` is tried at rest
before the escapes when levelling it alone brings it near the depth (``rest_first_gate``): under stereo noise that
is how a right fit usually falls short, and confirming it at rest costs a few verifications where the escapes cost
a dozen ICP runs. Where too little of the part stands out of the support to fit, the part is placed from its mask
at rest on the support (``resting.mask_hypotheses``).

The mask is cleaned with depth first (``perception.mask_cleanup``). The search ranks hypotheses by the verification
at the pixels' centres; every estimate carries the verdict's verification of the chosen one (each pixel over its
footprint, ``perception.verify``) in ``details["verify"]``, its confidence as the pose's ``score`` and the verdict as
``verified``.
"""

from __future__ import annotations

import itertools
import time
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from perception.icp import IcpConfig, icp
from perception.mask_cleanup import MaskCleanupConfig, clean_mask
from perception.observation import Observation
from perception.refine import model_surface, principal_axes, visible_model_points
from perception.resting import mask_hypotheses, planar_search, rest_on_support
from perception.results import Detection, ObjectPose
from perception.verify import PoseVerifier, Verification, raycaster
from sygrid.camera import CameraIntrinsics
from sygrid.metrics import symmetric_pose_errors
from sygrid.objects.model import ObjectModel
from sygrid.transforms import make_T

STRATEGIES = (
    "rgb", "rgbd", "rgbd+icp", "depth", "depth+icp", "depth+search", "hybrid", "hybrid+icp", "hybrid+search",
)  # fmt: skip
NETWORK_STRATEGIES = frozenset(s for s in STRATEGIES if s.split("+")[0] in ("rgb", "rgbd", "hybrid"))
CENTRE_POINTS = 300  # model surface samples that place a hypothesis on the depth points' centroid
EQUIVALENT_DEG = 10.0  # two axis assignments closer than this (modulo the part's symmetries) are one hypothesis


@dataclass(frozen=True)
class StrategyConfig:
    """Attributes:
    icp_hypotheses: hypotheses refined by ICP (the best by the coarse score), for the ``+icp`` strategies.
    coarse_tolerance_fraction: the verification's tolerance (x diameter) when ranking unrefined hypotheses.
    align_steps: depth alignments of each hypothesis (``_aligned``).
    escape_rounds: while the best ICP fit is short of ``good_confidence``, try it turned about its own axes
        (``_turns``), at most this many times (each from the best so far, while it improves).
    escape_quick: rank the turns by their verification after a short ICP (not the coarse score).
    good_confidence: a fit whose depth agreement (``Verification.depth_confidence``) reaches this ends the search
        (no further hypothesis is refined).
    polish_steps: step sizes (x diameter) of the slide search on a fit short of ``good_confidence`` (``_polish``).
    slide_fractions: the turns (``_turns``) also take the fit slid by these (x diameter) along its longest axis.
    min_points: fewer depth points than this in the cleaned mask: the network's pose (or none) with confidence 0.
    rest: offer the best fit at rest on the observation's support (``perception.resting``).
    rest_max_tilt_deg: the fit at rest replaces the free fit only when levelling it turned it by at most this ...
    rest_slack: ... and its verification confidence is at least the free fit's minus this.
    rest_steps: the in-plane search's steps: (fraction of the diameter, degrees), coarse to fine.
    rest_settled_deg, rest_settled_m: an accepted fit that levelling turns and moves no more than this is left as it
        is.
    rest_confident: an accepted free fit whose (ranking) depth agreement (``depth_confidence``) reaches this is left
        as it is (above 1: never).
    rest_first_gate: a best ICP fit short of ``good_confidence`` is tried at rest before the escapes when levelling
        it brings its depth agreement to this (``StrategyRunner._search``; above 1: never).
    """

    icp_hypotheses: int = 3
    coarse_tolerance_fraction: float = 0.15
    align_steps: int = 1
    escape_rounds: int = 2
    escape_quick: bool = True
    good_confidence: float = 0.95
    polish_steps: tuple[float, ...] = (0.08, 0.04, 0.02)
    slide_fractions: tuple[float, ...] = (0.25, 0.5)
    min_points: int = 10
    rest: bool = True
    rest_max_tilt_deg: float = 45.0
    rest_slack: float = 0.05
    rest_steps: tuple[tuple[float, float], ...] = ((0.08, 8.0), (0.04, 4.0), (0.02, 2.0), (0.01, 1.0))
    rest_settled_deg: float = 3.0
    rest_settled_m: float = 0.0015
    rest_confident: float = 0.99
    rest_first_gate: float = 0.85

    def __post_init__(self) -> None:
        steps_ok = all(f > 0 and deg > 0 for f, deg in self.rest_steps)
        settled_ok = self.rest_settled_deg >= 0 and self.rest_settled_m >= 0
        bounds_ok = settled_ok and min(self.rest_confident, self.rest_first_gate) > 0
        if not 0 <= self.rest_max_tilt_deg <= 180 or self.rest_slack < 0 or not steps_ok or not bounds_ok:
            raise ValueError(
                "StrategyConfig: need rest_max_tilt_deg in [0, 180], rest_slack, rest_settled_deg and rest_settled_m"
                " >= 0, rest_confident and rest_first_gate > 0 and positive rest_steps, got "
                f"{self.rest_max_tilt_deg}, {self.rest_slack}, {self.rest_settled_deg}, {self.rest_settled_m}, "
                f"{self.rest_confident}, {self.rest_first_gate}, {self.rest_steps}"
            )
        if self.icp_hypotheses < 1 or self.escape_rounds < 0 or self.min_points < 3 or self.align_steps < 0:
            raise ValueError(
                "StrategyConfig: need icp_hypotheses >= 1, escape_rounds >= 0, min_points >= 3 and align_steps >= 0,"
                f" got {self.icp_hypotheses}, {self.escape_rounds}, {self.min_points}, {self.align_steps}"
            )


def check_strategy(name: str, where: str) -> str:
    """``name`` if it is a known strategy; ValueError naming ``where`` (file and field) otherwise."""
    if name not in STRATEGIES:
        raise ValueError(f"{where}: unknown pose strategy {name!r} (known: {', '.join(STRATEGIES)})")
    return name


# ------------------------------------------------------------------------------------------------ hypotheses
def _proper_axis_maps() -> np.ndarray:
    """(24, 3, 3) the rotations that permute the coordinate axes with signs (the cube's rotation group)."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            Q = np.zeros((3, 3))
            Q[np.arange(3), perm] = signs
            if np.linalg.det(Q) > 0:
                out.append(Q)
    return np.stack(out)


@lru_cache(maxsize=64)
def _distinct_axis_maps(model: ObjectModel) -> tuple[np.ndarray, np.ndarray]:
    """The model's principal frame E (3, 3) and the axis maps Q (k, 3, 3) that stay distinct modulo the model's
    symmetries: two maps give object rotations ``E_s Q E^T`` that differ by ``E Q1^T Q2 E^T`` in the object frame,
    whatever the scene's frame, so one map of each symmetry class is kept."""
    points, _ = model_surface(model, 3000, 0)
    E = principal_axes(points)
    symmetries = model.symmetry_transforms(36)
    kept: list[np.ndarray] = []
    for Q in _proper_axis_maps():
        if not any(
            symmetric_pose_errors(make_T(E @ K.T @ Q @ E.T), np.eye(4), symmetries)[0] < EQUIVALENT_DEG for K in kept
        ):
            kept.append(Q)
    return E, np.stack(kept)


def axis_rotations(model: ObjectModel, scene_points: np.ndarray) -> list[np.ndarray]:
    """Rotations (object -> camera) that map the model's principal axes onto the depth cloud's, one per assignment
    of axes and signs that the model's symmetries do not make equivalent. The cloud is one visible side, so which
    model axis lies along which of its axes is open: every distinct assignment is a hypothesis."""
    E_model, maps = _distinct_axis_maps(model)
    E_scene = principal_axes(scene_points)
    return [E_scene @ Q @ E_model.T for Q in maps]


def centred_pose(R: np.ndarray, t_hint: np.ndarray, scene: np.ndarray, model: ObjectModel) -> np.ndarray | None:
    """The pose with rotation ``R`` whose camera-facing model surface has the depth points' centroid (the depth
    says where the part is far better than an RGB estimate of its distance); None when no surface faces the
    camera. ``t_hint``: where the visibility is judged from (the part's rough position)."""
    points, normals = model_surface(model, CENTRE_POINTS, 0)
    T = make_T(R, t_hint)
    p_cam, _ = visible_model_points(T, points, normals)
    if len(p_cam) < 3:
        return None
    # the same shift once more with the self-occluded points out (the visibility depends on the position a little)
    T[:3, 3] += scene.mean(axis=0) - p_cam.mean(axis=0)
    seen = raycaster(model).visible(T, points)
    if seen.sum() >= 3:
        T[:3, 3] += scene.mean(axis=0) - (points[seen] @ T[:3, :3].T + T[:3, 3]).mean(axis=0)
    return T


# ---------------------------------------------------------------------------------------------------- runner
@dataclass(frozen=True)
class _Candidate:
    T: np.ndarray
    source: str
    verification: Verification
    icp: dict | None = None


class StrategyRunner:
    """Runs a named strategy for one detection: cleans the mask, builds and refines hypotheses, verifies them.

    Args:
        icp_config: the ICP settings (``perception.icp``).
        verifier: scores hypotheses; its ``min_confidence`` decides acceptance.
        cleanup: the mask clean-up settings.
        config: the strategy settings.
    """

    def __init__(
        self,
        icp_config: IcpConfig | None = None,
        verifier: PoseVerifier | None = None,
        cleanup: MaskCleanupConfig | None = None,
        config: StrategyConfig | None = None,
    ) -> None:
        self.icp_config = icp_config or IcpConfig()
        self.quick_icp = IcpConfig(
            **{
                **self.icp_config.__dict__,
                "distance_fractions": self.icp_config.distance_fractions[:1],
                "max_iterations": 4,
            }
        )
        self.verifier = verifier or PoseVerifier()
        self.cleanup = cleanup or MaskCleanupConfig()
        self.config = config or StrategyConfig()

    def estimate(
        self,
        strategy: str,
        detection: Detection,
        depth_m: np.ndarray,
        intrinsics: CameraIntrinsics,
        model: ObjectModel,
        network_pose: ObjectPose | None = None,
        floor_plane_camera: np.ndarray | None = None,
    ) -> ObjectPose | None:
        """The pose of ``detection`` by ``strategy``; None when there is nothing to fit (no mask, too few depth
        points) and no network pose to fall back to.

        Raises:
            ValueError: unknown strategy, a network strategy without ``network_pose``, or a model of another part.
        """
        t0, c0 = time.perf_counter(), time.process_time()
        check_strategy(strategy, "strategy")
        if model.obj_id != detection.obj_id:
            raise ValueError(f"model: obj_id {model.obj_id} is not the detection's obj_id {detection.obj_id}")
        base, _, refine = strategy.partition("+")
        if strategy in NETWORK_STRATEGIES and network_pose is None:
            raise ValueError(f"strategy {strategy!r} needs the pose network's estimate (network_pose)")
        if detection.mask is None:
            return self._unverified(network_pose, strategy, "the detection has no mask", t0)
        raw = Observation.of_detection(depth_m, detection, intrinsics)
        obs, cleanup = clean_mask(raw, self.cleanup, floor_plane_camera)
        scene = obs.points
        if len(scene) < self.config.min_points:
            reason = f"{len(scene)} depth points in the cleaned mask, fewer than {self.config.min_points}"
            if not (refine and self.config.rest and obs.support is not None):
                return self._unverified(network_pose, strategy, reason, t0, cleanup)
            placed = raw.with_mask(raw.mask, obs.support)
            candidates = self._from_mask(placed, model, network_pose)
            if not candidates:
                return self._unverified(network_pose, strategy, reason, t0, cleanup)
            best = max(candidates, key=lambda c: c.verification.confidence)
            n = len(candidates)
            return self._result(best, model, placed, detection, strategy, network_pose, n, cleanup, t0, c0)
        # the part's rough position (for the visibility of its surface): the network's, else the depth's
        t_hint = network_pose.T_camera_object[:3, 3] if network_pose is not None else np.median(scene, axis=0)
        hypotheses: list[tuple[np.ndarray, str]] = []
        if base == "rgb":
            hypotheses.append((np.asarray(network_pose.T_camera_object, dtype=float), "network"))
        if base in ("rgbd", "hybrid"):
            T = centred_pose(network_pose.T_camera_object[:3, :3], t_hint, scene, model)
            if T is not None:
                hypotheses.append((T, "network_rotation"))
        if base in ("depth", "hybrid"):
            for k, R in enumerate(axis_rotations(model, scene)):
                T = centred_pose(R, t_hint, scene, model)
                if T is not None:
                    hypotheses.append((T, f"axes_{k}"))
        if not hypotheses:
            return self._unverified(network_pose, strategy, "no hypothesis shows any surface to the camera", t0)
        rested: dict[int, _Candidate] = {}  # id of a fit -> that fit at rest, where the search has levelled it
        if base == "rgb":  # the network's pose as it is: depth only verifies it
            candidates = [
                _Candidate(hypotheses[0][0], hypotheses[0][1], self.verifier.verify(hypotheses[0][0], model, obs))
            ]
        elif refine:
            candidates = self._search(hypotheses, scene, model, obs, rested, quick=refine == "search")
        else:
            candidates = []
            for T, src in hypotheses:
                T_aligned, _ = self._aligned(T, model, obs)
                candidates.append(_Candidate(T_aligned, src, self.verifier.verify(T_aligned, model, obs)))
        best = max(candidates, key=lambda c: c.verification.confidence)
        if refine and self.config.rest and obs.support is not None:
            best = rested[id(best)] if id(best) in rested else self._rested(best, model, obs)
        return self._result(best, model, obs, detection, strategy, network_pose, len(hypotheses), cleanup, t0, c0)

    def _result(
        self,
        best: _Candidate,
        model: ObjectModel,
        obs: Observation,
        detection: Detection,
        strategy: str,
        network_pose: ObjectPose | None,
        n_hypotheses: int,
        cleanup: dict,
        t0: float,
        c0: float,
    ) -> ObjectPose:
        """The chosen candidate as a verified pose, with the diagnostics in its details: the verdict's verification
        (each pixel over its footprint) in ``verify``, the confidence the search ranked it by in ``rank_confidence``."""
        v = self.verifier.verify(best.T, model, obs, footprint=True)
        details = {
            **(network_pose.details if network_pose is not None else {}),
            "strategy": strategy,
            "hypothesis": best.source,
            "hypotheses": n_hypotheses,
            "cleanup": cleanup,
            "verify": v.as_dict(),
            "rank_confidence": best.verification.confidence,
            "time_ms": (time.perf_counter() - t0) * 1e3,
            "cpu_ms": (time.process_time() - c0) * 1e3,
        }
        if best.icp is not None:
            details["icp"] = best.icp
        if network_pose is not None:
            details["network_score"] = network_pose.score
        return ObjectPose(detection, best.T, v.confidence, strategy, details, verified=v.accepted)

    def _search(
        self,
        hypotheses: list[tuple[np.ndarray, str]],
        scene: np.ndarray,
        model: ObjectModel,
        obs: Observation,
        rested: dict[int, _Candidate],
        quick: bool = False,
    ) -> list[_Candidate]:
        """ICP from the best hypotheses (``quick``: ranked after a short ICP each); short of ``good_confidence``, the
        best fit at rest where that is promising (``rest_first_gate``; ``rested`` keeps it, so that the final levelling
        does not search again), then from the best fit's turns (``_turns``), then the slide search (``_polish``).
        Every fit comes back verified."""
        cfg = self.config
        candidates = self._refine_ranked(hypotheses, scene, model, obs, quick)
        best = max(candidates, key=lambda c: c.verification.confidence)
        # a right fit under stereo noise usually falls short of the bar tilted and afloat: at rest (a few
        # verifications) it is confirmed where the escapes (a dozen ICP runs) would not; a fit that levelling does not
        # bring near the depth (``rest_first_gate``) is more likely the wrong one, and escapes first
        rest_first = cfg.rest and obs.support is not None and cfg.rest_first_gate <= 1
        if rest_first and best.verification.depth_confidence < cfg.good_confidence:
            at_rest = self._rested(best, model, obs, gate=cfg.rest_first_gate)
            if at_rest is not None:
                rested[id(best)] = at_rest
                if at_rest.verification.depth_confidence >= cfg.good_confidence:
                    return [at_rest if c is best else c for c in candidates]
        for _ in range(cfg.escape_rounds):
            if best.verification.depth_confidence >= cfg.good_confidence:
                break
            turned = self._refine_ranked(self._turns(best, scene, model), scene, model, obs, cfg.escape_quick)
            candidates += turned
            better = max(turned, key=lambda c: c.verification.confidence, default=best)
            if better.verification.confidence <= best.verification.confidence:
                break
            best = better
        if cfg.polish_steps and best.verification.depth_confidence < cfg.good_confidence:
            candidates.append(self._polish(best, scene, model, obs))
        return candidates

    def _from_mask(self, obs: Observation, model: ObjectModel, network_pose: ObjectPose | None) -> list[_Candidate]:
        """Too little of the part stands out of its support to fit (``obs``: the whole mask, with the support): it
        is placed from its mask at rest on the support (``mask_hypotheses``, and the network's pose levelled onto
        it where given), each slid and turned in the plane, verified."""
        hypotheses = [(T, "mask_rest") for T in mask_hypotheses(model, obs, obs.support)]
        if network_pose is not None:
            hypotheses.append((rest_on_support(network_pose.T_camera_object, model, obs.support)[0], "network_rest"))
        out = []
        for T, source in hypotheses:
            T, v = planar_search(T, model, obs, obs.support, self.verifier, self.config.rest_steps)
            out.append(_Candidate(T, source, v))
        return out

    def _rested(self, best: _Candidate, model: ObjectModel, obs: Observation, gate: float = 0.0) -> _Candidate | None:
        """The best fit at rest on the observation's support where the verification agrees, else the fit itself;
        None, without the in-plane search, where the levelled pose's depth agreement is below ``gate`` (the search
        trying a fit at rest before its escapes, ``rest_first_gate``)."""
        cfg = self.config
        T, tilt = rest_on_support(best.T, model, obs.support)
        if tilt > cfg.rest_max_tilt_deg:
            return best
        # an accepted fit already at rest (nothing to gain, and the search is the dearer part) or confirmed by the
        # depth (a part leaning on a neighbour, or exact depth) is left as it is; one the outline refuses is still
        # searched in the plane: a flat part's depth agrees wherever it lies on the floor, and only its outline
        # says where
        settled = tilt <= cfg.rest_settled_deg and np.linalg.norm(T[:3, 3] - best.T[:3, 3]) <= cfg.rest_settled_m
        if best.verification.accepted and (settled or best.verification.depth_confidence >= cfg.rest_confident):
            return best
        levelled = self.verifier.verify(T, model, obs)
        if levelled.depth_confidence < gate:
            return None
        T, v = planar_search(T, model, obs, obs.support, self.verifier, cfg.rest_steps, start=levelled)
        if v.confidence < best.verification.confidence - cfg.rest_slack:
            return best
        return _Candidate(T, f"{best.source}+rest", v, best.icp)

    def _aligned(self, T: np.ndarray, model: ObjectModel, obs: Observation) -> tuple[np.ndarray, Verification]:
        """A hypothesis moved along its viewing ray onto the observed surface (``align_steps`` times: the centroid
        of the visible model surface is a biased guess where the hypothesis shows other faces than the camera
        sees) and its coarse score (``coarse_tolerance_fraction``)."""
        v = None
        for _ in range(max(self.config.align_steps, 1)):
            T, v = self.verifier.align(
                T, model, obs, self.config.coarse_tolerance_fraction, move=self.config.align_steps > 0
            )
        return T, v

    def _refine_ranked(
        self,
        hypotheses: list[tuple[np.ndarray, str]],
        scene: np.ndarray,
        model: ObjectModel,
        obs: Observation,
        quick: bool = False,
    ) -> list[_Candidate]:
        """ICP from the ``icp_hypotheses`` best hypotheses by the coarse score (``quick``: by the verification after
        a short ICP, ``quick_icp``), best first, stopping at the first fit whose confidence reaches
        ``good_confidence``."""
        cfg = self.config
        if not hypotheses:
            return []
        aligned = [(*self._aligned(T, model, obs), src) for T, src in hypotheses]
        if quick:
            short = [icp(T, scene, model, self.quick_icp).T_camera_object for T, _, _ in aligned]
            aligned = [
                (T, self.verifier.verify(T, model, obs), src) for T, (_, _, src) in zip(short, aligned, strict=True)
            ]
        out = []
        for i in np.argsort([-v.confidence for _, v, _ in aligned], kind="stable")[: cfg.icp_hypotheses]:
            out.append(self._icp(aligned[i][0], aligned[i][2], scene, model, obs))
            if out[-1].verification.depth_confidence >= cfg.good_confidence:
                break
        return out

    def _polish(self, c: _Candidate, scene: np.ndarray, model: ObjectModel, obs: Observation) -> _Candidate:
        """A fit slid along the part's own axes while the verification improves, then ICP again: point-to-plane ICP
        leaves a part free to slide where its visible faces are parallel to one direction (a bracket's legs along
        their common edge, a bolt's shank along its axis), and there only the silhouette and the free space around
        the part tell where it ends."""
        cfg = self.config
        E, _ = _distinct_axis_maps(model)
        T, v = c.T, c.verification
        for fraction in cfg.polish_steps:
            step = fraction * float(model.diameter_m)
            moved, undo = True, None
            while moved:
                moved = False
                for k, axis in enumerate((T[:3, :3] @ E).T):
                    for sign in (1.0, -1.0):
                        if (k, sign) == undo:  # back to where the last slide came from: known to be worse
                            continue
                        T_try = T.copy()
                        T_try[:3, 3] += sign * step * axis
                        v_try = self.verifier.verify(T_try, model, obs)
                        if v_try.confidence > v.confidence + 1e-3:
                            T, v, moved, undo = T_try, v_try, True, (k, -sign)
        if T is c.T:
            return c
        refined = self._icp(T, f"{c.source}+polish", scene, model, obs)
        return (
            refined
            if refined.verification.confidence >= v.confidence
            else _Candidate(T, f"{c.source}+polish", v, c.icp)
        )

    def _turns(self, best: _Candidate, scene: np.ndarray, model: ObjectModel) -> list[tuple[np.ndarray, str]]:
        """Hypotheses around a fit short of ``good_confidence``: its pose turned by every axis map that the part's
        symmetry does not make equivalent (90 and 180 degree turns about its own principal axes: a bolt's head on
        the wrong end, a bracket's legs swapped), re-centred."""
        E, maps = _distinct_axis_maps(model)
        out = []
        for k, Q in enumerate(maps[1:], start=1):
            T = centred_pose(best.T[:3, :3] @ E @ Q @ E.T, best.T[:3, 3], scene, model)
            if T is not None:
                out.append((T, f"{best.source}+turn_{k}"))
        # slid along its longest axis: the visible surface may be one end of the part (a bolt's head, the shank
        # hidden under a neighbour), which the centroid placed at the middle
        longest = best.T[:3, :3] @ E[:, 2]
        for fraction in self.config.slide_fractions:
            for sign in (1.0, -1.0):
                T = best.T.copy()
                T[:3, 3] += sign * fraction * float(model.diameter_m) * longest
                out.append((T, f"{best.source}+slide_{sign * fraction:+.2f}"))
        return out

    def _icp(self, T: np.ndarray, source: str, scene: np.ndarray, model: ObjectModel, obs: Observation) -> _Candidate:
        """ICP from a hypothesis, verified."""
        result = icp(T, scene, model, self.icp_config)
        if not np.isfinite(result.T_camera_object).all():
            return _Candidate(T, source, self.verifier.verify(T, model, obs))
        v = self.verifier.verify(result.T_camera_object, model, obs)
        return _Candidate(result.T_camera_object, f"{source}+icp", v, {**result.as_dict(), "status": "refined"})

    def _unverified(
        self, network_pose: ObjectPose | None, strategy: str, reason: str, t0: float, cleanup: dict | None = None
    ) -> ObjectPose | None:
        if network_pose is None:
            return None
        details = {**network_pose.details, "strategy": strategy, "reason": reason, "cleanup": cleanup,
                   "time_ms": (time.perf_counter() - t0) * 1e3}  # fmt: skip
        return ObjectPose(network_pose.detection, network_pose.T_camera_object, 0.0, strategy, details, verified=False)
