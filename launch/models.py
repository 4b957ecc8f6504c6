"""``sygrid models pack``: turn a detector run and a pose run into a model folder the pipeline loads, with a model
card per model (data, command, seed, training time, size, metrics on a held-out test set). ``sygrid models
choose-pose`` (``launch.choose_pose``) measures the pose strategies per part and writes the choice into the folder.

    sygrid models pack --detector runs/detector --pose runs/pose --out models/builtin --test-data datasets/test

writes ``OUT/manifest.json``, ``OUT/detector.onnx``, ``OUT/pose.onnx``, ``OUT/eval_detector.json`` (the detector
alone at confidence 0.001, the convention for mAP), ``OUT/eval_direct.json`` and ``OUT/eval_refined.json``
(``sygrid eval`` of the pipeline at its operating threshold, direct estimate and with depth refinement; with
per-part pose strategies in the manifest, ``OUT/eval_strategies.json``, the folder as shipped, instead of the
refined one), and
``OUT/detector.card.md`` / ``OUT/pose.card.md``. Everything in the cards is read from the runs' ``train_log.json``,
the datasets' ledgers (``dataset.json``: recipe, seed, items) and the evaluations, so the cards cannot drift from
the files they describe.

The folder's parts (the manifest's ``objects``): the built-in parts the detector's classes name, or, for your own
parts, the parts catalogue the models were trained with (``--catalogue FILE``, default: the one the detector was
trained with, ``sygrid train detector --catalogue``). The catalogue is copied into the folder
(``OUT/catalogue/parts.toml`` with the parts' CAD files, the manifest's ``"catalogue"`` naming it), not referenced:
the networks are bound to the ids and meshes they were trained on, so the folder keeps them when the catalogue is
edited later or the folder is moved to the cell's machine. The detector's classes and the pose model's parts must
be the catalogue's by name and obj_id.

``--pose`` may also name a model folder (one with ``manifest.json``): a new detector is then packed beside that
folder's pose network, which keeps its manifest entry (method, per-part strategies), its verification settings and
its card (training lines and the strategy table), and the stages after it (refinement, verification, depth tare);
only the card's held-out evaluation is measured again. It may be
the ``--out`` folder itself. ``--detector`` may name a model folder the same way: its detector network is packed
with its card's training lines (what was trained, how, from what), and the held-out evaluation is measured again on
``--test-data`` (a detector trained once serving another camera's folder, e.g. the simulated cell's).
"""

from __future__ import annotations

import argparse
import hashlib
import math
import shutil
from pathlib import Path

from perception.model_card import replace_card_section
from sygrid.catalogue import copy_catalogue, load_catalogue
from sygrid.errors import ConfigError
from sygrid.fileio import read_json, write_bytes_atomic, write_json_atomic

COCO_CONF = 0.001  # the detection benchmarks' convention for mAP (the pipeline runs at the manifest's threshold)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", required=True, metavar="ACTION")
    pack = sub.add_parser("pack", help="model folder + model cards from a detector run and a pose run")
    pack.add_argument(
        "--detector", type=Path, required=True,
        help="'sygrid train detector' output folder, or a model folder whose detector network (and card) to keep",
    )  # fmt: skip
    pack.add_argument(
        "--pose", type=Path, required=True,
        help="'sygrid train pose' output folder, or a model folder whose pose network (and its choices) to keep",
    )  # fmt: skip
    pack.add_argument("--out", type=Path, required=True, help="model folder to write (e.g. models/builtin)")
    pack.add_argument(
        "--catalogue", type=Path, default=None,
        help="parts catalogue the models were trained with, copied into the folder (default: the detector run's)",
    )  # fmt: skip
    pack.add_argument("--test-data", type=Path, default=None, help="held-out dataset for the cards' metrics")
    pack.add_argument("--max-images", type=int, default=None, help="evaluate on the first N test images")
    pack.add_argument("--conf-threshold", type=float, default=0.4, help="the manifest's detector threshold")
    pack.add_argument("--method", choices=["direct", "pnp"], default="direct", help="the manifest's pose method")
    pack.add_argument(
        "--scale", type=float, default=None, help="the manifest's detector scale (network px per image px)"
    )
    pack.add_argument("--tile-px", type=int, default=None, help="the manifest's detector tiles (network px)")
    pack.add_argument(
        "--region", choices=["full", "bin"], default=None,
        help="where the card's evaluation looks (default: the bin's box where the test set knows its bin)",
    )  # fmt: skip
    fails = sub.add_parser("breakdown", help="where a model folder's detector fails: card section, min_part_px")
    fails.add_argument("--models", type=Path, required=True, help="model folder (manifest.json, detector.card.md)")
    fails.add_argument("--test-data", type=Path, required=True, help="held-out dataset")
    fails.add_argument("--max-images", type=int, default=None, help="evaluate on the first N test images")
    fails.add_argument(
        "--region", choices=["full", "bin"], default=None,
        help="where the detector looks (default: the bin's box where the test set knows its bin)",
    )  # fmt: skip

    choose = sub.add_parser(
        "choose-pose", help="measure every pose strategy per part on a test set, write the choice into the manifest"
    )
    from launch import choose_pose

    choose_pose.add_arguments(choose)


