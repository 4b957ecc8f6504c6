"""From the saved point records to what a reader sees: per axis a JSON (curves, failure points per method and per
group) and a chart, and over all axes a Markdown summary table and one overview chart.

Per axis (``axis_result``): each method's curve pools the seeds at each point (successes and trials added), its
failure point follows ``launch.stability.failure``; each group of trials (part family, part) gets its own curve
and failure point. ``seconds`` adds the wall time of every (point, seed) measured.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from launch.stability.failure import BELOW_FROM_START, FAILS, HOLDS, CurvePoint, failure_point
from launch.stability.sweep import Axis


def axis_result(axis: Axis, records: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """The axis's JSON: its declaration, and per method ``{"metric", "curve", "failure", "groups": {group:
    {"curve", "failure"}}}``."""
    methods = {}
    for m in axis.methods:
        mine = [r for r in records if r["method"] == m.name]
        curve = pooled_curve(axis, mine)
        groups = sorted({g for r in mine for g in r["groups"]}) if m.grouped else []
        methods[m.name] = {
            "metric": m.metric,
            "curve": [p.to_json() for p in curve],
            "failure": failure_point(curve, axis.criterion),
            "groups": {g: _group(axis, mine, g) for g in groups},
        }
    spent: dict[tuple[str, int], float] = {}
    for r in records:
        spent[(r["point"], r["seed"])] = float(r["seconds"])
    return {
        "axis": axis.name,
        "title": axis.title,
        "description": axis.description,
        "x_label": axis.x_label,
        "unit": axis.unit,
        "categorical": axis.categorical,
        "summary": axis.summary,
        "criterion": axis.criterion.to_json(),
        "seeds": list(axis.seeds),
        "settings": axis.settings,
        "points": [{"label": p.label, "x": p.x, "params": p.params} for p in axis.points],
        "seconds": sum(spent.values()),
        "points_measured": len(spent),
        "methods": methods,
        "notes": axis.notes(list(records)) if axis.notes is not None else None,
    }


def pooled_curve(axis: Axis, records: Sequence[dict[str, Any]], group: str | None = None) -> list[CurvePoint]:
    """One method's curve over ``axis.points`` (records of that method; of one ``group`` of trials if given)."""
    out = []
    for p in axis.points:
        k = n = 0
        for r in records:
            if r["point"] != p.label:
                continue
            kn = (r["k"], r["n"]) if group is None else r["groups"].get(group, (0, 0))
            k, n = k + int(kn[0]), n + int(kn[1])
        out.append(CurvePoint(p.label, p.x, k, n))
    return out


def _group(axis: Axis, records: Sequence[dict[str, Any]], group: str) -> dict[str, Any]:
    curve = pooled_curve(axis, records, group)
    return {"curve": [p.to_json() for p in curve], "failure": failure_point(curve, axis.criterion)}


# ----------------------------------------------------------------------------------------------- the summary
def describe_failure(failure: dict[str, Any], result: dict[str, Any]) -> str:
    """A failure point in words: "fails at 1.7 ± 0.2 x (between 1.5 and 2)", "holds to the last point (3)",
    "below the threshold from the first point (0)", "no data"."""
    unit = f" {result['unit']}" if result["unit"] else ""
    if failure["status"] == HOLDS:
        return f"holds through the hardest point measured ({failure.get('last_measured')})"
    if failure["status"] == BELOW_FROM_START:
        return f"below the threshold from the first point measured ({failure['label']})"
    if failure["status"] == FAILS and failure["x"] is not None:
        sigma = f" ± {_g(failure['sigma_x'])}" if failure["sigma_x"] is not None else ""
        a, b = failure["between"]
        return f"fails at {_g(failure['x'])}{sigma}{unit} (between {a} and {b})"
    if failure["status"] == FAILS:
        return f"below the threshold at {', '.join(failure.get('below') or [failure['label']])}"
    return "no data"


def headline(result: dict[str, Any], metric: str) -> str:
    """The axis's phrase for ``metric``, with the failure point of the method that lasts longest (``summary``'s
    ``{x}``): the last point where some method holds."""
    rows = {name: m for name, m in result["methods"].items() if m["metric"] == metric}
    if not rows:
        return ""
    name, best = max(rows.items(), key=lambda item: _reach(item[1]["failure"], result))
    f = best["failure"]
    note = f" (best: {name})" if len(rows) > 1 else ""
    if result["categorical"] and f["status"] in (HOLDS, FAILS):
        below = f.get("below") or []
        x = ", ".join(p["label"] for p in result["points"] if p["label"] not in below) or "none"
    elif f["status"] == HOLDS:
        last = next(p for p in result["points"] if p["label"] == f.get("last_measured"))
        x = _g(last["x"])
        note = f" or further: it holds at the hardest point measured{note}"
    elif f["status"] == FAILS:
        x = _g(f["x"]) + (f" ± {_g(f['sigma_x'])}" if f["sigma_x"] is not None else "")
    else:
        return f"{metric}: no method reaches the threshold at the easiest point"
    return f"{metric}: {result['summary'].format(x=x)}{note}"


