"""``sygrid show DIR [--items N] [--split SPLIT] [--out PNG] [--seed S]``: a picture of a dataset's labels.

Reads the BOP part of a generated dataset (``DIR/bop``: ``models/models_info.json`` for the 3D boxes, the items
through ``sygrid.writers.load_bop_item``) and draws, for each chosen item, the visible-mask outlines, the visible 2D
boxes, the 3D boxes and axes from the poses, and beside it the depth as a colour map; all items in one PNG grid.
Without ``--seed`` the first N items of the split are shown, with it N items drawn at random. Without ``--split``
the dataset's only split is shown, else ``train_pbr``. For a folder made by ``sygrid generate``, each shown item's
record (``DIR/records/``: the drop's stability figures and the quality gate's redraws) is printed, one line per item.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import cv2
import numpy as np

from sygrid.dataset import load_records
from sygrid.dataset_item import IMAGES_PER_SCENE
from sygrid.errors import ConfigError
from sygrid.fileio import read_json, write_bytes_atomic
from sygrid.visualize import compose_grid, depth_colormap, draw_annotation, put_caption
from sygrid.writers import load_bop_item

MM_PER_M = 1000.0
GRID_COLS = 2  # items per row; each item is RGB + depth side by side
MIN_TILE_HEIGHT_PX = 240


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dir", type=Path, help="dataset folder written by 'sygrid generate' (or a BOP root's parent)")
    parser.add_argument("--items", type=int, default=4, help="number of items to draw")
    parser.add_argument(
        "--split",
        default=None,
        help="BOP split folder, e.g. train_pbr, val_pbr, test (default: the only one, else train_pbr)",
    )
    parser.add_argument("--out", type=Path, default=None, help="PNG to write (default: DIR/show_<split>.png)")
    parser.add_argument("--seed", type=int, default=None, help="draw the items at random with this seed")


def load_model_bounds(bop_root: Path) -> dict[int, np.ndarray]:
    """obj_id -> (2, 3) model bounds in metres from ``models/models_info.json`` (millimetres in the file)."""
    path = bop_root / "models" / "models_info.json"
    if not path.is_file():
        raise ConfigError(f"{path}: missing; expected a dataset written by 'sygrid generate' (a BOP 'models' folder)")
    info = read_json(path, "models info")
    try:
        bounds = {}
        for key, entry in info.items():
            lo = np.array([entry["min_x"], entry["min_y"], entry["min_z"]], dtype=float) / MM_PER_M
            size = np.array([entry["size_x"], entry["size_y"], entry["size_z"]], dtype=float) / MM_PER_M
            bounds[int(key)] = np.stack([lo, lo + size])
    except (AttributeError, KeyError, TypeError, ValueError) as err:
        raise ConfigError(
            f"{path}: expected obj_id -> {{min_x, min_y, min_z, size_x, size_y, size_z}} (mm): {err!r}"
        ) from err
    return bounds


def choose_split(bop_root: Path, split: str | None) -> str:
    """``split``, or where it is None the BOP root's only split folder, else ``train_pbr``; several splits without
    ``train_pbr`` raise ConfigError listing them."""
    if split is not None:
        return split
    have = sorted(p.name for p in bop_root.iterdir() if p.is_dir() and p.name != "models") if bop_root.is_dir() else []
    if len(have) == 1:
        return have[0]
    if "train_pbr" in have or not have:
        return "train_pbr"
    raise ConfigError(f"{bop_root}: splits {have}; choose one with --split")


def list_items(bop_root: Path, split: str) -> list[tuple[int, int]]:
    """(scene_id, image_id) of every item of ``split`` that has a ``scene_gt.json`` entry, in order."""
    split_dir = bop_root / split
    if not split_dir.is_dir():
        have = sorted(p.name for p in bop_root.iterdir() if p.is_dir() and p.name != "models")
        raise ConfigError(f"{split_dir}: missing; splits in {bop_root}: {have or 'none'}")
    items = []
    for scene_dir in sorted(p for p in split_dir.iterdir() if p.is_dir() and p.name.isdigit()):
        gt_path = scene_dir / "scene_gt.json"
        if not gt_path.is_file():
            continue
        gt = read_json(gt_path, "BOP scene_gt")
        if not isinstance(gt, dict):
            raise ConfigError(f"{gt_path}: expected a JSON object keyed by image id, got {type(gt).__name__}")
        keys = gt.keys()
        items += [(int(scene_dir.name), int(k)) for k in sorted(keys, key=int)]
    if not items:
        raise ConfigError(f"{split_dir}: no items (no <scene>/scene_gt.json with entries)")
    return items


def item_picture(bop_root: Path, split: str, scene_id: int, image_id: int, bounds: dict[int, np.ndarray]) -> np.ndarray:
    """One item's labels drawn over its RGB, with its depth colour map to the right: (f H, 2 f W, 3) RGB uint8, where
    ``f`` is the smallest whole factor that makes the picture at least ``MIN_TILE_HEIGHT_PX`` high."""
    ann, rgb, depth_m = load_bop_item(bop_root, scene_id, image_id, split=split)
    overlay = draw_annotation(ann, rgb, bounds)
    if depth_m is None:
        depth_pic, depth_text = np.zeros_like(rgb), "no depth"
    else:
        # Colour range around the parts (from 1 cm before the nearest to 3 cm behind the farthest), so their relief
        # shows; the bin walls and floor beyond clip to the ends of the map.
        parts = np.zeros(depth_m.shape, dtype=bool)
        for inst in ann.instances:
            parts |= inst.mask_visib
        on_parts = depth_m[parts & (depth_m > 0)]
        near, far = (on_parts.min() - 0.01, on_parts.max() + 0.03) if on_parts.size else (None, None)
        depth_pic = depth_colormap(depth_m, near, far)
        valid = depth_m[depth_m > 0]
        depth_text = f"depth {valid.min():.3f}-{valid.max():.3f} m" if valid.size else "depth: none valid"
    picture = np.hstack([overlay, depth_pic])
    # Small items are scaled up (nearest neighbour, whole factors) so the captions and outlines stay readable.
    factor = max(1, math.ceil(MIN_TILE_HEIGHT_PX / picture.shape[0]))
    if factor > 1:
        picture = cv2.resize(picture, None, fx=factor, fy=factor, interpolation=cv2.INTER_NEAREST)
    seen = sum(1 for i in ann.instances if i.px_count_visib > 0)
    picture = put_caption(picture, f"{split} {scene_id:06d}/{image_id:06d}: {seen}/{len(ann.instances)} visible")
    w = picture.shape[1] // 2
    picture[:, w:] = put_caption(picture[:, w:], depth_text)
    return picture


def record_line(record: dict) -> str:
    """One line of an item's record: whether and when its pile settled, its penetration against the bound, and the
    attempts the quality gate redrew."""
    st = record.get("stability", {})
    settled = f"settled in {st['sim_time_s']:.2f} s" if st.get("settled") else "NOT settled"
    redraws = record.get("redraws", [])
    why = "; ".join(f"attempt {r['attempt']}: {r['reason']}" for r in redraws)
    return (
        f"{settled}, penetration {st.get('max_penetration_m', float('nan')) * 1e3:.3f} mm (bound "
        f"{st.get('penetration_bound_m', float('nan')) * 1e3:.2f} mm), {record.get('visible_instances', '?')}/"
        f"{record.get('instances', '?')} visible, {len(redraws)} redraw(s)" + (f" ({why})" if why else "")
    )


def run(args: argparse.Namespace) -> int:
    if args.items < 1:
        raise ConfigError(f"--items: expected >= 1, got {args.items}")
    if not args.dir.is_dir():
        raise ConfigError(f"{args.dir}: not a folder")
    # DIR is a generated dataset (DIR/bop/...) or a BOP root itself (DIR/models/...).
    bop_root = args.dir if (args.dir / "models").is_dir() and not (args.dir / "bop").is_dir() else args.dir / "bop"
    bounds = load_model_bounds(bop_root)
    split = choose_split(bop_root, args.split)
    items = list_items(bop_root, split)
    if args.seed is None:
        chosen = items[: args.items]
    else:
        picks = np.random.default_rng(args.seed).choice(len(items), size=min(args.items, len(items)), replace=False)
        chosen = [items[i] for i in sorted(picks)]
    pictures = [item_picture(bop_root, split, s, i, bounds) for s, i in chosen]
    records = load_records(args.dir) if bop_root == args.dir / "bop" else {}
    for s, i in chosen:
        record = records.get(s * IMAGES_PER_SCENE + i)
        if record is not None:
            print(f"{split} {s:06d}/{i:06d}: {record_line(record)}")
    sizes = {p.shape for p in pictures}
    if len(sizes) > 1:  # items of different sizes: scale all to the first one's size
        h, w = pictures[0].shape[:2]
        pictures = [cv2.resize(p, (w, h), interpolation=cv2.INTER_AREA) for p in pictures]
    grid = compose_grid(pictures, GRID_COLS)
    out = args.out if args.out is not None else args.dir / f"show_{split}.png"
    ok, png = cv2.imencode(".png", grid[..., ::-1])
    if not ok:
        raise OSError(f"{out}: PNG encoding failed")
    write_bytes_atomic(out, png.tobytes())
    print(f"wrote {out} ({len(chosen)} of {len(items)} items of {split}, {grid.shape[1]}x{grid.shape[0]} px)")
    return 0