def run(args: argparse.Namespace) -> int:
    if args.action == "breakdown":
        return run_breakdown(args)
    if args.action == "choose-pose":
        from launch import choose_pose

        return choose_pose.run(args)
    return pack(args)


def pack(args: argparse.Namespace) -> int:
    kept_detector = _kept_detector(args.detector)
    det_log = _train_log(args.detector, "detector.onnx") if kept_detector is None else kept_detector["log"]
    kept = _kept_pose(args.pose)
    pose_log = _train_log(args.pose, "pose.onnx") if kept is None else {"obj_ids": kept["obj_ids"]}
    args.out.mkdir(parents=True, exist_ok=True)
    for run_dir, name in ((args.detector, "detector.onnx"), (args.pose, "pose.onnx")):
        if (run_dir / name).resolve() == (args.out / name).resolve():
            continue  # the pose network kept in place
        tmp = args.out / f".{name}.tmp"
        shutil.copyfile(run_dir / name, tmp)
        tmp.replace(args.out / name)
    parts = pack_parts(args, det_log, pose_log)
    view = {k: v for k, v in (("scale", args.scale), ("tile_px", args.tile_px)) if v is not None}
    manifest = {
        "format": "sygrid-models/1",
        **parts,
        "detector": {"onnx": "detector.onnx", "conf_threshold": args.conf_threshold, **view},
        "pose": {"onnx": "pose.onnx", "method": args.method},
        "refine": {"enabled": True},
    }
    if kept is not None:
        manifest["pose"] = {**kept["manifest"]["pose"], "onnx": "pose.onnx"}
        manifest.update({k: v for k, v in kept["manifest"].items() if k in KEPT_WITH_POSE})
    write_json_atomic(args.out / "manifest.json", manifest)
    evals = _evaluate(args) if args.test_data else {}
    if evals:  # the pixels-per-part threshold, from the measured recall curve at the operating threshold
        min_px = evals["detector"]["breakdown"]["min_reliable_px"][f"{args.conf_threshold:g}"]
        if math.isfinite(min_px):
            manifest["detector"]["min_part_px"] = min_px
            write_json_atomic(args.out / "manifest.json", manifest)
    if kept_detector is None:
        (args.out / "detector.card.md").write_text(detector_card(det_log, args, evals))
    else:
        section = _detection_section(evals["detector"], evals["direct"]) if evals else None
        card = kept_detector_card(kept_detector["card"], args.detector, section)
        write_bytes_atomic(args.out / "detector.card.md", card.encode())
    if kept is None:
        (args.out / "pose.card.md").write_text(pose_card(pose_log, args, evals))
    else:
        card = kept_pose_card(kept["card"], _pose_section(evals) if evals else None)
        write_bytes_atomic(args.out / "pose.card.md", card.encode())
    print(
        f"wrote {args.out}: manifest.json, detector.onnx, pose.onnx, model cards" + (", evaluations" if evals else "")
    )
    return 0


CATALOGUE_COPY = "catalogue/parts.toml"