def _reach(failure: dict[str, Any], result: dict[str, Any]) -> float:
    """How far along the axis a failure point lies, in points (larger: lasts longer; on a categorical axis, the
    points not below the threshold)."""
    labels = [p["label"] for p in result["points"]]
    if result["categorical"] and failure["status"] in (HOLDS, FAILS):
        return len(labels) - len(failure.get("below") or [])
    if failure["status"] == HOLDS:
        return len(labels)
    if failure["status"] == FAILS:
        i = labels.index(failure["label"])
        xs = [p["x"] for p in result["points"]]
        if failure["x"] is not None and i > 0 and xs[i] != xs[i - 1]:
            return i - 1 + (failure["x"] - xs[i - 1]) / (xs[i] - xs[i - 1])
        return i - 0.5
    return -1.0


def summary_markdown(results: Sequence[dict[str, Any]]) -> str:
    """The summary table of every axis's JSON: one headline per axis and metric, then per method its failure point,
    best value, threshold, fewest trials at a point, and the groups (part families) that fail earlier."""
    lines = ["# Stability maps: where each method fails", "",
             "Generated by `sygrid bench stability` from `bench/results/stability_<axis>.json`; a method fails where "
             "its value drops below max(fraction x its best, floor) (crossing interpolated between points; ± one "
             "standard error from the binomial errors of the two points around it).", ""]  # fmt: skip
    lines += ["| axis | headline |", "|---|---|"]
    for r in results:
        metrics = list(dict.fromkeys(m["metric"] for m in r["methods"].values()))
        for metric in metrics:
            lines.append(f"| {r['title']} | {headline(r, metric)} |")
    for r in results:
        c = r["criterion"]
        lines += ["", f"## {r['title']}", "",
                  f"{r['description']} Points: {', '.join(p['label'] for p in r['points'])} ({r['x_label']}); seeds "
                  f"{r['seeds']}; criterion: below max({c['fraction']:g} x best, {c['floor']:g}); "
                  f"{r['points_measured']} (point, seed) measurements in {_duration(r['seconds'])}.", "",
                  "| method | metric | failure point | best | threshold | fewest trials | families failing earlier |",
                  "|---|---|---|---|---|---|---|"]  # fmt: skip
        for name, m in r["methods"].items():
            f = m["failure"]
            fewest = min((p["n"] for p in m["curve"] if p["n"]), default=0)
            lines.append(f"| {name} | {m['metric']} | {describe_failure(f, r)} | {_pct(f['best'])} | "
                         f"{_pct(f['threshold'])} | {fewest} | {_earlier_groups(m, r)} |")  # fmt: skip
        for what, figures in (r.get("notes") or {}).items():
            lines.append(f"\n{what}: " + ", ".join(f"{k} {_g(v) if isinstance(v, float) else v}"
                                                   for k, v in figures.items()))  # fmt: skip
    return "\n".join(lines) + "\n"


def _earlier_groups(method: dict[str, Any], result: dict[str, Any]) -> str:
    """The part families whose own failure point comes before the method's, with theirs."""
    own = _reach(method["failure"], result)
    out = []
    for g, row in method["groups"].items():
        if g.startswith("family ") and _reach(row["failure"], result) < own:
            out.append(f"{g.removeprefix('family ')}: {describe_failure(row['failure'], result)}")
    return "; ".join(out) or "none"


def _g(x: float) -> str:
    return f"{x:.3g}"


def _pct(x: float | None) -> str:
    return "n/a" if x is None or not math.isfinite(x) else f"{100 * x:.1f} %"


def _duration(seconds: float) -> str:
    return f"{seconds / 3600:.1f} h" if seconds >= 5400 else f"{seconds / 60:.1f} min"


