"""BRAVE-6D kernel: geometry, cameras, scene spec, scene-directory layout, CLI.

Our NumPy work is many small matrix products; OpenBLAS threads fighting over a few cores make
them 5-20x slower, so OpenBLAS is single-threaded unless the user set OPENBLAS_NUM_THREADS.
(torch and Open3D keep their own thread pools.)
"""

import os as _os

_os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
