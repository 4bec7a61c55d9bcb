"""Tests of diffstack.py, the method: the dynamics, the cost, the planner and the controller, the
predictor and the end-to-end gradient, each checked against an independent computation. Gradient
tests run in float64; every test runs on one thread (conftest.py).

Every other room has its test file (test_<room>.py); the shared helpers and fixtures are in
conftest.py."""

import dataclasses
import math

import pytest
import torch

import data_synth
import diffstack as ds
import train as tr
from conftest import DT, TINY, cast, make_batch, make_model, small_cfg
import copy
import pathlib
import sys
from torch.overrides import TorchFunctionMode
import experiments as ex


def rk4_reference(s, u, dt, substeps=2000):
    """An independent integrator of the unicycle ODE, to check the exact step against."""

    def f(x):
        return torch.stack(
            [
                x[..., 3] * torch.cos(x[..., 2]),
                x[..., 3] * torch.sin(x[..., 2]),
                u[..., 0],
                u[..., 1],
            ],
            -1,
        )

    h = dt / substeps
    x = s.clone()
    for _ in range(substeps):
        k1 = f(x)
        k2 = f(x + h / 2 * k1)
        k3 = f(x + h / 2 * k2)
        k4 = f(x + h * k3)
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
    H = torch.autograd.functional.hessian(
        lambda u: ds.unicycle_step(s.detach(), u, DT)[..., 0].sum(), u.detach()
    )
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
    JA, JB = torch.autograd.functional.jacobian(
        lambda s, u: ds.unicycle_step(s, u, DT), (s[1, 2], u[1, 2])
    )
    assert torch.allclose(A[1, 2], JA) and torch.allclose(B[1, 2], JB)
    states = ds.unicycle_rollout(s[:, 0], u, DT)
    assert states.shape == (3, 6, 4) and torch.allclose(
        states[:, 1], ds.unicycle_step(s[:, 0], u[:, 0], DT)
    )


@pytest.mark.parametrize("w_scale", [1e-3, 0.59, 0.61, 3.0])
def test_unicycle_curvature_matches_autodiff(w_scale):
    g = torch.Generator().manual_seed(2)
    s, u, lam = (torch.randn(10, k, generator=g, dtype=torch.float64) for k in (4, 2, 4))
    u[:, 0] *= w_scale  # both sides of the series switch
    H = ds.unicycle_curvature(s, u, lam, DT)

    def lagrangian(z, mult):
        return (mult * ds.unicycle_step(z[:4], z[4:], DT)).sum()

    expect = torch.vmap(torch.func.hessian(lagrangian))(torch.cat([s, u], -1), lam)
    assert torch.allclose(H, expect, atol=1e-12)


# ---------------------------------------------------------------------------------------------
# Cost, planner, controller on small hand-made scenes
# ---------------------------------------------------------------------------------------------


def toy_scene(B=3, K=4, A=2, L=2, P=40, dtype=torch.float64, seed=1):
    """Two parallel straight lanes along +x, a predicted agent ahead, two other agents."""
    g = torch.Generator().manual_seed(seed)
    T = 6
    lanes = torch.zeros(B, L, P, 3, dtype=dtype)
    lanes[..., 0] = torch.arange(P, dtype=dtype) * 2 - 10
    lanes[:, 1, :, 1] = 3.5
    lanes_mask = torch.ones(B, L, P, dtype=torch.bool)
    lanes_mask[0, 1, 30:] = False  # a shorter lane: the mask must be honoured
    s0 = torch.tensor([[0, 0.3, 0.05, 8.0], [0, -0.5, 0, 10.0], [0, 1, 0.1, 6.0]], dtype=dtype)[:B]
    preds = torch.randn(B, K, T, 2, generator=g, dtype=dtype) * 2 + torch.tensor(
        [12.0, 2.0], dtype=dtype
    )
    probs = torch.softmax(torch.randn(B, K, generator=g, dtype=dtype), -1)
    others = torch.randn(B, A, T, 2, generator=g, dtype=dtype) * 3 + torch.tensor(
        [20.0, -2.0], dtype=dtype
    )
    goal = torch.tensor([[24.0, 0, 0, 8], [28, 3.5, 0, 9], [18, 0, 0, 6]], dtype=dtype)[:B]
    ctx = ds.CostContext(
        preds,
        probs,
        torch.ones(B, dtype=dtype),
        others,
        torch.ones(B, A, dtype=dtype),
        goal[:, :2],
        lanes,
        lanes_mask,
    )
    return s0, goal, ctx


def stack_cost_fn(ctx):
    """The DiffStack cost as a solver callable, differentiable wrt weights, predictions, goal and
    lanes."""

    def cost_fn(x, u, w, preds, probs, goal, lanes):
        c = ds.CostContext(
            preds, probs, ctx.pred_mask, ctx.others, ctx.others_mask, goal, lanes, ctx.lanes_mask
        )
        return ds.total_cost(x, u, c, w)

    return cost_fn


def rel_err(a, b):
    return ((a - b).norm() / b.norm()).item()


def central_fd(f, x, idx, h=1e-6):
    e = torch.zeros_like(x)
    e[idx] = h
    return (f(x + e) - f(x - e)) / (2 * h)


def test_collision_mean_spread_identity():
    """The cost's collision term uses sum_k pi_k |s - s_k|^2 = |s - mu|^2 + spread: check against
    the sum."""
    s0, goal, ctx = toy_scene()
    x = ds.unicycle_rollout(s0, torch.zeros(3, 6, 2, dtype=torch.float64), DT)
    terms = ds.cost_terms(x, torch.zeros(3, 6, 2, dtype=torch.float64), ctx)
    pos = x[:, 1:, :2]
    d2 = (ctx.probs[:, :, None] * ((pos[:, None] - ctx.preds) ** 2).sum(-1)).sum(1)  # (B, T)
    others = (torch.exp(-((pos[:, None] - ctx.others) ** 2).sum(-1) / 4)).sum((1, 2))
    assert torch.allclose(terms[:, 0], torch.exp(-d2 / 4).sum(-1) + others)
    assert torch.allclose(terms[:, 1], ((pos[:, -1] - ctx.goal) ** 2).sum(-1))


def test_rbf_is_the_gaussian_kernel_down_to_its_floor():
    d2 = torch.tensor([0.0, 1.0, 50.0, 239.9, 240.1, 1e6], dtype=torch.float64)
    phi = ds.rbf(d2, 2.0)  # exp(-d2 / 4), floored at exp(-60): d2 = 240
    assert torch.equal(phi[:4], torch.exp(-d2[:4] / 4))
    assert torch.equal(phi[4:], torch.full((2,), math.exp(-60.0), dtype=torch.float64))
    assert torch.isfinite(torch.autograd.functional.jacobian(lambda d: ds.rbf(d, 2.0), d2)).all()


def test_lane_search_ranks_by_the_plain_distance():
    """nearest_lane_segment ranks lane points by one product of features; the point it picks is the
    argmin of the plain |q - p|^2 + lam (1 - cos(h_q - h_p)) over the valid points (float64, random
    lanes with padding), and the segment it returns has that point at one end."""
    g = torch.Generator().manual_seed(2)
    B, L, P, Q = 6, 4, 9, 11
    lanes = torch.randn(B, L, P, 3, generator=g, dtype=torch.float64) * torch.tensor([20, 20, 3.0])
    lanes_mask = torch.arange(P) < torch.randint(2, P + 1, (B, L, 1), generator=g)  # valid prefix
    pos = torch.randn(B, Q, 2, generator=g, dtype=torch.float64) * 20
    heading = torch.randn(B, Q, generator=g, dtype=torch.float64) * 3
    a, b, _ = ds.nearest_lane_segment(pos, heading, lanes, lanes_mask)
    pts = lanes.reshape(B, L * P, 3)
    dist2 = ((pos[:, :, None] - pts[:, None, :, :2]) ** 2).sum(-1)  # (B, Q, L*P)
    turn = 1 - torch.cos(heading[:, :, None] - pts[:, None, :, 2])
    rank = torch.where(lanes_mask.reshape(B, 1, L * P), dist2 + 50.0 * turn, math.inf)
    nearest = pts.gather(1, rank.argmin(-1)[..., None].expand(B, Q, 3))  # (B, Q, 3)
    at_an_end = (a == nearest).all(-1) | (b == nearest).all(-1)
    assert at_an_end.all()
    # a wrong ranking (the heading term left out) picks other points
    wrong = pts.gather(
        1, torch.where(rank.isinf(), math.inf, dist2).argmin(-1)[..., None].expand(B, Q, 3)
    )
    assert not ((a == wrong).all(-1) | (b == wrong).all(-1)).all()


def test_lane_projection_ignores_oncoming_lanes():
    lanes = torch.zeros(1, 2, 10, 3, dtype=torch.float64)
    lanes[..., 0] = torch.arange(10.0)
    lanes[0, 1, :, 1], lanes[0, 1, :, 2] = 1.0, math.pi  # a lane 1 m away, going the other way
    lanes[0, 1] = lanes[0, 1].flip(0)
    pos = torch.tensor([[[4.3, 0.8]]], dtype=torch.float64)
    d2, err, ok = ds.project_to_lanes(
        pos,
        torch.tensor([[0.1]], dtype=torch.float64),
        lanes,
        torch.ones(1, 2, 10, dtype=torch.bool),
    )
    assert ok.all() and torch.allclose(d2, torch.tensor([[0.64]], dtype=torch.float64))
    assert torch.allclose(err, torch.tensor([[0.1]], dtype=torch.float64))


