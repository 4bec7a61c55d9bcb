"""Every timing of the project, mpc.pytorch side by side, and the bounded LQR of
FreyJo/differentiable_nmpc (docs/performance.md): the median and IQR of --reps timed runs, each
after an untimed run, taking turns. mpc.pytorch, no dependency, is imported when its turn comes."""

from __future__ import annotations

import argparse
import contextlib
import functools
import importlib
import io
import itertools
import os
import pathlib
import statistics
import sys
import time
import warnings

import numpy as np
import scipy.linalg
import scipy.optimize
import torch
import torch.nn.functional as F
import torch.utils.benchmark as benchmark

import data_synth
import diffstack
from diffstack import Config, Predictor, Unicycle, ilqr, ilqr_solve, plan_candidates, pred_loss
from diffstack import run_stack, scene_plan, unicycle_jacobians, unicycle_rollout
from experiments import closed_loop_scenes, simulate, stack_policy
from lab.cli import add_shared_options, bounded, check_writable, machine
from lab.runs import ROOT, command_line, load_json, one_line, write_json
from lab.stats import markdown_table
from specs import CLOSED_LOOP_METHODS, DIFFSTACK
from train import alphas

DATA_CACHE = ROOT / "data_cache"
QUICK = dict(batch=16, reps=2)  # --quick: seconds, not minutes


# ---- 1. Measuring ------------------------------------------------------------------------------
def timed(fns: dict, reps, threads, dtype="f32", batch=None, notes=None) -> tuple[list, dict]:
    """fns {key: (name, callable)} taking turns at `threads` threads, each timed run after an
    untimed one (blocked_autorange's sizing): rows, Measurements by key."""
    timers = {
        key: benchmark.Timer("fn()", globals={"fn": fn}, description=key, num_threads=threads)
        for key, (_, fn) in fns.items()
    }
    # reps rounds, the timers taking turns in each
    runs = [[t.blocked_autorange(min_run_time=0) for t in timers.values()] for _ in range(reps)]
    m = {key: benchmark.Measurement.merge(ms)[0] for key, ms in zip(timers, zip(*runs))}
    rows = [
        figure(key, name, m[key].times, threads, dtype, batch, (notes or {}).get(key, ""))
        for key, (name, _) in fns.items()
    ]
    return rows, m


def figure(key: str, name: str, times, threads: int, dtype="f32", batch=None, note="") -> dict:
    """One row of the results: median and IQR (ms, interpolated as Measurement.iqr) of times (s)."""
    q1, q3 = statistics.quantiles(times, n=4, method="inclusive")[::2] if len(times) > 1 else [0, 0]
    row = dict(key=key, benchmark=name, dtype=dtype, threads=threads, batch=batch)
    median, iqr = 1e3 * statistics.median(times), 1e3 * (q3 - q1)
    return dict(row, median_ms=median, iqr_ms=iqr, runs=len(times), note=note)


# ---- 2. The problem: unicycle tracking, shared with mpc.pytorch ---------------------------------
def tracking_problem(B=256, T=6, dtype=torch.float64, seed=0, device="cpu"):
    """B unicycle tracking problems: the reference rolled out from smooth random controls (some
    outside the box), the start perturbed; drawn on the CPU, then moved to `device`."""
    g = torch.Generator().manual_seed(seed)

    def U(lo, hi, *shape):
        return lo + (hi - lo) * torch.rand(*shape, generator=g, dtype=dtype)

    x0 = torch.stack([U(-20, 20, B), U(-20, 20, B), U(-torch.pi, torch.pi, B), U(2.0, 15.0, B)], -1)
    tt = torch.arange(T, dtype=dtype) / (T - 1)
    yaw_rate = U(-0.5, 0.5, B, 1) + U(-0.6, 0.6, B, 1) * tt
    u_ref = torch.stack([yaw_rate, U(-3.0, 2.5, B, 1) + U(-3.5, 3.5, B, 1) * tt], -1)
    x_ref = unicycle_rollout(x0, u_ref, 0.5)  # (B, T+1, 4)
    noise = torch.tensor([1.0, 1.0, 0.15, 1.0], dtype=dtype)
    x_init = x0 + torch.randn(B, 4, generator=g, dtype=dtype) * noise
    Q, R = torch.tensor([1.0, 1.0, 1.0, 0.2], dtype=dtype), torch.tensor([0.5, 0.1], dtype=dtype)
    lo, hi = (torch.tensor(b, dtype=dtype) for b in (Config().u_lower, Config().u_upper))
    P = dict(x_init=x_init, x_ref=x_ref, u_ref=u_ref, Q=Q, R=R, lo=lo, hi=hi)
    return {k: v.to(device) for k, v in dict(P, u_init=u_ref.clamp(lo, hi)).items()}


