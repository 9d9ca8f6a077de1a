"""Lane width of the CPU compositing kernels, chosen for the CPU that Numba compiles for.

The compositing kernels (``kernels._fwd_tile`` / ``_bwd_tile``) process each 16 px tile row
in chunks of a fixed number of lanes.  With AVX-512 one 16-lane chunk fills one register, so
a row is one chunk (the original kernel).  With AVX2 (8 floats per register) a 16-lane chunk
needs two registers per value and spills; 8-lane chunks fit and let a row skip the half its
Gaussian cannot reach.  The width is a compile-time constant of the kernels (each width has
its own compiled and cached specialisation), picked per call from:

1. :func:`use_lane_width` (a context manager, for benchmarks and tests), else
2. the environment variable ``BRAVE6D_RASTER_LANES`` (``8`` or ``16``), else
3. :func:`lane_width_for` of the features Numba targets (:func:`target_cpu`).
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from functools import lru_cache

LANE_WIDTHS = (8, 16)
"""Supported lane widths (both divide the 16 px tile side)."""

LANE_ENV = "BRAVE6D_RASTER_LANES"
"""Environment variable that forces a lane width (``8`` or ``16``)."""

REPORTED_FEATURES = ("sse4.2", "avx", "avx2", "fma", "avx512f", "avx512vl", "avx512bw",
                     "prefer-256-bit")
"""CPU features worth printing next to a benchmark figure."""

_override: int | None = None


@dataclass(frozen=True)
class TargetCpu:
    """What Numba compiles for: LLVM's CPU name and its enabled features."""

    name: str
    features: frozenset[str]

    def summary(self) -> str:
        """One line such as ``znver3: +avx2 +fma -avx512f ...`` (+ enabled, - absent)."""
        shown = [("+" if f in self.features else "-") + f for f in REPORTED_FEATURES]
        return f"{self.name}: {' '.join(shown)}"


def _parse_feature_string(text: str) -> frozenset[str]:
    """``+avx2,-avx512f,...`` (LLVM's syntax, as in ``NUMBA_CPU_FEATURES``) -> enabled names."""
    return frozenset(item[1:] for item in text.split(",") if item.startswith("+"))


@lru_cache(maxsize=1)
def target_cpu() -> TargetCpu:
    """The CPU name and features Numba generates code for (``NUMBA_CPU_NAME`` /
    ``NUMBA_CPU_FEATURES`` when set, else the host as LLVM sees it)."""
    import llvmlite.binding as llvm
    import numba

    name = numba.config.CPU_NAME or llvm.get_host_cpu_name()
    if numba.config.CPU_FEATURES:
        features = _parse_feature_string(numba.config.CPU_FEATURES)
    elif numba.config.CPU_NAME and numba.config.CPU_NAME != "host":
        features = frozenset()  # a named generic target: no host features are assumed
    else:
        features = frozenset(k for k, on in llvm.get_host_cpu_features().items() if on)
    return TargetCpu(name=name, features=features)


def lane_width_for(features: Mapping[str, bool] | Iterable[str]) -> int:
    """Lane width for a CPU with these features: 16 with AVX-512 (``avx512f``), else 8.

    ``features`` is a set of enabled feature names or a name -> enabled mapping (like
    ``llvmlite.binding.get_host_cpu_features()``).
    """
    if isinstance(features, Mapping):
        enabled = {name for name, on in features.items() if on}
    else:
        enabled = set(features)
    return 16 if "avx512f" in enabled else 8


def _checked(width: int, source: str) -> int:
    if width not in LANE_WIDTHS:
        raise ValueError(f"{source}: lane width must be one of {LANE_WIDTHS}, got {width!r}")
    return width


def selected_lane_width() -> int:
    """The lane width the CPU backend uses now (see the module docstring for the order)."""
    if _override is not None:
        return _override
    forced = os.environ.get(LANE_ENV, "").strip()
    if forced:
        try:
            return _checked(int(forced), LANE_ENV)
        except ValueError:
            raise ValueError(
                f"{LANE_ENV}: lane width must be one of {LANE_WIDTHS}, got {forced!r}") from None
    return lane_width_for(target_cpu().features)


@contextmanager
def use_lane_width(width: int) -> Iterator[None]:
    """Force the CPU backend's lane width inside a ``with`` block (benchmarks, tests)."""
    global _override
    previous = _override
    _override = _checked(width, "use_lane_width")
    try:
        yield
    finally:
        _override = previous


def lane_tag(width: int) -> tuple[int, ...]:
    """The kernels' compile-time lane width: a tuple whose length is the width, so each
    width is its own Numba type signature (and its own on-disk cache entry)."""
    return (0,) * _checked(width, "lane_tag")
