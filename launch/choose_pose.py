"""``sygrid models choose-pose``: measure every pose strategy per part on a test set and write the choice into the
model folder.

    sygrid models choose-pose --models models/builtin --data datasets/builtin_cal [--data datasets/builtin_cal_noisy]
        [--max-images N] [--bar 0.9]

With ground-truth masks (the pose stage alone, ``perception.strategy_eval``), every strategy of
``perception.pose_strategies`` runs on every instance seen at least 10 %; the table gives per part and strategy the
ADD(-S) recall, the recall of the accepted estimates, median re and te, median wall and CPU milliseconds per object,
and the verification's false accepts, false refusals and (with ``--wrong-class``: the model of another part fitted
to each instance too, which doubles the time) accepted wrong-class fits. As at run time, the depth is
corrected on the bin's floor first (the manifest's ``depth_tare``) and the verification allows the depth noise of the
dataset's sensor (``VerifyConfig.for_sensor``). Several ``--data`` sets (the same views noise-free and through a
sensor model, say) are measured each with its own sensor's settings and pooled. The choice per part is the
cheapest strategy whose recall of accepted estimates reaches ``--bar`` (refused poses are dropped by the pipeline),
else the most accurate; the verification threshold is the lowest that keeps the chosen strategies' false accepts
within ``--max-false-accept`` (with ``--per-part-thresholds`` one per part instead, those that accept the most right
poses while the false accepts over all parts stay within it: ``perception.strategy_eval.choose_part_thresholds``),
the two chosen in turn until they agree. Writes ``MODELS/pose_strategies.json`` (every figure, the command and the
data) and the choice into ``MODELS/manifest.json`` (``pose.strategies``, ``verify.min_confidence``: the one
threshold, and with ``--per-part-thresholds`` ``verify.part_min_confidence``), both atomically. Per-part thresholds
fit the calibration views closer than one threshold does: measure them on a test set (``sygrid bench perception``)
before shipping them.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import TYPE_CHECKING

from perception.model_card import invoked_command, replace_card_section
from sygrid.errors import ConfigError
from sygrid.fileio import read_json, write_json_atomic

if TYPE_CHECKING:
    from perception.strategy_eval import StrategyRecord, Thresholds

RESULTS_NAME = "pose_strategies.json"
CARD_HEADING = "### Pose strategies per part"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--models", type=Path, required=True, help="model folder with manifest.json")
    parser.add_argument("--data", type=Path, action="append", required=True,
                        help="dataset made by 'sygrid generate' (repeat to pool several)")  # fmt: skip
    parser.add_argument("--split", default=None, help="BOP split (default: test, else val_pbr)")
    parser.add_argument("--max-images", type=int, default=None, help="the first N images")
    parser.add_argument("--bar", type=float, default=0.9, help="ADD(-S) recall a strategy must reach (0..1)")
    parser.add_argument("--max-false-accept", type=float, default=0.01, help="of the accepted estimates (0..1)")
    parser.add_argument("--strategies", default=None, help="comma-separated subset of the strategies (default: all)")
    parser.add_argument("--wrong-class", action="store_true", help="also fit every instance with another part's model")
    parser.add_argument("--per-part-thresholds", action="store_true",
                        help="a verification threshold per part (default: one for every part)")  # fmt: skip
    parser.add_argument("--threads", type=int, default=2, help="onnxruntime threads")
    parser.add_argument("--dry-run", action="store_true", help="print the table, write nothing")


def run(args: argparse.Namespace) -> int:
    from perception.evaluation import EvalSettings, frames_sensor
    from perception.manifest import load_manifest, manifest_models, tare_config
    from perception.pose import PoseEstimator
    from perception.pose_strategies import STRATEGIES, StrategyRunner, check_strategy
    from perception.strategy_eval import choose_all, choose_threshold, evaluate_strategies, summarize
    from perception.verify import PoseVerifier, VerifyConfig

    strategies = STRATEGIES if args.strategies is None else tuple(s.strip() for s in args.strategies.split(","))
    try:
        for s in strategies:
            check_strategy(s, "--strategies")
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    if not 0 < args.bar <= 1 or not 0 <= args.max_false_accept < 1:
        raise ConfigError(f"--bar must be in (0, 1] and --max-false-accept in [0, 1), got {args.bar}, "
                          f"{args.max_false_accept}")  # fmt: skip
    manifest = load_manifest(args.models)
    models = manifest_models(args.models, manifest)
    network = PoseEstimator(args.models / manifest.pose.onnx, models=models, num_threads=args.threads)
    settings = EvalSettings(split=args.split, max_images=args.max_images)
    tare = tare_config(manifest.depth_tare)
    records: dict[tuple[int, str], list[StrategyRecord]] = {}
    sets = []
    for data in args.data:
        sensor = frames_sensor(data, settings)
        verify = VerifyConfig(depth_noise_m=manifest.verify.depth_noise_m).for_sensor(sensor)
        runner = StrategyRunner(verifier=PoseVerifier(verify), config=manifest.pose.search_config())
        measured = evaluate_strategies(runner, network, models, data, strategies, settings, args.wrong_class,
                                       tare=tare.for_sensor(sensor) if tare is not None else None)  # fmt: skip
        for key, recs in measured.items():
            records.setdefault(key, []).extend(recs)
        sets.append({"data": str(data), "sensor": sensor.name, "verify_depth_noise_m": verify.depth_noise_m})
    choice, threshold = choose_all(records, args.bar, args.max_false_accept, per_part=args.per_part_thresholds)
    chosen = [r for (obj_id, s), recs in records.items() if choice[obj_id] == s for r in recs]
    names = {obj_id: m.name for obj_id, m in models.items()}
    per_part = {names[obj_id]: t for obj_id, t in threshold.items()} if isinstance(threshold, dict) else {}
    # the one threshold; beside per-part ones, the default for other parts and the table's comparison row
    one = choose_threshold(chosen, args.max_false_accept) if per_part else threshold
    beside = one if per_part else None
    print(format_choice(records, choice, threshold, names, beside))
    report = {
        "command": invoked_command("sygrid models choose-pose"),
        "data": sets,
        "max_images": args.max_images,
        "bar": args.bar,
        "max_false_accept": args.max_false_accept,
        "min_confidence": one,
        "part_min_confidence": per_part,
        "depth_tare": manifest.depth_tare.enabled,
        "choice": {names[k]: v for k, v in choice.items()},
        "rows": [
            {"part": names[obj_id], "strategy": s, **summarize(recs, threshold)}
            for (obj_id, s), recs in sorted(records.items())
        ],
        "chosen": summarize(chosen, threshold),
        **({"chosen_one_threshold": summarize(chosen, one)} if per_part else {}),
    }
    if args.dry_run:
        return 0
    write_json_atomic(args.models / RESULTS_NAME, report)
    write_choice(args.models, report["choice"], one, per_part)
    replace_card_section(args.models / "pose.card.md", CARD_HEADING, [
        CARD_HEADING, "",
        f"`{report['command']}`: ground-truth masks, every strategy on every instance at least 10 % visible; the "
        "chosen strategy per part marked `*` (the cheapest whose accepted recall reaches the bar, else the most "
        f"accurate). Full figures: `{RESULTS_NAME}`.", "",
        "```", format_choice(records, choice, threshold, names, beside), "```",
    ])  # fmt: skip
    print(f"wrote {args.models / RESULTS_NAME}, the choice into {args.models / 'manifest.json'} and the table into "
          f"{args.models / 'pose.card.md'}")  # fmt: skip
    return 0


def write_choice(
    folder: Path, choice: dict[str, str], min_confidence: float, part_min_confidence: dict[str, float] | None = None
) -> None:
    """Writes ``pose.strategies``, ``verify.min_confidence`` and ``verify.part_min_confidence`` (removed where
    None or empty) into the folder's manifest (atomically), keeping everything else in it; the result must load."""
    from perception.manifest import MANIFEST_NAME, load_manifest

    path = folder / MANIFEST_NAME
    data = read_json(path, "model manifest")
    data["pose"] = {**data["pose"], "strategies": dict(choice)}
    verify = {**data.get("verify", {}), "min_confidence": min_confidence}
    verify.pop("part_min_confidence", None)
    data["verify"] = {**verify, **({"part_min_confidence": part_min_confidence} if part_min_confidence else {})}
    write_json_atomic(path, data)
    load_manifest(folder)