def test_planner_splines_hit_terminal_states_and_reject_infeasible():
    cfg = ds.Config()
    s0, goal, ctx = toy_scene()
    c = ds.plan_candidates(s0, goal, ctx.lanes, ctx.lanes_mask, cfg)
    B, N = c.valid.shape
    assert c.s.shape == (B, N, 7, 4) and c.u.shape == (B, N, 6, 2)
    # on straight lanes along +x the terminal state is known in closed form
    acc = torch.tensor(cfg.plan_accels, dtype=torch.float64)
    v_f = (s0[:, 3:4] + acc * 3.0).clamp_min(0)  # (B, 8)
    dist = (s0[:, 3:4] + v_f) / 2 * 3.0
    lane0 = c.s[:, :24].reshape(B, 8, 3, 7, 4)  # first goal lane: the closest to the goal
    lane_y = torch.tensor([0.0, 3.5, 0.0], dtype=torch.float64)[:B]
    assert torch.allclose(
        lane0[..., -1, 0], (s0[:, 0:1] + dist)[..., None].expand(B, 8, 3), atol=1e-9
    )
    off = torch.tensor(cfg.plan_offsets, dtype=torch.float64)
    assert torch.allclose(
        lane0[..., -1, 1], (lane_y[:, None, None] + off).expand(B, 8, 3), atol=1e-9
    )
    assert torch.allclose(lane0[..., -1, 3], v_f[..., None].expand(B, 8, 3), atol=1e-9)
    assert torch.allclose(c.s[:, :, 0], s0[:, None].expand(B, N, 4))
    # every valid candidate respects the feasibility limits; hard stops from 10 m/s violate them
    lo, hi = (
        torch.tensor(cfg.u_lower, dtype=torch.float64),
        torch.tensor(cfg.u_upper, dtype=torch.float64),
    )
    ok_box = ((c.u >= lo) & (c.u <= hi)).all(-1).all(-1)
    assert (ok_box | ~c.valid).all() and not c.valid.all()
    # a sharp turn at speed is infeasible
    s_fast = s0.clone()
    s_fast[:, 3] = 25.0
    lanes = ctx.lanes.clone()
    lanes[..., 1] = 0.05 * lanes[..., 0] ** 2
    lanes[..., 2] = torch.atan(0.1 * lanes[..., 0])
    far = ds.plan_candidates(s_fast, goal, lanes, ctx.lanes_mask, cfg)
    assert far.valid.sum() < c.valid.sum()


def test_planner_takes_any_number_of_accelerations_and_offsets():
    """A Config with 3 accelerations and 1 offset (e.g. --set plan_accels=-1,0,1 --set
    plan_offsets=0) gives exactly the default planner's candidates for those terminal states."""
    s0, goal, ctx = toy_scene()
    full_cfg = ds.Config()
    small_cfg = ds.Config(plan_accels=(-1.0, 0.0, 1.0), plan_offsets=(0.0,))
    full = ds.plan_candidates(s0, goal, ctx.lanes, ctx.lanes_mask, full_cfg)
    small = ds.plan_candidates(s0, goal, ctx.lanes, ctx.lanes_mask, small_cfg)
    G = full.s.shape[1] // 24
    assert small.s.shape[1] == G * 3
    # accel -1, 0, 1; offset 0
    pick = full.s.reshape(3, G, 8, 3, 7, 4)[:, :, [2, 4, 6], 1].reshape(3, G * 3, 7, 4)
    assert torch.allclose(small.s, pick)
    assert torch.equal(
        small.valid, full.valid.reshape(3, G, 8, 3)[:, :, [2, 4, 6], 1].reshape(3, G * 3)
    )


def test_plan_is_argmin_and_flags_unplannable():
    cfg = ds.Config()
    s0, goal, ctx = toy_scene()
    w = ds.cost_weights(cfg, torch.float64)
    cands, cost, idx, ok, _ = ds.plan(s0, ctx, goal, w, cfg)
    assert ok.all()
    for b in range(3):  # the reference: a plain Python minimum over the valid candidates
        best = min((cost[b, n].item(), n) for n in range(cost.shape[1]) if cands.valid[b, n])
        assert idx[b].item() == best[1]
    ctx.lanes_mask[1] = False  # no lanes: no candidates, flagged, no crash
    ok = ds.plan(s0, ctx, goal, w, cfg).plannable
    assert ok.tolist() == [True, False, True]


def test_relaxed_planner_gradients():
    cfg = ds.Config()
    s0, goal, ctx = toy_scene()
    cands = ds.plan_candidates(s0, goal, ctx.lanes, ctx.lanes_mask, cfg)
    target = ds.masked_argmin(
        torch.arange(cands.valid.shape[1], dtype=torch.float64).expand_as(cands.valid), cands.valid
    )
    preds = ctx.preds.clone().requires_grad_()
    w = ds.cost_weights(cfg, torch.float64).requires_grad_()

    def loss(preds, w):
        c = ds.CostContext(
            preds,
            ctx.probs,
            ctx.pred_mask,
            ctx.others,
            ctx.others_mask,
            ctx.goal,
            ctx.lanes,
            ctx.lanes_mask,
        )
        return ds.plan_loss(
            ds.total_cost(cands.s, cands.u, c, w), cands.valid, target, cfg.beta
        ).sum()

    assert torch.autograd.gradcheck(loss, (preds, w))
    # p_n = softmax(-beta C_n): the loss is -log p of the target
    cost = torch.tensor([[1.0, 2.0, 0.5]], dtype=torch.float64)
    valid = torch.tensor([[True, True, False]])
    expect = -math.log(math.exp(-2.0) / (math.exp(-1.0) + math.exp(-2.0)))
    assert ds.plan_loss(cost, valid, torch.tensor([1]), 1.0).item() == pytest.approx(expect)


def linear_quadratic_problem(B=4, T=6, seed=0):
    g = torch.Generator().manual_seed(seed)
    A = torch.eye(4, dtype=torch.float64) + 0.1 * torch.randn(
        4, 4, generator=g, dtype=torch.float64
    )
    Bm = torch.randn(4, 2, generator=g, dtype=torch.float64)

    def dyn(x, u):
        return (A @ x[..., None])[..., 0] + (Bm @ u[..., None])[..., 0]

    Q = torch.randn(B, T + 1, 6, 6, generator=g, dtype=torch.float64)
    Q = Q @ Q.transpose(-1, -2) / 6 + 0.5 * torch.eye(6, dtype=torch.float64)
    q = torch.randn(B, T + 1, 6, generator=g, dtype=torch.float64) * 3

    def cost(x, u, Q, q):  # sum_t 1/2 z_t'Q_t z_t + q_t'z_t, z_t = (x_t, u_t); *S dims broadcast
        z = torch.cat([x, torch.cat([u, torch.zeros_like(u[..., :1, :])], -2)], -1)
        S = x.dim() - 3
        Qv, qv = Q.reshape(B, *[1] * S, *Q.shape[1:]), q.reshape(B, *[1] * S, *q.shape[1:])
        return (0.5 * (z[..., None, :] @ Qv @ z[..., None])[..., 0, 0] + (qv * z).sum(-1)).sum(-1)

    x0 = torch.randn(B, 4, generator=g, dtype=torch.float64)
    lo, hi = (
        torch.tensor([-0.5, -1.0], dtype=torch.float64),
        torch.tensor([0.5, 1.0], dtype=torch.float64),
    )
    return dyn, cost, x0, Q, q, lo, hi


def test_kkt_gradients_linear_dynamics_with_active_bounds():
    dyn, cost, x0, Q, q, lo, hi = linear_quadratic_problem()
    B, T = x0.shape[0], 6
    g = torch.Generator().manual_seed(5)
    wx, wu = (
        torch.randn(B, T + 1, 4, generator=g, dtype=torch.float64),
        torch.randn(B, T, 2, generator=g, dtype=torch.float64),
    )
    u0 = torch.zeros(B, T, 2, dtype=torch.float64)
    x0r, qr, Qr = (
        x0.clone().requires_grad_(),
        q.clone().requires_grad_(),
        Q.clone().requires_grad_(),
    )
    x, u_star, conv = ds.ilqr_solve(cost, dyn, x0r, u0, (Qr, qr), lo, hi, iters=20, tol=1e-10)
    assert conv.all()
    n_active = ((u_star - lo).abs() < 1e-8).sum() + ((hi - u_star).abs() < 1e-8).sum()
    assert n_active >= 5  # the check covers active bounds
    ((x * wx).sum() + (u_star * wu).sum()).backward()

    # re-solved from the solution: a few iterations reach the perturbed optimum
    def loss(x0_, Q_, q_):
        x, u, _ = ds.ilqr(cost, dyn, x0_, u_star.detach(), (Q_, q_), lo, hi, iters=30, tol=1e-13)
        return (x * wx).sum() + (u * wu).sum()

    idx_x = [(b, i) for b in range(B) for i in range(4)]
    fd = torch.stack([central_fd(lambda v: loss(v, Q, q), x0, i) for i in idx_x])
    assert rel_err(torch.stack([x0r.grad[i] for i in idx_x]), fd) < 1e-6
    idx_q = [(b, t, i) for b in range(B) for t, i in ((0, 4), (3, 1), (6, 2))]
    fd = torch.stack([central_fd(lambda v: loss(x0, Q, v), q, i) for i in idx_q])
    assert rel_err(torch.stack([qr.grad[i] for i in idx_q]), fd) < 1e-6
    idx_Q = [(1, 2, 0, 4), (2, 5, 3, 3), (0, 1, 5, 1)]
    fd = torch.stack([central_fd(lambda v: loss(x0, v, q), Q, i) for i in idx_Q])
    assert rel_err(torch.stack([Qr.grad[i] for i in idx_Q]), fd) < 1e-6


@pytest.fixture(scope="module")
def unicycle_problem():
    cfg = ds.Config()
    s0, goal, ctx = toy_scene()
    w = ds.cost_weights(cfg, torch.float64)
    lo, hi = (
        torch.tensor(cfg.u_lower, dtype=torch.float64),
        torch.tensor(cfg.u_upper, dtype=torch.float64),
    )
    cost_fn = stack_cost_fn(ctx)
    params = (w, ctx.preds, ctx.probs, ctx.goal, ctx.lanes)
    x, u, info = ds.ilqr(
        cost_fn,
        ds.Unicycle(DT),
        s0,
        torch.zeros(3, 6, 2, dtype=torch.float64),
        params,
        lo,
        hi,
        iters=50,
        tol=1e-11,
    )
    assert info.converged.all()
    g = torch.Generator().manual_seed(3)
    wx, wu = (
        torch.randn(3, 7, 4, generator=g, dtype=torch.float64),
        torch.randn(3, 6, 2, generator=g, dtype=torch.float64),
    )
    return dict(cost_fn=cost_fn, s0=s0, u=u, params=params, lo=lo, hi=hi, wx=wx, wu=wu)


def _kkt_grads(P, exact=True):
    leaves = [P["s0"].clone().requires_grad_()] + [p.clone().requires_grad_() for p in P["params"]]
    x, u, _ = ds.ilqr_solve(
        P["cost_fn"],
        ds.Unicycle(DT),
        leaves[0],
        P["u"],
        tuple(leaves[1:]),
        P["lo"],
        P["hi"],
        iters=30,
        tol=1e-11,
        exact=exact,
    )
    return torch.autograd.grad((x * P["wx"]).sum() + (u * P["wu"]).sum(), leaves)


