"""``sygrid convert SOURCE --out DIR``: SyGRID label pickles or YOLO-seg folders -> BOP / COCO / YOLO in the layout
``sygrid generate`` writes (``DIR/bop``, ``DIR/coco``, ``DIR/yolo``), with a report ``DIR/convert.json``.

SOURCE: a ``.pickle`` / ``.pkl`` file (SyGRID labels; images from ``--images``, depth from ``--depth``) or a YOLO-seg
folder (or its ``data.yaml``). The work is ``sygrid.convert``'s; this module parses the arguments and prints.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from sygrid.catalogue import load_catalogue
from sygrid.convert import FORMATS, REPORT_NAME, ConvertOptions, convert_sygrid_pickle, convert_yolo_seg
from sygrid.errors import ConfigError
from sygrid.id_map import load_id_map

PICKLE_SUFFIXES = (".pickle", ".pkl")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("source", type=Path, help="a SyGRID label pickle, or a YOLO-seg folder (or its data.yaml)")
    parser.add_argument("--out", type=Path, required=True, help="output dataset folder (must be new or empty)")
    parser.add_argument(
        "--formats",
        default=None,
        help=f"comma-separated, among {','.join(FORMATS)} (default: all for a pickle; coco,yolo for YOLO-seg, "
        "which has no poses)",
    )
    parser.add_argument("--split", default="test", help="split of a source without splits: train, val or test")
    parser.add_argument(
        "--id-map", type=Path, default=None, help="JSON object: class name or index (a pickle: its obj_id) -> obj_id"
    )
    parser.add_argument(
        "--catalogue", type=Path, default=None,
        help="parts catalogue (.toml/.json): class names -> its ids, the output's part names, meshes for bop",
    )  # fmt: skip
    parser.add_argument("--names", default=None, help="YOLO-seg without data.yaml: class names by index, a,b,c")
    parser.add_argument("--images", type=Path, default=None, help="pickle: image folder (default rgb/ or images/)")
    parser.add_argument("--depth", type=Path, default=None, help="pickle: depth PNG folder (default depth/, if any)")
    parser.add_argument("--no-depth", action="store_true", help="pickle: read no depth")
    parser.add_argument(
        "--depth-scale-mm", type=float, default=None, help="millimetres per unit of 16-bit depth PNGs (metric depth)"
    )
    parser.add_argument(
        "--bop-models", type=Path, default=None, help="BOP models folder (models_info.json, obj_*.ply): for bop"
    )
    parser.add_argument(
        "--box-tolerance-px",
        type=float,
        default=2.0,
        help="a stored box whose edge is further than this from its mask's is recomputed (%(default)s)",
    )
    parser.add_argument("--force", action="store_true", help="replace a non-empty --out")


def run(args: argparse.Namespace) -> int:
    is_pickle = args.source.is_file() and args.source.suffix.lower() in PICKLE_SUFFIXES
    if not args.source.exists():
        raise ConfigError(f"{args.source}: no such file or folder")
    default_formats = FORMATS if is_pickle else ("coco", "yolo")
    formats = tuple(f.strip() for f in args.formats.split(",") if f.strip()) if args.formats else default_formats
    options = ConvertOptions(
        formats=formats,
        split=args.split,
        id_map=load_id_map(args.id_map) if args.id_map is not None else None,
        box_tolerance_px=args.box_tolerance_px,
        depth_scale_mm=args.depth_scale_mm,
        bop_models=args.bop_models,
        depth=not args.no_depth,
        force=args.force,
        catalogue=load_catalogue(args.catalogue) if args.catalogue is not None else None,
    )
    if is_pickle:
        report = convert_sygrid_pickle(args.source, args.out, options, images_dir=args.images, depth_dir=args.depth)
    else:
        names = [n.strip() for n in args.names.split(",")] if args.names else None
        report = convert_yolo_seg(args.source, args.out, options, names=names)
    print(report.summary())
    if report.depth["dropped_non_metric"]:
        print(f"warning: {report.depth['dropped_non_metric']} depth maps are 8-bit (not metric depth): dropped")
    print(f"wrote {args.out} ({', '.join(formats)}) and {args.out / REPORT_NAME}")
    return 0