class TrackingCost:
    """sum_t 1/2 |x_t - r_t|^2_Q + 1/2 |u_t - ur_t|^2_R -> (B,), Q, R shared or per problem (so that
    the solver sets converged ones aside); its expansion in closed form, as mpc.pytorch's."""

    def __call__(self, x, u, x_ref, u_ref, Q, R):
        Q, R = (Q[:, None], R[:, None]) if Q.dim() == 2 else (Q, R)
        dx, du = x - x_ref, u - u_ref
        return 0.5 * (dx**2 * Q).sum((-1, -2)) + 0.5 * (du**2 * R).sum((-1, -2))

    def expansion(self, x, u, x_ref, u_ref, Q, R):
        """Gradient (B, T+1, 6) and block Hessian (B, T+1, 6, 6), the last control a zero pad."""
        g = torch.cat([(x - x_ref) * Q[:, None], F.pad((u - u_ref) * R[:, None], (0, 0, 0, 1))], -1)
        R_pad = F.pad(R[:, None].expand(*u.shape), (0, 0, 0, 1))
        return g, torch.diag_embed(torch.cat([Q[:, None].expand(*x.shape), R_pad], -1))


def ours_solve(P, x_init, x_ref, iters, eps):
    """P solved by our controller: x (B, T+1, 4), u (B, T, 2)."""
    params = (x_ref, P["u_ref"], P["Q"].expand(len(x_init), 4), P["R"].expand(len(x_init), 2))
    solve = functools.partial(ilqr_solve, iters=iters, tol=eps, refine=0)  # iLQR alone, as mpc
    return solve(TrackingCost(), Unicycle(0.5), x_init, P["u_init"], params, P["lo"], P["hi"])[:2]


def solver_runs(P, solve, iters, eps):
    """(forward, backward): a solve from leaves requiring grad; the final positions' backward."""
    x_init, x_ref = P["x_init"].clone().requires_grad_(), P["x_ref"].clone().requires_grad_()
    loss = solve(P, x_init, x_ref, iters, eps)[0][:, -1, :2].sum()
    return (lambda: solve(P, x_init, x_ref, iters, eps)), (lambda: loss.backward(retain_graph=True))


# ---- 3. Our modules ----------------------------------------------------------------------------
def bench_controller(B, dtype, reps, threads, device, key="", iters=5, tol=0.01) -> list:
    """iLQR forward and KKT backward on the tracking problems."""
    P = tracking_problem(B, dtype=dtype, device=device)
    forward, backward = solver_runs(P, ours_solve, iters, tol)
    dt = str(dtype).replace("torch.float", "f")
    fns = {
        f"ilqr_forward_{dt}{key}": (f"iLQR forward ({iters} iterations, tol {tol})", forward),
        f"kkt_backward_{dt}{key}": ("KKT backward", backward),
    }
    return timed(fns, reps, threads, dt, B)[0]


def bench_modules(batch, cfg: Config, reps, threads) -> list:
    """Candidates; the predictor's training iteration and eval forward; a DiffStack training step
    (RL), the scene plan it reuses, and its parts as laps: predict, plan, control, backward."""
    torch.manual_seed(0)
    model = Predictor(cfg).to(batch.agent_hist.device, batch.agent_hist.dtype)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    steps = itertools.count()  # the KL and logit-clip schedules see a growing step, as in training

    def train_iteration():
        it = next(steps)
        model.train()
        loss, _ = pred_loss(model(batch, use_posterior=True, step=it), batch, it, cfg)
        opt.zero_grad()
        loss.mean().backward()
        opt.step()

    def eval_forward():
        model.eval()
        with torch.no_grad():
            model(batch, use_posterior=False)

    torch.manual_seed(0)
    stack = Predictor(cfg).to(batch.agent_hist.device)
    a1, a2, a3 = alphas(DIFFSTACK, "rl", cfg)
    scene, solve, laps = scene_plan(batch, cfg), diffstack.ilqr_solve, []
    scene_cost = functools.partial(scene_plan, batch, cfg)

    def step():
        t, clock = {}, [time.perf_counter()]

        def lap(name):
            clock.append(time.perf_counter())
            t[name] = clock[-1] - clock[-2]

        hook = stack.register_forward_hook(lambda *_: lap("predict"))
        diffstack.ilqr_solve = lambda *a, **kw: lap("plan") or solve(*a, **kw)
        try:
            out = run_stack(batch, stack, DIFFSTACK, cfg, "rl", step=0, train=True, scene=scene)
        finally:
            diffstack.ilqr_solve = solve
            hook.remove()
        lap("control")
        (a1 * out.l_pred.mean() + a2 * out.l_plan.mean() + a3 * out.l_ctr.mean()).backward()
        lap("backward")
        laps.append(t)

    s0, n = batch.ego_hist[:, -1], 24 * cfg.max_goal_lanes  # 8 accelerations x 3 offsets a lane
    what = f"K = {cfg.pred_modes}, decoder {cfg.pred_dec_hidden}"
    plan = functools.partial(plan_candidates, s0, batch.goal, batch.lanes, batch.lanes_mask, cfg)
    groups = (  # measured group by group, each taking turns
        {"candidates": (f"planner: candidates (up to {n} per scenario)", plan)},
        {
            "predictor_train": (f"predictor: training iteration ({what})", train_iteration),
            "predictor_eval": ("predictor: eval forward", eval_forward),
        },
        {
            "stack_step": ("DiffStack training step (RL)", step),
            "stack_scene_plan": ("scene plan (once per data set in training)", scene_cost),
        },
    )
    rows = [r for fns in groups for r in timed(fns, reps, threads, batch=len(batch))[0]]
    for part in ("predict", "plan", "control", "backward"):
        name, times = f"DiffStack step: {part} (perf_counter lap)", [t[part] for t in laps[1:]]
        rows.append(figure(f"stack_{part}", name, times, threads, batch=len(batch)))
    return rows