def test_kkt_gradients_unicycle_full_cost_match_finite_differences(unicycle_problem):
    P = unicycle_problem
    exact, gauss_newton = _kkt_grads(P), _kkt_grads(P, exact=False)

    def loss(i, v):
        leaves = [P["s0"], *P["params"]]
        leaves[i] = v
        x, u, info = ds.ilqr(
            P["cost_fn"],
            ds.Unicycle(DT),
            leaves[0],
            P["u"],
            tuple(leaves[1:]),
            P["lo"],
            P["hi"],
            iters=50,
            tol=1e-11,
        )
        assert info.converged.all()
        return (x * P["wx"]).sum() + (u * P["wu"]).sum()

    # x_init, weights, predictions, goal, lanes
    for i, idx in [
        (0, [(b, j) for b in range(3) for j in range(4)]),
        (1, [(j,) for j in range(5)]),
        (2, [(b, k, t, b % 2) for b in range(3) for k, t in ((0, 1), (2, 4))]),
        (4, [(b, j) for b in range(3) for j in range(2)]),
        (5, [(b, 0, 8, 1) for b in range(3)]),
    ]:
        base = ([P["s0"], *P["params"]])[i]
        # h: above the solver's tolerance
        fd = torch.stack([central_fd(lambda v: loss(i, v), base, j, h=1e-4) for j in idx])
        assert rel_err(torch.stack([exact[i][j] for j in idx]), fd) < 1e-4, i
        if i in (0, 2):  # without the dynamics' curvature the gradient is measurably wrong
            assert rel_err(torch.stack([gauss_newton[i][j] for j in idx]), fd) > 1e-3


def test_kkt_backward_default_and_papers_variant_against_central_differences():
    """The controller's section states it: the default backward (exact=True, the Lagrangian's
    Hessian) is the derivative of the converged solution, within 1e-6 of central differences on a
    unicycle tracking a circle too tight for the yaw-rate bound (most controls at a bound); the
    paper's variant (exact=False, "the KKT conditions of the last LQR approximation") is printed
    beside it, and larger."""
    d, T = dict(dtype=torch.float64), 6
    s0 = torch.tensor([[0.0, 0.0, 0.0, 8.0], [0.0, 0.0, 0.3, 6.0]], **d)
    angle = torch.arange(1, T + 1, **d) * DT * 8 / 6  # radius 6 m at 8 m/s: 1.3 rad/s > 0.7
    circle = torch.stack([6 * torch.sin(angle), 6 * (1 - torch.cos(angle))], -1)  # (T, 2)
    ref = torch.stack([circle, 0.8 * circle])  # (2, T, 2)
    lo, hi = torch.tensor([-0.7, -5.0], **d), torch.tensor([0.7, 4.0], **d)
    g = torch.Generator().manual_seed(0)
    wx, wu = torch.randn(2, T + 1, 4, generator=g, **d), torch.randn(2, T, 2, generator=g, **d)
    u0, kw = torch.zeros(2, T, 2, **d), dict(iters=200, tol=1e-13)

    def cost_fn(x, u, ref):  # tracking: sum_t |p_t - ref_t|^2 + 0.1 |u_t|^2
        return ((x[..., 1:, :2] - ref) ** 2).sum((-1, -2)) + 0.1 * (u**2).sum((-1, -2))

    def loss(s, r):  # a random linear functional of the converged solution
        x, u, info = ds.ilqr(cost_fn, ds.Unicycle(DT), s, u0, (r,), lo, hi, **kw)
        assert info.converged.all()
        return (x * wx).sum() + (u * wu).sum()

    def kkt(exact):
        s, r = s0.clone().requires_grad_(), ref.clone().requires_grad_()
        x, u, conv = ds.ilqr_solve(cost_fn, ds.Unicycle(DT), s, u0, (r,), lo, hi, exact, **kw)
        assert conv.all() and ((u == lo) | (u == hi)).sum() >= 10  # bounds active
        return torch.autograd.grad((x * wx).sum() + (u * wu).sum(), (s, r))

    idx_s = [(b, j) for b in range(2) for j in range(4)]
    idx_r = [(0, 1, 0), (0, 4, 1), (1, 2, 1), (1, 5, 0)]
    fd_s = torch.stack([central_fd(lambda v: loss(v, ref), s0, i) for i in idx_s])
    fd_r = torch.stack([central_fd(lambda v: loss(s0, v), ref, i) for i in idx_r])
    errors = {}
    for exact in (True, False):
        grad_s, grad_r = kkt(exact)
        errors[exact] = max(
            rel_err(torch.stack([grad_s[i] for i in idx_s]), fd_s),
            rel_err(torch.stack([grad_r[i] for i in idx_r]), fd_r),
        )
    print(
        f"KKT backward vs central differences: default {errors[True]:.1e}, paper's variant "
        f"{errors[False]:.1e}"
    )
    assert errors[True] < 1e-6 and errors[False] > 100 * errors[True]


def test_kkt_gradients_match_autograd_through_unrolled_solver(unicycle_problem):
    P = unicycle_problem
    kkt = _kkt_grads(P)
    leaves = [P["s0"].clone().requires_grad_()] + [p.clone().requires_grad_() for p in P["params"]]
    # tol 0: every iteration is differentiated through
    x, u, _ = ds.ilqr(
        P["cost_fn"],
        ds.Unicycle(DT),
        leaves[0],
        torch.zeros_like(P["u"]),
        tuple(leaves[1:]),
        P["lo"],
        P["hi"],
        iters=20,
        tol=0.0,
    )
    unrolled = torch.autograd.grad(
        (x * P["wx"]).sum() + (u * P["wu"]).sum(), leaves, allow_unused=True
    )
    for a, b in zip(unrolled, kkt):
        if b.abs().sum() > 0:
            assert rel_err(a, b) < 1e-8


def test_closed_form_cost_expansion_matches_autodiff(small):
    """StackCost.expansion (the closed form the controller uses) equals forward-over-reverse
    autodiff of the same cost, on synthetic scenes with states on lanes, past a lane's end
    (clamped projection) and with no lane."""
    cfg = ds.Config()
    b = cast(small.train[:64], torch.float64)
    b = dataclasses.replace(b, lanes_mask=b.lanes_mask.clone())
    b.lanes_mask[:3] = False  # three scenarios without lanes
    B = len(b)
    g = torch.Generator().manual_seed(0)
    preds = b.agent_fut[:, None, :, :2] + torch.randn(B, 3, 6, 2, generator=g, dtype=torch.float64)
    probs = torch.softmax(torch.randn(B, 3, generator=g, dtype=torch.float64), -1)
    # some without a prediction
    ctx, _ = ds.cost_contexts(b, preds, probs, (torch.arange(B) % 3 > 0).to(torch.float64))
    u = torch.randn(B, 6, 2, generator=g, dtype=torch.float64) * torch.tensor(
        [0.6, 2.0], dtype=torch.float64
    )
    x = ds.unicycle_rollout(b.ego_hist[:, -1], u, cfg.dt)
    # per-scenario weights
    w = ds.cost_weights(cfg, torch.float64) * torch.rand(B, 5, generator=g, dtype=torch.float64)
    params = (w, *ctx.tensors())
    cost = ds.StackCost(cfg.rbf_var)
    g1, H1 = ds.cost_expansion(cost, x, u, params)  # closed form
    # a plain function: autodiff
    g2, H2 = ds.cost_expansion(lambda x, u, *p: cost(x, u, *p), x, u, params)
    assert rel_err(g1, g2) < 1e-12 and rel_err(H1, H2) < 1e-12
    # the check covers every case of the lane projection
    a, bb, has_lane = ds.nearest_lane_segment(x[:, 1:, :2], x[:, 1:, 2], ctx.lanes, ctx.lanes_mask)
    frac = ds.segment_projection(x[:, 1:, :2], a, bb)[0]
    assert (~has_lane).sum() >= 5 and (has_lane & ((frac == 0) | (frac == 1))).sum() >= 3
    assert (has_lane & (frac > 0) & (frac < 1)).sum() >= 100


def test_controller_with_the_closed_form_cost_gives_the_autodiff_gradients(unicycle_problem):
    """The KKT gradients through StackCost (closed-form expansion, per-scenario parameters,
    converged scenarios set aside) equal those through the same cost expanded by autodiff, whose
    gradients the test above checks against finite differences."""
    P = unicycle_problem
    s0, goal, ctx = toy_scene()
    cost = ds.StackCost(2.0)
    B = len(s0)
    base = (P["params"][0].expand(B, 5), *ctx.tensors())
    grads = []
    for fn in (cost, lambda x, u, *p: cost(x, u, *p)):
        leaves = [
            s0.clone().requires_grad_(),
            *[p.clone().requires_grad_() if p.is_floating_point() else p for p in base],
        ]
        x, u, _ = ds.ilqr_solve(
            fn,
            ds.Unicycle(DT),
            leaves[0],
            torch.zeros(B, 6, 2, dtype=torch.float64),
            tuple(leaves[1:]),
            P["lo"],
            P["hi"],
            iters=30,
            tol=1e-11,
        )
        loss = (x * P["wx"]).sum() + (u * P["wu"]).sum()
        # x0, w, preds, probs, lanes
        grads.append(torch.autograd.grad(loss, [leaves[i] for i in (0, 1, 2, 3, 7)]))
    for a, b in zip(*grads):
        assert a.abs().sum() > 0 and rel_err(a, b) < 1e-10