# ----------------------------------------------------------------------------------------------------- charts
def axis_chart(result: dict[str, Any]):
    """Per metric a panel of every method's curve (± one standard error), its failure point (a vertical line, the
    band ± sigma) and threshold (a short dash); below it, the part families' curves of the method that lasts
    longest."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    metrics = list(dict.fromkeys(m["metric"] for m in result["methods"].values()))
    fig, axes = plt.subplots(2, len(metrics), figsize=(6.5 * len(metrics), 9), squeeze=False)
    names = list(result["methods"])
    for col, metric in enumerate(metrics):
        top, bottom = axes[0][col], axes[1][col]
        rows = {n: m for n, m in result["methods"].items() if m["metric"] == metric}
        for name, m in rows.items():
            colour = _colour(names, name)
            _draw_curve(top, result, m["curve"], colour, name)
            _draw_failure(top, result, m["failure"], colour)
        best_name = max(rows, key=lambda n: _reach(rows[n]["failure"], result))
        families = {g: row for g, row in rows[best_name]["groups"].items() if g.startswith("family ")}
        for k, (g, row) in enumerate(families.items()):
            _draw_curve(bottom, result, row["curve"], f"C{k % 10}", g.removeprefix("family "))
            _draw_failure(bottom, result, row["failure"], f"C{k % 10}")
        top.set(title=f"{result['title']}: {metric}", ylabel=metric)
        bottom.set(title=f"{best_name}, per part family", ylabel=metric)
        for ax in (top, bottom) if families else (top,):
            _axis_frame(ax, result)
            if ax.get_legend_handles_labels()[0]:
                ax.legend(fontsize=7, loc="best")
        if not families:  # a whole-bin figure (or no groups measured): nothing per family to draw
            bottom.remove()
    fig.suptitle(f"sygrid bench stability: {result['title']} (failure: below max({result['criterion']['fraction']:g}"
                 f" x best, {result['criterion']['floor']:g}); bands: ± 1 s.e. of the failure point)")  # fmt: skip
    fig.tight_layout()
    return fig


def overview_chart(results: Sequence[dict[str, Any]]):
    """One panel per axis: every method's curve and failure point, in one figure."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = min(3, max(1, len(results)))
    rows = math.ceil(len(results) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(5.5 * cols, 4.2 * rows), squeeze=False)
    for ax, result in zip(axes.flat, results, strict=False):
        names = list(result["methods"])
        for name, m in result["methods"].items():
            colour = _colour(names, name)
            _draw_curve(ax, result, m["curve"], colour, name, errors=False)
            _draw_failure(ax, result, m["failure"], colour, band=False)
        _axis_frame(ax, result)
        ax.set_title(result["title"], fontsize=10)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=6, loc="best")
    for ax in list(axes.flat)[len(results) :]:
        ax.set_visible(False)
    fig.suptitle("sygrid bench stability: where each method fails (vertical lines: failure points)")
    fig.tight_layout()
    return fig


def _xs(result: dict[str, Any]) -> list[float]:
    """Where the points are drawn: their x, or their index on a categorical axis."""
    return [float(i) if result["categorical"] else p["x"] for i, p in enumerate(result["points"])]


def _draw_curve(ax, result: dict[str, Any], curve: list[dict], colour: str, label: str, errors: bool = True) -> None:
    xs = _xs(result)
    pts = [(x, p["value"], p["se"]) for x, p in zip(xs, curve, strict=True) if p["value"] is not None]
    if not pts:
        return
    x, y, se = zip(*pts, strict=True)
    if errors:
        ax.errorbar(x, y, yerr=se, color=colour, marker="o", ms=4, capsize=2, lw=1.2, label=label)
    else:
        ax.plot(x, y, color=colour, marker="o", ms=3, lw=1, label=label)


def _colour(names: list[str], name: str):
    """A method's colour: tab10's, or tab20's for more than ten methods."""
    import matplotlib

    i = names.index(name)
    return f"C{i % 10}" if len(names) <= 10 else matplotlib.colormaps["tab20"](i % 20)


def _draw_failure(ax, result: dict[str, Any], failure: dict[str, Any], colour: str, band: bool = True) -> None:
    """A crossing's vertical line (± sigma band) and threshold; nothing on a categorical axis (the summary names
    the points below)."""
    if failure["status"] != FAILS or result["categorical"] or failure["x"] is None:
        return
    x = failure["x"]
    ax.axvline(x, color=colour, ls="--", lw=0.9)
    if band and failure["sigma_x"] is not None:
        ax.axvspan(x - failure["sigma_x"], x + failure["sigma_x"], color=colour, alpha=0.12)
    if failure["threshold"] is not None:
        ax.plot([x], [failure["threshold"]], marker="_", ms=14, color=colour)


def _axis_frame(ax, result: dict[str, Any]) -> None:
    xs = _xs(result)
    if result["categorical"]:
        ax.set_xticks(xs, [p["label"] for p in result["points"]], rotation=20, fontsize=8)
    elif len(xs) > 1 and xs[-1] < xs[0]:
        ax.invert_xaxis()  # harder to the right
    ax.set(xlabel=result["x_label"] + " (harder to the right)", ylim=(-0.02, 1.02))
    ax.grid(alpha=0.3)
