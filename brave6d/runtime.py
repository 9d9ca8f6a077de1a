"""Process-wide runtime settings that must be made before torch or numba load."""

from __future__ import annotations

import logging
import os
import sys

log = logging.getLogger(__name__)


def quiet_openmp() -> None:
    """Make OpenMP threads sleep instead of spin while they wait (``OMP_WAIT_POLICY=PASSIVE``).

    torch and the numba CPU rasterizer each run their own OpenMP thread team. With the default
    (spinning) policy the team that just finished keeps the cores busy while the other one
    starts, and on a shared or small machine a render or a training step then takes several
    times longer (measured on 2 cores under load: 320x240 render median 210 ms spinning vs 50 ms
    passive). The variable is read when the OpenMP runtime loads, so this must run before torch
    / numba are imported; an explicit ``OMP_WAIT_POLICY`` in the environment is respected.
    """
    if "OMP_WAIT_POLICY" in os.environ:
        return
    if "torch" in sys.modules or "numba" in sys.modules:
        log.info("torch/numba already loaded: set OMP_WAIT_POLICY=PASSIVE before starting for lower latency")
        return
    os.environ["OMP_WAIT_POLICY"] = "PASSIVE"
