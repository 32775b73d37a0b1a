"""The runtime: the one control loop of the project and what plugs into it.

* ``loop``        — ``LoopRunner``: read -> estimate -> supervise -> record -> control -> limit -> write
  at a fixed period over any ``otbot_hw.robot.Robot``; timing stats, recording, faults, progress
* ``controllers`` — the ``Controller`` protocol; ``TrackingController`` (computed torque on a
  ``DesiredTrajectory``), ``OpenLoopTorques`` (a torque sequence)
* ``feedback``    — where the state comes from: ``EkfFeedback`` (``otbot_hw.estimation``) or
  ``TruthFeedback`` (a simulator's ground truth)
* ``supervisor``  — ``Supervisor`` and ``SafetyConfig`` (the ``safety:`` section of config/robot.yaml):
  torque limits, rate/speed/workspace/tracking-error/estimator/overrun checks, latched faults
* ``backends``    — back ends by name: ``sim`` (in-process model), ``bus sim``, ``bus config``
* ``tracking``    — the paper's scenarios run through the loop (``otbot track``)

With ``otbot_hw.cli`` the only library code that imports ``sim`` and ``drivers`` (it wires back
ends together).
"""
from otbot_hw.runtime.controllers import (ControlStep, Controller, Feedback, OpenLoopTorques, Reference,
                                          TrackingController)
from otbot_hw.runtime.feedback import EkfFeedback, FeedbackUnavailable, StateEstimate, TruthFeedback
from otbot_hw.runtime.loop import LoopResult, LoopRunner, LoopStats
from otbot_hw.runtime.supervisor import SafetyConfig, Supervisor, Violation

__all__ = ["ControlStep", "Controller", "Feedback", "OpenLoopTorques", "Reference", "TrackingController",
           "EkfFeedback", "FeedbackUnavailable", "StateEstimate", "TruthFeedback", "LoopResult", "LoopRunner",
           "LoopStats", "SafetyConfig", "Supervisor", "Violation"]
