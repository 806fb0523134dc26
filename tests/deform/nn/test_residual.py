import torch

from deform.nn.residual import ResidualGNN


def test_chain_propagation_equals_pyg_gcnconv():
    net = ResidualGNN(13)
    torch.nn.init.normal_(net.head[2].weight)  # a non-zero head so that the outputs differ from 0
    x, v = torch.randn(13, 3), torch.randn(13, 3)
    fast = net(x, v)
    ref = net.forward_pyg(x, v)
    assert fast.abs().max() > 0
    assert torch.allclose(fast, ref, atol=1e-6)


def test_residual_is_batched_and_translation_invariant():
    net = ResidualGNN(8)
    torch.nn.init.normal_(net.head[2].weight)
    x, v = torch.randn(5, 8, 3), torch.randn(5, 8, 3)
    out = net(x, v)
    assert out.shape == (5, 8, 3)
    assert torch.allclose(out[2], net(x[2], v[2]), atol=1e-6)
    assert torch.allclose(net(x + torch.tensor([1.0, -2.0, 0.5]), v), out, atol=1e-5)


def test_untrained_residual_is_zero():
    net = ResidualGNN(8)
    assert net(torch.randn(8, 3), torch.randn(8, 3)).abs().max() == 0