def format_choice(
    records: dict[tuple[int, str], list[StrategyRecord]],
    choice: dict[int, str],
    threshold: Thresholds,
    names: dict,
    one: float | None = None,
) -> str:
    """The table: one row per part and strategy at its part's threshold (the chosen one marked), then the chosen
    strategies together, and with ``one`` the same at that one threshold for every part."""
    from perception.strategy_eval import summarize, threshold_of

    head = (
        f"{'part':<11}{'strategy':<12}{'n':>5}{'ADD(-S)':>9}{'accepted':>10}{'re deg':>8}{'te mm':>8}{'ms':>7}"
        f"{'CPU ms':>8}{'false acc':>10}{'false ref':>10}{'wrong cls':>10}"
    )
    if isinstance(threshold, int | float):
        thresholds = f"threshold {threshold:.2f}"
    else:
        parts = sorted({obj_id for obj_id, _ in records})
        thresholds = "thresholds " + ", ".join(f"{names[o]} {threshold_of(threshold, o):.2f}" for o in parts)
    lines = [f"verification {thresholds} (fractions of the accepted / correct / wrong-class trials)", head]
    for (obj_id, s), recs in sorted(records.items()):
        mark = " *" if choice.get(obj_id) == s else ""
        lines.append(_row(names[obj_id], s + mark, summarize(recs, threshold)))
    chosen = [r for (obj_id, s), recs in records.items() if choice[obj_id] == s for r in recs]
    lines.append(_row("chosen", "", summarize(chosen, threshold)))
    if one is not None:
        lines.append(_row("chosen", f"one {one:.2f}", summarize(chosen, one)))
    return "\n".join(lines)


def _row(part: str, strategy: str, r: dict) -> str:
    return (
        f"{part:<11}{strategy:<12}{r['n']:>5}{_pct(r['add_recall']):>9}{_pct(r['accepted_recall']):>10}"
        f"{r['median_re_deg']:>8.2f}{r['median_te_mm']:>8.2f}{r['median_ms']:>7.1f}{r['median_cpu_ms']:>8.1f}"
        f"{_pct(r['false_accept']):>10}{_pct(r['false_refuse']):>10}{_pct(r['wrong_class_accept']):>10}"
    )


def _pct(x: float) -> str:
    return "n/a" if math.isnan(x) else f"{100 * x:.1f}%"
