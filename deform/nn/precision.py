"""The residual network's arithmetic precision in batched rollouts.

Why bfloat16: at planning scale (hundreds of rods per step) the network's four small matrix products
are about a fifth of a compiled step. On a CPU with native bfloat16 matrix instructions (AMX, or
AVX512-BF16) oneDNN runs them at several times the float32 rate; a predict step at 1024 rods took
0.91x the time, and the positions differ from the float32 network's by about 1 um after 20 steps
(the network's correction is a few mm/s; bfloat16 keeps 8 bits of it). On a CPU without them the
products are emulated and slower, so ``auto`` picks bfloat16 only where it is native. Training,
system identification and the 100 Hz loop keep float32: they need the gradients, or are one rod.
"""

from __future__ import annotations

import torch

SETTINGS = ("auto", "float32", "bfloat16")


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
