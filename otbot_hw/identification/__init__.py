"""Grey-box identification of Otbot's dynamic parameters (paper §4): prediction-error
fitting, the three identification steps, equation-error starts, reports and sweeps.

Modules: ``model`` (output prediction), ``experiment`` (data of one run), ``initial_state`` (fitted initial rates),
``prediction_error`` (the generic fitter) with ``residual_problem`` (residuals, batch Jacobian, rank check) and
``fit_result`` (``FitResult``), ``equation_error`` (linear start),
``experiments`` (the paper's experiments), ``steps`` (the three steps),
``report`` (tables, JSON, plots), ``executors`` and ``sweep`` (sensitivity sweeps).
"""
