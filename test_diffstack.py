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
    preds = torch.randn(B, K, T, 2, generator=g, dtype=dtype) * 2 + torch.tensor([12.0, 2.0], dtype=dtype)
    probs = torch.softmax(torch.randn(B, K, generator=g, dtype=dtype), -1)
    others = torch.randn(B, A, T, 2, generator=g, dtype=dtype) * 3 + torch.tensor([20.0, -2.0], dtype=dtype)
    goal = torch.tensor([[24.0, 0, 0, 8], [28, 3.5, 0, 9], [18, 0, 0, 6]], dtype=dtype)[:B]
    ctx = ds.CostContext(preds, probs, torch.ones(B, dtype=dtype), others, torch.ones(B, A, dtype=dtype),
                         goal[:, :2], lanes, lanes_mask)
    return s0, goal, ctx


def stack_cost_fn(ctx):
    """The DiffStack cost as a solver callable, differentiable wrt weights, predictions, goal and lanes."""
    def cost_fn(x, u, w, preds, probs, goal, lanes):
        c = ds.CostContext(preds, probs, ctx.pred_mask, ctx.others, ctx.others_mask, goal, lanes, ctx.lanes_mask)
        return ds.total_cost(x, u, c, w)
    return cost_fn


def rel_err(a, b):
    return ((a - b).norm() / b.norm()).item()


def central_fd(f, x, idx, h=1e-6):
    e = torch.zeros_like(x)
    e[idx] = h
    return (f(x + e) - f(x - e)) / (2 * h)


def test_collision_mean_spread_identity():
    """The cost's collision term uses sum_k pi_k |s - s_k|^2 = |s - mu|^2 + spread: check against the sum."""
    s0, goal, ctx = toy_scene()
    x = ds.unicycle_rollout(s0, torch.zeros(3, 6, 2, dtype=torch.float64), DT)
    terms = ds.cost_terms(x, torch.zeros(3, 6, 2, dtype=torch.float64), ctx)
    pos = x[:, 1:, :2]
    d2 = (ctx.probs[:, :, None] * ((pos[:, None] - ctx.preds) ** 2).sum(-1)).sum(1)  # (B, T)
    others = (torch.exp(-((pos[:, None] - ctx.others) ** 2).sum(-1) / 4)).sum((1, 2))
    assert torch.allclose(terms[:, 0], torch.exp(-d2 / 4).sum(-1) + others)
    assert torch.allclose(terms[:, 1], ((pos[:, -1] - ctx.goal) ** 2).sum(-1))


def test_lane_projection_ignores_oncoming_lanes():
    lanes = torch.zeros(1, 2, 10, 3, dtype=torch.float64)
    lanes[..., 0] = torch.arange(10.0)
    lanes[0, 1, :, 1], lanes[0, 1, :, 2] = 1.0, math.pi  # a lane 1 m away, going the other way
    lanes[0, 1] = lanes[0, 1].flip(0)
    pos = torch.tensor([[[4.3, 0.8]]], dtype=torch.float64)
    d2, err, ok = ds.project_to_lanes(pos, torch.tensor([[0.1]], dtype=torch.float64), lanes, torch.ones(1, 2, 10, dtype=torch.bool))
    assert ok.all() and torch.allclose(d2, torch.tensor([[0.64]], dtype=torch.float64)) and torch.allclose(err, torch.tensor([[0.1]], dtype=torch.float64))


