"""``sygrid bench render``: path-traced quality against time (spp x denoiser, raster), complete items, and RSS.

Three measurements on the 20-part bin (``launch/scenes/builtin_bin.json``, 640x480):

1. **Quality sweep.** For a few scenes (a drop seed, a camera pose and a render seed each) a reference is path
   traced at ``--ref-spp`` (1024) with no denoiser; then every spp in {1, 4, 16, 64, 256} without and with OIDN,
   and the rasterised mode, each from the same rng state as the reference, so materials, lights, sampler seed and
   camera are the same and only spp / denoiser (or the mode) differ. That is checked, not assumed: the render
   settings may differ only in those fields, the rng must end in the same state and the 1-spp id/depth pass must
   give the same bytes as the reference's. Quality is PSNR (``cv2.PSNR``) and SSIM (``cv2.quality.QualitySSIM``,
   mean over the colour channels) of the uint8 sRGB images against the reference. Time is the colour render:
   scene build + path tracing + denoising (``RenderResult.timings``). The renderer returns only the final uint8
   image, not the noisy linear colour and its guides, so the OIDN variant is a second render of the same samples
   (same seed) rather than OIDN applied to the first one.
2. **Complete items of the default preset** (the scene's own render settings, "fast": 4 spp + OIDN, box filter):
   ``sygrid.dataset_item.make_item`` (drop + render with full masks + annotations), then the item written in BOP, YOLO
   and COCO to a temporary folder by the generator's own writers. Median seconds per item and the split by stage.
3. **Memory**: the process's resident set size after each of ``--rss-items`` consecutive complete items; growth =
   last / first-after-warm-up - 1. The timings of step 2 are the medians of these same items.

Targets on a 2-core machine: a complete default-preset item in at most 3 s at no less than 38 dB PSNR against the
reference; RSS growth under 10 % over 300 items. PSNR against a 1024-spp reference is capped by the reference's own
noise (it is not the converged image), so the high-spp end of the curve flattens.
"""

from __future__ import annotations

import argparse
import logging
import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import matplotlib
import matplotlib.ticker

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from tqdm import tqdm

from sygrid.bench.common import DEFAULT_RESULTS_DIR, median, percentile, save_results
from sygrid.dataset import DatasetOutput
from sygrid.dataset_item import make_item
from sygrid.drop import drop_scene, resolve_objects
from sygrid.errors import ConfigError, SygridError
from sygrid.recipe import Recipe, parse_recipe
from sygrid.render import render_item, sample_T_world_camera
from sygrid.render.renderer import RenderResult
from sygrid.scene import SceneSpec, intrinsics_from_spec, load_scene, scene_to_json

log = logging.getLogger(__name__)

DEFAULT_SCENE = Path(__file__).resolve().parents[2] / "launch" / "scenes" / "builtin_bin.json"
SPPS = (1, 4, 16, 64, 256)
DENOISERS = ("none", "oidn")
REFERENCE_SPP = 1024
QUICK = {"scenes": 1, "ref_spp": 256, "rss_items": 10}
TARGETS = {"item_s": 3.0, "psnr_db": 38.0, "rss_growth": 0.10}
# Fields of the render settings that a sweep variant may change against the reference.
_SWEPT_FIELDS = {"spp", "denoiser"}
_RASTER_MIN_ID_AGREEMENT = 0.97  # share of pixels with the same instance id in the raster and reference images


# ------------------------------------------------------------------------------------------------ measures
def image_quality(reference: np.ndarray, image: np.ndarray) -> tuple[float, float]:
    """(PSNR in dB, SSIM) of a uint8 (H, W, 3) image against a uint8 reference of the same shape.

    PSNR over all channels together (OpenCV's ``cv2.PSNR``, peak 255; identical images give OpenCV's cap of about
    361 dB); SSIM is OpenCV contrib's ``QualitySSIM`` (Gaussian window, per channel), averaged over the channels.
    """
    reference, image = np.asarray(reference), np.asarray(image)
    if reference.shape != image.shape or reference.dtype != np.uint8 or image.dtype != np.uint8:
        raise ValueError(
            f"image_quality: expected two uint8 images of one shape, got {reference.dtype} {reference.shape} "
            f"and {image.dtype} {image.shape}"
        )
    psnr = float(cv2.PSNR(reference, image, 255.0))
    channels = 1 if reference.ndim == 2 else reference.shape[2]
    ssim = float(np.mean(cv2.quality.QualitySSIM_compute(reference, image)[0][:channels]))
    return psnr, ssim