def pack_parts(args: argparse.Namespace, det_log: dict, pose_log: dict) -> dict:
    """The manifest's ``objects`` (and ``catalogue``) for the detector's classes: the catalogue's parts, copied into
    the folder (``CATALOGUE_COPY``), where one is given or the detector was trained with one; else the built-in
    parts. Raises ConfigError when a class or a pose model's obj_id is not a part of that source by name and id."""
    names, ids = det_log["dataset"]["names"], [int(i) for i in det_log["dataset"]["obj_ids"]]
    pose_ids = [int(i) for i in pose_log.get("obj_ids", [])]
    source = args.catalogue or det_log["config"].get("catalogue")
    if source is None:
        from sygrid.objects.parts import BUILTIN_PARTS, builtin_part

        known = {n: builtin_part(n).obj_id for n in names if n in BUILTIN_PARTS}
        where = "the built-in parts"
    else:
        catalogue = load_catalogue(source)
        known = {p.name: p.id for p in catalogue.parts}
        where = f"the catalogue {source}"
    wrong = [f"{n!r} (obj_id {i})" for n, i in zip(names, ids, strict=True) if known.get(n) != i]
    unknown_pose = sorted(set(pose_ids) - set(known.values()))
    if wrong or unknown_pose:
        raise ConfigError(
            f"{args.detector}: the detector's classes {', '.join(wrong) or '(all fine)'} and the pose model's "
            f"obj_ids {unknown_pose or '(all fine)'} are not parts of {where} (by name and obj_id); pack with "
            "--catalogue FILE, the catalogue the models were trained with"
        )
    if source is None:
        return {"objects": [{"builtin": n} for n in names]}
    header = f"Copied by 'sygrid models pack' from {source}: the parts these models were trained for."
    copy_catalogue(catalogue, names, args.out / Path(CATALOGUE_COPY).parent, Path(CATALOGUE_COPY).name, header)
    return {"catalogue": CATALOGUE_COPY, "objects": [{"catalogue_part": n} for n in names]}


BREAKDOWN_HEADING = "### Where it fails"
HELD_OUT_HEADING = "## Held-out test set: "
# What a kept pose network keeps of its folder's manifest besides its own entry: the stages after the detector.
KEPT_WITH_POSE = ("refine", "verify", "depth_tare", "min_mask_px")


def run_breakdown(args: argparse.Namespace) -> int:
    """The detector alone at 0.001 on the test data (as ``pack`` evaluates it, with the breakdown): rewrites
    ``eval_detector.json``, the card's "Where it fails" section and the manifest's ``detector.min_part_px`` (the
    smallest nominal size recalled reliably at the operating threshold; left out when none is)."""
    from perception.detector import YoloSegDetector
    from perception.detector_eval import dataset_region
    from perception.evaluation import EvalSettings, evaluate_detector
    from perception.manifest import load_manifest
    from perception.pipeline import PipelineOverrides, detector_view

    manifest = load_manifest(args.models)
    d = manifest.detector
    detector = YoloSegDetector(args.models / d.onnx, conf_threshold=COCO_CONF, iou_threshold=d.iou_threshold,
                               input_size=d.input_size, view=detector_view(d, PipelineOverrides()))  # fmt: skip
    settings = EvalSettings(max_images=args.max_images, region=dataset_region(args.test_data, args.region))
    report = evaluate_detector(detector, args.test_data, settings, operating_threshold=d.conf_threshold)
    report["data"] = str(args.test_data)
    write_json_atomic(args.models / "eval_detector.json", report)
    data = read_json(args.models / "manifest.json", "model manifest")
    min_px = report["breakdown"]["min_reliable_px"][f"{d.conf_threshold:g}"]
    data["detector"].pop("min_part_px", None)
    if math.isfinite(min_px):
        data["detector"]["min_part_px"] = min_px
    write_json_atomic(args.models / "manifest.json", data)
    card_path = args.models / "detector.card.md"
    section = [f"Test set {_dataset_line(args.test_data)}, {report['n_images']} images, region {report['region']}, "
               f"detector scale {report['scale']:.2f}.", ""]  # fmt: skip
    replace_card_section(card_path, BREAKDOWN_HEADING, breakdown_section(report["breakdown"], section))
    print(f"wrote {args.models / 'eval_detector.json'}, {card_path} and manifest.json (min_part_px "
          f"{min_px if math.isfinite(min_px) else 'none'})")  # fmt: skip
    return 0


