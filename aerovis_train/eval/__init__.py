"""Evaluation of event keypoint detectors (numpy + OpenCV; importing it never imports torch).

* :mod:`.pose`: the SuperEvent relative-pose protocol (pair selection, essential-matrix RANSAC,
  rotation and max(rotation, translation) AUC) on canonical sequences.
* :mod:`aerovis_slam.classical` (shared with the SLAM runtime): ORB, SIFT and GFTT + rBRIEF
  baselines computed on the same time surfaces.
* :mod:`.cli`: ``aerovis-eval pose``.

Learned detectors plug in through ``aerovis_train.eval.learned.load_detector`` (imported lazily
by the CLI, since it needs torch or onnxruntime).
"""

from aerovis_slam.keypoints import match_keypoints

from .pose import (
    Detector,
    FramePlan,
    PoseError,
    evaluate_sequence,
    interpolate_poses,
    plan_frames,
    pose_auc,
    relative_pose_error,
    rotation_angle_deg,
    select_pairs,
    summarize,
)

__all__ = [
    "Detector",
    "FramePlan",
    "PoseError",
    "evaluate_sequence",
    "interpolate_poses",
    "match_keypoints",
    "plan_frames",
    "pose_auc",
    "relative_pose_error",
    "rotation_angle_deg",
    "select_pairs",
    "summarize",
]