def rss_bytes() -> int:
    """This process's resident set size in bytes (``VmRSS`` of ``/proc/self/status``; psutil elsewhere)."""
    status = Path("/proc/self/status")
    if status.exists():
        for line in status.read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024  # the kernel reports kB
    try:
        import psutil
    except ImportError as exc:
        raise RuntimeError("cannot read the RSS: no /proc/self/status and psutil is not installed") from exc
    return int(psutil.Process().memory_info().rss)


def colour_seconds(timings: dict[str, float]) -> float:
    """Seconds of the colour image of a render: scene build + colour pass + denoiser (no id/depth/mask passes)."""
    return timings.get("build", 0.0) + timings.get("rgb", 0.0) + timings.get("denoise", 0.0)


# ------------------------------------------------------------------------------------------------ scenes
def bench_scene(path: Path = DEFAULT_SCENE, width_px: int = 640, height_px: int = 480) -> SceneSpec:
    """The benchmark's scene file at ``width_px`` x ``height_px`` (its field of view kept)."""
    scene = load_scene(path)
    camera = scene.camera.model_copy(update={"width_px": int(width_px), "height_px": int(height_px)})
    return scene.model_copy(update={"camera": camera})


def with_render(scene: SceneSpec, **fields: object) -> SceneSpec:
    """``scene`` with some render settings replaced (``spp``, ``denoiser``, ``mode``)."""
    return scene.model_copy(update={"render": scene.render.model_copy(update=fields)})


@dataclass
class SweepScene:
    """One scene of the quality sweep: the settled pile, the camera and the seed every render starts from."""

    index: int
    drop: object  # sygrid.physics.DropResult
    T_world_camera: np.ndarray
    render_seed: int


def sweep_scenes(scene: SceneSpec, count: int, seed: int, base_dir: Path) -> list[SweepScene]:
    """``count`` scenes, scene k from ``SeedSequence([seed, k])``: a drop seed, a camera pose and a render seed."""
    out = []
    for k in range(count):
        drop_ss, camera_ss, render_ss = np.random.SeedSequence([seed, k]).spawn(3)
        drop_seed = int(np.random.default_rng(drop_ss).integers(0, 2**31 - 1))
        drop = drop_scene(scene, drop_seed, base_dir)
        if not drop.report.ok:
            log.warning("sweep scene %d: the drop did not fully settle (%s); rendering it anyway", k, drop.report)
        T_world_camera = sample_T_world_camera(scene.camera.pose_sampling, np.random.default_rng(camera_ss))
        render_seed = int(np.random.default_rng(render_ss).integers(0, 2**31 - 1))
        out.append(SweepScene(k, drop, T_world_camera, render_seed))
    return out


def render_sweep_item(scene: SceneSpec, s: SweepScene, base_dir: Path) -> tuple[RenderResult, dict]:
    """One render of sweep scene ``s`` from its seed, without full masks; also the rng state it leaves.
    ``timings["cpu"]`` is the process's CPU seconds (all threads) for the whole render."""
    rng = np.random.default_rng(s.render_seed)
    cpu0 = time.process_time()
    d = s.drop
    res = render_item(
        scene, d.models, d.instances, d.T_world_obj, s.T_world_camera, intrinsics_from_spec(scene.camera), rng,
        base_dir=base_dir, full_masks=False,
    )  # fmt: skip
    res.timings["cpu"] = time.process_time() - cpu0
    return res, rng.bit_generator.state


def check_same_scene(reference: tuple[RenderResult, dict], variant: tuple[RenderResult, dict], what: str) -> None:
    """Raises RuntimeError when a variant was not rendered from the reference's scene, camera and rng draws."""
    (ref, ref_state), (res, state) = reference, variant
    if state != ref_state:
        raise RuntimeError(f"{what}: the render's random draws differ from the reference's (rng state after it)")
    if not np.array_equal(ref.ids_visib, res.ids_visib) or not np.array_equal(ref.depth_m, res.depth_m):
        raise RuntimeError(f"{what}: the id/depth pass differs from the reference's: not the same scene and camera")


