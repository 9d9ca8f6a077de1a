"""The rasterizer's SIMD target report (brave6d.training.rasterizer.simd)."""

from __future__ import annotations

import llvmlite.binding as llvm
import numba
import pytest

from brave6d.training.rasterizer.simd import REPORTED_FEATURES, TargetCpu, enabled_features, target_cpu


@pytest.mark.parametrize("features", [
    "+avx2,-avx512f,+fma",
    {"avx2": True, "avx512f": False, "fma": True},
    ["avx2", "fma"],
])
def test_enabled_features_accepts_llvm_strings_mappings_and_names(features):
    assert enabled_features(features) == {"avx2", "fma"}


@pytest.mark.parametrize("features, lanes", [
    ({"avx512f", "avx2", "avx", "fma"}, 16),
    ({"avx2", "avx", "fma"}, 8),
    ({"sse4.2"}, 4),
])
def test_float32_lanes_follow_the_widest_vector_feature(features, lanes):
    assert TargetCpu("x", frozenset(features)).float32_lanes == lanes


def test_summary_marks_present_and_absent_features():
    line = TargetCpu("znver3", frozenset({"avx", "avx2", "fma"})).summary()
    assert line.startswith("znver3: ")
    assert "+avx2" in line and "+fma" in line and "-avx512f" in line
    assert "(8 float32 lanes" in line
    assert all(f in line for f in REPORTED_FEATURES)


def test_target_cpu_is_what_numba_compiles_for():
    cpu = target_cpu()
    if numba.config.CPU_NAME or numba.config.CPU_FEATURES:
        pytest.skip("NUMBA_CPU_NAME / NUMBA_CPU_FEATURES override the host")
    assert cpu.name == llvm.get_host_cpu_name()
    host = {k for k, on in llvm.get_host_cpu_features().items() if on}
    assert cpu.features == host
