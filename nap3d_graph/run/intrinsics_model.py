"""Which camera model a run's keyframes fit: the given intrinsics, or the self-calibrated ones too.

With ``AlignConfig.estimate_intrinsics="auto"`` each alignment fits the pose twice, with the
real camera's intrinsics as given and with them estimated, and keeps the self-calibrated fit
only when the data call for it (:func:`~nap3d_graph.nap3d.align.choose_intrinsics_model`).
That second fit is 10-20% of a keyframe's measurement with XFeat (fr1/desk's grid field with
``--odom dense``: 72 against 90 ms), yet the camera does not change during a run: when the given intrinsics
won ``check_every`` keyframes in a row, the run fits only them, and both again at every
``check_every``-th keyframe. A keyframe that chooses the self-calibrated model puts the run
back to fitting both at every keyframe until the given intrinsics win ``check_every`` times
in a row again. Keyframes whose alignment fails leave the count as it is.

What is given up: a keyframe fitted with the given intrinsics alone has no self-calibrated
fit to fall back on when its own fails (with both, a failed fixed fit returns the calibrated
one). With XFeat on fr1/desk's second half and the grid or view field no keyframe chose the
self-calibrated model, and the run's trajectory is the same to the bit with either; with SIFT,
whose few inliers let the self-calibrated model win 1-13 keyframes of a run whose camera is
right, each such win sets the run back to fitting both, and runs moved by 0.82-1.17x in ATE
either way (``benchmarks/intrinsics_tracker.py``).
"""

from __future__ import annotations

from nap3d_graph.results import Correction

__all__ = ["IntrinsicsModelTracker"]

#: ``corrections.csv``'s ``intrinsics_model`` for a keyframe fitted with the given intrinsics alone.
FIXED_ONLY = "fixed (only model fitted)"


class IntrinsicsModelTracker:
    """Decides, per keyframe job, whether its alignment fits the self-calibrated model too
    (:meth:`fits_both`), and learns from each correction's choice (:meth:`observe`).

    ``check_every``: how many fixed choices in a row settle the run, and how often a settled
    run fits both again (0: both at every keyframe, as ``AlignConfig`` alone does);
    ``active``: whether the alignments fit both at all (``estimate_intrinsics="auto"`` with
    the refined method); an inactive tracker never changes a job.
    """

    def __init__(self, check_every: int, active: bool):
        if check_every < 0:
            raise ValueError(f"check_every must be >= 0 keyframes, got {check_every}")
        self.check_every = int(check_every)
        self.active = bool(active) and check_every > 0
        self.fixed_in_a_row = 0
        self._since_both = 0
        self._jobs: dict[int, bool] = {}  # keyframe frame index -> fitted both

    @classmethod
    def for_run(cls, config) -> "IntrinsicsModelTracker":
        """The tracker of a run with ``config`` (a :class:`~nap3d_graph.run.config.PipelineConfig`)."""
        align = config.align
        return cls(config.intrinsics_check_every, align.estimate_intrinsics == "auto" and align.method == "refined")

    @property
    def settled(self) -> bool:
        """The given intrinsics won ``check_every`` keyframes in a row."""
        return self.active and self.fixed_in_a_row >= self.check_every

    def fits_both(self, frame_index: int) -> bool:
        """Whether keyframe ``frame_index``'s job fits the self-calibrated model too (called once
        per job, when it is made)."""
        both = not self.settled or self._since_both + 1 >= self.check_every
        self._since_both = 0 if both else self._since_both + 1
        self._jobs[frame_index] = both
        return both

    def observe(self, frame_index: int, correction: Correction) -> str:
        """Learn from keyframe ``frame_index``'s correction; returns the model it kept, for its
        record: "fixed", "calibrated", "calibrated (the fixed model failed)",
        ``FIXED_ONLY``, or "" (failed, or the self-calibrated fit failed and the fixed one
        was kept without a comparison)."""
        both = self._jobs.pop(frame_index, True)
        if not correction.success:
            return ""
        model = str(correction.alignment.diagnostics.get("intrinsics_model", ""))
        if not both and self.active:
            return FIXED_ONLY
        if model == "fixed":
            self.fixed_in_a_row += 1
        elif model.startswith("calibrated"):
            self.fixed_in_a_row = 0
        return model
