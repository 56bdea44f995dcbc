"""Did the run work? ``report.md`` and ``corrections.png`` beside ``metrics.json``, from
figures that need no ground truth (where the run has ground truth, its ATE is added so a
benchmark can check those figures against it).

Each figure is set against a line past which it says something went wrong; the lines come
from what the figures are, not from a recording's scores:

- **accepted share**: of the keyframes the map covered (placed, a render to align with), how
  many corrections the gate accepted. Below half, the field and the frames disagree more
  often than they agree (another place, a blurred field, a wrong depth unit).
- **gate consistency**: each measured correction's squared Mahalanobis distance ``d2`` to the
  odometry's prediction, under the correction's and the prediction's covariances, follows a
  chi-square with 6 degrees of freedom when both covariances are honest: median 5.35. Two
  sides: a median beyond the chi-square's 99% point (16.8) is *too confident* (the corrections
  are larger than the odometry and the field say they can be: good corrections get refused, bad
  ones weigh too much); a median below its 1% point (0.87) is *too cautious* (the covariances
  are several times larger than the errors: the corrections weigh too little and a false one
  passes the gate). Either way ``docs/usage`` says what to change.
- **placement**: a run on a map that was never placed has its poses in its own frame.
- **map coverage**: the share of keyframes, once placed, that found the field there (not
  refused for low opacity); below half, the run left the mapped place.
"""

from __future__ import annotations

import csv
import json
import logging
from pathlib import Path

import numpy as np

from nap3d_graph.factors.gate import chi2_threshold
from nap3d_graph.figure_report import FigureReport
from nap3d_graph.plots import pyplot

from .records import KeyframeRecord, refusal_kind

__all__ = ["RunReport", "run_report", "write_run_report", "read_run_report", "ACCEPTED_SHARE_BAD", "COVERAGE_BAD"]

log = logging.getLogger(__name__)

#: Below this share of covered keyframes accepted, the field and the frames mostly disagree.
ACCEPTED_SHARE_BAD = 0.5
#: Below this share of placed keyframes with the field there, the run left the map.
COVERAGE_BAD = 0.5
#: Refusals that mean no field was there to align with (not a disagreement).
_UNCOVERED_KINDS = ("low opacity", "no field", "not yet placed", "relocalised", "recovery", "no frame")


def _median_chi2_6() -> float:
    return chi2_threshold(0.5, 6)


#: The gate's consistency lines: the chi-square's (6 dof) 1% and 99% points.
CONSISTENCY_LINES = (0.01, 0.99)


def consistency(d2: np.ndarray) -> tuple[str, str, bool | None]:
    """The gate consistency row from the measured corrections' d2 (M,): its value (the median,
    and which side of the chi-square it is off, by about what factor of the covariances), its
    line and its verdict (None when nothing was measured). Two-sided: see the module's text."""
    low, high = (chi2_threshold(p, 6) for p in CONSISTENCY_LINES)
    line = f"{low:.2f} - {high:.1f} (its 1% and 99% points)"
    if not d2.size:
        return "none measured", line, None
    median = float(np.median(d2))
    value = f"{median:.2f} over {d2.size} (chi-square median {_median_chi2_6():.2f})"
    if median < low:
        value += (f": too cautious, the covariances about {_median_chi2_6() / max(median, 1e-9):.0f}x larger than the "
                  "corrections' errors")
    elif median > high:
        value += (f": too confident, the covariances about {median / _median_chi2_6():.0f}x smaller than the "
                  "corrections' errors")
    return value, line, low <= median <= high


class RunReport(FigureReport):
    """The figures of one run, built from its keyframe records and ``metrics``."""

    def __init__(self, keyframes, metrics: dict):
        super().__init__()
        self.keyframes = list(keyframes)
        self.metrics = metrics


def _covered(k) -> bool:
    return k.accepted or not refusal_kind(k.reason).startswith(_UNCOVERED_KINDS)


