"""Tests of diffstack.py and data_synth.py. Gradient tests run in float64."""
import math

import pytest
import torch

import diffstack as ds

DT = 0.5


def rk4_reference(s, u, dt, substeps=2000):
    """An independent integrator of the unicycle ODE, to check the exact step against."""
    def f(x):
        return torch.stack([x[..., 3] * torch.cos(x[..., 2]), x[..., 3] * torch.sin(x[..., 2]), u[..., 0], u[..., 1]], -1)
    h, x = dt / substeps, s.clone()
    for _ in range(substeps):
        k1 = f(x); k2 = f(x + h / 2 * k1); k3 = f(x + h / 2 * k2); k4 = f(x + h * k3)
        x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return x


# ---------------------------------------------------------------------------------------------
# Dynamics
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("w", [0.0, 1e-9, -0.05, 0.59, 0.61, -2.0])
def test_unicycle_matches_rk4(w):
    s = torch.tensor([[1.0, 2.0, 0.3, 5.0], [0.0, -1.0, -2.5, 0.5]], dtype=torch.float64)
    u = torch.tensor([[w, 1.0], [w, -2.0]], dtype=torch.float64)
    assert torch.allclose(ds.unicycle_step(s, u, DT), rk4_reference(s, u, DT), atol=1e-10)


def test_unicycle_gradients_finite_at_zero_yaw_rate():
    s = torch.tensor([[0.0, 0.0, 0.2, 3.0]], dtype=torch.float64, requires_grad=True)
    u = torch.zeros(1, 2, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda s, u: ds.unicycle_step(s, u, DT), (s, u))
    H = torch.autograd.functional.hessian(lambda u: ds.unicycle_step(s.detach(), u, DT)[..., 0].sum(), u.detach())
    assert torch.isfinite(H).all()
    # the series and the closed form agree on both sides of the switch, derivatives included
    for w0 in (ds._SERIES_SWITCH / DT - 1e-7, ds._SERIES_SWITCH / DT + 1e-7):
        uu = torch.tensor([[w0, 0.5]], dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradcheck(lambda u: ds.unicycle_step(s.detach(), u, DT), (uu,))


def test_unicycle_batched_and_jacobians():
    g = torch.Generator().manual_seed(0)
    s = torch.randn(3, 5, 4, generator=g, dtype=torch.float64)
    u = torch.randn(3, 5, 2, generator=g, dtype=torch.float64)
    assert ds.unicycle_step(s, u, DT).shape == (3, 5, 4)
    A, B = ds.unicycle_jacobians(s, u, DT)
    JA, JB = torch.autograd.functional.jacobian(lambda s, u: ds.unicycle_step(s, u, DT), (s[1, 2], u[1, 2]))
    assert torch.allclose(A[1, 2], JA) and torch.allclose(B[1, 2], JB)
    states = ds.unicycle_rollout(s[:, 0], u, DT)
    assert states.shape == (3, 6, 4) and torch.allclose(states[:, 1], ds.unicycle_step(s[:, 0], u[:, 0], DT))
