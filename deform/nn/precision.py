"""The residual network's arithmetic precision in batched rollouts.

Why bfloat16: at planning scale (hundreds of rods per step) the network's four small matrix products
are about a fifth of a compiled step. On a CPU with native bfloat16 matrix instructions (AMX, or
AVX512-BF16) oneDNN runs them faster than float32: one thread, 100-step rollouts of 512 rods
0.94x the time, 1024 rods 0.93x; the paper's metric moves by at most 0.0013 mm. Below
:data:`BFLOAT16_MIN_BATCH` rods the conversions cost more than the products gain (64 rods: 1.14x,
128: 1.07x, 256: 0.99x), so bfloat16 is used from that batch size on. On a CPU without native
bfloat16 the products are emulated and slower, so ``auto`` picks it only where it is native.
Training, system identification and the 100 Hz loop keep float32: they need the gradients, or are
one rod.
"""

from __future__ import annotations

import torch

SETTINGS = ("auto", "float32", "bfloat16")
BFLOAT16_MIN_BATCH = 512  # rods per step from which a bfloat16 network is used (see above)


def native_bfloat16() -> bool:
    """Whether this CPU multiplies bfloat16 matrices natively (AMX tiles or AVX512-BF16), as
    oneDNN uses them. False when torch cannot tell.

    Returns:
        True when a bfloat16 network is expected to be faster than a float32 one.
    """
    try:
        has_isa = torch.cpu._is_amx_tile_supported() or torch.cpu._is_avx512_bf16_supported()
        return bool(has_isa and torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):
        return False


def network_dtype(setting: str) -> torch.dtype | None:
    """The residual network's compute dtype for a ``workers.predict_network_dtype`` setting.

    Args:
        setting: ``"auto"`` (bfloat16 where :func:`native_bfloat16`, else float32), ``"float32"``
            or ``"bfloat16"``.

    Returns:
        ``torch.bfloat16``, or None for the network's own float32.
    """
    if setting not in SETTINGS:
        raise ValueError(f"network precision must be one of {SETTINGS}, not {setting!r}")
    if setting == "bfloat16" or (setting == "auto" and native_bfloat16()):
        return torch.bfloat16
    return None


def for_batch(network_dtype: torch.dtype | None, batch: int) -> torch.dtype | None:
    """The network's dtype for a step of ``batch`` rods: ``network_dtype`` from
    :data:`BFLOAT16_MIN_BATCH` rods on, float32 (None) below.

    Args:
        network_dtype: what the step was configured with (:func:`network_dtype`).
        batch: rods in the step (the compiled bucket).

    Returns:
        ``network_dtype`` or None.
    """
    return network_dtype if batch >= BFLOAT16_MIN_BATCH else None
