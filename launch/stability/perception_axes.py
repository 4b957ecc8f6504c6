"""The perception axes: what each point varies and what it measures (``launch.stability.perception_pass``).

- ``depth_noise`` (issue 25, axis 4): the test set's exact depth through the OAK-D stereo model with its random
  depth errors scaled (``SensorModel.scaled``), pose strategies with ground-truth masks; seeds draw the noise.
- ``occlusion`` (axis 3) and ``part_size`` (axis 1): one pass over the test set, binned by each instance's visible
  fraction, or by its nominal size in image pixels (``fx * diameter / z``; instances seen at least 50 %, so that
  occlusion does not read as size); detection recall and pose accuracy. The two axes share the pass (cached), its
  time counted in the first one measured.
- ``distance`` (axis 1, by the camera): small generated sets with the camera at a fixed distance from the bin.
- ``clutter`` (axis 2): generated sets with N parts per bin.
- ``lighting`` and ``material`` (axis 5): generated sets through the OAK-D sensor model (dark and specular pixels
  drop out of its depth) with the environment's light scaled, or every part of one material.

Every axis reports each method per part family and per part (axis 7, ``part_family``).
"""

from __future__ import annotations

import math

from launch.stability.failure import Criterion
from launch.stability.generated import generated_set
from launch.stability.options import Options
from launch.stability.perception_pass import PASS_VERSION, PerceptionStack, measure_set, tally
from launch.stability.sweep import Axis, Method, Point
from sygrid.bench.common import dataset_digest

PERCEPTION_CRITERION = Criterion(fraction=0.8, floor=0.3)
DETECTION_METRIC = "detection recall"
POSE_METRIC = "pose accuracy (accepted ADD(-S) < 0.1 d)"
DEPTH_NOISE_IMAGES = 50  # test-set images per (point, seed) of the depth-noise axis (the binned axes read them all)
WELL_SEEN = 0.5  # the size axis counts instances at least this visible
VISIBILITY_BINS = ((0.9, 1.01), (0.75, 0.9), (0.6, 0.75), (0.45, 0.6), (0.3, 0.45), (0.2, 0.3), (0.1, 0.2))
SIZE_BINS_PX = ((96.0, math.inf), (64.0, 96.0), (48.0, 64.0), (36.0, 48.0), (28.0, 36.0), (22.0, 28.0),
                (16.0, 22.0), (0.0, 16.0))  # fmt: skip


def _methods(stack: PerceptionStack, detection: bool = True) -> tuple[Method, ...]:
    from launch.stability.perception_pass import DETECTION_METHODS

    det = tuple(Method(n, DETECTION_METRIC) for n in DETECTION_METHODS) if detection else ()
    return det + tuple(Method(s, POSE_METRIC) for s in stack.strategies)


def _settings(opts: Options, stack: PerceptionStack, **more) -> dict:
    # The pass version makes a point measured by an older pass a settings mismatch, refused rather than mixed in.
    return {"models": str(opts.models), "strategies": list(stack.strategies), "pass_version": PASS_VERSION, **more}


def _test_set_settings(opts: Options, stack: PerceptionStack, max_images: int | None, **more) -> dict:
    """``_settings`` of an axis that reads the test set ``opts.data``: its path, the digest of its annotations (a
    set generated again is measured again) and the images read."""
    return _settings(opts, stack, data=str(opts.data), data_digest=dataset_digest(opts.data), max_images=max_images,
                     **more)  # fmt: skip


# Axes whose frames come through a stereo sensor model record the depth tare's version, so that a point measured
# with an older tare is refused (2: the tare averages over the sensor's disparity steps instead of sticking on one).
SENSOR_TARE_VERSION = 2


