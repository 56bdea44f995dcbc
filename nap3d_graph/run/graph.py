"""The run's keyframe graph in iSAM2: what goes in, the gate a correction passes, the window
that bounds it, the rebuild after a failed update, and the final solve.

Variables are a ``Pose3`` ``X(j)`` per keyframe (``T_world_cam``), and whatever the motion
model adds (the IMU path: ``V(j)``, ``B(j)``), and with an anchor ``M(0)`` (``T_world_map``:
the field's frame in the world). The motion model adds the first pose's prior and each
keyframe's motion factor (:mod:`nap3d_graph.run.motion`, :mod:`nap3d_graph.run.imu`) through
:meth:`KeyframeGraph.add`; the run adds each NAP3D correction through
:meth:`KeyframeGraph.gated_correction`, which enters only if it passes the chi-square gate
against iSAM2's prediction: the joint marginal covariance of the factor's variables carried
through the factor's Jacobians, plus the correction's own covariance.
"""

from __future__ import annotations

import logging

import gtsam
import numpy as np
from gtsam.symbol_shorthand import M, X

from nap3d_graph.conventions import T_to_pose3, pose3_to_T
from nap3d_graph.factors import chi2_gate_isam2, nap3d_anchor_factor, nap3d_prior_factor
from nap3d_graph.factors.gate import GateResult
from nap3d_graph.results import Correction
from nap3d_graph.run.config import PipelineConfig
from nap3d_graph.run.solve import gnc_solve, isam2_params, rebuilt_isam2

__all__ = ["KeyframeGraph"]

log = logging.getLogger(__name__)