# ---- 4. The peer: mpc.pytorch (`mpc` 0.0.6), side by side ------------------------------------
PEER_VENV = "python3 -m venv /tmp/peers && /tmp/peers/bin/pip install -r requirements.txt"
MPC_QUIET = dict(exit_unconverged=False, verbose=-1)  # mpc.pytorch: no assert, no printing


def import_peer(what: str, hint=True):
    """mpc.pytorch's module, or None after one line saying why and (hint) how to install it."""
    try:
        return importlib.import_module("mpc.mpc")
    except ImportError:
        why = "not installed"
    except Exception as e:  # a peer built for another torch may fail any way on import
        why = f"import failed: {type(e).__name__}: {' '.join(str(e).split())}"
    install = f"{PEER_VENV} && /tmp/peers/bin/pip install --no-deps mpc==0.0.6"
    how = f". To run it: {install}, then /tmp/peers/bin/python -m lab.bench" if hint else ""
    print(f"mpc.pytorch: {why}, {what} skipped{how}")


class UnicycleDx(torch.nn.Module):
    """The unicycle as mpc.pytorch takes it, with the closed-form Jacobians (ANALYTIC)."""

    def forward(self, x, u):
        return Unicycle(0.5)(x, u)  # the unchecked step our solver uses too, so both pay the same

    def grad_input(self, x, u):
        return unicycle_jacobians(x, u, 0.5)


def mpc_solve(P, x_init, x_ref, iters, eps):
    """One mpc.MPC solve with our solver's settings: x (B, T+1, 4), u (B, T, 2). T+1 stages costing
    1/2 tau' C tau + c' tau; the last control, idle, has reference 0 (stays 0, costs nothing)."""
    mpc_lib = importlib.import_module("mpc.mpc")
    B, T1, _ = x_ref.shape
    C = torch.diag(torch.cat([P["Q"], P["R"]])).expand(T1, B, 6, 6)
    c = torch.cat([-P["Q"] * x_ref, -P["R"] * F.pad(P["u_ref"], (0, 0, 0, 1))], -1)
    u0 = F.pad(P["u_init"], (0, 0, 0, 1)).transpose(0, 1).contiguous()
    lo, hi = (P[k].expand(T1, B, 2).contiguous() for k in ("lo", "hi"))
    opts = dict(lqr_iter=iters, eps=eps, n_batch=B, max_linesearch_iter=5, **MPC_QUIET)
    ctrl = mpc_lib.MPC(4, 2, T1, lo, hi, u_init=u0, **opts)
    x, u, _ = ctrl(x_init, mpc_lib.QuadCost(C, c.transpose(0, 1)), UnicycleDx())
    return x.transpose(0, 1), u.transpose(0, 1)[:, :-1]


def compare_mpc(B=256, threads=(1, 2), reps=5) -> dict | None:
    """Ours against mpc.pytorch on tracking_problem(B), float64, taking turns; speedup (its time /
    ours): 5 iterations, fewest threads."""
    if import_peer("comparison (speedup_vs_mpc_pytorch: null)") is None:
        return None
    P, rows, speedups = tracking_problem(B), [], []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # mpc 0.0.6 uses deprecated torch APIs
        for nt, (iters, eps) in itertools.product(sorted(threads), ((5, 0.01), (10, 1e-3))):
            fns = {}
            for who, solve in (("mpc", mpc_solve), ("ours", ours_solve)):
                for part, f in zip(("fwd", "bwd"), solver_runs(P, solve, iters, eps)):
                    name = f"{who} {part}, {iters} iterations, tol {eps}"
                    fns[f"{who}_{part}_{iters}it"] = (name, f)
            r, m = timed(fns, reps, nt, "f64", B)
            mpc_fwd, mpc_bwd, ours_fwd, ours_bwd = (v.median for v in m.values())
            speedups.append((mpc_fwd + mpc_bwd) / (ours_fwd + ours_bwd))
            r[2]["note"] = f"speed-up fwd {mpc_fwd / ours_fwd:.2f}x, fwd+bwd {speedups[-1]:.2f}x"
            rows += r
    verdict = f"mpc.pytorch time / ours, fwd+bwd, 5 iterations, B = {B}: {speedups[0]:.2f}x"
    return dict(figures=rows, speedup=speedups[0], verdict=verdict)


