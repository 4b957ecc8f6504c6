"""``sygrid bench perception``: the pose strategies per part, noise-free and with sensor noise, accuracy against time.

For each dataset given (``--data``, generated without sensor noise; ``--noisy-data``, the same recipe generated
through a stereo sensor model, e.g. ``launch/recipes/builtin_test_noisy.json``), one pass of each of:

- ground-truth masks, the pose stage alone (``perception.strategy_eval``): per strategy and per part, ADD(-S) < 0.1 d
  recall of all estimates and of the accepted ones (verification at the manifest's thresholds, each part's
  ``verify.part_min_confidence`` else ``verify.min_confidence``; refused estimates count as failures), median re
  and te, median wall and CPU milliseconds per object (the network's share where used, mask clean-up, hypotheses,
  refinement, verification), false accepts (wrong among the accepted) and false refusals (refused among the
  correct). The reference row is the manifest's per-part choice
  (``sygrid models choose-pose``), or without one the most accurate strategy per part; with a choice, it is also
  measured without the resting search (``perception.resting``), an ablation row, and with per-part thresholds the
  same estimates are also counted at the one ``verify.min_confidence``, another;
- end to end (``perception.evaluation.evaluate``): the model folder's detector and per-part strategies, ADD(-S)
  recall over every instance seen at least 10 % (missed or refused counts as a failure), per part, false accepts
  and false refusals of the verified estimates, median milliseconds per object (strategy, refinement and
  verification; the network's batch time is in the per-frame timings); with ``--thresholds``, the same again at
  each detector confidence threshold given (the manifest's is the main row): found parts against time per frame;
- the dataset's depth against the exact depth: AbsRel, delta1 and fill rate (0, 1 and 1 for a noise-free set), and
  after the depth tare on the bin's floor (``perception.depth_tare``, both passes), with the tare's offsets.

The verification allows the depth noise of each dataset's sensor (``VerifyConfig.for_sensor``).

Writes ``bench/results/NAME.{json,png}`` (``--name``, default ``perception``): accuracy against median milliseconds
per object, one point per strategy, one panel per dataset, the targets (``TARGETS``) drawn, and with
``--thresholds`` a second row: end-to-end accuracy against the pipeline's median milliseconds per frame, one point
per detector threshold; the printed table ends with every target and its measured value. Each dataset's pass and
each threshold's is saved when done in ``NAME.partial.json`` beside the results: ``--resume`` goes on with a
stopped run of the same settings (models, datasets, options and this package's code; another run's checkpoint is
refused).
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from dataclasses import replace
from functools import partial
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from matplotlib.ticker import FixedLocator, FormatStrFormatter, NullFormatter

from perception.detector_eval import dataset_region
from perception.evaluation import EvalSettings, dataset_sensor, evaluate, frames_sensor
from perception.manifest import MANIFEST_NAME, load_manifest
from perception.pipeline import PerceptionPipeline, PipelineOverrides
from perception.pose_strategies import STRATEGIES, StrategyRunner, check_strategy
from perception.strategy_eval import (
    StrategyRecord,
    Thresholds,
    choose,
    evaluate_strategies,
    summarize,
    visibility_gates,
)
from perception.verify import PoseVerifier
from sygrid.bench.common import (
    DEFAULT_RESULTS_DIR,
    StageCheckpoint,
    add_result_arguments,
    dataset_digest,
    folder_digest,
    replot,
    save_results,
)
from sygrid.errors import ConfigError

# issue 21's targets on builtin_test and its noisy twin; recall as fractions, time per object in milliseconds
TARGETS = {
    "gt_masks_recall": {"ideal": 0.97, "noisy": 0.93},
    "end_to_end_recall": {"ideal": 0.85, "noisy": 0.80},
    "end_to_end_part_recall": 0.70,
    "false_accept": 0.01,
    "ms_per_object": 15.0,
}
Records = dict[tuple[int, str], list[StrategyRecord]]
PACKAGE = Path(__file__).parent
VISIBILITY_GATES = (0.1, 0.2, 0.3, 0.4, 0.5)  # the reference's false accepts if instances below each were refused


def run_benchmark(
    models_dir: Path,
    data_dir: Path,
    noisy_dir: Path | None = None,
    strategies: tuple[str, ...] = STRATEGIES,
    max_images: int | None = None,
    threads: int = 2,
    wrong_class: bool = False,
    thresholds: tuple[float, ...] = (),
    progress: bool = True,
    checkpoint: StageCheckpoint | None = None,
    search_bars: tuple[float, ...] = (),
) -> dict:
    """Measures ``strategies`` (and the manifest's chosen ones) with ground-truth masks and the folder's pipeline end
    to end on each dataset, also at each detector confidence threshold of ``thresholds``; returns the results as a
    JSON-able dict (``conditions`` "ideal" and, with ``noisy_dir``, "noisy"); ``search_bars``: the manifest's choice
    again with each of these as the search's stopping bar (``StrategyConfig.good_confidence``). With a
    ``checkpoint``, each dataset's pass and each threshold's is a stage: saved when done, not measured again when the
    checkpoint has it."""
    stages = checkpoint or StageCheckpoint.in_memory()
    datasets = {"ideal": Path(data_dir), **({"noisy": Path(noisy_dir)} if noisy_dir is not None else {})}
    sensors = {name: checked_sensor(name, path) for name, path in datasets.items()}
    manifest = load_manifest(models_dir)
    pipeline = PerceptionPipeline.from_folder(models_dir, PipelineOverrides(num_threads=threads))
    min_confidence = manifest.verify.thresholds(pipeline.models, models_dir / MANIFEST_NAME)
    one_threshold = manifest.verify.min_confidence if manifest.verify.part_min_confidence else None
    verify = manifest.verify.config()
    measured = tuple(dict.fromkeys([*strategies, *(pipeline.strategies or {}).values()]))
    conditions = {}
    for name, path in datasets.items():
        if progress:
            print(f"-- {name}: {path}")
        settings = EvalSettings(max_images=max_images, region=dataset_region(path))  # as the cell: the bin's box
        sensor = frames_sensor(path, settings)
        pipeline.use_sensor(sensor)  # evaluate does it too; the ground-truth pass shares the pipeline's runner
        runner = pipeline.runner if pipeline.runner is not None else StrategyRunner(verifier=PoseVerifier(
            verify.for_sensor(sensor)))  # fmt: skip
        one_pass = partial(measure, pipeline, runner, path, settings, measured, min_confidence, wrong_class, progress,
                           one_threshold=one_threshold, search_bars=search_bars)  # fmt: skip
        conditions[name] = {
            "dataset_sensor": sensors[name],
            "region": settings.region,
            **stages.run(name, one_pass),
            "end_to_end_thresholds": {
                f"{t:g}": stages.run(f"{name} at {t:g}", partial(end_to_end_at, pipeline, t, path, settings, progress))
                for t in thresholds if t != pipeline.detector.conf_threshold
            },
        }  # fmt: skip
    return {
        "models": str(models_dir),
        "threads": threads,
        "max_images": max_images,
        "strategies": list(measured),
        "min_confidence": manifest.verify.min_confidence,
        "part_min_confidence": dict(manifest.verify.part_min_confidence),
        "wrong_class_trials": wrong_class,
        "targets": TARGETS,
        "conditions": conditions,
        "target_checks": target_checks(conditions),
    }


def checked_sensor(condition: str, data_dir: Path) -> str:
    """``dataset_sensor``, refused where it contradicts the condition: noise in the "ideal" set, none in the
    "noisy" one."""
    sensor = dataset_sensor(data_dir)
    if condition == "ideal" and sensor not in ("ideal", "unknown"):
        raise ConfigError(f"--data {data_dir}: generated through the sensor {sensor!r}; give it as --noisy-data")
    if condition == "noisy" and sensor == "ideal":
        raise ConfigError(f"--noisy-data {data_dir}: generated without a sensor model (its recipe's sensor is "
                          f"'ideal'); generate e.g. launch/recipes/builtin_test_noisy.json")  # fmt: skip
    return sensor


def measure(
    pipeline: PerceptionPipeline,
    runner: StrategyRunner,
    data_dir: Path,
    settings: EvalSettings,
    strategies: tuple[str, ...],
    min_confidence: Thresholds,
    wrong_class: bool = False,
    progress: bool = True,
    one_threshold: float | None = None,
    search_bars: tuple[float, ...] = (),
) -> dict:
    """One dataset: the strategies with ground-truth masks (``pipeline.pose`` the network, ``runner`` the strategies;
    accepted at ``min_confidence``; ``one_threshold``, given where ``min_confidence`` holds per-part thresholds: the
    reference counted at it too; the manifest's choice again without the resting search and at each of
    ``search_bars``), the pipeline end to end, and the depth metrics."""
    names = {obj_id: m.name for obj_id, m in pipeline.models.items()}
    records = evaluate_strategies(runner, pipeline.pose, pipeline.models, data_dir, strategies, settings,
                                  wrong_class=wrong_class, progress=progress,
                                  tare=pipeline.depth_tare)  # fmt: skip
    gt_masks = gt_mask_summary(records, min_confidence, names, pipeline.strategies)
    choice = pipeline.strategies
    if choice is not None:
        if one_threshold is not None:
            chosen = summary_by_part(records, lambda o, s: choice.get(o) == s, one_threshold, names)
            gt_masks["reference_one_threshold"] = chosen
        # the same choice with other search settings
        again = partial(_choice_with, pipeline, runner, data_dir, settings, min_confidence, names, progress)
        gt_masks["reference_without_rest"] = again(rest=False)  # perception.resting's share
        if search_bars:
            gt_masks["reference_at_search_bar"] = {f"{b:g}": again(good_confidence=b) for b in search_bars}
    report = evaluate(pipeline, data_dir, settings, progress=progress)
    return {
        "data": str(data_dir),
        "split": report["split"],
        "n_images": report["n_images"],
        "depth": report["depth"],
        "depth_tared": report["depth_tared"],
        "depth_tare": report["depth_tare"],
        "gt_masks": gt_masks,
        "end_to_end": end_to_end_summary(report),
    }


def _choice_with(
    pipeline: PerceptionPipeline,
    runner: StrategyRunner,
    data_dir: Path,
    settings: EvalSettings,
    min_confidence: Thresholds,
    names: dict[int, str],
    progress: bool,
    **changes,
) -> dict:
    """The manifest's choice with ground-truth masks, ``runner``'s search settings changed by ``changes``
    (``StrategyConfig`` fields), summarised per part."""
    config = replace(runner.config, **changes)
    varied = StrategyRunner(runner.icp_config, runner.verifier, runner.cleanup, config)
    records = evaluate_strategies(varied, pipeline.pose, pipeline.models, data_dir, (), settings, progress=progress,
                                  tare=pipeline.depth_tare, per_part=pipeline.strategies)  # fmt: skip
    return summary_by_part(records, lambda o, s: True, min_confidence, names)


def end_to_end_at(
    pipeline: PerceptionPipeline, threshold: float, data_dir: Path, settings: EvalSettings, progress: bool = True
) -> dict:
    """``end_to_end_summary`` with the pipeline's detector at the confidence ``threshold`` (restored after)."""
    own = pipeline.detector.conf_threshold
    pipeline.detector.conf_threshold = threshold
    try:
        return end_to_end_summary(evaluate(pipeline, data_dir, settings, progress=progress))
    finally:
        pipeline.detector.conf_threshold = own


def part_key(obj_id: int, names: dict[int, str]) -> str:
    """How a part is named in the results (as ``perception.evaluation`` names it): ``"<obj_id> <name>"``."""
    return f"{obj_id} {names.get(obj_id, '?')}"


def summary_by_part(
    records: Records, pick: Callable[[int, str], bool], min_confidence: Thresholds, names: dict[int, str]
) -> dict:
    """``strategy_eval.summarize`` of the records ``pick(obj_id, strategy)`` selects: over all of them and per part."""
    per_part = {part_key(o, names): summarize(recs, min_confidence) for (o, s), recs in sorted(records.items())
                if pick(o, s)}  # fmt: skip
    every = [r for (o, s), recs in records.items() if pick(o, s) for r in recs]
    return {"all": summarize(every, min_confidence), "per_part": per_part}


def gt_mask_summary(
    records: Records, min_confidence: Thresholds, names: dict[int, str], choice: dict[int, str] | None
) -> dict:
    """Per strategy (all parts, and per part), and the reference: ``choice`` (obj_id -> strategy, the manifest's),
    else the most accurate strategy per part (``strategy_eval.choose`` with an unreachable bar)."""
    strategies = list(dict.fromkeys(s for _, s in records))
    rows = {s: summary_by_part(records, lambda o, t, s=s: t == s, min_confidence, names) for s in strategies}
    label = "manifest's choice"
    if choice is None:
        choice, label = choose(records, math.inf, min_confidence), "most accurate per part"
    reference = summary_by_part(records, lambda o, t: choice.get(o) == t, min_confidence, names)
    chosen = [r for (o, t), recs in records.items() if choice.get(o) == t for r in recs]
    return {
        "strategies": rows,
        "reference": {"label": label, "choice": {part_key(o, names): s for o, s in sorted(choice.items())},
                      **reference, "visibility_gates": visibility_gates(chosen, min_confidence, VISIBILITY_GATES)},
    }  # fmt: skip


def end_to_end_summary(report: dict) -> dict:
    """The figures of ``perception.evaluation.evaluate``'s report that the benchmark keeps (None: not measured,
    e.g. no verification without per-part strategies)."""
    v = report.get("verification") or {}
    chain = report.get("strategies") or f"network {report['pose_method']}{' + ICP' if report['refine'] else ''}"
    return {
        "pose_chain": chain,
        "all": report["pose"]["all"],
        "per_part": report["pose"]["per_object"],
        "accepted": v.get("accepted"),
        "refused": v.get("refused"),
        "false_accept": v.get("false_accept"),
        "false_refuse": v.get("false_refuse"),
        "ms_per_object_median": _finite(report.get("pose_ms_per_object_median")),
        "cpu_ms_per_object_median": _finite(report.get("pose_cpu_ms_per_object_median")),
        "timings_ms_median": report["timings_ms_median"],
        "detections_per_image_median": report["detections_per_image_median"],
        "box_map50": report["detection"]["box_map50"],
        "mask_map50_95": report["detection"]["mask_map50_95"],
        "conf_threshold": report["conf_threshold"],
    }


def _finite(x: float | None) -> float | None:
    return x if x is not None and math.isfinite(x) else None


def target_checks(conditions: dict) -> list[dict]:
    """Every target of ``TARGETS`` per condition with its measured value; ``met`` None where not measured."""
    rows = []
    for name, c in conditions.items():
        ref, e2e = c["gt_masks"]["reference"], c["end_to_end"]
        parts = {p: r["add_recall"] for p, r in e2e["per_part"].items()}
        worst = min(parts, key=lambda p: parts[p]) if parts else None
        rows += [
            _check(f"GT masks, {ref['label']}: accepted ADD(-S) recall", name, ref["all"]["accepted_recall"], ">=",
                   TARGETS["gt_masks_recall"][name]),
            _check(f"GT masks, {ref['label']}: false accepts", name, ref["all"]["false_accept"], "<=",
                   TARGETS["false_accept"]),
            _check(f"GT masks, {ref['label']}: ms per object", name, ref["all"]["median_ms"], "<=",
                   TARGETS["ms_per_object"]),
            _check("end to end: ADD(-S) recall", name, e2e["all"]["add_recall"], ">=",
                   TARGETS["end_to_end_recall"][name]),
            _check(f"end to end: worst part ({worst})", name, parts.get(worst) if worst else None, ">=",
                   TARGETS["end_to_end_part_recall"]),
            _check("end to end: false accepts", name, e2e["false_accept"], "<=", TARGETS["false_accept"]),
            _check("end to end: ms per object", name, e2e["ms_per_object_median"], "<=", TARGETS["ms_per_object"]),
        ]  # fmt: skip
    return rows


def _check(target: str, condition: str, value: float | None, op: str, bound: float) -> dict:
    measured = value is not None and math.isfinite(value)
    met = (value >= bound if op == ">=" else value <= bound) if measured else None
    return {"target": target, "condition": condition, "value": value if measured else None, "op": op,
            "bound": bound, "met": met}  # fmt: skip


def chart(results: dict):
    conditions = results["conditions"]
    by_threshold = any(c.get("end_to_end_thresholds") for c in conditions.values())
    rows = 2 if by_threshold else 1
    fig, axes = plt.subplots(rows, len(conditions), figsize=(6 * len(conditions) + 2.5, 5.2 * rows), sharey=True,
                             squeeze=False)  # fmt: skip
    for ax, (name, c) in zip(axes[0], conditions.items(), strict=True):
        _panel(ax, name, c, results["strategies"])
    lo, hi = zip(*(ax.get_xlim() for ax in axes[0]), strict=True)
    for ax in axes[0]:  # per object: one scale across the datasets
        ax.set_xlim(min(lo), max(hi))
    axes[0][-1].legend(fontsize=7, loc="center left", bbox_to_anchor=(1.02, 0.5))
    if by_threshold:
        for ax, (name, c) in zip(axes[1], conditions.items(), strict=True):
            _threshold_panel(ax, name, c)
        axes[1][-1].legend(fontsize=7, loc="center left", bbox_to_anchor=(1.02, 0.5))
    fig.tight_layout()
    return fig


def threshold_rows(c: dict) -> list[dict]:
    """A condition's end-to-end summaries, the manifest's threshold among the others, by rising threshold."""
    rows = [c["end_to_end"], *c.get("end_to_end_thresholds", {}).values()]
    return sorted(rows, key=lambda e: e["conf_threshold"])


def _threshold_panel(ax, name: str, c: dict) -> None:
    """End to end, one point per detector threshold: ADD(-S) recall against the pipeline's time per frame."""
    rows = threshold_rows(c)
    ms = [e["timings_ms_median"]["total"] for e in rows]
    ax.plot(ms, [e["all"]["add_recall"] for e in rows], "k*-", ms=10, label="end to end, per detector threshold")
    for x, e in zip(ms, rows, strict=True):
        own = e is c["end_to_end"]
        label = f"{e['conf_threshold']:g}{' (manifest)' if own else ''}: false accepts {_pct(e['false_accept'])}"
        ax.annotate(label, (x, e["all"]["add_recall"]),
                    textcoords="offset points", xytext=(4, -12), fontsize=8)  # fmt: skip
    ax.axhline(TARGETS["end_to_end_recall"][name], color="grey", ls=":", lw=0.8, label="target, end to end")
    ax.set(xlabel="pipeline time per frame, median [ms] (detector, pose, verification, refinement)",
           ylabel="ADD(-S) < 0.1 d recall, end to end", ylim=(0, 1.02),
           title=f"{name}: the detector's confidence threshold")  # fmt: skip


def _panel(ax, name: str, c: dict, strategies: list[str]) -> None:
    """One dataset: per strategy a filled point (accepted recall) over a hollow one (recall of all estimates)."""
    for s, row in c["gt_masks"]["strategies"].items():
        a, colour = row["all"], f"C{strategies.index(s) % 10}"
        ax.vlines(a["median_ms"], a["accepted_recall"], a["add_recall"], color=colour, lw=0.8)
        ax.scatter(a["median_ms"], a["add_recall"], facecolors="none", edgecolors=colour)
        ax.scatter(a["median_ms"], a["accepted_recall"], color=colour, label=s)
    ref, e2e = c["gt_masks"]["reference"], c["end_to_end"]
    ax.scatter(ref["all"]["median_ms"], ref["all"]["accepted_recall"], marker="D", s=50, color="k",
               label=f"GT masks, {ref['label']}")  # fmt: skip
    if "reference_without_rest" in c["gt_masks"]:
        off = c["gt_masks"]["reference_without_rest"]["all"]
        ax.scatter(off["median_ms"], off["accepted_recall"], marker="D", s=50, facecolors="none", edgecolors="k",
                   label="the same without resting")  # fmt: skip
    for k, (bar, r) in enumerate(c["gt_masks"].get("reference_at_search_bar", {}).items()):
        ax.scatter(r["all"]["median_ms"], r["all"]["accepted_recall"], marker="s", s=40, facecolors="none",
                   edgecolors="k", label="the same, other search bars" if k == 0 else None)  # fmt: skip
        ax.annotate(bar, (r["all"]["median_ms"], r["all"]["accepted_recall"]), fontsize=7,
                    textcoords="offset points", xytext=(4, -8))  # fmt: skip
    if e2e["ms_per_object_median"] is not None:
        ax.scatter(e2e["ms_per_object_median"], e2e["all"]["add_recall"], marker="*", s=140, color="k",
                   label="end to end")  # fmt: skip
    ax.scatter([], [], facecolors="none", edgecolors="grey", label="hollow: before verification")
    ax.axhline(TARGETS["gt_masks_recall"][name], color="grey", ls="--", lw=0.8, label="target, GT masks")
    ax.axhline(TARGETS["end_to_end_recall"][name], color="grey", ls=":", lw=0.8, label="target, end to end")
    ax.axvline(TARGETS["ms_per_object"], color="grey", ls="-.", lw=0.8, label="target, ms per object")
    ax.set_xscale("log")
    ax.xaxis.set_major_locator(FixedLocator([1, 2, 5, 10, 20, 50, 100, 200, 500, 1000, 2000]))
    ax.xaxis.set_major_formatter(FormatStrFormatter("%g"))
    ax.xaxis.set_minor_formatter(NullFormatter())
    title = f"{name} (sensor {c['dataset_sensor']}): {c['n_images']} images, {ref['all']['n']} instances"
    ax.set(xlabel="pose + verification + refinement per object, median [ms]", ylabel="ADD(-S) < 0.1 d recall",
           ylim=(0, 1.02), title=title)  # fmt: skip


def format_results(results: dict) -> str:
    own = ", ".join(f"{p} {t:.2f}" for p, t in (results.get("part_min_confidence") or {}).items())
    lines = [f"onnxruntime threads {results['threads']}; verification threshold {results['min_confidence']:.2f}"
             + (f"; per part: {own}" if own else "")]  # fmt: skip
    for name, c in results["conditions"].items():
        d = c["depth"]
        lines += ["", f"== {name}: {c['data']} (sensor {c['dataset_sensor']}), {c['n_images']} images; depth AbsRel "
                      f"{d['abs_rel']:.4f}, delta1 {_pct(d['delta1'])}, fill {_pct(d['fill_rate'])}"]  # fmt: skip
        if c.get("depth_tare"):
            t, dt = c["depth_tare"], c.get("depth_tared") or {}
            lines.append(f"depth tare on the bin floor: applied in {t['applied']} of {t['images']} images, offset "
                         f"|median| {t['offset_mm_at_1m_abs_median']:.2f} mm at 1 m; depth AbsRel after it "
                         f"{dt.get('abs_rel', math.nan):.4f}")  # fmt: skip
        lines += _gt_mask_lines(c["gt_masks"]) + _end_to_end_lines(c["end_to_end"])
        if c.get("end_to_end_thresholds"):
            lines += _threshold_lines(c)
    lines += ["", "targets:"]
    for t in results["target_checks"]:
        verdict = {True: "met", False: "NOT MET", None: "n/a"}[t["met"]]
        value = "not measured" if t["value"] is None else _fmt(t["value"], t["bound"])
        lines.append(f"  {verdict:<8}{t['condition']:<7}{t['target']}: {value} {t['op']} "
                     f"{_fmt(t['bound'], t['bound'])}")  # fmt: skip
    return "\n".join(lines)


def _gt_mask_lines(g: dict) -> list[str]:
    head = (f"{'GT masks':<24}{'n':>5}{'ADD(-S)':>9}{'accepted':>10}{'re deg':>8}{'te mm':>8}{'ms':>7}{'CPU ms':>8}"
            f"{'false acc':>10}{'false ref':>10}")  # fmt: skip
    rows = {**{s: r["all"] for s, r in g["strategies"].items()}, g["reference"]["label"]: g["reference"]["all"]}
    if "reference_without_rest" in g:
        rows["  the same, no resting"] = g["reference_without_rest"]["all"]
    if "reference_one_threshold" in g:
        rows["  the same, one threshold"] = g["reference_one_threshold"]["all"]
    for bar, r in g.get("reference_at_search_bar", {}).items():
        rows[f"  the same, bar {bar}"] = r["all"]
    lines = [head] + [_row(s, r) for s, r in rows.items()]
    parts = list(next(iter(g["strategies"].values()))["per_part"]) if g["strategies"] else []
    lines.append(f"{'accepted recall per part':<24}" + "".join(f"{s:>14}" for s in g["strategies"]))
    for p in parts:
        cells = [g["strategies"][s]["per_part"].get(p, {}).get("accepted_recall", math.nan) for s in g["strategies"]]
        lines.append(f"{p:<24}" + "".join(f"{_pct(x):>14}" for x in cells))
    gates = g["reference"].get("visibility_gates", [])
    if gates:
        lines.append("the reference if instances less visible than a gate were refused (ground-truth visibility):")
        lines += [f"  >= {x['min_visible']:.0%} visible: false accepts {_pct(x['false_accept'])}, accepted recall "
                  f"{_pct(x['accepted_recall'])}" for x in gates]  # fmt: skip
    return lines


def _row(name: str, r: dict) -> str:
    return (f"{name:<24}{r['n']:>5}{_pct(r['add_recall']):>9}{_pct(r['accepted_recall']):>10}"
            f"{r['median_re_deg']:>8.2f}{r['median_te_mm']:>8.2f}{r['median_ms']:>7.1f}{r['median_cpu_ms']:>8.1f}"
            f"{_pct(r['false_accept']):>10}{_pct(r['false_refuse']):>10}")  # fmt: skip


def _end_to_end_lines(e: dict) -> list[str]:
    chain = e["pose_chain"] if isinstance(e["pose_chain"], str) else ", ".join(f"{k} {v}" for k, v in
                                                                                e["pose_chain"].items())  # fmt: skip
    ms = "n/a" if e["ms_per_object_median"] is None else f"{e['ms_per_object_median']:.1f}"
    lines = [f"end to end ({chain}): box mAP50 {e['box_map50']:.3f}, mask mAP50-95 {e['mask_map50_95']:.3f}; "
             f"false accepts {_pct(e['false_accept'])}, false refusals {_pct(e['false_refuse'])}; "
             f"ms per object {ms}",
             f"{'part':<24}{'n':>5}{'ADD(-S)':>9}{'re deg':>8}{'te mm':>8}"]  # fmt: skip
    for p, r in {**e["per_part"], "all": e["all"]}.items():
        lines.append(f"{p:<24}{r['n']:>5}{_pct(r['add_recall']):>9}{r['median_re_deg']:>8.2f}{r['median_te_mm']:>8.2f}")
    return lines


def _threshold_lines(c: dict) -> list[str]:
    lines = [
        f"{'end to end, threshold':<24}{'dets':>6}{'ADD(-S)':>9}{'false acc':>10}{'false ref':>10}{'ms/frame':>10}"
    ]
    for e in threshold_rows(c):
        lines.append(
            f"{e['conf_threshold']:<24g}{e['detections_per_image_median']:>6.0f}{_pct(e['all']['add_recall']):>9}"
            f"{_pct(e['false_accept']):>10}{_pct(e['false_refuse']):>10}{e['timings_ms_median']['total']:>10.1f}"
        )
    return lines


def _pct(x: float | None) -> str:
    return "n/a" if x is None or math.isnan(x) else f"{100 * x:.1f}%"


def _fmt(x: float, bound: float) -> str:
    return f"{x:.1f} ms" if bound > 1 else _pct(x)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--models", type=Path, default=Path("models/builtin"), help="model folder (manifest.json)")
    parser.add_argument("--data", type=Path, default=Path("datasets/builtin_test"),
                        help="noise-free test set (sygrid generate launch/recipes/builtin_test.json)")  # fmt: skip
    parser.add_argument("--noisy-data", type=Path, default=None,
                        help="its noisy twin (sygrid generate launch/recipes/builtin_test_noisy.json)")  # fmt: skip
    parser.add_argument("--max-images", type=int, default=None, help="the first N images of each set")
    parser.add_argument("--strategies", default=None, help="comma-separated subset of the strategies (default: all)")
    parser.add_argument("--threads", type=int, default=2, help="onnxruntime threads")
    parser.add_argument("--wrong-class", action="store_true", help="also fit every instance with another part's model")
    parser.add_argument(
        "--thresholds",
        default=None,
        help="comma-separated detector confidence thresholds to run end to end beside the manifest's",
    )
    parser.add_argument(
        "--search-bars", default=None,
        help="comma-separated stopping bars of the pose search (StrategyConfig.good_confidence, in (0, 1]) to run the "
        "manifest's choice at beside its own",
    )  # fmt: skip
    parser.add_argument("--quick", action="store_true", help="20 images")
    add_result_arguments(parser, "perception")
    parser.add_argument(
        "--resume", action="store_true",
        help="go on with a stopped run of the same settings from its checkpoint (NAME.partial.json)",
    )  # fmt: skip


def parse_strategies(value: str | None) -> tuple[str, ...]:
    """``--strategies``: the named strategies in order (all without a value); an unknown name is a ConfigError."""
    if value is None:
        return STRATEGIES
    try:
        names = tuple(check_strategy(s.strip(), "--strategies") for s in value.split(",") if s.strip())
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    if not names:
        raise ConfigError(f"--strategies {value!r}: name at least one of {', '.join(STRATEGIES)}")
    return names


def parse_thresholds(value: str | None) -> tuple[float, ...]:
    """``--thresholds``: the confidence thresholds in order (none without a value); each in (0, 1)."""
    return _fractions(value, "--thresholds", "(0, 1)", lambda t: 0.0 < t < 1.0)


def parse_search_bars(value: str | None) -> tuple[float, ...]:
    """``--search-bars``: the search's stopping bars in order (none without a value); each in (0, 1]."""
    return _fractions(value, "--search-bars", "(0, 1]", lambda t: 0.0 < t <= 1.0)


def _fractions(value: str | None, option: str, interval: str, valid: Callable[[float], bool]) -> tuple[float, ...]:
    """Comma-separated numbers in order (none without a value); a ConfigError naming ``option`` unless each is
    ``valid``."""
    if value is None:
        return ()
    error = ConfigError(f"{option} {value!r}: expected comma-separated numbers in {interval}")
    try:
        out = tuple(float(t) for t in value.split(",") if t.strip())
    except ValueError:
        raise error from None
    if not out or not all(valid(t) for t in out):
        raise error
    return out


def run(args: argparse.Namespace, out_dir: Path = DEFAULT_RESULTS_DIR) -> int:
    if args.replot:
        replot(args.name, chart, out_dir)
        return 0
    strategies, thresholds = parse_strategies(args.strategies), parse_thresholds(args.thresholds)
    search_bars = parse_search_bars(args.search_bars)
    max_images = 20 if args.quick and args.max_images is None else args.max_images
    settings = {
        "models": folder_digest(args.models), "data": dataset_digest(args.data),
        "noisy_data": None if args.noisy_data is None else dataset_digest(args.noisy_data),
        "strategies": strategies, "max_images": max_images, "threads": args.threads, "wrong_class": args.wrong_class,
        "thresholds": thresholds, "search_bars": search_bars,
        # the code that measures: a checkpoint of an older version is measured again, not mixed in
        "code": folder_digest(PACKAGE),
    }  # fmt: skip
    checkpoint = StageCheckpoint(out_dir / f"{args.name}.partial.json", settings, resume=args.resume)
    if checkpoint.done:
        print(f"resuming from {checkpoint.path}: {', '.join(checkpoint.done)} already measured")
    results = run_benchmark(
        args.models, args.data, args.noisy_data, strategies=strategies, max_images=max_images, threads=args.threads,
        wrong_class=args.wrong_class, thresholds=thresholds, checkpoint=checkpoint, search_bars=search_bars,
    )  # fmt: skip
    print(format_results(results))
    json_path, png_path = save_results(args.name, results, chart(results), out_dir)
    checkpoint.finish()
    print(f"wrote {json_path} and {png_path}")
    return 0
