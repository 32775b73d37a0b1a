"""The runtime: the one control loop of the project and what plugs into it.

* ``loop``        — ``LoopRunner``: read -> estimate -> supervise -> record -> control -> limit -> write
  at a fixed period over any ``otbot_hw.robot.Robot`` and its pacing; its parts ``loop_timing``
  (``LoopStats``, histograms, overruns), ``loop_recording`` (writer, topics, events) and
  ``loop_power`` (enable/disable, trips, the fault latch and quick stop)
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
import importlib

#: name -> submodule; imported on first use (PEP 562) so that a light module of this package (the
#: control protocol and client, for ``otbot ctl``) does not pull in the whole runtime
_EXPORTS = {
    **dict.fromkeys(["ControlStep", "Controller", "Feedback", "OpenLoopTorques", "Reference", "TrackingController"],
                    "controllers"),
    **dict.fromkeys(["EkfFeedback", "FeedbackUnavailable", "StateEstimate", "TruthFeedback"], "feedback"),
    **dict.fromkeys(["LoopResult", "LoopRunner"], "loop"),
    "LoopStats": "loop_timing",
    **dict.fromkeys(["SafetyConfig", "Supervisor", "Violation"], "supervisor"),
}


def __getattr__(name: str):
    if name in _EXPORTS:
        value = getattr(importlib.import_module(f"otbot_hw.runtime.{_EXPORTS[name]}"), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'otbot_hw.runtime' has no attribute {name!r}")


__all__ = list(_EXPORTS)