def test_planner_splines_hit_terminal_states_and_reject_infeasible():
    cfg = ds.Config()
    s0, goal, ctx = toy_scene()
    c = ds.plan_candidates(s0, goal, ctx.lanes, ctx.lanes_mask, cfg)
    B, N = c.valid.shape
    assert c.x.shape == (B, N, 7, 4) and c.u.shape == (B, N, 6, 2)
    # on straight lanes along +x the terminal state is known in closed form
    acc = torch.tensor(cfg.plan_accels, dtype=torch.float64)
    v_f = (s0[:, 3:4] + acc * 3.0).clamp_min(0)  # (B, 8)
    dist = (s0[:, 3:4] + v_f) / 2 * 3.0
    lane0 = c.x[:, :24].reshape(B, 8, 3, 7, 4)  # first goal lane: the closest to the goal
    lane_y = torch.tensor([0.0, 3.5, 0.0], dtype=torch.float64)[:B]
    assert torch.allclose(lane0[..., -1, 0], (s0[:, 0:1] + dist)[..., None].expand(B, 8, 3), atol=1e-9)
    off = torch.tensor(cfg.plan_offsets, dtype=torch.float64)
    assert torch.allclose(lane0[..., -1, 1], (lane_y[:, None, None] + off).expand(B, 8, 3), atol=1e-9)
    assert torch.allclose(lane0[..., -1, 3], v_f[..., None].expand(B, 8, 3), atol=1e-9)
    assert torch.allclose(c.x[:, :, 0], s0[:, None].expand(B, N, 4))
    # every valid candidate respects the feasibility limits; hard stops from 10 m/s violate them
    lo, hi = torch.tensor(cfg.u_lower, dtype=torch.float64), torch.tensor(cfg.u_upper, dtype=torch.float64)
    ok_box = ((c.u >= lo) & (c.u <= hi)).all(-1).all(-1)
    assert (ok_box | ~c.valid).all() and not c.valid.all()
    # a sharp turn at speed is infeasible
    s_fast = s0.clone(); s_fast[:, 3] = 25.0
    lanes = ctx.lanes.clone(); lanes[..., 1] = 0.05 * lanes[..., 0] ** 2; lanes[..., 2] = torch.atan(0.1 * lanes[..., 0])
    far = ds.plan_candidates(s_fast, goal, lanes, ctx.lanes_mask, cfg)
    assert far.valid.sum() < c.valid.sum()


def test_plan_is_argmin_and_flags_unplannable():
    cfg = ds.Config()
    s0, goal, ctx = toy_scene()
    w = ds.cost_weights(cfg, torch.float64)
    cands, cost, idx, ok = ds.plan(s0, ctx, goal, w, cfg)
    assert ok.all()
    for b in range(3):  # the reference: a plain Python minimum over the valid candidates
        best = min((cost[b, n].item(), n) for n in range(cost.shape[1]) if cands.valid[b, n])
        assert idx[b].item() == best[1]
    ctx.lanes_mask[1] = False  # no lanes: no candidates, flagged, no crash
    _, _, _, ok = ds.plan(s0, ctx, goal, w, cfg)
    assert ok.tolist() == [True, False, True]


def test_relaxed_planner_gradients():
    cfg = ds.Config()
    s0, goal, ctx = toy_scene()
    cands = ds.plan_candidates(s0, goal, ctx.lanes, ctx.lanes_mask, cfg)
    target = ds.masked_argmin(torch.arange(cands.valid.shape[1], dtype=torch.float64).expand_as(cands.valid), cands.valid)
    preds = ctx.preds.clone().requires_grad_()
    w = ds.cost_weights(cfg, torch.float64).requires_grad_()

    def loss(preds, w):
        c = ds.CostContext(preds, ctx.probs, ctx.pred_mask, ctx.others, ctx.others_mask, ctx.goal, ctx.lanes, ctx.lanes_mask)
        return ds.plan_loss(ds.total_cost(cands.x, cands.u, c, w), cands.valid, target, cfg.beta).sum()

    assert torch.autograd.gradcheck(loss, (preds, w))
    # p_n = softmax(-beta C_n): the loss is -log p of the target
    cost = torch.tensor([[1.0, 2.0, 0.5]], dtype=torch.float64)
    valid = torch.tensor([[True, True, False]])
    expect = -math.log(math.exp(-2.0) / (math.exp(-1.0) + math.exp(-2.0)))
    assert ds.plan_loss(cost, valid, torch.tensor([1]), 1.0).item() == pytest.approx(expect)


def linear_quadratic_problem(B=4, T=6, seed=0):
    g = torch.Generator().manual_seed(seed)
    A = torch.eye(4, dtype=torch.float64) + 0.1 * torch.randn(4, 4, generator=g, dtype=torch.float64)
    Bm = torch.randn(4, 2, generator=g, dtype=torch.float64)
    dyn = lambda x, u: (A @ x[..., None])[..., 0] + (Bm @ u[..., None])[..., 0]  # noqa: E731
    Q = torch.randn(B, T + 1, 6, 6, generator=g, dtype=torch.float64)
    Q = Q @ Q.transpose(-1, -2) / 6 + 0.5 * torch.eye(6, dtype=torch.float64)
    q = torch.randn(B, T + 1, 6, generator=g, dtype=torch.float64) * 3

    def cost(x, u, Q, q):  # sum_t 1/2 z_t'Q_t z_t + q_t'z_t, z_t = (x_t, u_t); *S dims broadcast
        z = torch.cat([x, torch.cat([u, torch.zeros_like(u[..., :1, :])], -2)], -1)
        S = x.dim() - 3
        Qv, qv = Q.reshape(B, *[1] * S, *Q.shape[1:]), q.reshape(B, *[1] * S, *q.shape[1:])
        return (0.5 * (z[..., None, :] @ Qv @ z[..., None])[..., 0, 0] + (qv * z).sum(-1)).sum(-1)

    x0 = torch.randn(B, 4, generator=g, dtype=torch.float64)
    lo, hi = torch.tensor([-0.5, -1.0], dtype=torch.float64), torch.tensor([0.5, 1.0], dtype=torch.float64)
    return dyn, cost, x0, Q, q, lo, hi


