"""The residual network in bfloat16: the same correction to its precision, chosen only where the
CPU multiplies bfloat16 natively, and a bad setting refused."""

import pytest
import torch

import deform.nn.precision as precision
from deform.nn.residual import ResidualGNN


def _trained_like(n: int = 13) -> ResidualGNN:
    torch.manual_seed(0)
    net = ResidualGNN(n)
    for p in net.parameters():  # every layer non-zero, as after training
        torch.nn.init.normal_(p, std=0.3)
    return net


def test_bfloat16_network_gives_the_float32_correction_to_its_precision():
    net = _trained_like()
    x, v = torch.randn(64, 13, 3) * 0.3, torch.randn(64, 13, 3) * 0.2
    ref = net(x, v)
    low = net(x, v, torch.bfloat16)
    assert low.dtype == torch.float32  # the caller's dtype, whatever the arithmetic
    scale = ref.abs().max()
    assert scale > 0
    err = (low - ref).abs().max() / scale
    assert 1e-5 < err < 0.05  # bfloat16's 8 bits through four layers (and not silently float32)


def test_float32_setting_leaves_the_network_as_it_was():
    net = _trained_like()
    x, v = torch.randn(4, 13, 3), torch.randn(4, 13, 3)
    assert torch.equal(net(x, v, None), net(x, v))
    assert precision.network_dtype("float32") is None


def test_auto_picks_bfloat16_only_where_it_is_native(monkeypatch):
    monkeypatch.setattr(precision, "native_bfloat16", lambda: False)
    assert precision.network_dtype("auto") is None
    assert precision.network_dtype("bfloat16") is torch.bfloat16  # asked for explicitly
    monkeypatch.setattr(precision, "native_bfloat16", lambda: True)
    assert precision.network_dtype("auto") is torch.bfloat16


def test_native_bfloat16_is_false_when_torch_cannot_tell(monkeypatch):
    def missing():
        raise AttributeError("no such probe in this torch")

    monkeypatch.setattr(torch.cpu, "_is_amx_tile_supported", missing)
    assert precision.native_bfloat16() is False


def test_bfloat16_only_from_the_batch_where_it_pays():
    assert precision.for_batch(torch.bfloat16, precision.BFLOAT16_MIN_BATCH) is torch.bfloat16
    assert precision.for_batch(torch.bfloat16, precision.BFLOAT16_MIN_BATCH - 1) is None
    assert precision.for_batch(None, 4096) is None


def test_unknown_setting_is_refused():
    with pytest.raises(ValueError, match="bfloat16"):
        precision.network_dtype("float16")