# ---- 5. The bounded LQR of FreyJo/differentiable_nmpc (Table 1 of its README) -------------------
# 128 problems x' = A x + B u + b (8 states, 4 controls, horizon 20), stage cost 1/2 tau' H tau,
# |u| <= umax; loss sum u_0. mpc.pytorch's u_20 is idle, ours costs x_20 by H: the same problem.
LQR_UMAX = (1e4, 1.0)  # the two configurations, in the order the reference script draws them
LQR_N, LQR_NX, LQR_NU, LQR_BATCH = 20, 8, 4, 128
LQR_SETTINGS = {  # ours at ilqr's defaults; until the step is below 1e-6; 2 iterations, then
    "defaults": dict(iters=5, tol=0.05),  # diffstack.active_set until the step is below 1e-6
    "tight": dict(iters=100, tol=1e-6),
    "active set": dict(iters=2, tol=1e-6, refine=100),
}
LQR_MPC = dict(lqr_iter=100, eps=1e-6)  # mpc.pytorch as the reference script runs it
LQR_CONVERGED = 1e-6  # a solve has converged when no control would move by more (kkt_residual)
LQR_PUBLISHED = (  # the README's rows (mpc.pytorch's: its multiples of acados' times)
    "Published (i7-8665U laptop, up to 4 threads; not measured here): solve + gradient at umax "
    "1e4 / 1.0: acados 36.6 / 58.4 ms, mpc.pytorch 118.2 / 25 754 ms"
)


def bounded_lqr_problem(umax: float, batch=LQR_BATCH, seed=42, horizon=LQR_N) -> dict:
    """The problems for umax as the reference script draws them (A, B, b, x0 twice, per umax)."""
    if umax not in LQR_UMAX:
        raise ValueError(f"umax: {umax} is none of the benchmark's {LQR_UMAX}")
    rng = np.random.RandomState(seed)
    for _ in LQR_UMAX[: LQR_UMAX.index(umax) + 1]:  # the draws up to umax's
        A = np.eye(LQR_NX) + 0.2 * rng.randn(LQR_NX, LQR_NX)
        B, b = rng.randn(LQR_NX, LQR_NU), rng.randn(LQR_NX)
        rng.randn(batch, LQR_NX)  # the timing run's x0
        x0 = rng.randn(batch, LQR_NX)
    P = dict(A=A, B=B, b=b, H=np.eye(LQR_NX + LQR_NU), x_init=x0, lo=-umax * np.ones(LQR_NU))
    P = dict(P, hi=-P["lo"], u_init=np.zeros((batch, horizon, LQR_NU)))
    return {k: torch.tensor(v, dtype=torch.float64) for k, v in P.items()}


class Affine:
    """x_{t+1} = A x_t + B u_t + b for x (..., n), u (..., m), its Jacobians in closed form."""

    def __init__(self, A, B, b):
        self.A, self.B, self.b = A, B, b

    def __call__(self, x, u):
        return x @ self.A.mT + u @ self.B.mT + self.b

    def jacobians(self, x, u):  # x (B, T, n) -> (B, T, n, n), (B, T, n, m)
        n, m = self.B.shape
        return self.A.expand(*x.shape[:-1], n, n), self.B.expand(*x.shape[:-1], n, m)


class StageQuadratic:
    """sum_{t<N} 1/2 tau_t' H tau_t + 1/2 x_N' H_xx x_N -> (B,), its expansion in closed form."""

    def __call__(self, x, u, H):
        n = x.shape[-1]
        tau = torch.cat([x[:, :-1], u], -1)  # (B, N, n+m)
        stages = 0.5 * torch.einsum("bti,ij,btj->b", tau, H, tau)
        return stages + 0.5 * torch.einsum("bi,ij,bj->b", x[:, -1], H[:n, :n], x[:, -1])

    def expansion(self, x, u, H):
        """Gradient (B, N+1, n+m) and Hessian (B, N+1, n+m, n+m); the last control a zero pad."""
        H_sym = (H + H.mT) / 2
        z = torch.cat([x, F.pad(u, (0, 0, 0, 1))], -1)  # (B, N+1, n+m)
        return z @ H_sym, H_sym.expand(*z.shape[:-1], *H.shape)


def costates(g_x, A):
    """lambda_N = g_x[N], lambda_t = g_x[t] + A_t' lambda_{t+1} -> (B, N+1, n), lambda_0 .. N."""
    lam = [g_x[:, -1]]
    for t in reversed(range(A.shape[1])):
        lam.append(g_x[:, t] + (A[:, t].mT @ lam[-1][..., None])[..., 0])
    return torch.stack(lam[::-1], 1)


