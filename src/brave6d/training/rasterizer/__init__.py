"""Differentiable 3D Gaussian Splatting rasterizer: one function, two backends.

``from brave6d.training.rasterizer import rasterize`` (also ``brave6d.training.rasterize``)::

    rgb, depth, alpha, info = rasterize(means, quats, scales, opacities, colors,
                                        viewmats, Ks, width, height, sh_degree=3)

* ``cuda``: ``gsplat.rasterization`` (non-packed, ``RGB+ED``), imported lazily: the only place
  in training that needs gsplat.
* ``cpu``: Numba kernels with forward and backward, compiled once per machine into an on-disk
  cache; same conventions as gsplat 1.5.3's CUDA kernels (EWA projection with the Jacobian
  clamp, eps2d = 0.3 px^2, opacity-aware 3.33 sigma boxes, 16 px tiles, depth order,
  alpha <= 0.999, skip below 1/255, stop before T <= 1e-4, SH up to degree 3 shifted by +0.5
  and clamped at 0).
* Intrinsics: ``Ks`` use OpenCV's pixel centres (integer coordinates, the project's ``K``);
  the principal point is moved +0.5 px into gsplat's convention once, for both backends
  (``_pixels``).
* ``antialiased=True``: the 2D mip filter (Mip-Splatting; gsplat's ``rasterize_mode="antialiased"``),
  each Gaussian's opacity times ``sqrt(max(det(cov2d) / det(cov2d + eps2d I), 0))`` per camera, in
  both backends and the reference.
* ``auto``: follows the tensors (CUDA tensors -> ``cuda``, CPU tensors -> ``cpu``).

Public modules besides :func:`rasterize` (what tests and benchmarks use; the ``_``-prefixed
modules are the backends' plumbing):

* ``constants``: the numerical conventions every backend shares (tile size, alpha cap, ...).
* ``kernels``: the compiled CPU kernels (projection, SH, tile binning, compositing and their
  backward passes), each testable on its own against ``reference``.
* ``median_depth``: the median depth on the GPU (a Triton kernel over gsplat's projections and
  tile lists; its interpreter runs it on CPU tensors for tests) and gsplat's tile lists in torch.
* ``simd``: the CPU name and SIMD features Numba compiles the kernels for (benchmarks print it).
* ``reference``: a slow pure-torch implementation (autograd for gradients), the yardstick of
  the kernels; only for tests and benchmarks, never for training.

Inputs are checked (``RasterInputError``, a ``BraveError``): NaN/inf are rejected by
name and count; zero or denormal quaternions act as the identity with zero gradient;
scales are clamped to ``[1e-9, 1e6]``; Gaussians outside ``[near_plane, far_plane]``
are culled.  ``info`` is what ``brave6d.training.strategy`` (and gsplat 1.5.3's ``DefaultStrategy``) reads
(``packed=False``).
On shared CPU machines set ``OMP_WAIT_POLICY=PASSIVE`` before torch starts: spinning
OpenMP threads otherwise steal the cores the kernels run on.
"""

from brave6d.core.runtime import pin_threading_layer

pin_threading_layer()  # before numba loads (library users too): its TBB layer can hang at exit

from ._api import rasterize  # noqa: E402
from ._validation import RasterBackendError, RasterInputError  # noqa: E402

__all__ = ["RasterBackendError", "RasterInputError", "rasterize"]