@pytest.mark.parametrize("all_free", [True, False])
def test_riccati_recursion_solves_the_lqr_exactly(all_free):
    """lqr_backward (the Q-function form, active set held) against the LQR solved as one dense
    problem: the controls as the only unknowns (the states rolled out from them), the optimum by one
    Newton step on that quadratic. Its policy du_t = k_t + K_t dx_t rolled out from a random dx_0
    gives the optimal controls, and p_0 is dV/d dx_0 at 0. all_free False: some controls are held at
    0 (the KKT backward's clamped controls); the dense problem then optimises the others only."""
    g = torch.Generator().manual_seed(4)
    Bsz, T, n, m = 3, 4, 4, 2
    R = torch.randn(Bsz, T + 1, n + m, n + m, generator=g, dtype=torch.float64)
    H = R @ R.transpose(-1, -2) / (n + m) + 0.3 * torch.eye(n + m, dtype=torch.float64)
    H[:, T, n:], H[:, T, :, n:] = 0.0, 0.0  # the last step has no control
    gv = torch.randn(Bsz, T + 1, n + m, generator=g, dtype=torch.float64)
    gv[:, T, n:] = 0.0
    A = torch.eye(n, dtype=torch.float64) + 0.3 * torch.randn(
        Bsz, T, n, n, generator=g, dtype=torch.float64
    )
    Bm = torch.randn(Bsz, T, n, m, generator=g, dtype=torch.float64)
    held = torch.zeros(Bsz, T, m, dtype=torch.bool)
    if not all_free:
        held[0, 1, 0] = held[1, 0, :] = held[2, 3, 1] = True
    k, K, free, p0 = ds.lqr_backward(A, Bm, H, gv, free=~held)
    assert torch.equal(free, ~held)

    def cost(du, dx0, b):  # du (T, m): the LQR's cost of the controls du from dx0, scenario b
        dx = dx0
        total = 0.0
        for t in range(T):
            z = torch.cat([dx, du[t]])
            total = total + 0.5 * z @ H[b, t] @ z + gv[b, t] @ z
            dx = A[b, t] @ dx + Bm[b, t] @ du[t]
        return total + 0.5 * dx @ H[b, T, :n, :n] @ dx + gv[b, T, :n] @ dx

    dx0 = torch.randn(Bsz, n, generator=g, dtype=torch.float64)
    for b in range(Bsz):
        du0 = torch.zeros(T, m, dtype=torch.float64)
        for start in (dx0[b], torch.zeros(n, dtype=torch.float64)):
            Hd = torch.autograd.functional.hessian(lambda du: cost(du, start, b), du0).reshape(
                T * m, T * m
            )
            gd = torch.autograd.functional.jacobian(lambda du: cost(du, start, b), du0).reshape(
                T * m
            )
            # the exact optimum over the free controls (cost is quadratic in du)
            f = ~held[b].reshape(-1)
            best = torch.zeros(T * m, dtype=torch.float64)
            best[f] = -torch.linalg.solve(Hd[f][:, f], gd[f])
            best = best.reshape(T, m)
            dx = start
            policy = []
            for t in range(T):
                policy.append(k[b, t] + K[b, t] @ dx)
                dx = A[b, t] @ dx + Bm[b, t] @ policy[-1]
            assert rel_err(torch.stack(policy), best) < 1e-10
        # V(dx0) = cost(du*(dx0), dx0): by the envelope theorem dV/d dx0 = d cost / d dx0 at du*(0)
        grad = torch.autograd.functional.jacobian(
            lambda x: cost(best, x, b), torch.zeros(n, dtype=torch.float64)
        )
        assert rel_err(p0[b], grad) < 1e-10


def test_solve_masked_keeps_the_fixed_rows_and_solves_the_free_ones():
    g = torch.Generator().manual_seed(0)
    L = torch.randn(500, 2, 2, generator=g, dtype=torch.float64)
    Q = L @ L.transpose(-1, -2) + 0.1 * torch.eye(2, dtype=torch.float64)
    rhs = torch.randn(500, 2, 4, generator=g, dtype=torch.float64)
    free = torch.rand(500, 2, generator=g) > 0.3
    y = ds.solve_masked(Q, rhs, free)
    assert rel_err(y[~free], rhs[~free]) < 1e-14  # fixed rows keep the right-hand side
    both = free.all(-1)
    assert rel_err(y[both], torch.linalg.solve(Q[both], rhs[both])) < 1e-10
    # control 0 free, 1 fixed: Q_00 y_0 = rhs_0 (the caller moved Q_01 d_1 over)
    one = free[:, 0] & ~free[:, 1]
    assert rel_err(y[one, 0], rhs[one, 0] / Q[one, 0, 0, None]) < 1e-10


def test_solve_small_is_the_linear_solve():
    """Cramer's rule for 2x2 (non-symmetric, so a transpose shows) and the general solve beyond, in
    float64."""
    g = torch.Generator().manual_seed(1)
    for m in (2, 3):
        M = torch.randn(300, m, m, generator=g, dtype=torch.float64) + 3 * torch.eye(
            m, dtype=torch.float64
        )
        rhs = torch.randn(300, m, 5, generator=g, dtype=torch.float64)
        assert rel_err(ds.solve_small(M, rhs), torch.linalg.solve(M, rhs)) < 1e-12
        assert rel_err(M @ ds.solve_small(M, rhs), rhs) < 1e-12


def test_ilqr_solves_each_scenario_of_a_batch_as_if_alone():
    """The batched iteration (a converged scenario stops moving through a mask; the line search's
    smaller scales taken where the full step failed) gives each scenario what solving it alone
    gives, on a problem where both happen: some scenarios converge early and some reject full
    steps."""
    cfg = ds.Config()
    s0, goal, ctx = toy_scene()
    lo, hi = (
        torch.tensor(cfg.u_lower, dtype=torch.float64),
        torch.tensor(cfg.u_upper, dtype=torch.float64),
    )
    cost = ds.StackCost(2.0)
    # collisions matter
    w = ds.cost_weights(cfg, torch.float64) * torch.tensor([10.0, 1, 1, 1, 1], dtype=torch.float64)
    params = (w.expand(3, 5), *ctx.tensors())
    # a hard left at full throttle
    u0 = torch.tensor([0.7, 4.0], dtype=torch.float64).expand(3, 6, 2)
    calls = []

    # counts the cost's evaluations: 1 at the start, then 1 per scale tried
    def recording(x, u, *p):
        calls.append(len(x))
        return cost(x, u, *p)

    recording.expansion = cost.expansion
    xa, ua, ia = ds.ilqr(recording, ds.Unicycle(DT), s0, u0, params, lo, hi, iters=8, tol=1e-3)
    for b in range(3):
        alone = tuple(p[b : b + 1] for p in params)
        xb, ub, ib = ds.ilqr(
            cost, ds.Unicycle(DT), s0[b : b + 1], u0[b : b + 1], alone, lo, hi, iters=8, tol=1e-3
        )
        assert torch.allclose(xa[b], xb[0], rtol=0, atol=1e-12) and torch.allclose(
            ua[b], ub[0], rtol=0, atol=1e-12
        )
        assert ia.iters[b] == ib.iters[0] and ia.converged[b] == ib.converged[0]
    assert ia.iters.min() < ia.iters.max()  # some scenarios stopped early
    assert len(calls) > 1 + ia.iters.max()  # and some iteration tried a smaller step scale


# bounds active in many problems; in none (the shortcut)
@pytest.mark.parametrize("bound", [0.2, 100.0])
def test_box_qp_meets_the_kkt_conditions(bound):
    """box_qp's answer is the optimum of the convex box QP: feasible, zero gradient on the free
    controls, the gradient pushing outwards on the clamped ones (the KKT conditions, which only the
    optimum meets)."""
    g = torch.Generator().manual_seed(1)
    L = torch.randn(400, 2, 2, generator=g, dtype=torch.float64)
    Q = L @ L.transpose(-1, -2) + 0.1 * torch.eye(2, dtype=torch.float64)
    q = torch.randn(400, 2, generator=g, dtype=torch.float64)
    lo, hi = (
        s * bound * (1 + torch.rand(400, 2, generator=g, dtype=torch.float64)) for s in (-1, 1)
    )
    d, free = ds.box_qp(Q, q, lo, hi)
    grad = (Q @ d[..., None])[..., 0] + q
    at_lo, at_hi = ~free & ((d - lo).abs() < 1e-12), ~free & ((d - hi).abs() < 1e-12)
    assert ((d >= lo - 1e-12) & (d <= hi + 1e-12)).all()
    assert (free | at_lo | at_hi).all()  # a control is free or at one of its bounds
    assert grad[free].abs().max() < 1e-10
    assert (grad[at_lo] >= -1e-10).all() and (grad[at_hi] <= 1e-10).all()
    assert (~free).any() == (bound < 1)  # the test covers both paths


def test_ilqr_descends_respects_bounds_and_flags_convergence():
    cfg = ds.Config()
    s0, goal, ctx = toy_scene()
    lo, hi = (
        torch.tensor(cfg.u_lower, dtype=torch.float64),
        torch.tensor(cfg.u_upper, dtype=torch.float64),
    )
    params = (ds.cost_weights(cfg, torch.float64), ctx.preds, ctx.probs, ctx.goal, ctx.lanes)
    u0 = torch.full((3, 6, 2), 3.0, dtype=torch.float64)  # far outside the box: clamped first
    for iters, tol in ((5, 0.05), (2, 0.05), (5, 1e-9)):
        x, u, info = ds.ilqr(
            stack_cost_fn(ctx), ds.Unicycle(DT), s0, u0, params, lo, hi, iters=iters, tol=tol
        )
        c = info.costs
        assert (c[:, 1:] <= c[:, :-1] * (1 + 1e-12) + 1e-12).all()  # the true cost never increases
        assert ((u >= lo) & (u <= hi)).all()
        assert torch.equal(info.converged, info.step_norm < tol)
        # the solution is dynamically consistent
        assert torch.allclose(x, ds.unicycle_rollout(s0, u, DT))
    assert not info.converged.all() or info.iters.max() <= 5


def test_unconverged_scenarios_get_no_gradient():
    dyn, cost, x0, Q, q, lo, hi = linear_quadratic_problem()
    qr = q.clone().requires_grad_()
    x, u, conv = ds.ilqr_solve(
        cost,
        dyn,
        x0,
        torch.zeros(4, 6, 2, dtype=torch.float64),
        (Q, qr),
        lo,
        hi,
        iters=1,
        tol=1e-12,
        refine=0,  # iLQR alone: one iteration does not converge
    )
    assert not conv.any()
    x.sum().backward()
    assert (qr.grad == 0).all()


# ---------------------------------------------------------------------------------------------
# Predictor
# ---------------------------------------------------------------------------------------------


# ---------------------------------------------------------------------------------------------
# Inputs
# ---------------------------------------------------------------------------------------------


def test_backward_differences_and_mask_prefix():
    t = torch.arange(9, dtype=torch.float64)
    x = torch.stack([2.0 * t, 0.5 * t**2], -1)[None]  # (1, 9, 2): v = (2, t - 1/4 ...) backward
    first = torch.tensor([0])
    v = ds.backward_diff(x, first, 1.0)
    assert torch.allclose(v[0, 1:, 0], torch.full((8,), 2.0, dtype=torch.float64))
    assert torch.allclose(v[0, 1:, 1], 0.5 * (t[1:] ** 2 - t[:-1] ** 2))  # backward, not central
    assert torch.allclose(v[0, 0], v[0, 1])  # no predecessor: copies the first difference
    # a history observed from step 3 on: steps <= 3 take the difference at 4; the masked values
    # never matter
    x2 = x.clone()
    x2[0, :3] = 1e3
    v2 = ds.backward_diff(x2, torch.tensor([3]), 1.0)
    assert torch.allclose(v2[0, :4], v[0, 4].expand(4, 2)) and torch.allclose(v2[0, 4:], v[0, 4:])