class AffineLQR(torch.autograd.Function):
    """diffstack.ilqr on the bounded LQR, differentiable in x_init, A, B, b and H: diffstack.py §5's
    KKT backward, and the dynamics' gradients from the costates (Amos et al. 2018, eq. 8)."""

    @staticmethod
    def forward(ctx, settings, lo, hi, u_init, x_init, A, B, b, H):
        with torch.no_grad():
            (cost, dynamics), settings = (StageQuadratic(), Affine(A, B, b)), dict(settings)
            refine = settings.pop("refine", 0)  # active_set after ilqr where a row asks for it
            x, u, info = ilqr(cost, dynamics, x_init, u_init, (H,), lo, hi, **settings)
            a = (lo, hi, info, settings.get("tol", 0.05), refine)
            x, u, info = diffstack.active_set(cost, dynamics, x, u, (H,), *a)
        ctx.save_for_backward(x, u, info.converged, lo.expand_as(u), hi.expand_as(u), A, B, b, H)
        ctx.mark_non_differentiable(info.converged, info.iters)
        return x, u, info.converged, info.iters

    @staticmethod
    def backward(ctx, grad_x, grad_u, _, __):
        x, u, converged, lo, hi, A, B, b, H = ctx.saved_tensors
        n = x.shape[-1]
        free = ((u - lo).abs() > 1e-8) & ((hi - u).abs() > 1e-8)  # the active set, held
        keep = converged.to(x.dtype)[:, None, None]
        cost, dynamics = StageQuadratic(), Affine(A, B, b)
        g, Hz = cost.expansion(x, u, H)  # (B, N+1, n+m), (B, N+1, n+m, n+m)
        A_t, B_t = dynamics.jacobians(x[:, :-1], u)
        rhs = torch.cat([grad_x * keep, F.pad(grad_u * keep, (0, 0, 0, 1))], -1)
        k, K, _, p0 = diffstack.lqr_backward(A_t, B_t, Hz, rhs, free=free)
        # the backward LQR's solution from dx_0 = 0: du = k + K dx, dx_{t+1} = A dx_t + B du_t
        linear, unbounded = Affine(A, B, 0 * b), torch.full_like(u, float("inf"))
        dx, du = diffstack.closed_loop_rollout(linear, 0 * x, 0 * u, k, K, -unbounded, unbounded)
        d = torch.cat([dx, F.pad(du, (0, 0, 0, 1))], -1)  # (B, N+1, n+m)
        lam = costates(g[..., :n], A_t)[:, 1:]  # (B, N, n): lambda_1 .. lambda_N
        dlam = costates(((Hz @ d[..., None])[..., 0] + rhs)[..., :n], A_t)[:, 1:]
        (grad_H,) = diffstack.params_gradients(cost, x, u, (H.detach().requires_grad_(),), dx, du)
        # lambda, dlambda: the forward problem's and the backward LQR's costates; summed over b, t:
        # dL/dA = sum_t dlambda_{t+1} x_t' + lambda_{t+1} dx_t',  dL/db = sum_t dlambda_{t+1}
        # dL/dB = sum_t dlambda_{t+1} u_t' + lambda_{t+1} du_t'
        outer = functools.partial(torch.einsum, "bti,btj->ij")
        grad_A = outer(dlam, x[:, :-1]) + outer(lam, dx[:, :-1])
        grad_B = outer(dlam, u) + outer(lam, du)
        return None, None, None, None, p0, grad_A, grad_B, dlam.sum((0, 1)), grad_H


def condensed_qp(P) -> tuple:
    """The problems in the controls alone, U = (u_0 .. u_{N-1}): 1/2 U'M U + q'U + const -> M, q."""
    cost, dynamics = StageQuadratic(), Affine(P["A"], P["B"], P["b"])
    N = P["u_init"].shape[1]

    def of(U, x0):  # one problem's cost
        u = U.reshape(1, N, LQR_NU)
        return cost(diffstack.rollout(dynamics, x0[None], u), u, P["H"])[0]

    U0 = torch.zeros(N * LQR_NU, dtype=torch.float64)
    M = torch.func.hessian(of)(U0, P["x_init"][0])
    return M, torch.func.vmap(torch.func.grad(of), (None, 0))(U0, P["x_init"])


def kkt_residual(u, M, q, lo, hi):
    """How far controls u (batch, N, m) are from the box QP's solution (batch,): the largest move
    of a projected coordinate-Newton step."""
    U = u.reshape(len(u), -1)
    grad = U @ M + q  # (batch, N m), M symmetric; by diag M as d/du_0 is ~1e5 d/du_19 here
    lo, hi = lo.repeat(u.shape[1]), hi.repeat(u.shape[1])
    return (U - (U - grad / M.diagonal()).clamp(lo, hi)).abs().amax(-1)