class KeyframeGraph:
    """iSAM2 over the keyframes, with everything it was given kept for a rebuild and the final
    solve. ``factor_log`` holds ``(factor, is NAP3D, keyframe frame index)``: NAP3D factors are
    logged without their robust kernel (the final GNC weighs them), gated-out ones too."""

    def __init__(self, config: PipelineConfig, anchored: bool):
        self.config, self.anchored = config, anchored
        self.isam = gtsam.ISAM2(isam2_params(config.relinearize_threshold))
        self.new_factors = gtsam.NonlinearFactorGraph()
        self.new_values = gtsam.Values()
        self.graph_all = gtsam.NonlinearFactorGraph()  # everything iSAM2 was given (a rebuild's input)
        self.values_all = gtsam.Values()
        self.factor_log: list[tuple[gtsam.NonlinearFactor, bool, int]] = []
        self.frozen: dict[int, np.ndarray] = {}  # keyframes marginalised out of the window: their poses
        self.first_live = 0  # the oldest keyframe still in iSAM2
        self.rebuilds = 0
        self.gnc_outliers: list[int] = []
        self.gnc_recovered: list[int] = []

    # --- what goes in ----------------------------------------------------------------------

    def add(self, factor: gtsam.NonlinearFactor) -> None:
        """A factor known to hold (a prior, a motion factor): in at the next update."""
        self.new_factors.add(factor)
        self.factor_log.append((factor, False, -1))

    def insert(self, key: int, value) -> None:
        self.new_values.insert(key, value)

    def add_anchor(self, factor: gtsam.NonlinearFactor, T_world_field: np.ndarray) -> None:
        """The map anchor ``M(0)`` (the field's frame in the world) with its prior ``factor``
        and its first value (4, 4)."""
        self.add(factor)
        self.insert(M(0), T_to_pose3(T_world_field))

    def enter(self, entry) -> None:
        """What a motion model returns for a new keyframe (:class:`~nap3d_graph.run.motion.KeyframeEntry`):
        its factors and its first values, in at the next update."""
        for factor in entry.factors:
            self.add(factor)
        for key, value in entry.values:
            self.insert(key, value)

    def add_past_gate(self, key: int, correction: Correction, frame_index: int) -> gtsam.NonlinearFactor:
        """The NAP3D factor of ``correction`` on ``key``, added without the gate (a pose found
        afresh, when the prediction it would be gated against is what went wrong) and logged
        for the final solve as a gated correction is. Raises ValueError when its covariance is
        not usable (nothing is added then)."""
        factor = self.nap3d_factor(key, correction, self.config.robust)
        self.new_factors.add(factor)
        self.factor_log.append((self.nap3d_factor(key, correction, None), True, frame_index))
        return factor

    def reframed(self, T_new_old: np.ndarray) -> "KeyframeGraph":
        """A fresh graph holding this one's factors with every pose moved into another frame
        (``T_new_cam = T_new_old @ T_old_cam``), less the first keyframe's prior, which held
        the old frame's gauge: whoever calls this adds what holds the new one (a prior) before
        the next :meth:`update`. Only for a graph that kept every keyframe (no window has moved)
        and holds poses alone (no anchor, no IMU state)."""
        if self.frozen or self.anchored or self.new_factors.size():
            raise ValueError("only a whole graph of poses, updated, moves into another frame")
        moved = KeyframeGraph(self.config, self.anchored)
        estimate = self.isam.calculateEstimate()
        for key in estimate.keys():
            if gtsam.Symbol(key).chr() != ord("x"):
                raise ValueError(f"{gtsam.DefaultKeyFormatter(key)} is not a pose: it cannot move into another frame")
            moved.insert(key, T_to_pose3(T_new_old @ pose3_to_T(estimate.atPose3(key))))
        for factor, is_nap3d, frame_index in self.factor_log:
            if isinstance(factor, gtsam.PriorFactorPose3) and list(factor.keys()) == [X(0)] and not is_nap3d:
                continue  # the provisional frame's gauge
            moved.new_factors.add(factor)
            moved.factor_log.append((factor, is_nap3d, frame_index))
        return moved

    def update(self, extra_step: bool = False) -> None:
        """Give iSAM2 what was added since the last update (a second step when a correction can
        have moved a pose far from its linearisation); rebuild it when the update fails."""
        self.graph_all.push_back(self.new_factors)
        self.values_all.insert(self.new_values)
        try:
            self.isam.update(self.new_factors, self.new_values)
            if extra_step:
                self.isam.update()
        except RuntimeError as exc:  # gtsam's IndeterminateSystemException, thrown mid-update
            self._rebuild(str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__)
        # Fresh containers every update: iSAM2 keeps what it was given.
        self.new_factors = gtsam.NonlinearFactorGraph()
        self.new_values = gtsam.Values()

    def _rebuild(self, why: str) -> None:
        """After a failed iSAM2 update (its state is then undefined): a fresh iSAM2 from
        everything it was given (:func:`~nap3d_graph.run.solve.rebuilt_isam2`)."""
        log.warning("iSAM2 update failed (%s); rebuilding it from the %d factors so far", why, self.graph_all.size())
        self.isam = rebuilt_isam2(self.isam, self.graph_all, self.values_all, self.config.relinearize_threshold)
        self.rebuilds += 1

    # --- what comes out ----------------------------------------------------------------------

    def has(self, key: int) -> bool:
        return bool(self.isam.valueExists(key))

    def pose(self, key: int) -> np.ndarray:
        """(4, 4) iSAM2's current estimate of a ``Pose3`` variable."""
        return pose3_to_T(self.isam.calculateEstimatePose3(key))

    def estimate(self) -> gtsam.Values:
        return self.isam.calculateEstimate()

    def anchor(self) -> np.ndarray:
        """(4, 4) ``T_world_map`` as estimated now (identity without an anchor)."""
        return self.pose(M(0)) if self.anchored and self.has(M(0)) else np.eye(4)

    # --- corrections -------------------------------------------------------------------------

    def nap3d_factor(self, key: int, correction: Correction, robust: str | None):
        if self.anchored:
            return nap3d_anchor_factor(key, M(0), None, correction, robust=robust)
        return nap3d_prior_factor(key, None, correction, robust=robust)

    def gated_correction(self, key: int, correction: Correction, frame_index: int
                         ) -> tuple[gtsam.NonlinearFactor | None, GateResult | None]:
        """The NAP3D factor of ``correction`` on keyframe ``key``, added when it passes the gate
        (``chi2_gate_isam2``); returns it (None when it did not enter) and the gate's result
        (None when its covariance is unusable: never put in the graph). Whatever the gate
        said, a usable correction is logged for the final solve, which weighs it again."""
        try:
            factor = self.nap3d_factor(key, correction, self.config.robust)
        except ValueError as exc:  # a covariance GTSAM cannot use: skip, never corrupt the graph
            log.warning("correction at %s not usable: %s", gtsam.DefaultKeyFormatter(key), exc)
            return None, None
        gate = chi2_gate_isam2(factor, self.isam, p=self.config.gate_p)
        self.factor_log.append((self.nap3d_factor(key, correction, None), True, frame_index))
        if not gate.accepted:
            return None, gate
        self.new_factors.add(factor)
        return factor, gate

    # --- the window ----------------------------------------------------------------------------

    def bound(self, num_keyframes: int) -> int | None:
        """With ``graph_window`` N: once more than 1.5 N keyframes are live, marginalise the
        oldest down to N and fix their poses (see :class:`PipelineConfig`). What is kept for a
        rebuild and for the final solve becomes iSAM2's own factors, the marginal included; the
        final solve is then Levenberg-Marquardt on them (GNC takes no marginal). Returns the
        index of the oldest keyframe still live when the window moved, else None."""
        window = self.config.graph_window
        if not window or num_keyframes - self.first_live <= window + window // 2:
            return None
        cut = num_keyframes - window
        # Poses about to be fixed: relinearise everything first (iSAM2 relinearises lazily, past
        # a threshold, and the final solve will not polish these any more), then solve fully.
        try:
            self.isam.update(force_relinearize=True)
            self.isam.update(force_relinearize=True)
        except RuntimeError as exc:
            log.debug("relinearisation before the window moved failed (%s)", exc)
            return None
        best = self.isam.calculateBestEstimate()
        frozen = {j: pose3_to_T(best.atPose3(X(j))) for j in range(self.first_live, cut)}
        leaving = gtsam.KeyList()
        for j in frozen:
            leaving.push_back(X(j))
        try:
            self.isam.marginalizeLeaves(leaving)
        except RuntimeError as exc:  # not leaves of the Bayes tree: keep them, try again later
            log.debug("keyframes %d-%d not marginalised yet (%s)", self.first_live, cut - 1, exc)
            return None
        self.frozen.update(frozen)
        self.first_live = cut
        gone = {X(j) for j in frozen}
        self.factor_log = [entry for entry in self.factor_log if not gone & set(entry[0].keys())]
        factors = self.isam.getFactorsUnsafe()  # marginalised factors leave empty slots
        self.graph_all = gtsam.NonlinearFactorGraph()
        for k in range(factors.size()):
            if (factor := factors.at(k)) is not None:
                self.graph_all.add(factor)
        self.values_all = self.isam.calculateEstimate()
        return cut

    # --- the final solve ---------------------------------------------------------------------

    def final_estimate(self, accepted_frames: set[int]) -> gtsam.Values:
        """iSAM2's estimate polished by a batch solve on the same factors: iSAM2 relinearises
        lazily (every few updates, past a threshold), the written trajectory should be the
        converged optimum. With NAP3D factors (and no window): graduated non-convexity (TLS)
        over every correction, those the gate accepted (``accepted_frames``) and those it
        refused (the prediction it judged them by may have been wrong); the odometry and the
        priors are known inliers. Accepted corrections it weighs out are recorded in
        ``gnc_outliers``, refused ones it takes back in ``gnc_recovered``."""
        estimate = self.isam.calculateEstimate()
        nap3d = [k for k, (_, is_nap3d, _) in enumerate(self.factor_log) if is_nap3d]
        try:
            # GNC needs every factor with a noise model; a window's marginal has none (the window's
            # own robust factors then decide, with Levenberg-Marquardt).
            if self.config.final_gnc and nap3d and not self.frozen:
                result, weights = gnc_solve([f for f, _, _ in self.factor_log], estimate, nap3d, self.config.gnc_p)
                self._note_gnc(nap3d, weights, accepted_frames)
                return result
            return gtsam.LevenbergMarquardtOptimizer(self.graph_all, estimate).optimize()
        except RuntimeError as exc:  # keep iSAM2's answer rather than lose the run
            log.warning("final batch optimisation failed (%s); writing the iSAM2 estimate", exc)
            return estimate

    def _note_gnc(self, nap3d: list[int], weights: np.ndarray, accepted: set[int]) -> None:
        self.gnc_outliers = [self.factor_log[k][2] for k in nap3d if weights[k] < 0.5
                             and self.factor_log[k][2] in accepted]
        self.gnc_recovered = [self.factor_log[k][2] for k in nap3d if weights[k] >= 0.5
                              and self.factor_log[k][2] not in accepted]
        if self.gnc_outliers or self.gnc_recovered:
            log.info("final solve: %d accepted corrections weighed out (frames %s), %d refused ones taken back "
                     "(frames %s)", len(self.gnc_outliers), self.gnc_outliers[:10], len(self.gnc_recovered),
                     self.gnc_recovered[:10])

    def accepted_graph(self, accepted_frames: set[int]) -> gtsam.NonlinearFactorGraph:
        """The known factors and the NAP3D factors of ``accepted_frames`` (their Gaussian twins),
        e.g. for the marginals of the final estimate."""
        graph = gtsam.NonlinearFactorGraph()
        for factor, is_nap3d, frame in self.factor_log:
            if not is_nap3d or frame in accepted_frames:
                graph.add(factor)
        return graph
