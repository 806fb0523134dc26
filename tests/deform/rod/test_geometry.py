import math

import torch

from deform.rod import geometry as G
from deform.rod.layout import batch_major, vertex_major
from tests.deform.rod.helpers import random_rod


def test_parallel_transport_maps_tangent_and_preserves_angles():
    gen = torch.Generator().manual_seed(1)
    a = G.normalize(torch.randn(3, 50, generator=gen, dtype=torch.float64))
    b = G.normalize(torch.randn(3, 50, generator=gen, dtype=torch.float64))
    u = torch.randn(3, 50, generator=gen, dtype=torch.float64)
    assert torch.allclose(G.parallel_transport(a, a, b), b, atol=1e-12)
    pu = G.parallel_transport(u, a, b)
    assert torch.allclose(G.norm(pu), G.norm(u), atol=1e-12)
    assert torch.allclose(G.dot(pu, b), G.dot(u, a), atol=1e-12)
    axis = G.cross(a, b)
    assert torch.allclose(G.dot(G.parallel_transport(axis, a, b), axis), G.dot(axis, axis), atol=1e-12)


def test_curvature_binormal_magnitude_is_twice_tan_half_turning_angle():
    phi = torch.tensor([0.1, 0.7, 1.5], dtype=torch.float64)
    e0 = torch.tensor([1.0, 0, 0], dtype=torch.float64)[:, None].expand(3, 3)
    e1 = torch.stack([torch.cos(phi), torch.sin(phi), torch.zeros(3, dtype=torch.float64)]) * 0.3
    kb = G.curvature_binormal(torch.stack([e0, e1]))[0]  # (3, rods)
    assert torch.allclose(G.norm(kb), 2 * torch.tan(phi / 2), atol=1e-12)
    assert torch.allclose(kb[:2], torch.zeros(2, 3, dtype=torch.float64))  # along +z


def test_space_parallel_frame_has_no_reference_twist_and_is_orthonormal():
    x, _ = random_rod(3, 12)
    t = G.normalize(G.edges(x))
    d1 = G.space_parallel_frame(t)
    assert torch.allclose(G.dot(d1, t), torch.zeros(11, 3, dtype=torch.float64), atol=1e-12)
    assert torch.allclose(G.norm(d1), torch.ones(11, 3, dtype=torch.float64), atol=1e-12)
    assert G.reference_twist(d1, t).abs().max() < 1e-10


def test_reference_twist_measures_a_rotation_of_one_director():
    x, _ = random_rod(1, 6)
    t = G.normalize(G.edges(x))
    d1 = G.space_parallel_frame(t)
    d2 = G.cross(t, d1)
    ang = 0.3
    d1r = d1.clone()
    d1r[3] = math.cos(ang) * d1[3] + math.sin(ang) * d2[3]
    tw = G.reference_twist(d1r, t)[:, 0]
    assert torch.allclose(tw, torch.tensor([0, 0, ang, -ang], dtype=torch.float64), atol=1e-10)


def test_layout_round_trip_and_batch_innermost():
    """The physics' layout: (B, n, 3) <-> (n, 3, B), the rods contiguous innermost, values unchanged."""
    x = torch.randn(5, 7, 3, dtype=torch.float64)
    vm = vertex_major(x, 2)
    assert vm.shape == (7, 3, 5) and vm.stride() == (15, 5, 1)
    assert torch.equal(vm[2, 1], x[:, 2, 1])
    assert torch.equal(batch_major(vm, (5,)), x)
    rest = torch.rand(7, dtype=torch.float64)  # one rod's values broadcast to a batch
    assert torch.equal(vertex_major(rest, 1, (5,)), rest[:, None].expand(7, 5))