def depth_noise_axis(opts: Options, stack: PerceptionStack) -> Axis:
    from sygrid.sensor import sensor_preset

    scales = (0.0, 1.0, 3.0) if opts.quick else (0.0, 0.5, 1.0, 1.5, 2.0, 3.0)
    base = sensor_preset("oak-d")
    max_images = opts.images_or(DEPTH_NOISE_IMAGES, quick=3)

    def measure(point: Point, seed: int) -> dict:
        sensor = base.scaled(point.params["noise_scale"])
        rows = measure_set(stack, opts.data, max_images, opts.cache_dir, detection=False, sensor=sensor,
                           sensor_seed=seed, progress=opts.progress)  # fmt: skip
        return tally(stack, rows)

    return Axis(
        name="depth_noise", title="Depth noise", x_label="depth noise (x the OAK-D model's)",
        points=tuple(Point(f"{s:g}x", s, {"noise_scale": s}) for s in scales),
        methods=_methods(stack, detection=False), measure=measure, seeds=opts.seeds_or((0,) if opts.quick else (0, 1)),
        criterion=PERCEPTION_CRITERION, summary="pose holds to {x} times the OAK-D's depth noise", unit="x",
        settings=_test_set_settings(opts, stack, max_images, sensor="oak-d", depth_tare=SENSOR_TARE_VERSION),
        description="The noise-free test set's exact depth through the OAK-D stereo model, its disparity noise, bias "
        "and dropouts scaled (the stereo geometry and the RGB noise as the preset's); pose strategies on "
        "ground-truth masks; seeds draw the noise.",
    )  # fmt: skip


def _binned(opts: Options, stack: PerceptionStack):
    """The test-set pass both binned axes read (cached on disk by ``measure_set``)."""
    max_images = opts.images_or(None, quick=5)
    return max_images, lambda: measure_set(stack, opts.data, max_images, opts.cache_dir, progress=opts.progress)


def occlusion_axis(opts: Options, stack: PerceptionStack) -> Axis:
    max_images, rows = _binned(opts, stack)

    def measure(point: Point, seed: int) -> dict:
        lo, hi = point.params["visible_fraction"]
        return tally(stack, rows(), lambda r: lo <= r["visib"] < hi)

    return Axis(
        name="occlusion", title="Occlusion", x_label="visible part of the part [%] (bin centres)",
        points=tuple(Point(f"{100 * lo:.0f}-{min(100 * hi, 100):.0f}%", 50 * (lo + min(hi, 1.0)),
                           {"visible_fraction": [lo, hi]}) for lo, hi in VISIBILITY_BINS),
        methods=_methods(stack), measure=measure, seeds=(0,), criterion=PERCEPTION_CRITERION,
        summary="holds down to {x} % of the part visible", unit="%",
        settings=_test_set_settings(opts, stack, max_images),
        description="One pass over the noise-free test set (the detector at its operating threshold; pose "
        "strategies on ground-truth masks), each instance binned by its visible fraction.",
    )  # fmt: skip


def size_axis(opts: Options, stack: PerceptionStack) -> Axis:
    max_images, rows = _binned(opts, stack)

    def measure(point: Point, seed: int) -> dict:
        lo, hi = point.params["nominal_px"]
        hi = math.inf if hi is None else hi
        return tally(stack, rows(), lambda r: r["visib"] >= WELL_SEEN and r["nominal_px"] is not None
                     and lo <= r["nominal_px"] < hi)  # fmt: skip

    def centre(lo: float, hi: float) -> float:
        return 1.15 * lo if math.isinf(hi) else (0.85 * hi if lo == 0 else math.sqrt(lo * hi))

    return Axis(
        name="part_size", title="Part size in pixels", x_label="nominal part size [image px] (fx x diameter / z)",
        points=tuple(Point(f"{lo:g}-{hi:g}px" if math.isfinite(hi) else f">{lo:g}px", round(centre(lo, hi), 1),
                           {"nominal_px": [lo, hi if math.isfinite(hi) else None]}) for lo, hi in SIZE_BINS_PX),
        methods=_methods(stack), measure=measure, seeds=(0,), criterion=PERCEPTION_CRITERION,
        summary="works down to {x} px", unit="px",
        settings=_test_set_settings(opts, stack, max_images, well_seen=WELL_SEEN),
        description="The occlusion axis's pass, instances seen at least 50 % binned by their nominal size (the "
        "model's diameter projected at the part's depth); detector scale 1 (network px = image px) for the "
        "built-in models.",
    )  # fmt: skip