def test_kkt_gradients_linear_dynamics_with_active_bounds():
    dyn, cost, x0, Q, q, lo, hi = linear_quadratic_problem()
    B, T = x0.shape[0], 6
    g = torch.Generator().manual_seed(5)
    wx, wu = torch.randn(B, T + 1, 4, generator=g, dtype=torch.float64), torch.randn(B, T, 2, generator=g, dtype=torch.float64)
    u0 = torch.zeros(B, T, 2, dtype=torch.float64)
    x0r, qr, Qr = x0.clone().requires_grad_(), q.clone().requires_grad_(), Q.clone().requires_grad_()
    x, u_star, conv = ds.ilqr_solve(cost, dyn, x0r, u0, (Qr, qr), lo, hi, iters=20, tol=1e-10)
    assert conv.all()
    n_active = ((u_star - lo).abs() < 1e-8).sum() + ((hi - u_star).abs() < 1e-8).sum()
    assert n_active >= 5  # the check covers active bounds
    ((x * wx).sum() + (u_star * wu).sum()).backward()

    def loss(x0_, Q_, q_):  # re-solved from the solution: a few iterations reach the perturbed optimum
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
    lo, hi = torch.tensor(cfg.u_lower, dtype=torch.float64), torch.tensor(cfg.u_upper, dtype=torch.float64)
    cost_fn = stack_cost_fn(ctx)
    params = (w, ctx.preds, ctx.probs, ctx.goal, ctx.lanes)
    x, u, info = ds.ilqr(cost_fn, ds.Unicycle(DT), s0, torch.zeros(3, 6, 2, dtype=torch.float64), params, lo, hi, iters=50, tol=1e-11)
    assert info.converged.all()
    g = torch.Generator().manual_seed(3)
    wx, wu = torch.randn(3, 7, 4, generator=g, dtype=torch.float64), torch.randn(3, 6, 2, generator=g, dtype=torch.float64)
    return dict(cost_fn=cost_fn, s0=s0, u=u, params=params, lo=lo, hi=hi, wx=wx, wu=wu)


def _kkt_grads(P, exact=True):
    leaves = [P["s0"].clone().requires_grad_()] + [p.clone().requires_grad_() for p in P["params"]]
    x, u, _ = ds.ilqr_solve(P["cost_fn"], ds.Unicycle(DT), leaves[0], P["u"], tuple(leaves[1:]), P["lo"], P["hi"],
                            iters=30, tol=1e-11, exact=exact)
    return torch.autograd.grad((x * P["wx"]).sum() + (u * P["wu"]).sum(), leaves)


def test_kkt_gradients_unicycle_full_cost_match_finite_differences(unicycle_problem):
    P = unicycle_problem
    exact, gauss_newton = _kkt_grads(P), _kkt_grads(P, exact=False)

    def loss(i, v):
        leaves = [P["s0"], *P["params"]]
        leaves[i] = v
        x, u, info = ds.ilqr(P["cost_fn"], ds.Unicycle(DT), leaves[0], P["u"], tuple(leaves[1:]), P["lo"], P["hi"], iters=50, tol=1e-11)
        assert info.converged.all()
        return (x * P["wx"]).sum() + (u * P["wu"]).sum()

    # x_init, weights, predictions, goal, lanes
    for i, idx in [(0, [(b, j) for b in range(3) for j in range(4)]), (1, [(j,) for j in range(5)]),
                   (2, [(b, k, t, b % 2) for b in range(3) for k, t in ((0, 1), (2, 4))]),
                   (4, [(b, j) for b in range(3) for j in range(2)]), (5, [(b, 0, 8, 1) for b in range(3)])]:
        base = ([P["s0"], *P["params"]])[i]
        fd = torch.stack([central_fd(lambda v: loss(i, v), base, j, h=1e-4) for j in idx])  # h: above the solver's tolerance
        assert rel_err(torch.stack([exact[i][j] for j in idx]), fd) < 1e-4, i
        if i in (0, 2):  # without the dynamics' curvature the gradient is measurably wrong
            assert rel_err(torch.stack([gauss_newton[i][j] for j in idx]), fd) > 1e-3


