"""``sygrid bench render`` on a tiny image: the quality measures, the same-scene check, and the JSON it writes.

64x48 renders of the 20-part bin, 1 scene, spp {1, 4} against a 16-spp reference, 2 complete items: a few
seconds. No timing assertions (speed is the benchmark's business, not the tests').
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from sygrid.bench import render as br


def test_image_quality_matches_the_definitions():
    ref = np.full((48, 64, 3), 100, dtype=np.uint8)
    off_by_one = ref + 1  # MSE 1 -> PSNR = 10 log10(255^2) = 48.13 dB
    psnr, ssim = br.image_quality(ref, off_by_one)
    assert psnr == pytest.approx(10 * np.log10(255.0**2), abs=1e-6)
    assert ssim == pytest.approx(1.0, abs=1e-3)  # a constant offset of 1/255 barely changes structure
    noisy = np.clip(ref + np.random.default_rng(0).normal(0, 20, ref.shape), 0, 255).astype(np.uint8)
    psnr_noisy, ssim_noisy = br.image_quality(ref, noisy)
    assert psnr_noisy < 30 and ssim_noisy < 0.5
    with pytest.raises(ValueError, match="two uint8 images of one shape"):
        br.image_quality(ref, ref[:10])


def _args(**overrides: object) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    br.add_arguments(parser)
    args = parser.parse_args(["--size", "64", "48", "--scenes", "1", "--spp", "1", "4", "--ref-spp", "16"])
    for key, value in overrides.items():
        setattr(args, key, value)
    return args


@pytest.fixture(scope="module")
def results(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, Path]:
    out = tmp_path_factory.mktemp("bench_render")
    assert br.run(_args(rss_items=2), out_dir=out) == 0
    return json.loads((out / "render.json").read_text()), out


def test_quality_rises_with_spp_and_with_the_denoiser(results):
    data, _ = results
    by = {s["variant"]: s for s in data["sweep"]["summary"]}
    assert set(by) == {"reference", "1 spp, none", "1 spp, oidn", "4 spp, none", "4 spp, oidn", "raster"}
    assert by["4 spp, none"]["median_psnr_db"] > by["1 spp, none"]["median_psnr_db"] + 3.0  # ~6 dB per 4x spp
    assert by["4 spp, none"]["median_ssim"] > by["1 spp, none"]["median_ssim"]
    assert by["1 spp, oidn"]["median_psnr_db"] > by["1 spp, none"]["median_psnr_db"]
    assert by["raster"]["mode"] == "raster" and np.isfinite(by["raster"]["median_psnr_db"])
    runs = data["sweep"]["runs"]
    assert all(r["scene"] == 0 and r["render_s"] > 0 for r in runs)


def test_json_has_every_figure_and_the_png_is_written(results):
    data, out = results
    assert (out / "render.png").stat().st_size > 10_000
    assert {"machine", "config", "targets", "sweep", "default_preset", "rss_mb", "items", "failed_items"} <= set(data)
    cfg = data["config"]
    assert (cfg["width_px"], cfg["height_px"], cfg["scenes"], cfg["reference_spp"]) == (64, 48, 1, 16)
    d = data["default_preset"]
    assert d["preset"] == {"name": "fast", "spp": 4, "denoiser": "oidn", "max_depth": 8,
                           "reconstruction_filter": "box"}  # fmt: skip
    assert d["items"] == 2 and d["warmup_items"] == 1 and d["failed"] == 0
    assert d["sweep_point"]["variant"] == "4 spp, oidn"  # the preset's own row of the sweep gives its quality
    assert d["targets_met"]["psnr_db"] is (d["sweep_point"]["median_psnr_db"] >= 38.0)
    assert set(d["median_stage_s"]) == {
        "drop",
        "build",
        "rgb",
        "denoise",
        "ids_depth",
        "masks_full",
        "annotate",
        "write",
    }
    assert d["median_item_s"] >= sum(d["median_stage_s"].values()) * 0.5
    assert len(data["rss_mb"]) == 2 and all(r > 50 for r in data["rss_mb"])
    assert d["rss_growth"] == pytest.approx(data["rss_mb"][-1] / data["rss_mb"][1] - 1)
    item = data["items"][0]
    assert item["instances"] == 20 and item["item_s"] > item["drop_s"] > 0


def test_a_variant_from_other_random_draws_is_refused():
    scene = br.bench_scene(br.DEFAULT_SCENE, 32, 24)
    s = br.sweep_scenes(scene, 1, 0, br.DEFAULT_SCENE.parent)[0]
    one = br.with_render(scene, spp=1, denoiser="none")
    ref = br.render_sweep_item(one, s, br.DEFAULT_SCENE.parent)
    same = br.render_sweep_item(br.with_render(one, spp=2), s, br.DEFAULT_SCENE.parent)
    br.check_same_scene(ref, same, "same seed")  # passes
    other = br.render_sweep_item(one, replace(s, render_seed=s.render_seed + 1), br.DEFAULT_SCENE.parent)
    with pytest.raises(RuntimeError, match=r"other seed: the render's random draws differ"):
        br.check_same_scene(ref, other, "other seed")
