"""The dynamic model: pure functions of state, input and parameters (paper §3 and the effects).

Importing the package points numba's on-disk cache at a folder keyed by the kernels' sources
(``kernel_cache``), before any compiled kernel is decorated."""
from otbot_hw.model import kernel_cache as _kernel_cache

_kernel_cache.configure()
