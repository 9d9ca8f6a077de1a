"""The CPU that Numba compiles the rasterizer kernels for: LLVM's CPU name and SIMD features.

Benchmarks print it next to their figures: the compositing kernels' 16-lane row loops fill
one AVX-512 register or two AVX2 registers, so a figure means little without it.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from functools import lru_cache

REPORTED_FEATURES = ("sse4.2", "avx", "avx2", "fma", "avx512f", "avx512vl", "avx512bw")
"""SIMD features worth printing next to a benchmark figure."""


@dataclass(frozen=True)
class TargetCpu:
    """What Numba compiles for: LLVM's CPU name and its enabled features."""

    name: str
    features: frozenset[str]

    @property
    def float32_lanes(self) -> int:
        """float32 values per widest vector register: 16 (AVX-512), 8 (AVX) or 4 (SSE)."""
        if "avx512f" in self.features:
            return 16
        return 8 if "avx" in self.features else 4

    def summary(self) -> str:
        """One line such as ``znver3: +avx2 +fma -avx512f ... (8 float32 lanes)``."""
        shown = " ".join(("+" if f in self.features else "-") + f for f in REPORTED_FEATURES)
        return f"{self.name}: {shown} ({self.float32_lanes} float32 lanes per register)"


def enabled_features(features: Mapping[str, bool] | Iterable[str] | str) -> frozenset[str]:
    """Enabled feature names from a name -> enabled mapping (``llvmlite.binding.
    get_host_cpu_features()``), an iterable of names, or LLVM's ``+avx2,-avx512f`` string
    (the syntax of ``NUMBA_CPU_FEATURES``)."""
    if isinstance(features, str):
        return frozenset(item.strip()[1:] for item in features.split(",")
                         if item.strip().startswith("+"))
    if isinstance(features, Mapping):
        return frozenset(name for name, on in features.items() if on)
    return frozenset(features)


@lru_cache(maxsize=1)
def target_cpu() -> TargetCpu:
    """The CPU name and features Numba generates code for: ``NUMBA_CPU_NAME`` /
    ``NUMBA_CPU_FEATURES`` when set (a portable cache), else the host as LLVM sees it."""
    import llvmlite.binding as llvm
    import numba

    name = numba.config.CPU_NAME or llvm.get_host_cpu_name()
    if numba.config.CPU_FEATURES:
        features = enabled_features(numba.config.CPU_FEATURES)
    elif numba.config.CPU_NAME and numba.config.CPU_NAME != "host":
        features = frozenset()  # a named target without a feature list: none assumed
    else:
        features = enabled_features(llvm.get_host_cpu_features())
    return TargetCpu(name=name, features=features)
