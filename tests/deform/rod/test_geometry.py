import math

import torch

from deform.rod import geometry as G
from tests.deform.rod.helpers import random_rod


def test_parallel_transport_maps_tangent_and_preserves_angles():
    gen = torch.Generator().manual_seed(1)
    a = G.normalize(torch.randn(50, 3, generator=gen, dtype=torch.float64))
    b = G.normalize(torch.randn(50, 3, generator=gen, dtype=torch.float64))
    u = torch.randn(50, 3, generator=gen, dtype=torch.float64)
    assert torch.allclose(G.parallel_transport(a, a, b), b, atol=1e-12)
    pu = G.parallel_transport(u, a, b)
    assert torch.allclose(pu.norm(dim=-1), u.norm(dim=-1), atol=1e-12)
    assert torch.allclose(G.dot(pu, b), G.dot(u, a), atol=1e-12)
    axis = torch.linalg.cross(a, b, dim=-1)
    assert torch.allclose(G.dot(G.parallel_transport(axis, a, b), axis), G.dot(axis, axis), atol=1e-12)


def test_curvature_binormal_magnitude_is_twice_tan_half_turning_angle():
    phi = torch.tensor([0.1, 0.7, 1.5], dtype=torch.float64)
    e0 = torch.tensor([[1.0, 0, 0]], dtype=torch.float64).expand(3, 3)
    e1 = torch.stack([torch.cos(phi), torch.sin(phi), torch.zeros(3, dtype=torch.float64)], -1) * 0.3
    kb = G.curvature_binormal(torch.stack([e0, e1], dim=1))[:, 0]
    assert torch.allclose(kb.norm(dim=-1), 2 * torch.tan(phi / 2), atol=1e-12)
    assert torch.allclose(kb[:, :2], torch.zeros(3, 2, dtype=torch.float64))  # along +z


def test_space_parallel_frame_has_no_reference_twist_and_is_orthonormal():
    x, _ = random_rod(3, 12)
    t = G.normalize(G.edges(x))
    d1 = G.space_parallel_frame(t)
    assert torch.allclose(G.dot(d1, t), torch.zeros_like(d1[..., 0]), atol=1e-12)
    assert torch.allclose(d1.norm(dim=-1), torch.ones_like(d1[..., 0]), atol=1e-12)
    assert G.reference_twist(d1, t).abs().max() < 1e-10


def test_reference_twist_measures_a_rotation_of_one_director():
    x, _ = random_rod(1, 6)
    t = G.normalize(G.edges(x))
    d1 = G.space_parallel_frame(t)
    d2 = torch.linalg.cross(t, d1, dim=-1)
    ang = 0.3
    d1r = d1.clone()
    d1r[:, 3] = math.cos(ang) * d1[:, 3] + math.sin(ang) * d2[:, 3]
    tw = G.reference_twist(d1r, t)[0]
    assert torch.allclose(tw, torch.tensor([0, 0, ang, -ang], dtype=torch.float64), atol=1e-10)