def test_state_features_values():
    cfg = ds.Config()
    b = make_batch(4)
    f = ds.state_features(
        b.agent_hist, b.agent_hist[:, -1, :2], torch.zeros(4, dtype=torch.long), cfg
    )
    assert f.shape == (4, 9, 8)
    # relative to the current position
    assert torch.allclose(f[:, -1, :2], torch.zeros(4, 2, dtype=torch.float64))
    vel = (b.agent_hist[:, -1, :2] - b.agent_hist[:, -2, :2]) / DT
    assert torch.allclose(f[:, -1, 2:4] * 15.0, vel)
    assert torch.allclose(f[:, -1, 6] * math.pi, ds.wrap_angle(b.agent_hist[:, -1, 2]))


# ---------------------------------------------------------------------------------------------
# The model: shapes, masks, no leakage, determinism in eval
# ---------------------------------------------------------------------------------------------


def test_shapes_and_probabilities():
    cfg = ds.Config(pred_dec_hidden=16)  # K = 25
    model = make_model(cfg)
    b = make_batch(8)
    for use_post in (True, False):
        p = model(b, use_posterior=use_post, step=0 if use_post else None)
        assert p.states.shape == (8, 25, 6, 4) and p.controls.shape == (8, 25, 6, 2)
        assert (
            p.means.shape == (8, 25, 6, 2)
            and p.pos_cov.shape == (8, 25, 6, 2, 2)
            and p.s0.shape == (8, 4)
        )
        assert p.probs.shape == (8, 25) and torch.allclose(
            p.probs.sum(-1), torch.ones(8, dtype=torch.float64)
        )
        assert (p.log_q is not None) == use_post
        assert torch.allclose(p.probs, (p.log_q if use_post else p.log_p).exp())
        assert torch.linalg.eigvalsh(p.pos_cov).min() > 0  # proper covariances
    # logit clipping: at step 0 the logits lie within +-c(0) ~ 0.083, at step 1000 within +-5
    p = model(b, use_posterior=True, step=0)
    c0 = 0.05 + 4.95 / (1 + math.exp(5))
    for lg in (p.log_p, p.log_q):
        spread = lg.max(-1).values - lg.min(-1).values
        assert (spread <= 2 * c0 + 1e-9).all() and (spread > c0).any()


def test_masks_padding_radius_and_history_mask():
    cfg = small_cfg()
    model = make_model(cfg).eval()
    b = make_batch(8)
    ref = model(b, use_posterior=False)
    # padded agents' values do not matter
    oh = b.others_hist.clone()
    oh[~b.others_mask] = 7.0
    assert torch.allclose(model(b.replace(others_hist=oh), use_posterior=False).states, ref.states)
    # neither do agents beyond 30 m (moved from 31 to 100 m away)
    far = b.agent_hist[:, -1:, None, :2] + torch.tensor([31.0, 0.0], dtype=torch.float64)
    b_far = b.replace(
        others_hist=torch.cat([b.others_hist[..., :2] * 0 + far, b.others_hist[..., 2:]], -1)
    )
    b_farther = b.replace(
        others_hist=torch.cat([b.others_hist[..., :2] * 0 + far + 69.0, b.others_hist[..., 2:]], -1)
    )
    assert torch.allclose(
        model(b_far, use_posterior=False).states, model(b_farther, use_posterior=False).states
    )
    # but a near agent does change the prediction (the test above could not pass by ignoring
    # everyone)
    near = b.agent_hist[:, -1:, None, :2] + torch.tensor([5.0, 0.0], dtype=torch.float64)
    b_near = b.replace(
        others_hist=torch.cat([b.others_hist[..., :2] * 0 + near, b.others_hist[..., 2:]], -1),
        others_mask=torch.ones_like(b.others_mask),
    )
    assert not torch.allclose(model(b_near, use_posterior=False).states, ref.states)
    # agent_hist_mask: unobserved early steps (filled with the earliest observed state) do not
    # matter
    m = b.agent_hist_mask.clone()
    m[:4, :3] = False
    h1, h2 = b.agent_hist.clone(), b.agent_hist.clone()
    h1[:4, :3] = b.agent_hist[:4, 3:4]
    h2[:4, :3] = 50.0
    p1 = model(b.replace(agent_hist=h1, agent_hist_mask=m), use_posterior=False)
    p2 = model(b.replace(agent_hist=h2, agent_hist_mask=m), use_posterior=False)
    assert torch.allclose(p1.states, p2.states) and torch.allclose(p1.probs, p2.probs)
    assert not torch.allclose(p1.states[:4], ref.states[:4])  # the mask is used


def test_no_neighbours_no_nan():
    cfg = small_cfg()
    model = make_model(cfg)
    b = make_batch(8)
    ego_far = b.ego_hist.clone()
    ego_far[..., 1] += 500.0  # the ego is a neighbour too: move it out of range
    b0 = b.replace(others_mask=torch.zeros_like(b.others_mask), ego_hist=ego_far)
    x, _ = model.encode(b0)
    # zero context
    assert torch.equal(x[:, cfg.pred_enc_hidden :], torch.zeros_like(x[:, cfg.pred_enc_hidden :]))
    p = model(b0, use_posterior=True, step=0)
    loss, _ = ds.pred_loss(p, b0, 0, cfg)
    loss.mean().backward()
    assert torch.isfinite(loss).all()
    assert all(torch.isfinite(q.grad).all() for q in model.parameters() if q.grad is not None)


def _drive_rho_to_the_edge(model, pre_tanh):
    """Every step's rho output (dec_out's last row) set to the constant pre_tanh, whatever the
    hidden state."""
    with torch.no_grad():
        model.dec_out.weight[4].zero_()
        model.dec_out.bias[4] = pre_tanh


def _training_step_is_finite(model, b, cfg):
    model.zero_grad()
    # training mode: the sample u = mu + L eps uses sqrt(1 - rho^2)
    p = model(b, use_posterior=True, step=0)
    # the GMM likelihood inverts Sigma_u's propagation (rho s_w s_a off-diagonal)
    loss, _ = ds.pred_loss(p, b, 0, cfg)
    loss.mean().backward()
    grads = [q.grad for q in model.parameters() if q.grad is not None]
    return (
        torch.isfinite(p.states).all()
        and torch.isfinite(p.pos_cov).all()
        and torch.isfinite(loss).all()
        and all(torch.isfinite(g).all() for g in grads)
    )


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("pre_tanh", [50.0, -50.0])
def test_decoder_correlation_at_the_edge_stays_finite(dtype, pre_tanh, monkeypatch):
    """tanh(+-50) is +-1 exactly in floating point: the clamp of bounded_correlation keeps the
    training forward, the loss and the backward finite. With plain tanh (the code before the clamp)
    the same model gives NaN."""
    cfg = small_cfg()
    model = make_model(cfg).to(dtype)
    b = make_batch(8, dtype=dtype)
    _drive_rho_to_the_edge(model, pre_tanh)
    assert abs(ds.bounded_correlation(torch.tensor(pre_tanh, dtype=dtype))) == 1 - ds.RHO_MARGIN
    assert _training_step_is_finite(model, b, cfg)
    # no clamp: the test would catch its removal
    monkeypatch.setattr(ds, "bounded_correlation", torch.tanh)
    assert not _training_step_is_finite(model, b, cfg)


def test_bounded_correlation_is_tanh_inside_the_bounds():
    """Ordinary pre-tanh values: the same values and gradients as tanh, bit for bit
    (same seed, same numbers)."""
    for dtype in (torch.float32, torch.float64):
        x = torch.linspace(-5, 5, 101, dtype=dtype, requires_grad=True)
        y = torch.tanh(x)
        (gx,) = torch.autograd.grad(y.sum(), x)
        y2 = ds.bounded_correlation(x)
        (gx2,) = torch.autograd.grad(y2.sum(), x)
        assert torch.equal(y, y2) and torch.equal(gx, gx2)


def test_stationary_agent_is_finite():
    cfg = small_cfg()
    model = make_model(cfg)
    b = make_batch(4)
    still = b.agent_hist[:, -1:].expand(-1, 9, -1).clone()
    still[..., 3] = 0.0  # parked: no motion, no speed, no velocity direction
    b0 = b.replace(agent_hist=still, agent_fut=still[:, :6])
    p = model(b0, use_posterior=True, step=500)
    # the tracked heading + a correction
    assert (ds.wrap_angle(p.s0[:, 2] - still[:, -1, 2]).abs() < 1).all()
    loss, _ = ds.pred_loss(p, b0, 500, cfg)
    loss.mean().backward()
    assert torch.isfinite(loss).all() and torch.linalg.eigvalsh(p.pos_cov).min() >= 0.05**2 - 1e-12
    assert all(torch.isfinite(q.grad).all() for q in model.parameters() if q.grad is not None)


def test_prior_does_not_see_the_future_and_eval_is_deterministic():
    cfg = small_cfg()
    model = make_model(cfg).eval()
    b = make_batch(8)
    p1 = model(b, use_posterior=False)
    p2 = model(
        b.replace(agent_fut=b.agent_fut + 3.0, others_fut=b.others_fut + 3.0), use_posterior=False
    )
    assert torch.equal(p1.states, p2.states) and torch.equal(p1.probs, p2.probs)
    q1 = model(b, use_posterior=True).probs
    assert not torch.allclose(
        q1, model(b.replace(agent_fut=b.agent_fut + 3.0), use_posterior=True).probs
    )
    model.train()  # training feeds sampled controls back: two calls differ
    assert not torch.allclose(
        model(b, use_posterior=False).states, model(b, use_posterior=False).states
    )


# ---------------------------------------------------------------------------------------------
# Dynamics: modes, covariance propagation, the Gaussian density
# ---------------------------------------------------------------------------------------------


def test_modes_are_the_unicycle_integration_of_the_mean_controls():
    cfg = small_cfg()
    model = make_model(cfg).eval()
    b = make_batch(6)
    p = model(b, use_posterior=False)
    # (B, K, 7, 4)
    ref = ds.unicycle_rollout(p.s0[:, None].expand(-1, cfg.pred_modes, -1), p.controls, DT)
    assert torch.allclose(p.states, ref[:, :, 1:], atol=1e-10)
    assert torch.allclose(p.s0[:, :2], b.agent_hist[:, -1, :2]) and torch.allclose(
        p.s0[:, 3], b.agent_hist[:, -1, 3]
    )
    # heading = velocity direction + a correction bounded by 1 rad
    vel = b.agent_hist[:, -1, :2] - b.agent_hist[:, -2, :2]
    assert (ds.wrap_angle(p.s0[:, 2] - torch.atan2(vel[:, 1], vel[:, 0])).abs() < 1).all()