def _generated_axis(opts: Options, stack: PerceptionStack, name: str, title: str, x_label: str, points, summary: str,
                    unit: str, description: str, sensor: bool = False) -> Axis:  # fmt: skip
    """``sensor``: the points' sets are generated through a stereo sensor model (their settings name the tare's
    version)."""
    count = min(opts.images_per_point, 2) if opts.quick else opts.images_per_point

    def measure(point: Point, seed: int) -> dict:
        data = generated_set(opts.recipe, point.params, count, seed, opts.cache_dir, name, point.label)
        return tally(stack, measure_set(stack, data, None, opts.cache_dir, progress=opts.progress))

    return Axis(
        name=name, title=title, x_label=x_label, points=tuple(points), methods=_methods(stack), measure=measure,
        seeds=opts.seeds_or((0,) if opts.quick else (0, 1)), criterion=PERCEPTION_CRITERION, summary=summary,
        unit=unit, settings=_settings(opts, stack, recipe=str(opts.recipe), images_per_point=count,
                                      **({"depth_tare": SENSOR_TARE_VERSION} if sensor else {})),
        description=description,
    )  # fmt: skip


def distance_axis(opts: Options, stack: PerceptionStack) -> Axis:
    ds = (0.6, 1.5) if opts.quick else (0.5, 0.75, 1.0, 1.25, 1.5, 2.0)
    key = "scene.camera.pose_sampling.distance_m"
    return _generated_axis(
        opts, stack, "distance", "Camera distance", "camera distance to the bin [m]",
        (Point(f"{d:g}m", d, {key: [d, d]}) for d in ds), "works out to {x} m from the bin", "m",
        "Generated sets of the test recipe with the camera at a fixed distance (tilt and aim drawn as the recipe's).",
    )  # fmt: skip


def clutter_axis(opts: Options, stack: PerceptionStack) -> Axis:
    ns = (5, 20) if opts.quick else (5, 10, 20, 30, 45, 60)
    return _generated_axis(
        opts, stack, "clutter", "Clutter", "parts per bin", (Point(f"{n} parts", n, {"parts_per_bin": n}) for n in ns),
        "holds up to {x} parts per bin", "parts",
        "Generated sets of the test recipe with N parts per bin (the kinds in the recipe's proportions).",
    )  # fmt: skip


def lighting_axis(opts: Options, stack: PerceptionStack) -> Axis:
    levels = (1.0, 0.12) if opts.quick else (2.0, 1.0, 0.5, 0.25, 0.12, 0.06)
    return _generated_axis(
        opts, stack, "lighting", "Lighting", "environment light (x the recipe's)",
        (Point(f"{s:g}x light", s, {"scene.environment.strength": s, "sensor": "oak-d"}) for s in levels),
        "holds down to {x} times the recipe's light", "x",
        "Generated sets through the OAK-D sensor model (dark pixels drop out of its depth) with the environment "
        "light scaled; the recipe's random lights kept.", sensor=True,
    )  # fmt: skip


def material_axis(opts: Options, stack: PerceptionStack) -> Axis:
    materials = ("painted", "steel") if opts.quick else ("painted", "catalogued", "zinc", "steel")
    return _generated_axis(
        opts, stack, "material", "Material", "every part's material",
        (Point(m, None, {"sensor": "oak-d", **({} if m == "catalogued" else {"material": m})}) for m in materials),
        "holds through {x}", "",
        "Generated sets through the OAK-D sensor model (specular metal drops out of its depth in patches) with "
        "every part painted, as catalogued, or of one metal.", sensor=True,
    )  # fmt: skip
