"""Process-wide runtime settings that must be made before torch or numba load (OpenMP wait policy,
numba threading layer); :func:`prepare_process` makes them all."""

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


#: Threading layers that cannot hang at exit: numba's own work queue and OpenMP.
SAFE_LAYERS = ("omp", "workqueue")
#: Priority for ``NUMBA_THREADING_LAYER=default``: numba takes the first layer that loads, and
#: ``workqueue`` always loads, so TBB (which numba would otherwise prefer) is never reached.
SAFE_PRIORITY = "omp workqueue tbb"


def pin_threading_layer() -> None:
    """Keep numba off its TBB threading layer, whose pool can hang the process at exit.

    Where a usable oneTBB is installed (Debian's ``libtbb12``, pulled in by ``libopencv-dev``
    and many other packages) numba prefers it, and a process that ran a parallel kernel (the CPU
    rasterizer) from a worker thread, as the server and the demo do, can hang for ever at
    interpreter exit in ``tbb::finalize`` (numba/numba#10556: TBB runs no worker threads when it
    sees one CPU, and the task numba started on the worker thread waits on the main thread).
    An explicit ``omp`` or ``workqueue`` is respected; the default becomes the priority
    ``omp workqueue tbb`` (OpenMP, the layer chosen when TBB is absent, then numba's work queue);
    any other value (``tbb``, or ``safe``, ``threadsafe``, ``forksafe``, which can select TBB) is
    replaced by ``omp`` with a warning. numba reads the variables when it loads (again on each compile),
    so this runs before numba is imported; if numba is loaded already, its configuration is
    reloaded, which takes effect unless a parallel kernel has run.
    """
    layer = os.environ.get("NUMBA_THREADING_LAYER", "default").strip().lower()
    if layer in SAFE_LAYERS:
        return
    if layer == "default":
        os.environ["NUMBA_THREADING_LAYER_PRIORITY"] = SAFE_PRIORITY
    else:
        log.warning("NUMBA_THREADING_LAYER=%s replaced by 'omp' (brave6d runs 'omp' or 'workqueue' only: numba's "
                    "TBB layer can hang the process at exit after a render from a worker thread, numba/numba#10556)",
                    layer)
        os.environ["NUMBA_THREADING_LAYER"] = "omp"
    if "numba" in sys.modules:
        _reload_numba_config()


def _reload_numba_config() -> None:
    """Make an already imported numba read the pinned variables; warn if a layer already runs."""
    import numba
    from numba.core import config

    config.reload_config()
    try:
        running = numba.threading_layer()
    except ValueError:  # no parallel kernel has run yet: the reloaded settings apply
        return
    if running not in SAFE_LAYERS:
        log.warning("numba already runs its %s threading layer: set NUMBA_THREADING_LAYER=omp before starting",
                    running)


def prepare_process() -> None:
    """Every process-wide setting that must precede torch / numba: call first in an entry point."""
    quiet_openmp()
    pin_threading_layer()
