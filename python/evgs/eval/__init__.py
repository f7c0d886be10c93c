"""Evaluation (paper §4, §5.4): alignment, trajectory / image / ELOPE metrics as plain functions of
arrays; figures, reports and the ``evgs eval`` command on top."""

from evgs.eval.align import Sim3, align_first_pose, umeyama
from evgs.eval.associate import Association, associate, interpolate_poses
from evgs.eval.elope import elope_score, velocities, write_submission
from evgs.eval.images import ImageMetrics, evaluate_images, lpips, psnr, ssim
from evgs.eval.trajectory import RPE, TrajectoryMetrics, evaluate_trajectory, rpe

__all__ = [
    "RPE",
    "Association",
    "ImageMetrics",
    "Sim3",
    "TrajectoryMetrics",
    "align_first_pose",
    "associate",
    "elope_score",
    "evaluate_images",
    "evaluate_trajectory",
    "interpolate_poses",
    "lpips",
    "psnr",
    "rpe",
    "ssim",
    "umeyama",
    "velocities",
    "write_submission",
]
