"""The bench identification procedure (``otbot bench``): the paper's experiments through the loop and the drivers.

* ``procedure`` — ``BenchProcedure``: per step set-up, checks, excitation, recording checks,
  identification with gates (pass / redo); then the session's identification, diagnosis, summary
* ``steps``     — the steps (fixture, set-up), ``BenchSettings``, ``BenchError`` / ``BenchAbort``
* ``runs``      — ``BenchRuns``: supervised runs through the loop, idle watchdogs reset; ``warm_up``
* ``robot_fit`` — a designed excitation scaled to the robot the fixture probe shows
* ``analysis``  — the step's identification, the geometry refit, the diagnosis of the session
* ``summary``   — the JSON result (parameters, unloaded platform, combinations, truth and error/std)
* ``checks``    — the checks judged from the sensors (drives, IMU, rest, limits, fixture, saturation, clipping)
* ``excitation``— the paper's or a designed excitation, the fixture probe, the brake, predicted margins
* ``operator``  — the person at the bench: prompts on stdin, or ``--yes`` (the simulated plant's
  operator channel does the set-up)
* ``session``   — the session folder and its manifest (resume), the robot's identity
* ``buslog``    — the raw bus log (python-can BLF)
* ``report``    — Markdown report with PNG plots
"""