def reference_controls(M, q, lo, hi) -> torch.Tensor:
    """The box QP solved another way: scipy's bounded-variable least squares on 1/2 ||L'U + L^-1
    q||^2, M = L L' (its default cap of N m iterations stops it short here)."""
    L = scipy.linalg.cholesky(M.numpy(), lower=True)
    N = len(M) // len(lo)
    bounds = (lo.repeat(N).numpy(), hi.repeat(N).numpy())
    U = []
    for qi in q.numpy():
        b = -scipy.linalg.solve_triangular(L, qi, lower=True)
        res = scipy.optimize.lsq_linear(L.T, b, bounds, "bvls", tol=1e-14, max_iter=10_000)
        if res.status <= 0:
            raise RuntimeError(f"the reference solver stopped short: {res.message}")
        U.append(res.x)
    return torch.tensor(np.array(U)).reshape(len(U), N, len(lo))


def lqr_args(P, grad):
    """The parameters (x_init, A, B, b, H); with grad, fresh leaves requiring it."""
    args = [P[k] for k in ("x_init", "A", "B", "b", "H")]
    return [a.detach().clone().requires_grad_() for a in args] if grad else args


def ours_lqr(P, settings, grad=False):
    """Our solve: x (batch, N+1, n), u (batch, N, m), iterations (batch,), the parameters."""
    args = lqr_args(P, grad)
    x, u, _, iters = AffineLQR.apply(settings, P["lo"], P["hi"], P["u_init"], *args)
    return x, u, iters, args


def mpc_lqr(P, grad=False, **settings):
    """mpc.pytorch's solve: x, u (21st control idle), iterations (LQR passes but the last)."""
    mpc_lib = importlib.import_module("mpc.mpc")
    AffineDynamics = importlib.import_module("mpc.dynamics").AffineDynamics
    B, T1 = len(P["x_init"]), LQR_N + 1
    x_init, *dynamics, H = args = lqr_args(P, grad)
    lo, hi = (P[k].expand(T1, B, LQR_NU).contiguous() for k in ("lo", "hi"))
    opts = dict(backprop=grad, n_batch=B, **settings, **MPC_QUIET)
    ctrl = mpc_lib.MPC(LQR_NX, LQR_NU, T1, lo, hi, **opts)
    passes, subproblem = [], ctrl.solve_lqr_subproblem
    ctrl.solve_lqr_subproblem = lambda *a, **kw: passes.append(1) or subproblem(*a, **kw)
    cost = mpc_lib.QuadCost(H, torch.zeros(LQR_NX + LQR_NU, dtype=torch.float64))
    with contextlib.redirect_stdout(io.StringIO()):  # its inner QP's "did not converge" lines
        x, u, _ = ctrl(x_init, cost, AffineDynamics(*dynamics))
    return x.transpose(0, 1), u.transpose(0, 1), len(passes) - 1, args


def bounded_lqr_at(umax, batch, reps, solvers) -> tuple[list, list, dict]:
    """Each solver {name: (settings, solve)} at umax checked, then timed: rows, entries, grads."""
    P = bounded_lqr_problem(umax, batch)
    M, q = condensed_qp(P)
    ref = reference_controls(M, q, P["lo"], P["hi"])
    fns, notes, entries, grads = {}, {}, {}, {}
    for n, (s, f) in solvers.items():
        _, u, iters, args = f(P, grad=True)
        u = u[:, :LQR_N]  # mpc.pytorch's idle 21st control dropped
        u[:, 0].sum().backward()
        grads[n] = torch.cat([a.grad.flatten() for a in args[1:]])
        iters = torch.as_tensor(iters).double()
        med, most = iters.median().item(), iters.max().item()
        converged = int((kkt_residual(u.detach(), M, q, P["lo"], P["hi"]) < LQR_CONVERGED).sum())
        key = "lqr_" + n.replace(".", "_").replace(", ", "_") + f"_umax{umax:g}"
        e = dict(solver=n, settings=s, iterations_median=med, iterations_max=most)
        e.update(converged=converged, max_du=(u.detach() - ref).abs().max().item())
        entries[key] = dict(e, umax=umax, batch=batch)
        what = f"bounded LQR umax {umax:g}: {n} forward"
        fns[key + "_fwd"] = (what, functools.partial(f, P))

        def with_grad(f=f):  # and the gradient of sum u_0: "solution + adjoint sensitivities"
            f(P, grad=True)[1][:, 0].sum().backward()

        fns[key + "_fwd_bwd"] = (f"{what} + backward", with_grad)
        notes[key + "_fwd"] = f"iterations {med:g} / {most:g}, converged {converged} / {batch}"
    rows, m = timed(fns, reps, 1, "f64", batch, notes)
    for key, e in entries.items():
        fwd, both = m[key + "_fwd"].median, m[key + "_fwd_bwd"].median
        e.update(forward_ms=1e3 * fwd, forward_backward_ms=1e3 * both)
        e["us_per_problem_stage"] = 1e6 * both / (batch * LQR_N)
    return rows, list(entries.values()), grads