def _kept_pose(folder: Path) -> dict | None:
    """For ``--pose`` naming a model folder: its manifest, pose card and the pose network's obj_ids (the folder's
    parts); None for a training run's folder."""
    if not (folder / "manifest.json").is_file():
        return None
    from perception.manifest import load_manifest, manifest_models

    for name in ("pose.onnx", "pose.card.md"):
        if not (folder / name).is_file():
            raise ConfigError(f"{folder}: --pose names a model folder without {name}")
    manifest = read_json(folder / "manifest.json", "model folder manifest")
    obj_ids = sorted(manifest_models(folder, load_manifest(folder)))
    return {"manifest": manifest, "card": (folder / "pose.card.md").read_text(), "obj_ids": obj_ids}


def _kept_detector(folder: Path) -> dict | None:
    """For ``--detector`` naming a model folder: its detector card and, as a training log would give them, the
    network's classes (names and obj_ids, read from the network) and the folder's catalogue copy; None for a
    training run's folder."""
    if not (folder / "manifest.json").is_file():
        return None
    from perception.detector import YoloSegDetector

    for name in ("detector.onnx", "detector.card.md"):
        if not (folder / name).is_file():
            raise ConfigError(f"{folder}: --detector names a model folder without {name}")
    detector = YoloSegDetector(folder / "detector.onnx", num_threads=1)
    manifest = read_json(folder / "manifest.json", "model folder manifest")
    catalogue = str(folder / manifest["catalogue"]) if manifest.get("catalogue") else None
    log = {
        "dataset": {"names": list(detector.class_names), "obj_ids": [int(i) for i in detector.class_obj_ids]},
        "config": {"catalogue": catalogue},
    }
    return {"log": log, "card": (folder / "detector.card.md").read_text()}


_PACKED_FROM = "- packed from the model folder "


def kept_detector_card(card: str, source: Path, evaluation: list[str] | None) -> str:
    """A kept detector card: its lines before the held-out evaluation (the network, its data and training), a line
    naming the folder it was kept from (one: a card packed again names only its latest source), and ``evaluation``
    (None: none; the source's own evaluations, of another test set, are left out)."""
    head = [
        line
        for line in card.split(HELD_OUT_HEADING, 1)[0].rstrip("\n").split("\n")
        if not line.startswith(_PACKED_FROM)
    ]
    lines = [*head, f"{_PACKED_FROM}`{source}` (its card has the network's other evaluations)"]
    if evaluation is not None:
        lines += ["", *evaluation]
    return "\n".join(lines).rstrip("\n") + "\n"


def kept_pose_card(card: str, evaluation: list[str] | None) -> str:
    """A kept pose card with its held-out evaluation section (``HELD_OUT_HEADING`` up to the next section of the
    same or a higher level, or the end) replaced by ``evaluation``; None keeps the card as it is."""
    if evaluation is None or HELD_OUT_HEADING not in card:
        return card if evaluation is None else card.rstrip("\n") + "\n\n" + "\n".join(evaluation) + "\n"
    head, rest = card.split(HELD_OUT_HEADING, 1)
    tail = rest.split("\n### ", 1)[1] if "\n### " in rest else ""
    tail = "\n### " + tail if tail else ""
    return head.rstrip("\n") + "\n\n" + "\n".join(evaluation).rstrip("\n") + "\n" + tail


def _train_log(run_dir: Path, onnx_name: str) -> dict:
    if not (run_dir / onnx_name).is_file():
        raise ConfigError(f"{run_dir}: no {onnx_name} (has the training run finished and exported?)")
    return read_json(run_dir / "train_log.json", "training log")


