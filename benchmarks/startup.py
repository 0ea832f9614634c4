"""Start-up time: import, init and the first scan (kernels compiled, or loaded from
Taichi's offline cache when warm: run it twice).

    python benchmarks/startup.py
"""

import time

t0 = time.perf_counter()
import numpy as np  # noqa: E402

import ndtom_ti  # noqa: E402

t1 = time.perf_counter()
ndtom_ti.init("cpu")  # the library's defaults
m = ndtom_ti.NdtOmMap(0.2)
m.insert_scan(np.random.default_rng(0).normal(size=(50_000, 3)) * 10.0, np.eye(4))
t2 = time.perf_counter()
print(f"import {t1 - t0:.2f} s, init + first scan {t2 - t1:.2f} s, total {t2 - t0:.2f} s")