def run_report(keyframes, metrics: dict) -> RunReport:
    """The run's figures without ground truth (see the module docstring)."""
    report = RunReport(keyframes, metrics)
    placed = [k for k in report.keyframes if not refusal_kind(k.reason).startswith(("not yet placed", "relocalised"))]
    covered = [k for k in placed if _covered(k)]
    accepted = sum(k.accepted for k in covered)
    share = accepted / len(covered) if covered else float("nan")
    report.add("corrections accepted, of the keyframes the field covered", f"{accepted} / {len(covered)}",
               f">= {ACCEPTED_SHARE_BAD:.0%}", None if not covered else share >= ACCEPTED_SHARE_BAD)
    coverage = len(covered) / len(placed) if placed else float("nan")
    report.add("map coverage: placed keyframes that found the field there", f"{len(covered)} / {len(placed)}",
               f">= {COVERAGE_BAD:.0%}", None if not placed else coverage >= COVERAGE_BAD)
    d2 = np.array([k.gate_d2 for k in report.keyframes if np.isfinite(k.gate_d2)])
    report.add("gate consistency: median d2 of the measured corrections (chi-square, 6 dof)", *consistency(d2))
    sizes = np.array([k.correction_m for k in report.keyframes if k.accepted and np.isfinite(k.correction_m)])
    if sizes.size:
        report.add("accepted correction size (median, p90, max)",
                   f"{np.median(sizes) * 100:.2f}, {np.percentile(sizes, 90) * 100:.2f}, {sizes.max() * 100:.2f} cm",
                   "the odometry's drift between keyframes", None)
    placement = (metrics.get("map") or {}).get("placement")
    if placement is not None:
        placed_at = placement.get("placed_at_frame")
        where = ("never" if not placement.get("placed") else "at its given start" if placed_at is None
                 else f"at frame {placed_at}")
        report.add("placed in the map", where, "placed", bool(placement.get("placed")))
        recoveries = (metrics.get("map") or {}).get("recoveries") or []
        report.add("recoveries (relocalised after refused keyframes)", str(len(recoveries)), "few", None)
    estimate = metrics.get("estimate") or {}
    ate = estimate.get("ate_m")
    if isinstance(ate, dict) and "rmse" in ate:
        odometry = (metrics.get("odometry") or {}).get("ate_m") or {}
        report.add("ATE against the ground truth (where there is one)",
                   f"{ate['rmse'] * 100:.2f} cm (odometry alone {odometry.get('rmse', float('nan')) * 100:.2f})",
                   "the reference the figures above are checked against", None)
    elif estimate.get("ate_se3_aligned_m") is not None:
        # Frames not tied (a run never placed, a map without ground truth): the aligned figure only.
        odometry = (metrics.get("odometry") or {}).get("ate_se3_aligned_m")
        report.add(f"ATE against the ground truth ({metrics.get('scored', 'SE(3)-aligned only')})",
                   f"{estimate['ate_se3_aligned_m'] * 100:.2f} cm" + (
                       f" (odometry alone {odometry * 100:.2f})" if odometry is not None else ""),
                   "the reference the figures above are checked against", None)
    return report


def _plot(path: Path, keyframes) -> None:
    """Corrections over the run: accepted sizes, refused keyframes by kind, and d2 against
    the chi-square's 99% line."""
    plt = pyplot()
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(8, 5.5), sharex=True)
    frames = np.array([k.frame_index for k in keyframes])
    accepted = np.array([k.accepted for k in keyframes], dtype=bool)
    sizes = np.array([k.correction_m for k in keyframes]) * 100
    top.plot(frames[accepted], sizes[accepted], "o", ms=3, label="accepted")
    kinds = sorted({refusal_kind(k.reason) for k in keyframes if not k.accepted})
    for row, kind in enumerate(kinds):
        at = frames[[not k.accepted and refusal_kind(k.reason) == kind for k in keyframes]]
        top.plot(at, np.full(len(at), -0.2 * (row + 1)), "x", ms=4, label=f"refused: {kind}")
    top.set_ylabel("correction (cm)")
    top.legend(fontsize=7, loc="upper right")
    d2 = np.array([k.gate_d2 for k in keyframes])
    finite = np.isfinite(d2)
    bottom.semilogy(frames[finite], np.maximum(d2[finite], 1e-3), ".", ms=4)
    bottom.axhline(chi2_threshold(0.99, 6), color="r", lw=1, label="chi-square 99% (6 dof)")
    bottom.axhline(_median_chi2_6(), color="g", lw=1, ls="--", label="chi-square median")
    bottom.set_ylabel("gate d2")
    bottom.set_xlabel("frame")
    bottom.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_run_report(run_dir: Path, keyframes, metrics: dict) -> RunReport:
    """Write ``report.md`` and ``corrections.png`` into ``run_dir``; returns the report."""
    run_dir = Path(run_dir)
    report = run_report(keyframes, metrics)
    if keyframes:
        try:
            _plot(run_dir / "corrections.png", report.keyframes)
        except (OSError, ValueError) as exc:  # a plot must not lose the run's files
            log.warning("corrections.png not written (%s)", exc)
    report.write(run_dir / "report.md", "Did the run work?", "![corrections over the run](corrections.png)")
    return report


def read_run_report(run_dir: Path) -> RunReport:
    """The report of a run already written to ``run_dir``, built again from its
    ``corrections.csv`` and ``metrics.json`` (what ``report.md`` was built from)."""
    run_dir = Path(run_dir)
    keyframes = []
    with (run_dir / "corrections.csv").open(newline="") as f:
        for row in csv.DictReader(f):
            keyframes.append(KeyframeRecord(int(row["run_index"]), float(row["timestamp"]), 0,
                                            accepted=row["accepted"] == "1", reason=row["reason"],
                                            gate_d2=float(row["gate_d2"] or "nan"),
                                            correction_m=float(row["correction_m"] or "nan")))
    return run_report(keyframes, json.loads((run_dir / "metrics.json").read_text()))