def _evaluate(args: argparse.Namespace) -> dict[str, dict]:
    from perception.detector import YoloSegDetector
    from perception.detector_eval import dataset_region
    from perception.evaluation import EvalSettings, evaluate, evaluate_detector, format_table
    from perception.pipeline import PerceptionPipeline, PipelineOverrides
    from perception.tiling import ViewSettings

    settings = EvalSettings(max_images=args.max_images, region=dataset_region(args.test_data, args.region))
    detector = YoloSegDetector(args.out / "detector.onnx", conf_threshold=COCO_CONF,
                               view=ViewSettings(args.scale, args.tile_px))  # fmt: skip
    report = evaluate_detector(detector, args.test_data, settings, operating_threshold=args.conf_threshold)
    report["data"] = str(args.test_data)
    write_json_atomic(args.out / "eval_detector.json", report)
    evals = {"detector": report}
    # With per-part pose strategies in the manifest, the second evaluation is the folder as shipped (strategies and
    # verification); an override of refinement would run the network-and-refiner path instead.
    strategies = read_json(args.out / "manifest.json", "model manifest")["pose"].get("strategies")
    second = ("strategies", PipelineOverrides()) if strategies else ("refined", PipelineOverrides(refine=True))
    for label, overrides in (("direct", PipelineOverrides(refine=False)), second):
        pipeline = PerceptionPipeline.from_folder(args.out, overrides)
        report = evaluate(pipeline, args.test_data, settings)
        report["data"] = str(args.test_data)
        print(format_table(report))
        write_json_atomic(args.out / f"eval_{label}.json", report)
        evals[label] = report
    for stale in {"refined", "strategies"} - set(evals):  # the other kind's file, from an earlier pack
        (args.out / f"eval_{stale}.json").unlink(missing_ok=True)
    return evals


def _dataset_line(folder: Path) -> str:
    """Where a dataset came from, from its ledger: recipe name and hash, seed, items."""
    ledger_path = Path(folder) / "dataset.json"
    if not ledger_path.is_file():
        return f"`{folder}` (no ledger: not made by `sygrid generate`)"
    ledger = read_json(ledger_path, "dataset ledger")
    items = sum(b - a + 1 for a, b in ledger["done"])
    return (
        f"`{folder}`: recipe `{ledger['recipe']['name']}` (sha256 {ledger['recipe_sha256'][:12]}), seed "
        f"{ledger['seed']}, {items} items ({len(ledger['failed'])} failed)"
    )


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _file_line(path: Path) -> str:
    return f"`{path.name}`: {path.stat().st_size / 1e6:.2f} MB, sha256 {_sha256(path)[:16]}"


def detector_card(log: dict, args: argparse.Namespace, evals: dict[str, dict]) -> str:
    cfg, epochs = log["config"], log["epochs"]
    seconds = sum(e.get("train_seconds", 0.0) + e.get("val_seconds", 0.0) for e in epochs)
    last_val = next((e["val"] for e in reversed(epochs) if e.get("val")), None)
    data = [cfg["data"]] if isinstance(cfg["data"], str) else cfg["data"]
    command = (
        f"sygrid train detector {' '.join(f'--data {d}' for d in data)} --out {cfg['out']} --epochs {cfg['epochs']} "
        f"--imgsz {cfg['imgsz']} --batch {cfg['batch']} --width {cfg['size']} --lr {cfg['lr']} --seed {cfg['seed']} "
        f"--threads {cfg['threads']}" + (f" --init {cfg['init']}" if cfg.get("init") else "")
    )
    lines = [
        "# Model card: detector (YOLOv8-style instance segmentation)",
        "",
        f"- file: {_file_line(args.out / 'detector.onnx')}; ultralytics YOLOv8-seg output layout, dynamic input",
        f"- network: size `{cfg['size']}`, {log['model']['parameters'] / 1e6:.2f} M parameters, "
        f"{log['model']['num_classes']} classes: {', '.join(log['dataset']['names'])}",
        f"- data: {'; '.join(_dataset_line(Path(d)) for d in data)}; {log['dataset']['train_images']} training / "
        f"{log['dataset']['val_images']} validation images",
        f"- command: `{command}`",
        f"- seed: {cfg['seed']}; training time {seconds / 3600:.2f} h on this project's 2-core CPU machine "
        f"({len(epochs)} epochs x {log['iters_per_epoch']} iterations), best epoch {log['best_epoch']}",
    ]
    if cfg.get("init"):
        lines.append(f"- fine-tuned: the run started from the weights of `{cfg['init']}` (see that run's card)")
    if last_val:
        lines.append(
            f"- validation (last epoch): box mAP50 {last_val['box_map50']:.3f}, box mAP50-95 "
            f"{last_val['box_map50_95']:.3f}, mask mAP50-95 {last_val['mask_map50_95']:.3f}"
        )
    if evals:
        lines += ["", *_detection_section(evals["detector"], evals["direct"])]
    return "\n".join(lines) + "\n"


