import torch

from deform.rod.tridiagonal import solve_tridiagonal_pd, thomas, to_dense


def _systems(seed: int, batch: int, k: int):
    """``batch`` diagonally dominant (positive definite) systems of ``k`` unknowns: diag, off, rhs."""
    gen = torch.Generator().manual_seed(seed)
    off = torch.randn(batch, k - 1, generator=gen, dtype=torch.float64)
    diag = 2.5 * (off.abs().max() + 1) + torch.rand(batch, k, generator=gen, dtype=torch.float64)
    return diag, off, torch.randn(batch, k, generator=gen, dtype=torch.float64)


def test_thomas_and_dense_cholesky_agree_and_detect_indefinite_systems():
    diag, off, rhs = _systems(0, 5, 30)
    x_dense, ok_dense = solve_tridiagonal_pd(diag, off, rhs)
    x_thomas, ok_thomas = thomas(diag, off, rhs)
    assert ok_dense.all() and ok_thomas.all()
    assert torch.allclose(x_dense, x_thomas, atol=1e-12)
    assert torch.allclose((to_dense(diag, off) @ x_thomas.unsqueeze(-1)).squeeze(-1), rhs, atol=1e-10)
    diag[2, 7] = -1.0
    assert not solve_tridiagonal_pd(diag, off, rhs)[1][2] and not thomas(diag, off, rhs)[1][2]
    assert solve_tridiagonal_pd(diag, off, rhs)[1][[0, 1, 3, 4]].all()


def test_unknowns_along_the_first_axis_give_the_same_solution():
    """Vertex-major arrays (the systems' batch last, dim=0) solve to the same values."""
    diag, off, rhs = _systems(1, 4, 12)
    x, ok = thomas(diag, off, rhs)
    x0, ok0 = thomas(diag.T, off.T, rhs.T, dim=0)
    assert torch.equal(x0, x.T) and torch.equal(ok0, ok)
    xd, okd = solve_tridiagonal_pd(diag.T, off.T, rhs.T, dim=0)
    assert torch.allclose(xd, x.T, atol=1e-12) and okd.all()
