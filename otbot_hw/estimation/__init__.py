"""Pose estimation: the EKF over encoders and IMU (filterpy), its configuration and its use on recordings.

``PoseEKF`` is stepped by the loop runner once per cycle; ``estimate_recording`` runs it over a
recording (``otbot estimate``). Design, choices and measured accuracy: docs/estimation.md.
"""
from otbot_hw.estimation.config import EstimatorConfig
from otbot_hw.estimation.ekf import STATE_NAMES, UPDATE_KINDS, Estimate, EstimatorFault, PoseEKF
from otbot_hw.estimation.replay import EstimationRun, estimate_recording, run_recording

__all__ = ["EstimatorConfig", "Estimate", "EstimatorFault", "PoseEKF", "EstimationRun", "estimate_recording",
           "run_recording", "STATE_NAMES", "UPDATE_KINDS"]