def pose_card(log: dict, args: argparse.Namespace, evals: dict[str, dict]) -> str:
    cfg, arch = log["config"], log["architecture"]
    entries = log.get("entries", [])
    seconds = entries[-1]["seconds"] if entries else float("nan")
    base = (
        f"sygrid train pose --data {cfg['data_dir']} --out {cfg['out_dir']} --batch {cfg['batch_size']} "
        f"--input-size {cfg['input_size']} --output-stride {cfg['output_stride']} --width {cfg['width']} "
        f"--lr {cfg['lr']} --seed {cfg['seed']}" + (f" --threads {cfg['threads']}" if cfg.get("threads") else "")
    )
    runs = log.get("runs") or [{"start_iteration": 0, "epochs": cfg["epochs"]}]
    command = "`, then `".join(
        f"{base} --epochs {r['epochs']}" + (" --resume" if r["start_iteration"] else "") for r in runs
    )
    lines = [
        "# Model card: 6D pose (GDR-Net-style: XYZ map, mask, regions -> Patch-PnP -> allocentric R6d + SITE)",
        "",
        f"- file: {_file_line(args.out / 'pose.onnx')}",
        f"- network: RoI {arch['input_size']} px, dense output {arch['output_size']} px, width {arch['width']}, "
        f"{arch['num_regions']} surface regions, one model for the obj_ids {log['obj_ids']}",
        f"- data: {_dataset_line(Path(cfg['data_dir']))}; {log['train_instances']} training instances, "
        f"{log['val_instances']} validation instances",
        f"- command: `{command}`"
        + (
            " (a resume with more epochs restarts the cosine learning-rate schedule where the new length puts it)"
            if len(runs) > 1
            else ""
        ),
        f"- seed: {cfg['seed']}; training time {seconds / 3600:.2f} h on this project's 2-core CPU machine",
    ]
    if evals:
        lines += ["", *_pose_section(evals)]
    return "\n".join(lines) + "\n"


def _detection_section(det: dict, pipeline_report: dict) -> list[str]:
    at_operating = pipeline_report["detection"]
    lines = [
        f"## Held-out test set: {_dataset_line(Path(det['data']))}, {det['n_images']} images",
        "",
        f"box mAP50 **{det['box_map50']:.3f}**, box mAP50-95 {det['box_map50_95']:.3f}, mask mAP50 "
        f"{det['mask_map50']:.3f}, mask mAP50-95 **{det['mask_map50_95']:.3f}** (pycocotools, confidence threshold "
        f"{det['conf_threshold']}; instances less than 10 % visible ignored). At the pipeline's operating threshold "
        f"{pipeline_report['conf_threshold']}: box mAP50 {at_operating['box_map50']:.3f}, "
        f"mask mAP50-95 {at_operating['mask_map50_95']:.3f}. Median detector time per frame "
        f"{pipeline_report['timings_ms_median']['detect']:.1f} ms (onnxruntime CPU, 2 threads).",
        "",
        "| obj_id | box AP50 | box AP50-95 | mask AP50-95 | instances |",
        "|---|---|---|---|---|",
    ]
    for obj_id, row in det["per_class"].items():
        lines.append(
            f"| {obj_id} | {row['box_ap50']:.3f} | {row['box_ap50_95']:.3f} | {row['mask_ap50_95']:.3f} "
            f"| {row.get('n_gt', '')} |"
        )
    if "breakdown" in det:
        lines += ["", *breakdown_section(det["breakdown"])]
    return lines


