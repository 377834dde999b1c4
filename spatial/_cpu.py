"""The CPU the kernels are compiled for: the architecture's baseline (numba's ``generic``),
not this host's model.

numba keys its on-disk cache by CPU name and features, so kernels compiled for one host's
model load only on that model; for the baseline they load on any host of the architecture,
which is what lets a wheel ship them compiled (``deploy/build_backend.py``). The baseline costs
nothing measurable here: the kernels are scalar walks and loops (query p50 and build times
within noise of the host's own, ``benchmarks.spatial_bench``). ``NUMBA_CPU_NAME`` set in the
environment wins (a host's model, to compile for it alone).

Imported first by ``spatial``: numba reads the setting when its CPU target is first made.
"""

import os
import sys

__all__: list[str] = []  # it acts when imported


def _choose_baseline() -> None:
    numba = sys.modules.get("numba")
    if numba is not None and "_toplevel_target_context" in vars(numba.core.registry.cpu_target):
        return  # this process has compiled for its host already: stay consistent with it
    os.environ.setdefault("NUMBA_CPU_NAME", "generic")
    if numba is not None:
        numba.core.config.reload_config()  # imported, not yet compiling: it reads the variable again


_choose_baseline()