def compare_bounded_lqr(B, reps, quick=False, hint=True) -> dict:
    """The bounded LQR at one thread, the published size (--quick: B, 20 iterations at most):
    figures, verdict, doc; gradients compared where all converged."""
    batch, cap = (B, 20) if quick else (LQR_BATCH, 10**9)
    solvers = {}
    for k, s in LQR_SETTINGS.items():
        s = dict(s, iters=min(s["iters"], cap))
        solvers[f"diffstack, {k}"] = (s, functools.partial(ours_lqr, settings=s))
    if import_peer("its bounded-LQR rows (gradient_vs_mpc: {})", hint) is not None:
        s = dict(LQR_MPC, lqr_iter=min(LQR_MPC["lqr_iter"], cap))
        solvers["mpc.pytorch"] = (s, functools.partial(mpc_lqr, **s))
    torch.set_num_threads(1)
    rows, table, gradient = [], [], {}
    verdict = f"bounded LQR: converged = no control moves by more than {LQR_CONVERGED:g}"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # mpc 0.0.6 uses deprecated torch APIs
        for umax in LQR_UMAX:
            r, entries, grads = bounded_lqr_at(umax, batch, min(reps, 3), solvers)
            rows, table = rows + r, table + entries
            if "mpc.pytorch" in grads:
                pair = ("diffstack, active set", "mpc.pytorch")
                conv = [e["converged"] for e in entries if e["solver"] in pair]
                ours, mpc = (grads[name] for name in pair)
                rel = ((ours - mpc).norm() / mpc.norm()).item() if conv == [batch] * 2 else None
                gradient[f"{umax:g}"] = dict(relative_difference=rel, converged=conv)
                rel = "n/a (not all converged)" if rel is None else f"{rel:.1e}"
                verdict += f"; umax {umax:g}: gradient vs mpc.pytorch's, relative difference {rel}"
    doc = dict(table=table, gradient_vs_mpc=gradient)
    return dict(figures=rows, verdict=f"{verdict}\n{LQR_PUBLISHED}", doc=doc)


# ---- 6. Running: the table, the JSON file, the command line -------------------------------------
def print_results(title: str, rows, peers=()) -> None:
    """Our figures and the peers' as one markdown table under a title, then the peers' verdicts."""
    lines = []
    for r in rows + [r for p in peers for r in p["figures"]]:
        med, iqr = (f"{v:.1f}" if v < 100 else f"{v:.0f}" for v in (r["median_ms"], r["iqr_ms"]))
        first = [r["benchmark"], "" if r["batch"] is None else str(r["batch"]), r["dtype"]]
        lines.append(first + [str(r["threads"]), med, iqr, str(r["runs"]), r["note"]])
    head = ["benchmark", "B", "dtype", "threads", "median (ms)", "IQR (ms)", "runs", "note"]
    print(f"\n{title}; median and IQR (ms) of the timed runs\n{markdown_table(head, lines)}")
    print(*(p["verdict"] for p in peers), sep="\n")


def run(threads=(1, 2), reps=5, B=256, quick=False, closed_loop=True, device=torch.device("cpu")):
    """Every benchmark -> the JSON document; off the CPU, without the closed loop and the peers."""
    if quick:  # a small dataset in memory: nothing written to the cache
        data = data_synth.make_dataset(max(2 * B, 64), seed=0)
    else:
        data = data_synth.load_or_generate(max(2000, 2 * B), seed=0, cache_dir=DATA_CACHE)
    batch, cfg, rows = data.train[:B].to(device=device), Config(), []  # 85 % of the samples train
    for nt in threads:
        torch.set_num_threads(nt)  # the untimed set-up too; the Timers set it for every run
        print(f"threads {nt}: controller, planner, predictor, training step", file=sys.stderr)
        for dtype in (torch.float64, torch.float32):
            rows += bench_controller(B, dtype, reps, nt, device)
        rows += bench_modules(batch, cfg, reps, nt)
    total = {}  # what one more problem costs the controller (ms, the slope)
    for b in (B, 2 * B) if quick else (1024, 4096):
        rows += bench_controller(b, torch.float64, min(reps, 3), 1, device, f"_B{b}")
        total[b] = rows[-2]["median_ms"] + rows[-1]["median_ms"]
    if closed_loop and device.type == "cpu":  # log replay with each stack of Table 5, one thread
        n, sim_time, cl_reps = (2, 2.0, 1) if quick else (100, 10.0, min(reps, 3))
        if not quick:
            data = data_synth.load_or_generate(10000, seed=0, cache_dir=DATA_CACHE)
        scenes = closed_loop_scenes(data.val_scenes, cfg, sim_time)[:n]
        torch.manual_seed(0)
        model, fns = Predictor(cfg), {}  # untrained
        for m in CLOSED_LOOP_METHODS:
            policy = stack_policy(model if m.predictor == "learned" else None, m, cfg)
            name = f"closed loop, {m.name} ({len(scenes)} scenes x {sim_time:g} s)"
            replay = functools.partial(simulate, scenes, policy, cfg, sim_time)
            fns["closed_loop_" + m.name.lower().replace(" ", "_")] = (name, replay)
        rows += timed(fns, cl_reps, 1)[0]
    (lo, t_lo), (hi, t_hi) = total.items()
    mpc = lqr = None
    if device.type == "cpu":
        mpc = compare_mpc(B, threads, reps)
        lqr = compare_bounded_lqr(B, reps, quick, hint=False)
    else:
        print(f"--device {device}: the closed loop and mpc.pytorch (CPU only) are left out")
    peers, meta = [p for p in (mpc, lqr) if p], run_meta(threads, reps, B, quick, device)
    title = f"DiffStack benchmarks on {meta['device_name']}, B = {B}, torch {torch.__version__}"
    print_results(title, rows, peers)
    step = [r["median_ms"] for r in rows if r["key"] == "stack_step" and r["threads"] == 1]
    return dict(
        stack_step_ms_1thread=(step or [None])[0],  # None when --threads leaves out 1
        speedup_vs_mpc_pytorch=mpc and mpc["speedup"],
        controller_ms_per_problem=(t_hi - t_lo) / (hi - lo),
        meta=meta,
        figures=rows + (lqr["figures"] if lqr else []),
        mpc_pytorch=mpc and {"figures": mpc["figures"]},
        bounded_lqr=lqr and lqr["doc"],
    )