def sweep_one_scene(
    scene: SceneSpec, s: SweepScene, spps: tuple[int, ...], ref_spp: int, base_dir: Path, raster: bool = True
) -> tuple[list[dict], dict[str, np.ndarray]]:
    """Reference + every (spp, denoiser) + the rasterised mode for one scene.

    Returns one row per variant (``spp``, ``denoiser``, ``mode``, ``render_s`` colour seconds, ``total_s`` with the
    id/depth pass, ``cpu_s``, ``psnr_db``, ``ssim``; the reference's PSNR is None) and the uint8 images by label.
    """
    ref_scene = with_render(scene, spp=int(ref_spp), denoiser="none", mode="pathtrace")
    reference = render_sweep_item(ref_scene, s, base_dir)
    ref_rgb = reference[0].rgb
    images = {"reference": ref_rgb}
    rows = [_row(s, "reference", "pathtrace", ref_spp, "none", reference[0], ref_rgb)]
    for spp in spps:
        for denoiser in DENOISERS:
            v_scene = with_render(ref_scene, spp=int(spp), denoiser=denoiser)
            changed = {k for k, v in v_scene.render if v != getattr(ref_scene.render, k)}
            if not changed <= _SWEPT_FIELDS:
                raise RuntimeError(f"sweep variant changes {sorted(changed)}; only {sorted(_SWEPT_FIELDS)} may differ")
            label = f"{spp} spp, {denoiser}"
            variant = render_sweep_item(v_scene, s, base_dir)
            check_same_scene(reference, variant, f"scene {s.index}, {label}")
            images[label] = variant[0].rgb
            rows.append(_row(s, label, "pathtrace", spp, denoiser, variant[0], ref_rgb))
    if raster:
        res, _ = render_sweep_item(with_render(ref_scene, mode="raster"), s, base_dir)
        # Another rasteriser, so edge pixels differ; the instance ids must still agree almost everywhere (same pile,
        # same camera): 99.9 % of the pixels at 640x480, 98.7 % at 64x48 where edges are a large share.
        agree = float(np.mean(res.ids_visib == reference[0].ids_visib))
        if agree < _RASTER_MIN_ID_AGREEMENT:
            raise RuntimeError(f"scene {s.index}, raster: instance ids agree with the reference's on only {agree:.1%}")
        images["raster"] = res.rgb
        rows.append(_row(s, "raster", "raster", 0, "none", res, ref_rgb))
    return rows, images


def _row(s: SweepScene, label: str, mode: str, spp: int, denoiser: str, res: RenderResult, ref: np.ndarray) -> dict:
    psnr, ssim = image_quality(ref, res.rgb) if label != "reference" else (None, 1.0)
    return {
        "scene": s.index, "variant": label, "mode": mode, "spp": int(spp), "denoiser": denoiser,
        "render_s": colour_seconds(res.timings), "total_s": res.timings.get("total", float("nan")),
        "cpu_s": res.timings.get("cpu", float("nan")),
        "denoise_s": res.timings.get("denoise", 0.0), "psnr_db": psnr, "ssim": ssim, "backend": res.variant,
    }  # fmt: skip


def summarise_sweep(rows: list[dict]) -> list[dict]:
    """Per variant over scenes: median colour seconds, median and min PSNR, median SSIM."""
    out = []
    for label in dict.fromkeys(r["variant"] for r in rows):
        sel = [r for r in rows if r["variant"] == label]
        finite = [r["psnr_db"] for r in sel if r["psnr_db"] is not None]
        out.append(
            {
                "variant": label, "mode": sel[0]["mode"], "spp": sel[0]["spp"], "denoiser": sel[0]["denoiser"],
                "scenes": len(sel), "median_render_s": median([r["render_s"] for r in sel]),
                "median_total_s": median([r["total_s"] for r in sel]),
                "median_cpu_s": median([r["cpu_s"] for r in sel]),
                "median_psnr_db": median(finite) if finite else None,
                "min_psnr_db": min(finite) if finite else None,
                "median_ssim": median([r["ssim"] for r in sel]),
            }
        )  # fmt: skip
    return out