def test_kkt_gradients_match_autograd_through_unrolled_solver(unicycle_problem):
    P = unicycle_problem
    kkt = _kkt_grads(P)
    leaves = [P["s0"].clone().requires_grad_()] + [p.clone().requires_grad_() for p in P["params"]]
    x, u, _ = ds.ilqr(P["cost_fn"], ds.Unicycle(DT), leaves[0], torch.zeros_like(P["u"]), tuple(leaves[1:]),
                      P["lo"], P["hi"], iters=20, tol=0.0)  # tol 0: every iteration is differentiated through
    unrolled = torch.autograd.grad((x * P["wx"]).sum() + (u * P["wu"]).sum(), leaves, allow_unused=True)
    for a, b in zip(unrolled, kkt):
        if b.abs().sum() > 0:
            assert rel_err(a, b) < 1e-8


def test_ilqr_descends_respects_bounds_and_flags_convergence():
    cfg = ds.Config()
    s0, goal, ctx = toy_scene()
    lo, hi = torch.tensor(cfg.u_lower, dtype=torch.float64), torch.tensor(cfg.u_upper, dtype=torch.float64)
    params = (ds.cost_weights(cfg, torch.float64), ctx.preds, ctx.probs, ctx.goal, ctx.lanes)
    u0 = torch.full((3, 6, 2), 3.0, dtype=torch.float64)  # far outside the box: clamped first
    for iters, tol in ((5, 0.05), (2, 0.05), (5, 1e-9)):
        x, u, info = ds.ilqr(stack_cost_fn(ctx), ds.Unicycle(DT), s0, u0, params, lo, hi, iters=iters, tol=tol)
        c = info.costs
        assert (c[:, 1:] <= c[:, :-1] * (1 + 1e-12) + 1e-12).all()  # the true cost never increases
        assert ((u >= lo) & (u <= hi)).all()
        assert torch.equal(info.converged, info.step_norm < tol)
        assert torch.allclose(x, ds.unicycle_rollout(s0, u, DT))  # the solution is dynamically consistent
    assert not info.converged.all() or info.iters.max() <= 5


def test_unconverged_scenarios_get_no_gradient():
    dyn, cost, x0, Q, q, lo, hi = linear_quadratic_problem()
    qr = q.clone().requires_grad_()
    x, u, conv = ds.ilqr_solve(cost, dyn, x0, torch.zeros(4, 6, 2, dtype=torch.float64), (Q, qr), lo, hi, iters=1, tol=1e-12)
    assert not conv.any()
    x.sum().backward()
    assert (qr.grad == 0).all()


@pytest.mark.parametrize("bad, match", [
    (dict(x_init=torch.zeros(3, 4, dtype=torch.float32)), "u_init"),  # dtype mismatch
    (dict(u_init=torch.zeros(2, 6, 2, dtype=torch.float64)), "u_init"),  # batch mismatch
    (dict(x_init=torch.tensor([[math.nan, 0, 0, 1]] * 3, dtype=torch.float64)), "x_init"),
    (dict(lo=torch.tensor([1.0, -1.0], dtype=torch.float64)), "lo"),
    (dict(params=(torch.full((5,), math.inf, dtype=torch.float64),)), r"params\[0\]"),
])
def test_controller_bad_input_names_the_argument(bad, match):
    args = dict(cost_fn=lambda x, u, w: (u**2).sum((-1, -2)), dynamics=ds.Unicycle(DT),
                x_init=torch.zeros(3, 4, dtype=torch.float64), u_init=torch.zeros(3, 6, 2, dtype=torch.float64),
                params=(torch.ones(5, dtype=torch.float64),), lo=torch.tensor([-0.7, -5.0], dtype=torch.float64),
                hi=torch.tensor([0.7, 4.0], dtype=torch.float64))
    args.update(bad)
    with pytest.raises(ValueError, match=match):
        ds.ilqr_solve(**args)


def test_planner_bad_input_names_the_argument():
    cfg = ds.Config()
    s0, goal, ctx = toy_scene()
    w = ds.cost_weights(cfg, torch.float64)
    with pytest.raises(ValueError, match="goal_state"):
        ds.plan(s0, ctx, goal[:2], w, cfg)
    with pytest.raises(ValueError, match="s0"):
        ds.plan(torch.full_like(s0, math.nan), ctx, goal, w, cfg)