def run_meta(threads, reps, batch, quick, device) -> dict:
    """Where and how the figures were taken."""
    gpu = f", {torch.cuda.get_device_name(device)}" if device.type == "cuda" else ""
    where = dict(date=time.strftime("%Y-%m-%d %H:%M"), machine=machine(), cores=os.cpu_count())
    how = dict(threads=list(threads), reps=reps, batch=batch, quick=quick, device=str(device))
    return dict(where, torch=torch.__version__, **how, device_name=f"{device}{gpu}")


def check_args(args) -> None:
    """Before the minutes of work, ValueError naming the bad --device or --json."""
    if args.device.type == "mps":
        raise ValueError("argument --device: mps has no float64, which the solvers here use")
    if args.json is None:
        return
    if args.json.is_dir():
        raise ValueError(f"argument --json: {args.json} is a folder, expected a file path")
    if args.json.exists() and not args.overwrite:
        command = ""  # this command's (or bench.py's, before the move into lab/)
        with contextlib.suppress(ValueError, KeyError, TypeError):
            command = str(load_json(args.json, "--json")["meta"]["command"])
        if not command.startswith(("python -m lab.bench", "python bench.py")):
            raise ValueError(
                f"argument --json: {args.json} exists and is no lab.bench result; to keep it, "
                "name another file; to replace it, add --overwrite"
            )
    check_writable(args.json.parent, "argument --json")


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser("python -m lab.bench", description=__doc__.split(" (")[0])
    n = functools.partial(bounded, int, 1)
    threads = "torch thread counts (default 1 2)"
    ap.add_argument("--threads", type=n(256, "--threads"), nargs="+", default=[1, 2], help=threads)
    reps = "timed runs per figure (default 5; closed loop at most 3; --quick 2)"
    ap.add_argument("--reps", type=n(10_000, "--reps"), help=reps)
    ap.add_argument("--batch", type=n(10**6, "--batch"), help="B (default 256; --quick 16)")
    ap.add_argument("--json", type=pathlib.Path, help="also write every figure to this JSON file")
    ap.add_argument("--skip-closed-loop", action="store_true", help="leave out the closed loop")
    ap.add_argument("--quick", action="store_true", help="tiny sizes and reps: under a minute")
    ap.add_argument("--bounded-lqr", action="store_true", help="only the bounded LQR benchmark")
    add_shared_options(
        ap,
        overwrite="let --json replace a file that is not an earlier result of this command",
        device="where our modules run (cpu, cuda, cuda:N); elsewhere without closed loop and peers",
    )
    args = ap.parse_args(argv)
    reps = args.reps or (QUICK["reps"] if args.quick else 5)
    B = args.batch or (QUICK["batch"] if args.quick else 256)
    before = torch.get_num_threads()
    try:  # the project's errors and a file's (the data cache, --json) as one line
        with one_line(ap):
            check_args(args)
            if args.bounded_lqr:
                lqr = compare_bounded_lqr(B, reps, args.quick)
                print_results("Bounded LQR", [], [lqr])
                batch = B if args.quick else LQR_BATCH
                meta = run_meta([1], min(reps, 3), batch, args.quick, args.device)
                doc = dict(bounded_lqr=lqr["doc"], figures=lqr["figures"], meta=meta)
            else:
                threads = list(dict.fromkeys(args.threads))  # in the order given, once each
                doc = run(threads, reps, B, args.quick, not args.skip_closed_loop, args.device)
            doc["meta"]["command"] = command_line(ap.prog, sys.argv[1:] if argv is None else argv)
            if args.json is not None:
                write_json(args.json, doc, indent=1)
                print(f"\nwrote {args.json}")
    finally:
        torch.set_num_threads(before)  # main() may run inside another process (the tests)
    return doc


if __name__ == "__main__":
    main()
