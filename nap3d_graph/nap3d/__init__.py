"""NAP3D, one keyframe's correction read top to bottom in one folder:

``config`` (:class:`AlignConfig`) -> ``matching`` (SIFT, ratio test) -> ``correspondences``
(back-projection, noise sigmas) -> ``ransac`` (anisotropic residual, opacity-weighted
Procrustes) -> ``refine`` (least squares over pixels and depths, covariance) -> ``align``
(:func:`align_views`: the stages for one real frame and one rendered view) -> ``correct``
(:func:`correct_pose`: render at the believed pose, align, re-render).

The peers it is compared with live in :mod:`nap3d_graph.baselines`.
"""

from .align import align_correspondences, align_views, prepare_correspondences, view_features
from .config import AlignConfig
from .correct import correct_pose, render_safely

__all__ = ["AlignConfig", "align_views", "align_correspondences", "prepare_correspondences", "view_features",
           "correct_pose", "render_safely"]
