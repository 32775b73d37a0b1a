"""Tracking control of Otbot (paper §5): computed-torque law, gains, torque limiting,
reference trajectories, torque-feasibility check, trajectory planner and scenarios.

One concept per module:

* ``gains``           — K_p, K_v from a stabilization time per axis
* ``task_model``      — compiled closed-form M_bar, C_bar (the law's model evaluation)
* ``computed_torque`` — the control law and the feedback interface (``TaskState``)
* ``limiter``         — run-time torque saturation that reports every episode
* ``trajectories``    — desired trajectories p_d(t) with derivatives (analytic: polyline, path, stop, placed)
* ``sampled_trajectory`` — a trajectory given by samples (splines) and its CSV format
* ``prediction``      — the task state one period ahead (the loop's sample delay compensated)
* ``metrics``         — tracking errors, peaks and settle times of events
* ``interval``        — small interval arithmetic used by ``feasibility``
* ``feasibility``     — interval bound of the torques for given error bounds (§5.3)
* ``planner``         — direct-collocation planner (CasADi + IPOPT)
* ``scenarios``       — the paper's test cases (§5.4) and the figures of a run; the runs go through
  the loop runner (``otbot_hw.runtime.tracking``)
"""