# ------------------------------------------------------------------------------------------------ complete items
def bench_recipe(scene: SceneSpec, base_dir: Path) -> Recipe:
    """A recipe of ``scene`` as it is (its own render preset, no raster items), all three formats, full masks."""
    data = {
        "name": "bench_render", "scene": scene_to_json(scene), "split": "train", "val_fraction": 0.0,
        "formats": ["bop", "yolo", "coco"], "raster_fraction": 0.0, "full_masks": True,
    }  # fmt: skip
    return parse_recipe(data, "bench render recipe", base_dir)


def complete_item(recipe: Recipe, output: DatasetOutput, seed: int, index: int) -> dict:
    """Item ``index`` of ``recipe`` made (``make_item``) and written by ``output``; its row: stage seconds,
    ``item_s`` = drop + render + annotate + write, ``cpu_s`` (this process, every thread), the render ``mode``,
    ``instances`` and ``rss_mb`` after the item. Raises ``SygridError`` for a drop that never settles."""
    cpu0 = time.process_time()
    item = make_item(recipe, seed, index)
    t = time.perf_counter()
    output.write(item)
    write_s = time.perf_counter() - t
    cpu_s = time.process_time() - cpu0
    tm = item.timings
    render_s = tm.get("render_total", 0.0)
    row = {"index": index, "mode": item.mode, "drop_s": tm["drop"], "render_s": render_s}
    row.update({k.removeprefix("render_"): v for k, v in tm.items() if k.startswith("render_")})
    row.pop("total")
    row.update(
        annotate_s=max(tm["item"] - tm["drop"] - render_s, 0.0),
        write_s=write_s,
        item_s=tm["item"] + write_s,
        cpu_s=cpu_s,
        instances=len(item.annotation.instances),
        rss_mb=rss_bytes() / 2**20,
    )
    return row


def complete_items(recipe: Recipe, count: int, seed: int, progress: bool = True) -> dict:
    """``count`` consecutive complete items (``complete_item``, written into a temporary folder).

    Returns ``items`` (``complete_item``'s rows) plus ``failed`` (index -> error) and ``finish_s`` (assembling the
    COCO JSON / data.yaml once at the end).
    """
    models = resolve_objects(recipe.scene, recipe.base_dir)
    items: list[dict] = []
    failed: dict[int, str] = {}
    with tempfile.TemporaryDirectory(prefix="sygrid_bench_render_") as tmp:
        output = DatasetOutput(Path(tmp), recipe, models)
        for i in tqdm(range(count), desc="complete items", unit="item", disable=not progress):
            try:
                items.append(complete_item(recipe, output, seed, i))
            except SygridError as exc:  # a drop that never settles: recorded, the run goes on
                failed[i] = f"{type(exc).__name__}: {exc}"
        t = time.perf_counter()
        output.finish()
        finish_s = time.perf_counter() - t
    return {"items": items, "failed": failed, "finish_s": finish_s}