def breakdown_section(b: dict, intro: list[str] | None = None) -> list[str]:
    """Where the detector fails: recall and AP per part, size bin and visibility bin at each threshold (markdown);
    ``intro``: lines after the heading."""
    sizes = [label for label, _, _ in b["size_bins_px"]]
    visib = [label for label, _, _ in b["visibility_bins"]]
    labels = ["all", *sizes, *visib]
    header = "| part | " + " | ".join(["all", *(f"{s} px" for s in sizes), *(f"{v} visible" for v in visib)]) + " |"
    rule = "|---" * (len(labels) + 1) + "|"
    lines = [
        BREAKDOWN_HEADING,
        "",
        *(intro or []),
        "Sizes: the longer side of the visible box in the image; instances less than 10 % visible left out. Recall: "
        "found by a detection of the same part with mask IoU >= 0.5 (n instances in brackets).",
    ]
    for t in (f"{t:g}" for t in b["thresholds"]):
        lines += ["", f"Recall at confidence {t}:", "", header, rule]
        for part, row in b["recall"].items():
            cells = [f"{_pct(row[k][f'recall@{t}'])} ({row[k]['n']})" for k in labels]
            lines.append(f"| {part} | " + " | ".join(cells) + " |")
    for t in (f"{t:g}" for t in b["thresholds"]):
        lines += ["", f"Box AP50 / mask AP50-95 at confidence {t} (obj_id):", "", header, rule]
        for part, row in b["ap"][t].items():
            cells = [f"{_num(row[k]['box_ap50'])} / {_num(row[k]['mask_ap50_95'])}" for k in labels]
            lines.append(f"| {part} | " + " | ".join(cells) + " |")
        px = b["min_reliable_px"][t]
        found = f"**{px:g} network px**." if math.isfinite(px) else "none (no size bin reaches the criterion)."
        lines += [
            "",
            f"Smallest nominal part size (fx x diameter / distance x scale) resolved reliably at {t}: {found}",
        ]
    return lines


def _pct(x: float) -> str:
    return "n/a" if not math.isfinite(x) else f"{100 * x:.1f} %"


def _num(x: float) -> str:
    return "n/a" if not math.isfinite(x) else f"{x:.3f}"


def _pose_section(evals: dict[str, dict]) -> list[str]:
    direct = evals["direct"]
    label = "strategies" if "strategies" in evals else "refined"
    refined = evals[label]
    second = {
        "refined": "refined = + point-to-plane ICP on depth",
        "strategies": "strategies = the folder as shipped: each part's pose strategy (``pose.strategies``) and the "
        "verification",
    }[label]
    lines = [
        f"{HELD_OUT_HEADING}{_dataset_line(Path(direct['data']))}, {direct['n_images']} images",
        "",
        "ADD(-S) < 0.1 d recall over every instance at least 10 % visible (a missed detection counts as a failure); "
        f"re and te are medians over the estimated instances. Direct = the network's own pose; {second}.",
        "",
        f"| part | metric | n | ADD(-S) direct | ADD(-S) {label} | re direct [deg] | te direct [mm] | re {label} "
        f"[deg] | te {label} [mm] |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    rows_d = {**direct["pose"]["per_object"], "all": direct["pose"]["all"]}
    rows_r = {**refined["pose"]["per_object"], "all": refined["pose"]["all"]}
    for name, d in rows_d.items():
        r = rows_r[name]
        lines.append(
            f"| {name} | {d['metric']} | {d['n']} | {100 * d['add_recall']:.1f} % | {100 * r['add_recall']:.1f} % | "
            f"{d['median_re_deg']:.2f} | {d['median_te_mm']:.2f} | {r['median_re_deg']:.2f} | {r['median_te_mm']:.2f} |"
        )
    t_d, t_r = direct["timings_ms_median"], refined["timings_ms_median"]
    lines += [
        "",
        f"Median milliseconds per frame (about {direct['detections_per_image_median']:.0f} detections): pose "
        f"{t_d['pose']:.1f}, refinement {t_r['refine']:.1f}.",
    ]
    return lines
