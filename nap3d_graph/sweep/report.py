"""A sweep's tables: ``sweep.csv`` (one row per cell), ``summary.md`` and a plot per swept setting.

Every figure comes from the cells' own ``result.json`` files, so the tables can be rebuilt at
any time (``nap3d-graph sweep ... --report-only``) and always agree with the cells.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

from nap3d_graph.provenance import provenance

from .run import cell_status

__all__ = ["collect_rows", "write_report", "CSV_COLUMNS"]

CSV_COLUMNS = ["cell", "recording", "seed", "status", "ate_odometry_cm", "ate_estimate_cm", "ate_causal_cm",
               "ate_estimate_max_cm", "accepted", "keyframes", "seconds", "error", "command"]


def _cm(value) -> float | None:
    return None if value is None else round(float(value) * 100.0, 4)


def collect_rows(spec, folder: Path) -> list[dict]:
    """One row per cell of ``spec``, from its files (status ``pending`` when it has none)."""
    folder = Path(folder)
    swept = spec.swept_keys()
    rows = []
    for cell in spec.cells():
        status = cell_status(folder, cell) or {"status": "pending"}
        field_path = None if cell.field.untrained else folder / "fields" / f"{cell.field.id}.pt"
        row = {"cell": cell.id, "recording": cell.recording.name, **{k: v for k, v in cell.settings},
               "seed": cell.seed, "status": status.get("status"),
               "ate_odometry_cm": _cm(status.get("ate_odometry_m")), "ate_estimate_cm": _cm(status.get("ate_estimate_m")),
               "ate_causal_cm": _cm(status.get("ate_causal_m")), "ate_estimate_max_cm": _cm(status.get("ate_estimate_max_m")),
               "accepted": status.get("accepted"), "keyframes": status.get("keyframes"),
               "seconds": None if status.get("seconds") is None else round(float(status["seconds"]), 2),
               "error": status.get("error", ""),
               "command": cell.command(field_path, folder / "cells" / cell.id / "run")}
        for key in swept:
            row.setdefault(key, dict(cell.settings).get(key))
        rows.append(row)
    return rows


def _stats(values: list[float]) -> str:
    if not values:
        return "-"
    a = np.asarray(values, dtype=float)
    return f"{a.mean():.2f} +- {a.std():.2f} (worst {a.max():.2f})"


def _group(rows: list[dict], keys: list[str]) -> dict[tuple, list[dict]]:
    groups: dict[tuple, list[dict]] = {}
    for row in rows:
        groups.setdefault(tuple(row.get(k) for k in keys), []).append(row)
    return groups


def _table(rows: list[dict], keys: list[str]) -> list[str]:
    header = [*keys, "runs", "failed", "ATE estimate cm: mean +- std (worst)", "causal", "odometry", "estimate / odometry"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for values, group in _group(rows, keys).items():
        ok = [r for r in group if r["status"] == "ok" and r["ate_estimate_cm"] is not None]
        failed = sum(r["status"] == "failed" for r in group)
        ratios = [r["ate_estimate_cm"] / r["ate_odometry_cm"] for r in ok if r["ate_odometry_cm"]]
        ratio = f"{np.mean(ratios):.2f} (worst {np.max(ratios):.2f})" if ratios else "-"
        lines.append("| " + " | ".join([*(str(v) for v in values), str(len(group)), str(failed),
                                        _stats([r["ate_estimate_cm"] for r in ok]),
                                        _stats([r["ate_causal_cm"] for r in ok if r["ate_causal_cm"] is not None]),
                                        _stats([r["ate_odometry_cm"] for r in ok if r["ate_odometry_cm"] is not None]),
                                        ratio]) + " |")
    return lines


def write_report(spec, folder: Path, counts: dict | None = None) -> dict:
    """Write sweep.csv, summary.md and the plots; returns ``{"rows": n, "ok": n, "failed": n,
    "pending": n}``."""
    folder = Path(folder)
    rows = collect_rows(spec, folder)
    swept = spec.swept_keys()
    columns = [CSV_COLUMNS[0], "recording", *swept, *CSV_COLUMNS[2:]]
    with open(folder / "sweep.csv", "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=columns, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    tally = {s: sum(r["status"] == s for r in rows) for s in ("ok", "failed", "pending")}
    lines = [f"# Sweep: {len(rows)} cells ({tally['ok']} ok, {tally['failed']} failed, {tally['pending']} pending)", "",
             f"Recordings: {', '.join(r.name for r in spec.recordings)}; swept: {', '.join(swept) or 'nothing'}; "
             f"seeds: {', '.join(str(s) for s in spec.seeds)}. ATE is evo's RMSE without alignment (drift), in cm; "
             "every cell's command is in sweep.csv.", ""]
    if counts:
        lines += [f"This pass: {counts.get('ran', 0)} cells run, {counts.get('skipped', 0)} already finished, "
                  f"{counts.get('fields_trained', 0)} fields trained, on {counts.get('pool')} with "
                  f"{counts.get('workers')} workers.", ""]
    lines += ["## By recording and setting", "", *_table(rows, ["recording", *swept]), ""]
    for key in swept:
        lines += [f"## {key}", "", *_table(rows, [key]), ""]
    failures = [r for r in rows if r["status"] == "failed"]
    if failures:
        lines += ["## Failed cells", ""] + [f"- `{r['cell']}`: {r['error']}" for r in failures] + [""]
    (folder / "summary.md").write_text("\n".join(lines))
    for key in swept:
        _plot(rows, key, folder / f"plot_{key.replace('.', '_')}.png")
    record = {"provenance": provenance({"spec": str(spec.path)}), "cells": len(rows), **tally, "swept": swept}
    (folder / "summary.json").write_text(json.dumps(record, indent=1))
    return {"rows": len(rows), **tally}


def _plot(rows: list[dict], key: str, path: Path) -> None:
    """ATE of every finished run, one box per value of ``key`` and recording."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    recordings = sorted({r["recording"] for r in rows})
    values = sorted({str(r.get(key)) for r in rows})
    fig, ax = plt.subplots(figsize=(max(4.0, 1.2 * len(values) * len(recordings)), 3.2))
    width = 0.8 / max(len(recordings), 1)
    for j, recording in enumerate(recordings):
        data = [[r["ate_estimate_cm"] for r in rows if r["recording"] == recording and str(r.get(key)) == v
                 and r["status"] == "ok" and r["ate_estimate_cm"] is not None] for v in values]
        positions = [i + (j - (len(recordings) - 1) / 2) * width for i in range(len(values))]
        colour = f"C{j % 10}"
        kept = [(p, d) for p, d in zip(positions, data) if d]
        if kept:
            box = ax.boxplot([d for _, d in kept], positions=[p for p, _ in kept], widths=width * 0.8,
                             patch_artist=True, manage_ticks=False)
            for patch in box["boxes"]:
                patch.set_facecolor(colour)
                patch.set_alpha(0.6)
        ax.plot([], [], color=colour, lw=6, alpha=0.6, label=recording)
    ax.set_xticks(range(len(values)), values)
    ax.set_xlabel(key)
    ax.set_ylabel("ATE (cm, smoothed)")
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