def warmup_items(count: int) -> int:
    """Items left out of medians and of the RSS baseline: JIT compilation, caches and imports settle in them."""
    return max(1, min(10, count // 5))


def summarise_items(run: dict) -> dict:
    """Median and 90th-percentile seconds per complete item, the per-stage medians and the RSS growth."""
    items = run["items"]
    if not items:
        raise RuntimeError(f"no complete item succeeded: {run['failed']}")
    w = min(warmup_items(len(items)), len(items) - 1)
    timed = items[w:]
    stages = ("drop_s", "build", "rgb", "denoise", "ids_depth", "masks_full", "annotate_s", "write_s")
    rss = [it["rss_mb"] for it in items]
    slope = float(np.polyfit(np.arange(len(rss) - w), rss[w:], 1)[0]) if len(rss) - w >= 2 else float("nan")
    return {
        "items": len(items), "warmup_items": w, "failed": len(run["failed"]),
        "median_item_s": median([it["item_s"] for it in timed]),
        "p90_item_s": percentile([it["item_s"] for it in timed], 90),
        "median_item_cpu_s": median([it["cpu_s"] for it in timed]),
        "median_stage_s": {s.removesuffix("_s"): median([it.get(s, 0.0) for it in timed]) for s in stages},
        "finish_s": run["finish_s"],
        "rss_first_mb": rss[0], "rss_after_warmup_mb": rss[w], "rss_last_mb": rss[-1], "rss_peak_mb": max(rss),
        "rss_growth": rss[-1] / rss[w] - 1.0, "rss_slope_mb_per_item": slope,
    }  # fmt: skip


# ------------------------------------------------------------------------------------------------ the chart
def chart(summary: list[dict], default: dict, rss_mb: list[float], warmup: int, title: str):
    fig, axes = plt.subplots(1, 3, figsize=(19, 5.2))
    ax_psnr, ax_ssim, ax_rss = axes
    colours = {"none": "tab:blue", "oidn": "tab:orange"}
    for ax, key in ((ax_psnr, "median_psnr_db"), (ax_ssim, "median_ssim")):
        for den in DENOISERS:
            sel = [
                s for s in summary if s["mode"] == "pathtrace" and s["denoiser"] == den and s["variant"] != "reference"
            ]
            sel = sorted(sel, key=lambda s: s["spp"])
            x, y = [s["median_render_s"] for s in sel], [s[key] for s in sel]
            ax.plot(x, y, "o-", color=colours[den], label="no denoiser" if den == "none" else "OIDN")
            for s in sel:
                ax.annotate(f"{s['spp']}", (s["median_render_s"], s[key]), textcoords="offset points", xytext=(4, -10),
                            fontsize=7, color=colours[den])  # fmt: skip
        for s in summary:
            if s["mode"] == "raster":
                ax.scatter(s["median_render_s"], s[key], marker="s", s=60, color="tab:green", label="raster (MuJoCo)")
        fast = default.get("sweep_point")
        if fast is not None:
            ax.scatter(fast["median_render_s"], fast[key], marker="o", s=160, facecolors="none", edgecolors="red",
                       label="default preset: render")  # fmt: skip
            if key == "median_psnr_db":
                ax.plot([fast["median_render_s"], default["median_item_s"]], [fast[key]] * 2, "--", color="red", lw=1)
                ax.scatter(default["median_item_s"], fast[key], marker="*", s=220, color="red", zorder=5,
                           label="default preset: complete item")  # fmt: skip
        ax.set_xscale("log")
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.grid(alpha=0.3, which="both")
    ax_psnr.axhline(TARGETS["psnr_db"], color="grey", ls=":", lw=1)
    ax_psnr.axvline(TARGETS["item_s"], color="grey", ls=":", lw=1)
    ax_psnr.text(TARGETS["item_s"], ax_psnr.get_ylim()[0], " 3 s / item", fontsize=7, color="grey", va="bottom")
    ax_psnr.text(ax_psnr.get_xlim()[1], TARGETS["psnr_db"], "38 dB ", fontsize=7, color="grey", va="bottom", ha="right")
    ax_psnr.set(xlabel="seconds per render (colour: build + trace + denoise), median; star: complete item",
                ylabel="PSNR against the reference [dB]", title="Quality against time")  # fmt: skip
    ax_psnr.legend(fontsize=7, loc="lower right")
    ax_ssim.set(xlabel="seconds per render, median", ylabel="SSIM against the reference", title="SSIM")
    x = np.arange(len(rss_mb))
    ax_rss.plot(x, rss_mb, "-", color="tab:purple", lw=1)
    ax_rss.axvspan(-0.5, warmup - 0.5, color="grey", alpha=0.15, label="warm-up")
    if len(rss_mb) > warmup:
        ax_rss.axhline(rss_mb[warmup] * (1 + TARGETS["rss_growth"]), color="grey", ls=":", lw=1,
                       label="+10 % over the first item after warm-up")  # fmt: skip
    ax_rss.set(xlabel="complete item (default preset)", ylabel="RSS after the item [MiB]", title="Memory")
    ax_rss.set_ylim(0, 1.15 * max([*rss_mb, rss_mb[min(warmup, len(rss_mb) - 1)] * (1 + TARGETS["rss_growth"])]))
    ax_rss.legend(fontsize=7, loc="lower right")
    ax_rss.grid(alpha=0.3)
    fig.suptitle(title)
    return fig


# ------------------------------------------------------------------------------------------------ the command
def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", type=Path, default=DEFAULT_SCENE, help="scene file (default: the 20-part bin)")
    parser.add_argument("--scenes", type=int, default=3, help="scenes in the quality sweep (drop + camera each)")
    parser.add_argument("--spp", type=int, nargs="+", default=list(SPPS), help="samples per pixel to sweep")
    parser.add_argument("--ref-spp", type=int, default=REFERENCE_SPP, help="samples per pixel of the reference")
    parser.add_argument("--rss-items", type=int, default=300, help="consecutive complete items (timing + RSS)")
    parser.add_argument("--size", type=int, nargs=2, default=[640, 480], metavar=("W", "H"), help="image size")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-raster", action="store_true", help="leave the rasterised mode out of the sweep")
    parser.add_argument("--quick", action="store_true", help="1 scene, reference at 256 spp, 10 complete items")


def run_benchmark(args: argparse.Namespace, progress: bool = True) -> dict:
    """Every measurement of the module docstring; returns the JSON-ready results (without the machine info)."""
    if args.quick:
        args.scenes, args.ref_spp, args.rss_items = QUICK["scenes"], QUICK["ref_spp"], QUICK["rss_items"]
    if args.scenes < 1 or args.rss_items < 2 or args.ref_spp < 1 or min(args.spp) < 1:
        raise ConfigError("--scenes >= 1, --rss-items >= 2, --ref-spp >= 1 and every --spp >= 1 expected")
    os.environ.setdefault("MUJOCO_GL", "egl")  # the raster mode renders headless
    width, height = args.size
    scene = bench_scene(args.scene, width, height)
    base_dir = args.scene.parent
    # A variant at or above the reference's spp would be compared with (a copy of) itself.
    spps = tuple(sorted(v for v in set(args.spp) if v < args.ref_spp))
    if not spps:
        raise ConfigError(f"--spp: every value is >= --ref-spp {args.ref_spp}; nothing to compare")
    load_before = os.getloadavg()
    scenes = sweep_scenes(scene, args.scenes, args.seed, base_dir)
    # Not timed: the one-time costs of the process (Mitsuba variant check, first JIT kernels, OIDN's library load)
    # belong to no variant; a long generator run pays them once.
    render_sweep_item(with_render(scene, spp=1, denoiser="oidn", mode="pathtrace"), scenes[0], base_dir)
    rows = []
    for s in tqdm(scenes, desc="quality sweep", unit="scene", disable=not progress):
        scene_rows, _ = sweep_one_scene(scene, s, spps, args.ref_spp, base_dir, raster=not args.no_raster)
        rows += scene_rows
    summary = summarise_sweep(rows)
    rs = scene.render
    items_run = complete_items(bench_recipe(scene, base_dir), args.rss_items, args.seed, progress)
    default = summarise_items(items_run)
    point = next(
        (s for s in summary if s["mode"] == "pathtrace" and s["spp"] == rs.spp and s["denoiser"] == rs.denoiser), None
    )
    default["sweep_point"] = point
    default["preset"] = {"name": rs.preset, "spp": rs.spp, "denoiser": rs.denoiser, "max_depth": rs.max_depth,
                         "reconstruction_filter": rs.reconstruction_filter}  # fmt: skip
    psnr = point["median_psnr_db"] if point else None
    load_after = os.getloadavg()
    default["targets_met"] = {
        "item_s": default["median_item_s"] <= TARGETS["item_s"],
        "psnr_db": psnr is not None and psnr >= TARGETS["psnr_db"],
        "rss_growth": default["rss_growth"] < TARGETS["rss_growth"],
    }
    return {
        "config": {
            "scene": str(args.scene), "width_px": width, "height_px": height, "scenes": args.scenes,
            "spps": list(spps), "reference_spp": args.ref_spp, "rss_items": args.rss_items, "seed": args.seed,
            "max_depth": rs.max_depth, "reconstruction_filter": rs.reconstruction_filter, "quick": bool(args.quick),
            "backend": rows[0]["backend"] if rows else "",
            "load_average_1_5_15_min": {"start": list(load_before), "end": list(load_after)},
        },
        "targets": TARGETS,
        "sweep": {"summary": summary, "runs": rows},
        "default_preset": default,
        "rss_mb": [it["rss_mb"] for it in items_run["items"]],
        "items": items_run["items"],
        "failed_items": {str(k): v for k, v in items_run["failed"].items()},
    }  # fmt: skip


def print_table(results: dict) -> None:
    cfg, d = results["config"], results["default_preset"]
    print(f"quality sweep: {cfg['scenes']} scene(s), {cfg['width_px']}x{cfg['height_px']}, reference "
          f"{cfg['reference_spp']} spp, {cfg['backend']}")  # fmt: skip
    print(f"{'variant':<18}{'render s':>10}{'+ids s':>9}{'CPU s':>8}{'PSNR dB':>9}{'min dB':>8}{'SSIM':>8}")
    for s in results["sweep"]["summary"]:
        if s["variant"] == "reference":
            print(f"{'reference':<18}{s['median_render_s']:>10.2f}{s['median_total_s']:>9.2f}{s['median_cpu_s']:>8.2f}")
            continue
        print(f"{s['variant']:<18}{s['median_render_s']:>10.2f}{s['median_total_s']:>9.2f}{s['median_cpu_s']:>8.2f}"
              f"{s['median_psnr_db']:>9.2f}{s['min_psnr_db']:>8.2f}{s['median_ssim']:>8.4f}")  # fmt: skip
    p = d["preset"]
    print(f"\ncomplete items, preset '{p['name']}' ({p['spp']} spp, {p['denoiser']}, {p['reconstruction_filter']} "
          f"filter): {d['items']} items ({d['warmup_items']} warm-up), {d['failed']} failed")  # fmt: skip
    stages = ", ".join(f"{k} {v:.2f}" for k, v in d["median_stage_s"].items())
    print(f"  median {d['median_item_s']:.2f} s/item (p90 {d['p90_item_s']:.2f}), CPU {d['median_item_cpu_s']:.2f} "
          f"s/item (all threads); stages (median s): {stages}")  # fmt: skip
    point = d["sweep_point"]
    met = d["targets_met"]
    psnr = f"{point['median_psnr_db']:.2f} dB" if point else "n/a (preset not in the sweep)"
    print(f"  PSNR of the preset: {psnr}; targets: <= {TARGETS['item_s']} s {'met' if met['item_s'] else 'NOT met'}, "
          f">= {TARGETS['psnr_db']} dB {'met' if met['psnr_db'] else 'NOT met'}")  # fmt: skip
    print(f"memory: RSS {d['rss_after_warmup_mb']:.0f} MiB after warm-up -> {d['rss_last_mb']:.0f} MiB after item "
          f"{d['items']} (peak {d['rss_peak_mb']:.0f}): growth {100 * d['rss_growth']:+.1f} % "
          f"({d['rss_slope_mb_per_item']:+.3f} MiB/item), target < {100 * TARGETS['rss_growth']:.0f} % "
          f"{'met' if met['rss_growth'] else 'NOT met'}")  # fmt: skip


def run(args: argparse.Namespace, out_dir: Path = DEFAULT_RESULTS_DIR) -> int:
    logging.getLogger("sygrid.physics").setLevel(logging.ERROR)  # per-drop warnings are not this benchmark's topic
    results = run_benchmark(args)
    print_table(results)
    d = results["default_preset"]
    cfg = results["config"]
    title = (
        f"sygrid bench render: {cfg['width_px']}x{cfg['height_px']}, {Path(cfg['scene']).stem}, reference "
        f"{cfg['reference_spp']} spp, {cfg['scenes']} scene(s), {cfg['backend']}, {os.cpu_count()} shared CPU cores"
    )
    fig = chart(results["sweep"]["summary"], d, results["rss_mb"], d["warmup_items"], title)
    json_path, png_path = save_results("render", results, fig, out_dir)
    plt.close(fig)
    print(f"wrote {json_path} and {png_path}")
    return 0
