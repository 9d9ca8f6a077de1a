"""What the project's Triton kernels share: the interpreter switch and the ahead-of-time build.

Triton decides at its first import whether kernels compile for a GPU or run in its interpreter
(``TRITON_INTERPRET=1``: NumPy on CPU tensors, how CI proves the kernels without a GPU). The
ahead-of-time build needs no GPU either: Triton ships its own ``ptxas``, so CI compiles every
kernel for the GPUs the project runs on (sm_90: H100/H200).
"""

from __future__ import annotations

import os
from typing import Any


def interpreting() -> bool:
    """Whether triton runs in interpreter mode (``TRITON_INTERPRET=1`` at its first import)."""
    try:
        from triton import knobs
    except ImportError:  # triton < 3.4
        return os.environ.get("TRITON_INTERPRET", "0") == "1"
    return bool(knobs.runtime.interpret)


def compile_ahead(kernel: Any, signature: dict[str, str], constants: dict[str, Any], arch: int = 90
                  ) -> dict[str, Any]:
    """Compile a ``@triton.jit`` kernel for CUDA compute capability ``arch`` without a GPU;
    Triton's stages by name (``ttir``, ``ptx``, ``cubin``, ...). ``signature`` types every argument
    (``"*fp32"``, ``"i32"``, ``"constexpr"``); ``constants`` gives the constexprs' values."""
    import triton
    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource

    source = ASTSource(kernel, signature, constexprs=constants)
    return dict(triton.compile(source, target=GPUTarget("cuda", arch, 32)).asm)


__all__ = ["compile_ahead", "interpreting"]
