"""Evaluation (paper §4, §5.4): alignment, trajectory / image / ELOPE metrics as plain functions of
arrays; figures, reports and the ``evgs eval`` command on top.

Image metrics live in :mod:`evgs.eval.images` and are not imported here: they pull in torch, which the
``evgs`` command line should not pay for at start-up.
"""

from evgs.eval.align import Sim3, align_first_pose, umeyama
from evgs.eval.associate import Association, associate, interpolate_poses
from evgs.eval.elope import elope_score, velocities, write_submission
from evgs.eval.trajectory import RPE, TrajectoryMetrics, evaluate_trajectory, rpe

__all__ = [
    "RPE",
    "Association",
    "Sim3",
    "TrajectoryMetrics",
    "align_first_pose",
    "associate",
    "elope_score",
    "evaluate_trajectory",
    "interpolate_poses",
    "rpe",
    "umeyama",
    "velocities",
    "write_submission",
]