def test_covariance_one_step_by_hand():
    cfg = ds.Config(pred_pos_std_min=0.0)
    v = 2.0
    sw, sa, rho = 0.3, 0.8, 0.4
    s = torch.tensor([[[0.0, 0.0, 0.0, v]]], dtype=torch.float64)  # (1, T=1, 4), heading 0
    u = torch.zeros(1, 1, 2, dtype=torch.float64)  # w = a = 0
    cov_u = torch.tensor([[[[sw**2, rho * sw * sa], [rho * sw * sa, sa**2]]]], dtype=torch.float64)
    # x' = x + v dt + a dt^2/2,  y' = y + v w dt^2/2 + O(w^2)  =>  dx/da = dt^2/2, dy/dw = v dt^2/2
    gx, gy = DT**2 / 2, v * DT**2 / 2
    cxy = gx * gy * rho * sw * sa
    expect = torch.tensor([[gx**2 * sa**2, cxy], [cxy, gy**2 * sw**2]], dtype=torch.float64)
    got = ds.integrate_modes(s[:, 0], u, cov_u, cfg)[1][0, 0]
    assert torch.allclose(got, expect, atol=1e-12)


def test_covariance_propagation_matches_monte_carlo():
    cfg = ds.Config(pred_pos_std_min=0.0)
    g = torch.Generator().manual_seed(1)
    s0 = torch.tensor([1.0, -2.0, 0.4, 6.0], dtype=torch.float64)
    mu = torch.tensor(
        [[0.2, 1.0], [0.1, -0.5], [-0.3, 0.0], [0.0, 0.5], [0.25, -1.0], [0.0, 0.0]],
        dtype=torch.float64,
    )
    sig = torch.tensor([0.05, 0.3], dtype=torch.float64)
    cov_u = torch.diag(sig**2).expand(6, 2, 2)
    ekf = ds.integrate_modes(s0, mu, cov_u, cfg)[1]  # (6, 2, 2)
    n = 40000
    u = mu + sig * torch.randn(n, 6, 2, generator=g, dtype=torch.float64)
    xy = ds.unicycle_rollout(s0.expand(n, 4), u, DT)[:, 1:, :2]  # (n, 6, 2)
    d = xy - xy.mean(0)
    mc = torch.einsum("nti,ntj->tij", d, d) / (n - 1)  # (6, 2, 2)
    assert torch.allclose(ekf, mc, rtol=0.1, atol=2e-3 * mc.abs().max())
    assert not torch.allclose(ekf[1:], ekf[:-1], rtol=0.1)  # it grows


def test_gaussian_log_prob_matches_torch_distributions():
    g = torch.Generator().manual_seed(0)
    A = torch.randn(5, 2, 2, generator=g, dtype=torch.float64)
    cov = A @ A.transpose(-1, -2) + 0.1 * torch.eye(2, dtype=torch.float64)
    mean, y = (
        torch.randn(5, 2, generator=g, dtype=torch.float64),
        torch.randn(5, 2, generator=g, dtype=torch.float64),
    )
    ref = torch.distributions.MultivariateNormal(mean, covariance_matrix=cov).log_prob(y)
    assert torch.allclose(ds.gaussian2_log_prob(y, mean, cov), ref)
    # the floor's bound: inactive here
    assert torch.allclose(ds.gaussian2_log_prob(y, mean, cov, min_var=0.1), ref)


def test_gaussian_log_prob_survives_a_long_thin_covariance_in_float32():
    """A covariance the predictor produced in training (20-epoch DiffStack (1, 5, 5), seed 4, step
    461): variances ~1e5 m^2 along a line, the 0.05 m floor across it. In float32 a c - b^2 cancels
    to 0 and the log-likelihood was NaN; with the floor's bound it is finite and close to the
    float64 density of the same matrix with its floor."""
    s2 = ds.Config().pred_pos_std_min ** 2
    cov = torch.tensor([[22144.466796875, 47221.01171875], [47221.01171875, 100694.40625]])
    y, mean = torch.tensor([3.0, 7.0]), torch.tensor([0.0, 0.0])
    assert not torch.isfinite(ds.gaussian2_log_prob(y, mean, cov))  # what training met
    got = ds.gaussian2_log_prob(y, mean, cov, min_var=s2)
    # float64: the propagated part made exactly singular (its smallest eigenvalue removed), then the
    # floor added
    c64 = cov.double() - s2 * torch.eye(2, dtype=torch.float64)
    lam, vec = torch.linalg.eigh(c64)
    c64 = vec @ torch.diag(lam.clamp_min(0)) @ vec.T + s2 * torch.eye(2, dtype=torch.float64)
    ref = torch.distributions.MultivariateNormal(mean.double(), covariance_matrix=c64).log_prob(
        y.double()
    )
    assert torch.isfinite(got) and abs(got.double() - ref) < 0.05 * abs(ref), (got, ref)


def test_gradients_through_the_covariance_propagation():
    cfg = ds.Config()
    g = torch.Generator().manual_seed(2)
    s = (
        torch.tensor([[0.0, 0.0, 0.3, 4.0]], dtype=torch.float64)
        .expand(3, 4)
        .clone()
        .requires_grad_(True)
    )
    u = (0.2 * torch.randn(3, 2, generator=g, dtype=torch.float64)).requires_grad_(True)
    cu = (
        torch.diag(torch.tensor([0.04, 0.2], dtype=torch.float64))
        .expand(3, 2, 2)
        .clone()
        .requires_grad_(True)
    )
    assert torch.autograd.gradcheck(
        lambda s, u, c: ds.integrate_modes(s[0], u, c, cfg)[1], (s, u, cu)
    )


# ---------------------------------------------------------------------------------------------
# The stack end to end
# ---------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def synth_small():
    return data_synth.make_dataset(300, seed=1)


@pytest.mark.parametrize("plan_dt", [None, pytest.param(0.1, marks=pytest.mark.slow)])
def test_end_to_end_gradient_matches_finite_differences(synth_small, plan_dt):
    """dL/dtheta through predictor, relaxed planner and iLQR (KKT backward) against central
    differences; plan_dt = 0.1: also through the interpolation of the predicted modes to the
    planner's 0.1 s clock."""
    # 30 steps converge slower
    cfg = ds.Config(**TINY, ilqr_iters=40 if plan_dt is None else 100, ilqr_tol=1e-10)
    batch = synth_small.train[:6].to(torch.float64)
    torch.manual_seed(0)
    model = ds.Predictor(cfg).double()
    method = tr.Method("DiffStack", losses=(1, 1, 1))
    a1, a2, a3 = tr.alphas(method, "rl", cfg)

    def loss():
        torch.manual_seed(1)  # the decoder samples its next inputs in training mode
        out = ds.run_stack(batch, model, method, cfg, "rl", step=500, train=True, plan_dt=plan_dt)
        assert out.converged.all() and out.plannable.all()
        return a1 * out.l_pred.mean() + a2 * out.l_plan.mean() + a3 * out.l_ctr.mean()

    params = [model.p_z[2].weight, model.p_z[2].bias, model.dec_h0.weight]
    grads = torch.autograd.grad(loss(), params)
    picks = [(0, (0, 3)), (0, (2, 5)), (1, (1,)), (1, (4,)), (2, (3, 0)), (2, (7, 9))]
    analytic, fd = [], []
    with torch.no_grad():
        for i, idx in picks:
            p = params[i]
            h = 1e-5
            p[idx] += h
            up = loss()
            p[idx] -= 2 * h
            down = loss()
            p[idx] += h
            fd.append((up - down) / (2 * h))
            analytic.append(grads[i][idx])
    assert rel_err(torch.stack(analytic), torch.stack(fd)) < 1e-4


def test_upsample_keeps_the_knots_and_interpolates_linearly():
    g = torch.Generator().manual_seed(0)
    now, fut = (
        torch.randn(3, 2, generator=g, dtype=torch.float64),
        torch.randn(3, 6, 2, generator=g, dtype=torch.float64),
    )
    assert ds.upsample(now, fut, 1) is fut
    fine = ds.upsample(now, fut, 5)  # (3, 30, 2)
    assert fine.shape == (3, 30, 2) and torch.allclose(fine[:, 4::5], fut, rtol=0, atol=1e-15)
    assert torch.allclose(fine[:, 0], 0.8 * now + 0.2 * fut[:, 0]) and torch.allclose(
        fine[:, 7], 0.4 * fut[:, 0] + 0.6 * fut[:, 1]
    )


@pytest.mark.parametrize("plan_dt", [0.3, 0.0, -0.1, 1.0])
def test_plan_dt_that_does_not_divide_dt_is_refused(synth_small, plan_dt):
    with pytest.raises(ValueError, match="plan_dt"):
        ds.run_stack(
            synth_small.val[:4],
            None,
            tr.Method("GT prediction", "gt"),
            ds.Config(),
            plan_dt=plan_dt,
        )


def test_plan_dt_changes_the_resolution_not_the_problem(synth_small):
    """plan_dt = dt is the default stack exactly; at 0.1 s the same 3 s are planned in 30 steps and,
    with the per-step terms scaled by 1/5, the costs and the trajectory at the logged steps stay
    close to the 0.5 s ones (unscaled, control effort and lane terms would count 5x and the goal
    1x)."""
    cfg = ds.Config()
    batch = synth_small.train[:64].to(torch.float64)
    gt = tr.Method("GT prediction", "gt")
    base = ds.run_stack(batch, None, gt, cfg)
    same = ds.run_stack(batch, None, gt, cfg, plan_dt=0.5)
    assert torch.equal(base.s, same.s) and torch.equal(base.hindsight, same.hindsight)
    fine = ds.run_stack(batch, None, gt, cfg, plan_dt=0.1)
    assert fine.s.shape == (64, 31, 4) and fine.u.shape == (64, 30, 2)
    k = base.plannable & fine.plannable & base.converged & fine.converged
    assert k.sum() > 30
    assert abs(fine.hindsight[k].mean() / base.hindsight[k].mean() - 1) < 0.03
    assert (fine.s[k, 5::5, :2] - base.s[k, 1:, :2]).norm(dim=-1).mean() < 0.3
    # the model moves the ego by the unicycle at 0.1 s
    assert torch.allclose(ds.unicycle_rollout(fine.s[:, 0], fine.u, 0.1), fine.s, atol=1e-8)


def test_stack_gradients_reach_predictor_through_planner_and_controller(synth_small):
    cfg = ds.Config(**TINY)
    batch = synth_small.train[:32]
    torch.manual_seed(0)
    model = ds.Predictor(cfg)
    out = ds.run_stack(
        batch, model, tr.Method("DiffStack", losses=(0, 1, 1)), cfg, "rl", step=0, train=True
    )
    for loss in (out.l_plan.mean(), out.l_ctr.mean()):
        g = torch.autograd.grad(loss, model.dec_h0.weight, retain_graph=True)[0]
        assert g.abs().sum() > 0
    # No prediction and GT prediction need no model; GT prediction plans at least as well in
    # hindsight on average
    none = ds.run_stack(batch, None, tr.Method("No prediction", "none"), cfg)
    gt = ds.run_stack(batch, None, tr.Method("GT prediction", "gt"), cfg)
    assert (
        torch.isfinite(none.hindsight).all() and gt.hindsight.mean() <= none.hindsight.mean() + 1e-6
    )


def test_decoder_matches_a_plain_gru_cell():
    """Predictor.decode's gate-by-gate GRU against torch.nn.GRUCell with the same weights, in eval
    mode (the mean fed back) and in training mode (the reparameterised sample fed back, same
    seed)."""
    cfg = small_cfg()
    model = make_model(cfg)
    K, T, Hd, E = cfg.pred_modes, cfg.horizon, cfg.pred_dec_hidden, cfg.pred_enc_hidden
    g = torch.Generator().manual_seed(3)
    B = 4
    x = torch.randn(B, 2 * E, generator=g, dtype=torch.float64)
    f0 = torch.randn(B, 8, generator=g, dtype=torch.float64)
    cell = torch.nn.GRUCell(K + 2 * E + 2, Hd, dtype=torch.float64)
    with torch.no_grad():
        cell.weight_ih.copy_(model.dec_in.weight)
        cell.bias_ih.copy_(model.dec_in.bias)
        cell.weight_hh.copy_(model.dec_hh.weight)
        cell.bias_hh.copy_(model.dec_hh.bias)

    def reference(train):  # rows b*K + k, as decode's
        zx = torch.cat(
            [torch.eye(K, dtype=x.dtype).expand(B, K, K), x[:, None].expand(B, K, 2 * E)], -1
        )
        zx = zx.reshape(B * K, K + 2 * E)  # (B*K, K+X): (one_hot(k), x)
        h = model.dec_h0(zx)  # (B*K, Hd)
        u = model.dec_u0(f0).repeat_interleave(K, 0)  # (B*K, 2)
        mus, covs = [], []
        for _ in range(T):
            h = cell(torch.cat([zx, u], -1), h)
            out = model.dec_out(h)
            mu, s_w, s_a = out[:, :2], out[:, 2].exp(), out[:, 3].exp()
            rho = torch.tanh(out[:, 4]).clamp(-1 + ds.RHO_MARGIN, 1 - ds.RHO_MARGIN)
            c = rho * s_w * s_a
            covs.append(
                torch.stack([torch.stack([s_w**2, c], -1), torch.stack([c, s_a**2], -1)], -2)
            )
            mus.append(mu)
            if train:
                # Sigma_u = L L'
                L = torch.stack(
                    [
                        torch.stack([s_w, 0 * s_w], -1),
                        torch.stack([rho * s_a, s_a * (1 - rho**2).sqrt()], -1),
                    ],
                    -2,
                )
                u = mu + (L @ torch.randn_like(mu)[..., None])[..., 0]
            else:
                u = mu
        return torch.stack(mus, 1).reshape(B, K, T, 2), torch.stack(covs, 1).reshape(B, K, T, 2, 2)

    with torch.no_grad():
        for train in (False, True):
            model.train(train)
            torch.manual_seed(7)
            mu, cov = model.decode(x, f0)
            torch.manual_seed(7)
            mu_ref, cov_ref = reference(train)
            assert torch.allclose(mu, mu_ref, rtol=0, atol=1e-10), (
                train,
                (mu - mu_ref).abs().max(),
            )
            assert torch.allclose(cov, cov_ref, rtol=0, atol=1e-10), (
                train,
                (cov - cov_ref).abs().max(),
            )
    # the sample fed back does matter
    assert not torch.allclose(mu, model.eval().decode(x, f0)[0], atol=1e-6)


def test_integrate_modes_matches_the_step_by_step_recursion():
    """integrate_modes (cumulative sums, the unrolled covariance) against unicycle_step and the EKF
    recursion Sigma_{t+1} = A Sigma A' + B Su B' over the whole 4-D state, one step at a time."""
    cfg = ds.Config()
    g = torch.Generator().manual_seed(5)
    n, T = 6, cfg.horizon

    def rnd(*shape):
        return torch.rand(*shape, generator=g, dtype=torch.float64)

    # (n, 4): x, y, h, v
    s0 = torch.stack([20 * rnd(n) - 10, 20 * rnd(n) - 10, 6 * rnd(n) - 3, 12 * rnd(n)], -1)
    u = torch.randn(n, T, 2, generator=g, dtype=torch.float64) * torch.tensor(
        [0.4, 1.5], dtype=torch.float64
    )
    u[0, :, 0] = 0.0  # straight: the yaw-rate series branch
    L = torch.randn(n, T, 2, 2, generator=g, dtype=torch.float64) * 0.5
    cov_u = L @ L.mT + 0.01 * torch.eye(2, dtype=torch.float64)
    states, pos_cov = ds.integrate_modes(s0, u, cov_u, cfg)
    s, Sigma = s0, torch.zeros(n, 4, 4, dtype=torch.float64)
    ref_states, ref_cov = [s0], []
    for t in range(T):
        A, B = ds.unicycle_jacobians(s, u[:, t], cfg.dt)  # (n, 4, 4), (n, 4, 2)
        Sigma = A @ Sigma @ A.mT + B @ cov_u[:, t] @ B.mT
        s = ds.unicycle_step(s, u[:, t], cfg.dt)
        ref_states.append(s)
        ref_cov.append(
            Sigma[:, :2, :2] + cfg.pred_pos_std_min**2 * torch.eye(2, dtype=torch.float64)
        )
    ref_states, ref_cov = torch.stack(ref_states, 1), torch.stack(ref_cov, 1)
    assert torch.allclose(states, ref_states, rtol=0, atol=1e-10), (states - ref_states).abs().max()
    assert torch.allclose(pos_cov, ref_cov, rtol=0, atol=1e-10), (pos_cov - ref_cov).abs().max()
    # the covariances grow well beyond the floor
    assert pos_cov[:, -1].diagonal(dim1=-2, dim2=-1).max() > 1


@pytest.mark.parametrize(
    "field, value",
    [
        ("dt", 0.0),
        ("dt", -0.5),
        ("dt", math.nan),
        ("horizon", 0),
        ("horizon", 2.5),
        ("hist_len", True),
        ("rbf_var", 0.0),
        ("beta", math.inf),
        ("w_coll", -1.0),
        ("u_lower", (1.0, -5.0)),
        ("u_upper", (0.7,)),
        ("ilqr_iters", 0),
        ("line_search_decay", 1.0),
        ("pred_modes", 0),
        ("batch_size", 0),
        ("lr", 0.0),
        ("plan_accels", ()),
        ("pred_lr_decay", 1.5),
        ("alpha_rl", (1.0, -1.0, 1.0)),
        ("pred_scales", (1.0, 1.0, 1.0, 0.0)),
        ("batch_size", 10**9),
        ("pred_modes", 10**6),
        ("dt", 1e-300),
        ("horizon", 10**4),
        ("lr", 1e9),
    ],
)
def test_config_refuses_values_that_would_fail_later(field, value):
    with pytest.raises(ValueError, match=field):
        ds.Config(**{field: value})


def test_config_accepts_its_defaults_and_the_tests_small_models():
    ds.Config(), ds.Config(**TINY), ds.Config(pred_pos_std_min=0.0)


def test_every_number_of_the_config_has_a_range_named_in_its_refusal():
    for f in dataclasses.fields(ds.Config):
        if f.type in ("int", "float"):
            with pytest.raises(
                ValueError,
                match=rf"^Config\.{f.name}: must be a (whole|finite) number from \S+ to \S+, got",
            ):
                ds.Config(**{f.name: 10**12})
        if f.type == "int":  # a flag or a fraction is no count, though Python calls True 1
            for v in (True, 2.5):
                with pytest.raises(ValueError, match=rf"^Config\.{f.name}: must be a whole number"):
                    ds.Config(**{f.name: v})


# ---------------------------------------------------------------------------------------------
# Devices
# ---------------------------------------------------------------------------------------------
# The stack runs unchanged on any device: every tensor it makes is made on the device (and dtype)
# of its inputs. Checked on the CPU, without a GPU, in two ways (1, 2), and the stack on a GPU
# against the CPU where there is one (its body also runs on the CPU, so that it is tested without
# one). The --device argument of the command lines is tested in test_runs.py.
#
# 1. The meta trick. Inside `with torch.device("meta"):` every factory called WITHOUT device=
#    (torch.zeros, tensor, arange, ones, eye, full, linspace, randn, ...) makes a meta tensor (no
#    storage), while one called with device=x.device still makes a CPU tensor for CPU inputs. We
#    feed CPU inputs: the first time a forgotten factory's meta tensor meets a CPU tensor, torch
#    raises "Tensor on device meta is not on the expected device cpu!" -- just as a CPU tensor
#    meeting a CUDA one would on a GPU. (Stricter than CUDA, which lets 0-dim CPU tensors mix
#    with CUDA ones: good for us.) test_the_meta_trick_catches_a_missing_device shows it on a
#    planted bug.
#    One blind spot: indexing a CPU tensor with a meta index tensor does not raise (torch.arange(B)
#    used only as an index slips through; on CUDA it works too, with a host-to-device copy).
# 2. The factory audit, which covers that blind spot and names the line: a TorchFunctionMode (the
#    mechanism torch.device("meta") itself uses) records every factory called without device=
#    directly from diffstack.py, experiments.py or data_synth.py (the caller's frame), while the
#    stack runs normally: none may be left, each named by its file, line and function.

TINY16 = dict(
    pred_modes=5, pred_dec_hidden=16, pred_enc_hidden=8, pred_latent_hidden=8, batch_size=16
)


FACTORIES = {
    getattr(torch, name)
    for name in (
        "tensor",
        "as_tensor",
        "asarray",
        "scalar_tensor",
        "zeros",
        "ones",
        "empty",
        "full",
        "arange",
        "linspace",
        "logspace",
        "eye",
        "rand",
        "randn",
        "randint",
        "randperm",
        "tril_indices",
        "triu_indices",
    )
    if hasattr(torch, name)
}


HERE = pathlib.Path(__file__).resolve().parent


# data_synth: sample_at
AUDITED = {
    str(HERE / name): name
    for name in ("diffstack.py", "train.py", "experiments.py", "data_synth.py")
    + ("lab/data.py", "lab/nuscenes.py", "lab/waymo.py")
}


class FactoryAudit(TorchFunctionMode):
    """Records (file, line, function, factory) for every tensor factory called without device=
    straight from an audited file. Only the direct caller counts: factories inside torch (an
    optimiser's state) are torch's affair."""

    def __init__(self):
        super().__init__()
        self.calls = set()

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if func in FACTORIES and kwargs.get("device") is None:
            caller = sys._getframe(1)  # the Python frame that called the factory
            name = AUDITED.get(caller.f_code.co_filename)
            if name is not None:
                self.calls.add((name, caller.f_lineno, caller.f_code.co_name, func.__name__))
        return func(*args, **kwargs)


@pytest.fixture(scope="module")
def setup():
    """Real synthetic data (made on the CPU, as always), a tiny config, and the modules (a
    predictor, the cost weights), made here on the CPU: a module built inside torch.device("meta")
    would itself be on meta."""
    scfg = data_synth.SynthConfig()
    data = data_synth.make_dataset(60, scfg, seed=5)
    cfg = ds.Config(**TINY16)
    torch.manual_seed(0)
    return data, cfg, ds.Predictor(cfg), scfg, tr.CostWeights(cfg)


def run_dynamics():
    """Section 2 (ours): the unicycle and its derivatives, float32 and float64."""
    for dtype in (torch.float32, torch.float64):
        g = torch.Generator().manual_seed(0)
        cpu = dict(dtype=dtype, device="cpu")  # CPU inputs, also under meta
        s = torch.randn(5, 4, generator=g, **cpu)
        u = torch.randn(5, 3, 2, generator=g, **cpu) * torch.tensor([0.5, 1.0], **cpu)
        u[0, 0, 0] = 0.0  # the series branch of the moments
        lam = torch.randn(5, 4, generator=g, **cpu)
        assert ds.unicycle_step(s, u[:, 0], 0.5).device.type == "cpu"
        assert ds.unicycle_rollout(s, u, 0.5).shape == (5, 4, 4)
        A, B = ds.unicycle_jacobians(s, u[:, 0], 0.5)
        H = ds.unicycle_curvature(s, u[:, 0], lam, 0.5)
        assert A.device.type == B.device.type == H.device.type == "cpu"
        up = ds.upsample(s[:, :2], u, 5)
        assert up.shape == (5, 15, 2) and up.device.type == "cpu"


def run_stack_everything(setup):
    """Section 7: the stack with every kind of predictor and option the experiments use."""
    data, cfg, model, *_ = setup
    batch = data.train[:8]
    outs = []
    for method in (
        tr.Method("No prediction", "none"),
        tr.Method("GT prediction", "gt"),
        tr.Method("DiffStack", losses=(1, 1, 1)),
    ):
        out = ds.run_stack(batch, model, method, cfg, "rl", step=0, train=True)
        outs.append(out)
    learned = tr.Method("DiffStack", losses=(1, 1, 1))
    outs.append(ds.run_stack(batch, model, learned, cfg, "il", planner=False, plan_others=False))
    outs.append(ds.run_stack(batch, model, learned, cfg, "rl", controller=False))
    outs.append(ds.run_stack(batch, model, learned, cfg, "rl", plan_dt=0.25))
    # the KKT backward as well
    (outs[-1].l_plan.sum() + outs[2].l_ctr.sum() + outs[2].l_pred.sum()).backward()
    for out in outs:
        assert out.s.device.type == "cpu" and out.hindsight.device.type == "cpu"
    return outs


def run_training(setup):
    """Section 8: two training steps (predictor, and the cost weights), and the evaluation."""
    data, cfg, model, _, weights = setup
    # training changes them (learning the cost freezes the model)
    model, weights = copy.deepcopy(model), copy.deepcopy(weights)
    small = data.train[:32]
    tr.train_stack(
        model, small, tr.Method("DiffStack", losses=(1, 1, 1)), cfg, "rl", epochs=1.0, log=None
    )
    tr.train_stack(
        model,
        small,
        tr.Method("Grad-cost weighted", weighting="grad_cost"),
        cfg,
        "rl",
        epochs=0.5,
        log=None,
    )
    tr.train_stack(
        model,
        small,
        tr.Method("Cost weights", losses=(0, 0, 1)),
        cfg,
        "il",
        epochs=0.5,
        log=None,
        weights=weights,
    )
    for method in (tr.Method("No prediction", "none"), tr.Method("Standard")):
        r = tr.evaluate_stack(
            model if method.predictor == "learned" else None, data.val[:16], method, cfg, "rl"
        )
        assert isinstance(r["hindsight"], float)


def run_closed_loop(setup):
    """experiments.py: one closed-loop step (the simulation on the CPU, the stack on the model's
    device)."""
    data, cfg, model, scfg, _ = setup
    scenes = data.val_scenes[:2]
    roll = ex.simulate(
        scenes, ex.stack_policy(model, tr.Method("Standard"), cfg), cfg, 0.5, scfg=scfg
    )
    assert roll.ego.device.type == "cpu" and roll.ego.shape[1] == 2
    m = ex.closed_loop_metrics(scenes, roll, cfg)
    assert all(v.device.type == "cpu" for v in m.values())


EVERYTHING = (run_stack_everything, run_training, run_closed_loop)


def _buggy_upsample(now, fut, substeps):
    """diffstack.upsample with its device= removed: the bug the tests must catch."""
    knots = torch.cat([now[..., None, :], fut], -2)
    a, b = knots[..., :-1, None, :], knots[..., 1:, None, :]
    f = torch.arange(1, substeps + 1, dtype=fut.dtype)[:, None] / substeps  # the bug: no device=
    return (a + (b - a) * f).flatten(-3, -2)


def test_the_meta_trick_catches_a_missing_device():
    now, fut = torch.zeros(3, 2), torch.ones(3, 4, 2)
    # on the CPU the bug is invisible
    assert torch.equal(_buggy_upsample(now, fut, 2), ds.upsample(now, fut, 2))
    with torch.device("meta"):
        # the real one: device= of its input, a CPU tensor
        assert ds.upsample(now, fut, 2).device.type == "cpu"
        with pytest.raises(RuntimeError, match="meta"):
            # the forgotten factory made a meta tensor, which met a CPU one
            _buggy_upsample(now, fut, 2)


def test_the_audit_names_a_missing_device(monkeypatch):
    monkeypatch.setitem(AUDITED, __file__, "test_diffstack.py")
    now, fut = torch.zeros(3, 2), torch.ones(3, 4, 2)
    with FactoryAudit() as audit:
        ds.upsample(now, fut, 2)
        _buggy_upsample(now, fut, 2)
    assert audit.calls == {
        (
            "test_diffstack.py",
            _buggy_upsample.__code__.co_firstlineno + 4,
            "_buggy_upsample",
            "arange",
        )
    }


def test_dynamics_make_every_tensor_on_their_inputs_device():
    with torch.device("meta"):
        run_dynamics()


@pytest.mark.parametrize("run", EVERYTHING, ids=lambda f: f.__name__)
def test_the_stack_makes_every_tensor_on_its_inputs_device(run, setup):
    """Every part of the stack under torch.device("meta"): a tensor made without device= lands on
    meta, which has no values, and the run fails. Torch's own code must pass too: torch 2.11's Adam
    makes its step counter on the default device and fails here (seen where 2.11 was installed), so
    training is checked from 2.13 on (pinned in requirements.txt), whose Adam keeps it on the CPU;
    the factory audit below covers our own code on any version."""
    if run is run_training and tuple(
        int(v) for v in torch.__version__.split("+")[0].split(".")[:2]
    ) < (2, 13):
        pytest.skip(
            f"torch {torch.__version__}'s Adam makes its step counter on the default device "
            "(meta here)"
        )
    with torch.device("meta"):
        run(setup)


@pytest.fixture(scope="module")
def audit(setup):
    """Every factory without device= that the stack calls from diffstack.py, experiments.py and
    data_synth.py (the closed loop cuts its samples with data_synth.sample_at; generating the data
    is not audited: it is made on the CPU)."""
    with FactoryAudit() as a:
        run_dynamics()
        for run in EVERYTHING:
            run(setup)
    return a.calls


def test_no_factory_without_device(audit):
    """Anywhere in the audited files: every factory the stack calls is given device=."""
    calls = sorted(audit)
    assert not calls, "tensor factories without device=: " + "; ".join(
        f"{f}:{n} {fn}() torch.{t}" for f, n, fn, t in calls
    )


@pytest.mark.parametrize(
    "device",
    [
        "cpu",
        pytest.param(
            "cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
        ),
    ],
)
def test_the_stack_on_a_device_matches_the_cpu(device, setup):
    """On cuda the real check; on the CPU the same body runs (trivially equal), so that a mistake in
    the test itself (a float32 batch for a float64 model, say) shows on machines without a GPU too.
    """
    data, cfg, model, *_ = setup
    batch = data.val[:16].to(torch.float64)
    cpu_model = ds.Predictor(cfg).double()
    cpu_model.load_state_dict(model.state_dict())
    dev_model = ds.Predictor(cfg).double().to(device)
    dev_model.load_state_dict(model.state_dict())
    for method in (tr.Method("No prediction", "none"), tr.Method("Standard")):
        a = ds.run_stack(batch, cpu_model.eval(), method, cfg)
        b = ds.run_stack(batch.to(device=device), dev_model.eval(), method, cfg)
        assert b.s.device.type == device
        assert torch.allclose(a.hindsight, b.hindsight.cpu(), atol=1e-6)
    # training on the device: the data stays on the CPU (in the model's float64), each batch moved
    # as it is drawn
    history = tr.train_stack(
        dev_model,
        data.train[:32].to(torch.float64),
        tr.Method("DiffStack", losses=(1, 1, 1)),
        cfg,
        epochs=1.0,
        log=None,
    )
    assert history and all(torch.isfinite(torch.tensor(h["loss"])) for h in history)
