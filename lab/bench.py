"""Benchmarks of the DiffStack reference: every timing of the project, in one module.

    python -m lab.bench                   # everything, 1 and 2 threads, B = 256 (about 15 minutes,
                                          # most of it the bounded LQR)
    python -m lab.bench --threads 1 --reps 3 --skip-closed-loop
    python -m lab.bench --quick           # tiny sizes and reps, well under a minute (test_bench.py)
    python -m lab.bench --json runs/bench.json
                                          # also every figure, in a JSON file
    python -m lab.bench --device cuda --threads 1
                                          # our modules on a GPU (without the peers and closed loop)
    python -m lab.bench --bounded-lqr     # only the bounded LQR of differentiable_nmpc (minutes)

What is timed (B = --batch scenarios or problems, default 256):
    controller    ilqr_solve's forward (box-constrained iLQR, up to 5 iterations, tol 0.01) and its
                  KKT backward on tracking_problem (B unicycle tracking problems, T = 6, dt 0.5), in
                  float64 and float32; the cost is TrackingCost (its quadratic expansion in closed
                  form, as the peers are handed it); and in float64 at B = 1024 and 4096 (--quick: B
                  and 2 B), whose slope is the cost of one more problem
    planner       plan_candidates: the planner's spline candidates (48 per scenario)
    predictor     a training iteration (forward, InfoVAE loss, backward, Adam step) and an eval
                  forward (K = 25)
    stack         one DiffStack training step (RL) as train_stack takes it: run_stack on the batch's
                  scene plan and the backward of L = a1 L_pred + a2 L_plan + a3 L_ctr; its parts
                  predict / plan / control / backward as perf_counter laps; and scene_plan (goal,
                  candidates, their prediction-free cost terms), which train_stack computes once for
                  its data set rather than at every step
    closed loop   log replay of 100 scenes x 10 s (20 replanning steps) with each stack of Table 5,
                  one thread
    peers         the controller side by side with mpc.pytorch on the same problems, with the same
                  solver settings, and with PyPose's MPC (pp.module.MPC) on the same problems with
                  the box widened until inactive (PyPose has no bounds), one thread, B = 64 ...
                  4096, after checking that both reach the same solution; every peer's gradient
                  against finite differences
    bounded LQR   the published benchmark of FreyJo/differentiable_nmpc (128 problems, 8 states, 4
                  controls, N = 20, umax 1e4 and 1.0): our box-iLQR and KKT backward, with the
                  gradient wrt A, B, b and H, beside mpc.pytorch (one thread, alternating); each
                  solve checked against the QP's solution from scipy; the published acados and
                  mpc.pytorch rows printed beside ours, labelled as such (section 4c)

How: every figure is a torch.utils.benchmark.Timer measurement at a stated torch thread count
(Timer's num_threads): the median and the interquartile range (IQR) of --reps timed runs. Each timed
run follows an untimed run of the same code (blocked_autorange(min_run_time=0) runs the statement
once to size its block, then times one block of one run), and the benchmarks measured together take
turns, so that a change in the machine's load hits them alike.

--json PATH writes (atomically) stack_step_ms_1thread (the whole DiffStack step at one thread; null
when --threads leaves out 1), speedup_vs_mpc_pytorch (mpc.pytorch time / ours, iLQR forward +
backward, 5 iterations, float64, box controls, at the fewest threads; null without mpc),
speedup_vs_pypose (PyPose time / ours, forward + backward, 5 iterations, float64, no bound active,
one thread, B = 256 (--quick: its B); null without pypose), controller_ms_per_problem (ms per
problem of iLQR forward + KKT backward, float64, box, one thread: the slope from B = 1024 to 4096),
meta, figures (every row of the table: key, benchmark, dtype, threads, batch, median_ms, iqr_ms,
runs, note), mpc_pytorch and pypose (its figures, the per-B table, the agreement check and the
gradient errors), bounded_lqr (its table: per solver and umax the times, µs per problem-stage,
iterations, converged problems, distance to the reference; the gradient against mpc.pytorch's).

Peers are no dependencies of the project. Without one, its part is skipped with a one-line hint; to
compare, install it in a throwaway venv (--no-deps keeps the torch of requirements.txt):
    python3 -m venv /tmp/peers && /tmp/peers/bin/pip install -r requirements.txt
    /tmp/peers/bin/pip install --no-deps mpc==0.0.6
    /tmp/peers/bin/pip install --no-deps pypose==0.9.5
    /tmp/peers/bin/python -m lab.bench

Map of the module:
    1. Measuring     measure(): Timer measurements taking turns; figure(): one row of the results
    2. The problem   tracking_problem, tracking_cost: the controller's benchmark, shared with the
                     peers
    3. Our modules   controller, planner, predictor, a DiffStack training step, the closed loop
    4. Peers         mpc.pytorch, then PyPose, side by side (each skipped with a hint when it is not
                     installed); the bounded LQR of differentiable_nmpc, ours beside mpc.pytorch
    5. Running       run(), the tables, the JSON file, the command line
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import importlib
import io
import itertools
import json
import math
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
from diffstack import (
    Config,
    Predictor,
    Unicycle,
    ilqr,
    ilqr_solve,
    plan_candidates,
    pred_loss,
    run_stack,
    scene_plan,
    unicycle_jacobians,
    unicycle_rollout,
)
from lab.cli import bounded, check_writable, device_arg, machine
from lab.stats import markdown_table
from train import Method, alphas
from experiments import closed_loop_scenes, simulate, stack_policy
from lab.runs import command_line, one_line, write_atomic
from specs import CLOSED_LOOP_METHODS

DATA_CACHE = pathlib.Path(__file__).resolve().parent.parent / "data_cache"

# ============================================================================================
# 1. Measuring
# ============================================================================================


def measure(fns: dict, reps: int, threads: int, label: str = "") -> dict:
    """{name: torch.utils.benchmark Measurement of fns[name]()}: reps timed runs of each callable at
    `threads` torch threads. The callables take turns, one run each per round (a drift in load hits
    them alike); each timed run follows an untimed one of the same callable, which
    blocked_autorange(min_run_time=0) makes to size its block (one run for anything slower than
    microseconds) -- so no callable inherits another's warm caches."""
    timers = {
        name: benchmark.Timer(
            "fn()", globals={"fn": fn}, label=label, description=name, num_threads=threads
        )
        for name, fn in fns.items()
    }
    runs = {name: [] for name in fns}
    for _ in range(reps):
        for name, timer in timers.items():
            runs[name].append(timer.blocked_autorange(min_run_time=0))
    # one Measurement per callable
    return {name: benchmark.Measurement.merge(ms)[0] for name, ms in runs.items()}


def figure(key: str, name: str, times, threads: int, dtype="", batch=None, note="") -> dict:
    """One row of the results: median and IQR (ms) of run times (s; a Measurement's .times, or
    perf_counter laps), quartiles interpolated linearly as Measurement.iqr does."""
    times = sorted(times)
    q1, q3 = (
        statistics.quantiles(times, n=4, method="inclusive")[::2]
        if len(times) > 1
        else (times[0], times[0])
    )
    return dict(
        key=key,
        benchmark=name,
        dtype=dtype,
        threads=threads,
        batch=batch,
        median_ms=1e3 * statistics.median(times),
        iqr_ms=1e3 * (q3 - q1),
        runs=len(times),
        note=note,
    )


# ============================================================================================
# 2. The problem: unicycle tracking, shared with the peers
# ============================================================================================


def tracking_problem(B=256, T=6, dtype=torch.float64, seed=0, device="cpu"):
    """B unicycle tracking problems, the benchmark shared with mpc.pytorch (section 4):
        min sum_t 1/2 (s_t - r_t)' Q (s_t - r_t) + 1/2 (u_t - ur_t)' R (u_t - ur_t),  box controls,
    the reference rolled out from smooth random controls (some outside the box), the start
    perturbed. Drawn on the CPU (the same problems whatever the device), then moved to `device`."""
    g = torch.Generator().manual_seed(seed)

    def U(lo, hi, *shape):
        return lo + (hi - lo) * torch.rand(*shape, generator=g, dtype=dtype)

    x0 = torch.stack([U(-20, 20, B), U(-20, 20, B), U(-math.pi, math.pi, B), U(2.0, 15.0, B)], -1)
    tt = torch.arange(T, dtype=dtype) / (T - 1)
    u_ref = torch.stack(
        [
            U(-0.5, 0.5, B, 1) + U(-0.6, 0.6, B, 1) * tt,
            U(-3.0, 2.5, B, 1) + U(-3.5, 3.5, B, 1) * tt,
        ],
        -1,
    )
    x_ref = unicycle_rollout(x0, u_ref, 0.5)  # (B, T+1, 4)
    x_init = x0 + torch.randn(B, 4, generator=g, dtype=dtype) * torch.tensor(
        [1.0, 1.0, 0.15, 1.0], dtype=dtype
    )
    Q, R = torch.tensor([1.0, 1.0, 1.0, 0.2], dtype=dtype), torch.tensor([0.5, 0.1], dtype=dtype)
    cfg = Config()
    lo, hi = torch.tensor(cfg.u_lower, dtype=dtype), torch.tensor(cfg.u_upper, dtype=dtype)
    P = dict(
        x_init=x_init, x_ref=x_ref, u_ref=u_ref, Q=Q, R=R, lo=lo, hi=hi, u_init=u_ref.clamp(lo, hi)
    )
    return {k: v.to(device) for k, v in P.items()}


def tracking_cost(x, u, x_ref, u_ref, Q, R):
    """The tracking benchmark's cost: x (B, *S, T+1, 4), u (B, *S, T, 2) -> (B, *S); Q (4,) and R
    (2,) shared or per problem, (B, 4) and (B, 2)."""

    def view(t):
        return t.reshape(t.shape[0], *([1] * (x.dim() - 3)), *t.shape[1:])

    if Q.dim() == 2:  # per problem: broadcast over *S and the steps
        Q, R = (w.reshape(len(w), *([1] * (x.dim() - 2)), w.shape[-1]) for w in (Q, R))
    return 0.5 * ((x - view(x_ref)) ** 2 * Q).sum((-1, -2)) + 0.5 * (
        (u - view(u_ref)) ** 2 * R
    ).sum((-1, -2))


class TrackingCost:
    """tracking_cost as our controller takes it: with its expansion in closed form (the cost is
    quadratic: gradient Q (x - x_ref) and R (u - u_ref), Hessian diag(Q, R) at every step), as
    mpc.pytorch and PyPose are handed the quadratic directly; parameters per problem (ours_params),
    so that the solver sets converged problems aside."""

    def __call__(self, x, u, x_ref, u_ref, Q, R):
        return tracking_cost(x, u, x_ref, u_ref, Q, R)

    def expansion(self, x, u, x_ref, u_ref, Q, R):
        """Gradient (B, T+1, 6) and block Hessian (B, T+1, 6, 6), the last step's control a
        zero pad."""
        B, T = u.shape[:2]

        def pad(t):  # (B, T, 2) -> (B, T+1, 2)
            return torch.cat([t, torch.zeros_like(t[:, :1])], 1)

        g = torch.cat([(x - x_ref) * Q[:, None], pad((u - u_ref) * R[:, None])], -1)
        H = torch.cat([Q[:, None].expand(B, T + 1, 4), pad(R[:, None].expand(B, T, 2))], -1)
        return g, torch.diag_embed(H)


def ours_params(P, x_ref=None):
    """Our solver's parameters for the tracking problems P: (x_ref, u_ref, Q, R), each per problem
    (a view)."""
    B = len(P["x_init"])
    return (
        P["x_ref"] if x_ref is None else x_ref,
        P["u_ref"],
        P["Q"].expand(B, 4),
        P["R"].expand(B, 2),
    )


# ============================================================================================
# 3. Our modules
# ============================================================================================


def bench_controller(
    B=256, dtype=torch.float64, reps=5, threads=1, iters=5, tol=0.01, device="cpu"
) -> list:
    """iLQR forward and KKT backward on the tracking problem; the note gives the converged share."""
    P = tracking_problem(B, dtype=dtype, device=device)
    params = ours_params(P)

    def solve(x_init, params):
        return ilqr_solve(
            TrackingCost(),
            Unicycle(0.5),
            x_init,
            P["u_init"],
            params,
            P["lo"],
            P["hi"],
            iters=iters,
            tol=tol,
        )

    # the backward alone: one solve with x_init and x_ref requiring grad builds the graph, each run
    # walks it again (retain_graph keeps ILQR's saved tensors; the gradients accumulating in .grad
    # cost a few additions)
    x_init, x_ref = P["x_init"].clone().requires_grad_(), P["x_ref"].clone().requires_grad_()
    x, u, converged = solve(x_init, (x_ref, *params[1:]))  # (B, T+1, 4), (B, T, 2), (B,)
    loss = x.sum()
    m = measure(
        {
            "forward": lambda: solve(P["x_init"], params),
            "backward": lambda: loss.backward(retain_graph=True),
        },
        reps,
        threads,
        "controller",
    )
    dt = str(dtype).replace("torch.float", "f")
    conv = f"converged {converged.float().mean().item():.2f}"
    return [
        figure(
            f"ilqr_forward_{dt}",
            f"iLQR forward ({iters} iterations, tol {tol})",
            m["forward"].times,
            threads,
            dt,
            B,
            conv,
        ),
        figure(f"kkt_backward_{dt}", "KKT backward", m["backward"].times, threads, dt, B),
    ]


def bench_controller_scaling(
    batches=(1024, 4096), reps=3, iters=5, tol=0.01, device="cpu"
) -> tuple[list, float]:
    """The controller's cost per problem: iLQR forward + KKT backward (float64, box, one thread) at
    two batch sizes; the slope between them (ms per problem) is what a problem costs once the per-op
    overhead is paid."""
    rows = []
    med = {}
    for B in batches:
        fwd, bwd = solver_runs(tracking_problem(B, device=device), ours_solve, iters, tol)
        m = measure({"forward": fwd, "backward": bwd}, reps, 1, f"controller, B = {B}")
        med[B] = 1e3 * (m["forward"].median + m["backward"].median)
        rows += [
            figure(
                f"ilqr_forward_f64_B{B}",
                f"iLQR forward ({iters} iterations, tol {tol})",
                m["forward"].times,
                1,
                "f64",
                B,
            ),
            figure(f"kkt_backward_f64_B{B}", "KKT backward", m["backward"].times, 1, "f64", B),
        ]
    lo, hi = batches
    return rows, (med[hi] - med[lo]) / (hi - lo)


def bench_candidates(batch, cfg: Config, reps=5, threads=1) -> list:
    """The planner's candidate splines (plan_candidates) for every scenario of the batch."""
    s0 = batch.ego_hist[:, -1]  # (B, 4)
    m = measure(
        {"candidates": lambda: plan_candidates(s0, batch.goal, batch.lanes, batch.lanes_mask, cfg)},
        reps,
        threads,
        "planner",
    )
    n = 24 * cfg.max_goal_lanes  # 8 accelerations x 3 offsets per goal lane
    return [
        figure(
            "candidates",
            f"planner: candidates (up to {n} per scenario)",
            m["candidates"].times,
            threads,
            "f32",
            len(batch),
        )
    ]


def bench_predictor(batch, cfg: Config | None = None, reps=5, threads=1) -> list:
    """A training iteration (forward with q(z|x,y), InfoVAE loss, backward, Adam step) and an eval
    forward, on the batch's device."""
    cfg = cfg or Config()
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

    m = measure({"train": train_iteration, "eval": eval_forward}, reps, threads, "predictor")
    what = f"K = {cfg.pred_modes}, decoder {cfg.pred_dec_hidden}"
    return [
        figure(
            "predictor_train",
            f"predictor: training iteration ({what})",
            m["train"].times,
            threads,
            "f32",
            len(batch),
        ),
        figure(
            "predictor_eval", "predictor: eval forward", m["eval"].times, threads, "f32", len(batch)
        ),
    ]


def bench_stack_step(batch, cfg: Config, reps=5, threads=1) -> list:
    """One DiffStack training step (RL) as train_stack takes it: run_stack with train=True on the
    batch's scene plan (goal, candidates and their prediction-free cost terms, which train_stack
    computes once for its data set), then the backward of the weighted losses; beside it, that scene
    plan's own cost (scene_plan, once per scenario in training). The step is a Timer measurement;
    its parts are perf_counter laps over the same runs (all but the very first, which pays for
    first-call allocations): predict, the predictor's forward (a forward hook); plan, from there to
    the controller's start (L_pred, the candidates' costs, L_plan; diffstack.ilqr_solve wrapped);
    control, the controller and the hindsight cost; backward. On a GPU the laps are times to launch,
    not to finish; the step's Timer does synchronise."""
    torch.manual_seed(0)
    model = Predictor(cfg).to(batch.agent_hist.device)
    method = Method("DiffStack", losses=(1, 1, 1))
    a1, a2, a3 = alphas(method, "rl", cfg)
    scene = scene_plan(batch, cfg)
    solve = diffstack.ilqr_solve
    laps = []

    def step():
        t = {}
        clock = [time.perf_counter()]

        def lap(name):
            clock.append(time.perf_counter())
            t[name] = clock[-1] - clock[-2]

        def timed_solve(*args, **kw):
            lap("plan")
            return solve(*args, **kw)

        hook = model.register_forward_hook(lambda *_: lap("predict"))
        diffstack.ilqr_solve = timed_solve
        try:
            out = run_stack(batch, model, method, cfg, "rl", step=0, train=True, scene=scene)
        finally:
            diffstack.ilqr_solve = solve
            hook.remove()
        lap("control")
        (a1 * out.l_pred.mean() + a2 * out.l_plan.mean() + a3 * out.l_ctr.mean()).backward()
        lap("backward")
        laps.append(t)

    m = measure(
        {"step": step, "scene": lambda: scene_plan(batch, cfg)}, reps, threads, "DiffStack step"
    )
    rows = [
        figure(
            "stack_step",
            "DiffStack training step (RL)",
            m["step"].times,
            threads,
            "f32",
            len(batch),
        ),
        figure(
            "stack_scene_plan",
            "scene plan (once per data set in training)",
            m["scene"].times,
            threads,
            "f32",
            len(batch),
        ),
    ]
    for part in ("predict", "plan", "control", "backward"):
        rows.append(
            figure(
                f"stack_{part}",
                f"DiffStack step: {part} (perf_counter lap)",
                [t[part] for t in laps[1:]],
                threads,
                "f32",
                len(batch),
            )
        )
    return rows


def bench_closed_loop(scenes, cfg: Config | None = None, n=100, sim_time=10.0, reps=3) -> list:
    """Log replay of n scenes for sim_time with each stack of Table 5, one thread. The predictor is
    untrained: the time does not depend on its weights."""
    cfg = cfg or Config()
    scenes = closed_loop_scenes(scenes, cfg, sim_time)[:n]
    torch.manual_seed(0)
    model = Predictor(cfg)

    def replay(method):
        policy = stack_policy(model if method.predictor == "learned" else None, method, cfg)
        return lambda: simulate(scenes, policy, cfg, sim_time)

    m = measure({meth.name: replay(meth) for meth in CLOSED_LOOP_METHODS}, reps, 1, "closed loop")
    what = f"{len(scenes)} scenes x {sim_time:g} s"
    return [
        figure(
            "closed_loop_" + name.lower().replace(" ", "_"),
            f"closed loop, {name} ({what})",
            mm.times,
            1,
            "f32",
        )
        for name, mm in m.items()
    ]


# ============================================================================================
# 4. Peers: mpc.pytorch (locuslab, `mpc` 0.0.6) and PyPose (`pypose` 0.9.x), side by side
# ============================================================================================
#
# 4a. mpc.pytorch: the same problems (tracking_problem, float64), the same initial controls,
# iterations, tolerance, line search (decay 1/5, 5 steps) and box; runs alternate in one process.
# mpc.pytorch's T = 7 convention adds a 7th control that drives nothing: it gets weight R and
# reference 0, so it stays 0 and costs nothing.

PEER_BASE = "python3 -m venv /tmp/peers && /tmp/peers/bin/pip install -r requirements.txt"
PEER_VENV = f"{PEER_BASE} && /tmp/peers/bin/pip install --no-deps mpc==0.0.6"


def import_peer(name: str):
    """(module, None), or (None, why) when it cannot be imported: a missing peer is a skip, never a
    traceback."""
    try:
        return importlib.import_module(name), None
    except ImportError:
        return None, "not installed"
    except Exception as e:  # a peer built for another torch may fail any way on import
        return None, f"import failed: {type(e).__name__}: {' '.join(str(e).split())}"


def mpc_hint(why: str) -> str:
    """The one line printed instead of the mpc.pytorch comparison."""
    return (
        f"mpc.pytorch: {why}, comparison skipped (speedup_vs_mpc_pytorch: null). To run it: "
        f"{PEER_VENV} then /tmp/peers/bin/python -m lab.bench"
    )


class UnicycleDx(torch.nn.Module):
    """The unicycle as mpc.pytorch wants it, with the exact closed-form Jacobians
    (GradMethods.ANALYTIC)."""

    def forward(self, x, u):
        return Unicycle(0.5)(x, u)  # the unchecked step our solver uses too, so both pay the same

    def grad_input(self, x, u):
        return unicycle_jacobians(x, u, 0.5)


def mpc_solve(P, x_init, x_ref, iters, eps):
    """One mpc.MPC solve of the tracking problem: x (B, T+1, 4), u (B, T, 2)."""
    from mpc import mpc as mpc_lib  # a dictionary look-up after the first import

    B, T1, _ = x_ref.shape
    C = torch.diag(torch.cat([P["Q"], P["R"]])).expand(T1, B, 6, 6)
    # u_ref: (B, T+1, 2) the idle 7th control
    u_ref = torch.cat([P["u_ref"], torch.zeros_like(P["u_ref"][:, :1])], 1)
    c = torch.cat([-P["Q"] * x_ref, -P["R"] * u_ref], -1).transpose(0, 1)  # (T+1, B, 6)
    lo, hi = P["lo"].expand(T1, B, 2).contiguous(), P["hi"].expand(T1, B, 2).contiguous()
    # u0: (T+1, B, 2)
    u0 = (
        torch.cat([P["u_init"], torch.zeros_like(P["u_init"][:, :1])], 1)
        .transpose(0, 1)
        .contiguous()
    )
    ctrl = mpc_lib.MPC(
        4,
        2,
        T1,
        u_lower=lo,
        u_upper=hi,
        u_init=u0,
        lqr_iter=iters,
        eps=eps,
        grad_method=mpc_lib.GradMethods.ANALYTIC,
        exit_unconverged=False,
        backprop=True,
        verbose=-1,
        n_batch=B,
        linesearch_decay=0.2,
        max_linesearch_iter=5,
    )
    # time-major: (T+1, B, 4), (T+1, B, 2)
    x, u, _ = ctrl(x_init, mpc_lib.QuadCost(C, c), UnicycleDx())
    return x.transpose(0, 1), u.transpose(0, 1)[:, :-1]


def ours_solve(P, x_init, x_ref, iters, eps):
    """The same solve with diffstack's controller: x (B, T+1, 4), u (B, T, 2)."""
    x, u, _ = ilqr_solve(
        TrackingCost(),
        Unicycle(0.5),
        x_init,
        P["u_init"],
        ours_params(P, x_ref),
        P["lo"],
        P["hi"],
        iters=iters,
        tol=eps,
    )
    return x, u


def solver_runs(P, solve, iters, eps):
    """(forward, backward) callables: a solve with x_init and x_ref requiring grad (both solvers
    build their graph in the forward), and the backward of the final positions' sum wrt them on one
    prebuilt graph."""
    x_init, x_ref = P["x_init"].clone().requires_grad_(), P["x_ref"].clone().requires_grad_()
    x, _ = solve(P, x_init, x_ref, iters, eps)
    # the final positions depend on every control: the gradient crosses every step
    loss = x[:, -1, :2].sum()
    return (lambda: solve(P, x_init, x_ref, iters, eps)), (lambda: loss.backward(retain_graph=True))


def gradient_errors(P, solve, idx, iters):
    """Relative error of d(x_T + y_T)/dx_init per problem in idx against central finite differences
    of our tight solve (which test_diffstack.py checks against finite differences and unrolled
    autograd)."""
    sub = {k: (v[idx] if torch.is_tensor(v) and v.dim() > 1 else v) for k, v in P.items()}
    x_init = sub["x_init"].clone().requires_grad_()
    x, _ = solve(sub, x_init, sub["x_ref"], iters, 1e-9)
    (g,) = torch.autograd.grad((x[:, -1, 0] + x[:, -1, 1]).sum(), x_init)  # (b, 4)

    def loss(xi):
        x, u, _ = ilqr(
            tracking_cost,
            Unicycle(0.5),
            xi,
            sub["u_init"],
            (sub["x_ref"], sub["u_ref"], sub["Q"], sub["R"]),
            sub["lo"],
            sub["hi"],
            iters=200,
            tol=1e-12,
        )
        return x[:, -1, 0] + x[:, -1, 1]

    h = 1e-5
    fd = torch.zeros_like(g)
    for j in range(4):
        e = torch.zeros_like(sub["x_init"])
        e[:, j] = h
        fd[:, j] = (loss(sub["x_init"] + e) - loss(sub["x_init"] - e)) / (2 * h)
    return (g - fd).norm(dim=-1) / fd.norm(dim=-1)  # (b,)


def compare_mpc(B=256, threads=(1, 2), reps=5, log=print) -> dict | None:
    """diffstack's iLQR against mpc.pytorch on tracking_problem(B), float64, at 5 iterations / tol
    0.01 and 10 / 1e-3. Returns {rows, speedup (mpc time / ours, forward + backward, 5 iterations,
    the fewest threads), gradient_error}, or None after one line of hint when mpc cannot be
    imported."""
    mpc_lib, why = import_peer("mpc.mpc")
    if mpc_lib is None:
        log(mpc_hint(why))
        return None
    P = tracking_problem(B, dtype=torch.float64)
    head = [
        "threads",
        "iterations, tol",
        "mpc.pytorch fwd / bwd (ms)",
        "diffstack fwd / bwd (ms)",
        "speed-up fwd / fwd+bwd",
    ]
    rows = []
    lines = []
    speedup = None

    def ms(m):
        return f"{1e3 * m.median:.1f} (±{1e3 * m.iqr:.1f})"

    with warnings.catch_warnings():
        # mpc 0.0.6 uses deprecated torch APIs (torch.lu, uint8 masks)
        warnings.simplefilter("ignore")
        for nt in sorted(threads):
            for iters, eps in ((5, 0.01), (10, 1e-3)):
                fns = {}
                for name, solve in (("mpc", mpc_solve), ("ours", ours_solve)):
                    fns[name + " fwd"], fns[name + " bwd"] = solver_runs(P, solve, iters, eps)
                m = measure(fns, reps, nt, f"iLQR vs mpc.pytorch, {iters} iterations")
                med = {k: v.median for k, v in m.items()}
                fwd = med["mpc fwd"] / med["ours fwd"]
                total = (med["mpc fwd"] + med["mpc bwd"]) / (med["ours fwd"] + med["ours bwd"])
                # the headline: the controller's default settings, the fewest threads
                if speedup is None:
                    speedup = total
                for k, v in m.items():
                    rows.append(
                        figure(
                            f"{k.replace(' ', '_')}_{iters}it",
                            f"{k}, {iters} iterations, tol {eps}",
                            v.times,
                            nt,
                            "f64",
                            B,
                        )
                    )
                lines.append(
                    [
                        str(nt),
                        f"{iters}, {eps}",
                        f"{ms(m['mpc fwd'])} / {ms(m['mpc bwd'])}",
                        f"{ms(m['ours fwd'])} / {ms(m['ours bwd'])}",
                        f"{fwd:.2f}x / {total:.2f}x",
                    ]
                )
        idx = torch.arange(0, B, 16)  # 16 problems at B = 256
        errors = {}
        for name, solve in (("mpc.pytorch", mpc_solve), ("diffstack", ours_solve)):
            err = gradient_errors(P, solve, idx, 100)
            q = err.quantile(torch.tensor([0.5, 0.9], dtype=err.dtype))
            errors[name] = dict(
                median=q[0].item(), p90=q[1].item(), max=err.max().item(), problems=len(idx)
            )
    log(
        f"mpc.pytorch side by side: B = {B} unicycle tracking problems, T = 6, dt 0.5, float64, "
        f"box controls; median (IQR) of {reps} alternating runs"
    )
    log(markdown_table(head, lines))
    for name, e in errors.items():
        log(
            f"{name:12s} d(x_T + y_T)/d x_init vs finite differences, {e['problems']} problems: "
            f"median {e['median']:.1e}, 90th percentile {e['p90']:.1e}, max {e['max']:.1e}"
        )
    return dict(rows=rows, speedup=speedup, gradient_error=errors)


# --------------------------------------------------------------------------------------------
# 4b. PyPose (`pypose` 0.9.x, pp.module.MPC), side by side
# --------------------------------------------------------------------------------------------
#
# PyPose's MPC is iLQR with full steps: no control bounds and no line search. So both solve the same
# tracking problems with the box widened to +-WIDE, which no control comes near (checked on every
# solution). Its horizon convention is mpc.pytorch's: T' = 7 stages tau_t = (x_t, u_t), t = 0..6,
# each costing 1/2 tau' Q tau + p' tau, with x_7 = f(x_6, u_6) uncosted. So Q_t = diag(Q, R) and
# p_t = (-Q r_t, -R ur_t), with the idle 7th control's reference 0 (it stays 0 and costs nothing);
# the cost it reports lacks the constant 1/2 r'Q r + 1/2 ur'R ur. Stock PyPose cannot run this
# benchmark as it is; what changed, and nothing else (PyPoseUnicycle, PyPoseMPC):
#   1. Jacobians: NLS.A/B are torch.autograd.functional.jacobian of the whole batch, (B, 4, B, 4)
#      for B > 1, which LQR cannot use. set_refpoint computes diffstack's closed-form
#      unicycle_jacobians (B, 4, 4) and (B, 4, 2) instead (the same Jacobians mpc.pytorch and ours
#      get), detached as autograd's jacobian returns them (create_graph=False); it skips NLS's f and
#      g at the reference point, which LQR never reads.
#   2. The state transition is diffstack's unchecked unicycle step (ours uses the same) on a clone
#      of the state, as PyPose's own LTI does: runsys and lqr_forward write the states in place into
#      one tensor, which the step's saved views would otherwise break in the backward.
#   3. Stopping: ReduceToBason(iters, tol=-inf, decreasing=-inf), so that it runs exactly `iters`
#      LQR passes (iters - 1 without grad, then one with grad) like our `iters` iterations. Its
#      default tol 1e-5 stops after the first pass whenever every cost is negative, which the
#      constant-less tracking cost is.
#   4. The best iterate, per problem: MPC.forward compares the batch's costs with `cost < best` (an
#      error for B > 1); PyPoseMPC keeps each problem's best u, a new one winning ties up to the
#      rounding allowance of our line search (100 eps (1 + |cost|)); a strict `<` keeps a stale
#      iterate whose cost differs by rounding only (1.7e-7 from the optimum in u, B = 256). The last
#      pass starts from the best u, as MPC.forward does.

WIDE = 1e3  # the box of the PyPose comparison, +-WIDE: never active
PYPOSE_BATCHES = (64, 256, 1024, 4096)  # the full run's batch sizes; --quick: its --batch only
PYPOSE_SPEEDUP_BATCH = 256  # speedup_vs_pypose: PyPose time / ours, forward + backward, at this B
PYPOSE_VENV = "/tmp/peers/bin/pip install --no-deps pypose==0.9.5"  # it imports only torch
_PYPOSE_CLASSES = {}


def pypose_hint(why: str) -> str:
    """The one line printed instead of the PyPose comparison."""
    return (
        f"pypose: {why}, comparison skipped (speedup_vs_pypose: null). To run it: {PEER_BASE} && "
        f"{PYPOSE_VENV} then /tmp/peers/bin/python -m lab.bench"
    )


def pypose_classes(pp):
    """(PyPoseUnicycle, PyPoseMPC): subclasses of pp.module.NLS and pp.module.MPC with the changes
    1-4 above."""
    if _PYPOSE_CLASSES.get("pp") is not pp:

        class PyPoseUnicycle(pp.module.NLS):
            """The unicycle as a PyPose system, with closed-form Jacobians (changes 1 and 2)."""

            def __init__(self, dt):
                super().__init__()
                self.step = Unicycle(dt)

            def state_transition(self, state, input, t=None):
                return self.step(state.clone(), input)

            def observation(self, state, input, t=None):
                return state

            def set_refpoint(self, state=None, input=None, t=None):
                self._ref_state, self._ref_input, self._ref_t = state, input, t
                self._A, self._B = self.step.jacobians(state.detach(), input.detach())
                return self

            @property
            def A(self):
                return self._A

            @property
            def B(self):
                return self._B

        class PyPoseMPC(pp.module.MPC):
            """pp.module.MPC keeping each problem's best iterate (change 4); the rest is
            MPC.forward's."""

            def forward(self, dt, x_init, u_init=None, u_lower=None, u_upper=None, du=None):
                u = u_init
                best_u = u_init
                best = None
                self.stepper.reset()
                with torch.no_grad():
                    while self.stepper.continual():
                        x, u, cost = self.lqr(x_init, dt, u)
                        self.stepper.step(cost)
                        if best is None:
                            best_u, best = u, cost
                        else:
                            win = cost <= best + 100 * torch.finfo(cost.dtype).eps * (
                                1 + best.abs()
                            )
                            best_u, best = (
                                torch.where(win[:, None, None], u, best_u),
                                torch.where(win, cost, best),
                            )
                return self.lqr(x_init, dt, u_traj=best_u)

        _PYPOSE_CLASSES.update(pp=pp, classes=(PyPoseUnicycle, PyPoseMPC))
    return _PYPOSE_CLASSES["classes"]


def unconstrained(P: dict) -> dict:
    """The tracking problems with the box widened to +-WIDE (the initial controls: the reference's,
    unclipped)."""
    lo, hi = torch.full_like(P["lo"], -WIDE), torch.full_like(P["hi"], WIDE)
    return dict(P, lo=lo, hi=hi, u_init=P["u_ref"].clamp(lo, hi))


def pypose_solve(P, x_init, x_ref, iters, eps):
    """One PyPose MPC solve of the (unconstrained) tracking problem: x (B, T+1, 4), u (B, T, 2).
    Exactly `iters` LQR passes; eps is unused (PyPose has no step tolerance, its stepper's tol is
    -inf: change 3)."""
    import pypose as pp
    from pypose.utils.stepper import ReduceToBason

    system, MPC = pypose_classes(pp)
    B, T1, _ = x_ref.shape
    Q = torch.diag(torch.cat([P["Q"], P["R"]])).expand(B, T1, 6, 6)
    # u_ref: (B, T+1, 2) the idle 7th control
    u_ref = torch.cat([P["u_ref"], torch.zeros_like(P["u_ref"][:, :1])], 1)
    p = torch.cat([-P["Q"] * x_ref, -P["R"] * u_ref], -1)  # (B, T+1, 6)
    u0 = torch.cat([P["u_init"], torch.zeros_like(P["u_init"][:, :1])], 1)  # (B, T+1, 2)
    # MPC runs iters - 1 passes, then 1 more
    stepper = ReduceToBason(iters, tol=-math.inf, decreasing=-math.inf)
    # (B, T+2, 4), (B, T+1, 2)
    x, u, _ = MPC(system(0.5), Q, p, T1, stepper=stepper)(0.5, x_init, u_init=u0)
    return x[:, :T1], u[:, : T1 - 1]


def pypose_agreement(P, iters=50) -> dict:
    """Both solvers on the unconstrained problems P, to convergence (iters, tol 1e-12): the largest
    difference in u and x, and the largest |u| (against WIDE: no bound active)."""
    xo, uo = ours_solve(P, P["x_init"], P["x_ref"], iters, 1e-12)
    xp, up = pypose_solve(P, P["x_init"], P["x_ref"], iters, 1e-12)
    return dict(
        iters=iters,
        problems=len(uo),
        max_du=(up - uo).abs().max().item(),
        max_dx=(xp - xo).abs().max().item(),
        max_abs_u=max(uo.abs().max().item(), up.abs().max().item()),
    )


def time_pypose(B, reps, iters, tol):
    """One B of the PyPose comparison: (figures, the table's entry, the printed row). Both solvers
    take turns on forward and backward (one thread); the entry also says how many iterations ours
    ran and that no bound was near the solutions of the timed settings."""
    P = unconstrained(tracking_problem(B, dtype=torch.float64))
    fns = {}
    for name, solve in (("pypose", pypose_solve), ("ours", ours_solve)):
        fns[name + " fwd"], fns[name + " bwd"] = solver_runs(P, solve, iters, tol)
    _, uo, info = ilqr(
        tracking_cost,
        Unicycle(0.5),
        P["x_init"],
        P["u_init"],
        (P["x_ref"], P["u_ref"], P["Q"], P["R"]),
        P["lo"],
        P["hi"],
        iters=iters,
        tol=tol,
    )
    _, up = pypose_solve(P, P["x_init"], P["x_ref"], iters, tol)
    m = measure(fns, reps, 1, f"iLQR vs PyPose, B = {B}")
    med = {k: 1e3 * v.median for k, v in m.items()}
    total = (med["pypose fwd"] + med["pypose bwd"]) / (med["ours fwd"] + med["ours bwd"])
    rows = [
        figure(
            f"{k.replace(' ', '_')}_{iters}it_unconstrained",
            f"{k}, {iters} iterations, tol {tol}, box +-{WIDE:g}",
            v.times,
            1,
            "f64",
            B,
        )
        for k, v in m.items()
    ]
    entry = dict(
        batch=B,
        **{k.replace(" ", "_") + "_ms": v for k, v in med.items()},
        speedup=total,
        ours_iterations=int(info.iters.max()),
        ours_converged=info.converged.double().mean().item(),
        # at these settings (ours stops moving a problem below tol)
        max_du=(up - uo).abs().max().item(),
        bounds_inactive=max(uo.abs().max().item(), up.abs().max().item()) < WIDE / 2,
    )

    def ms(k):
        return f"{1e3 * m[k].median:.1f} (±{1e3 * m[k].iqr:.1f})"

    line = [
        str(B),
        f"{ms('pypose fwd')} / {ms('pypose bwd')}",
        f"{ms('ours fwd')} / {ms('ours bwd')}",
        str(entry["ours_iterations"]),
        f"{med['pypose fwd'] / med['ours fwd']:.2f}x / {total:.2f}x",
    ]
    return rows, entry, line


def compare_pypose(batches=PYPOSE_BATCHES, reps=5, iters=5, tol=0.01, log=print) -> dict | None:
    """diffstack's iLQR against PyPose's MPC on tracking_problem(B) with the box widened (no bound
    active), float64, one thread, `iters` iterations (ours: tol too), forward + backward of a loss
    on the solution to x_init and the reference, at each B in batches. First both solvers to
    convergence at the smallest B (they must agree), then the timings, then both gradients against
    finite differences (16 problems). Returns {rows, table, speedup (PyPose time / ours at
    PYPOSE_SPEEDUP_BATCH, or at the largest B below it, or the smallest), speedup_batch, agreement,
    gradient_error}, or None after one line of hint when pypose cannot be imported."""
    pp, why = import_peer("pypose")
    if pp is None:
        log(pypose_hint(why))
        return None
    batches = sorted(set(batches))
    rows = []
    table = []
    lines = []
    errors = {}
    before = torch.get_num_threads()
    torch.set_num_threads(1)  # the untimed set-up too; the Timers set it for every run
    try:
        P = unconstrained(tracking_problem(batches[0], dtype=torch.float64))
        agree = pypose_agreement(P)
        for B in batches:
            r, entry, line = time_pypose(B, reps, iters, tol)
            rows, table, lines = rows + r, table + [entry], lines + [line]
        idx = torch.arange(0, len(P["x_init"]), max(1, len(P["x_init"]) // 16))[:16]
        for name, solve in (("PyPose", pypose_solve), ("diffstack", ours_solve)):
            err = gradient_errors(P, solve, idx, 100)
            q = err.quantile(torch.tensor([0.5, 0.9], dtype=err.dtype))
            errors[name] = dict(
                median=q[0].item(), p90=q[1].item(), max=err.max().item(), problems=len(idx)
            )
    finally:
        torch.set_num_threads(before)
    at = [t for t in table if t["batch"] <= PYPOSE_SPEEDUP_BATCH] or table[:1]
    log(
        "PyPose side by side: unicycle tracking problems, T = 6, dt 0.5, float64, box widened "
        f"to ±{WIDE:g} (PyPose has no bounds), one thread, {iters} iterations (ours: tol {tol}; "
        f"PyPose: exactly {iters} LQR passes); median (IQR) of {reps} alternating runs"
    )
    same = agree["max_du"] < 1e-8
    log(
        f"same solution: {'yes' if same else 'NO'}, both to convergence ({agree['iters']} "
        f"iterations, tol 1e-12) on {agree['problems']} problems: max |u_pypose - u_ours| "
        f"{agree['max_du']:.1e}, max |x difference| {agree['max_dx']:.1e}; largest |u| "
        f"{agree['max_abs_u']:.2f}, far inside ±{WIDE:g}: no bound active"
    )
    if agree["max_abs_u"] >= WIDE / 2 or not all(t["bounds_inactive"] for t in table):
        log(
            f"WARNING: a control came within {WIDE / 2:g} of the box: the comparison is not of "
            "the same problem"
        )
    log(
        markdown_table(
            [
                "B",
                "PyPose fwd / bwd (ms)",
                "diffstack fwd / bwd (ms)",
                "our iterations",
                "speed-up fwd / fwd+bwd",
            ],
            lines,
        )
    )
    for name, e in errors.items():
        log(
            f"{name:12s} d(x_T + y_T)/d x_init vs finite differences, {e['problems']} problems: "
            f"median {e['median']:.1e}, 90th percentile {e['p90']:.1e}, max {e['max']:.1e}"
        )
    return dict(
        rows=rows,
        table=table,
        speedup=at[-1]["speedup"],
        speedup_batch=at[-1]["batch"],
        agreement=agree,
        gradient_error=errors,
    )


# --------------------------------------------------------------------------------------------
# 4c. The bounded LQR of differentiable_nmpc (Frey et al., acados), beside mpc.pytorch
# --------------------------------------------------------------------------------------------
#
# The benchmark of Table 1 in the README of FreyJo/differentiable_nmpc: 128 problems sharing one
# affine system x' = A x + B u + b, 8 states, 4 controls, horizon N = 20, stage cost
# 1/2 tau_t' H tau_t with H = I (12 x 12; tau_t = (x_t, u_t)), u within +-umax, float64, from
# zero controls; the loss is the sum of the first controls over the batch, its gradient taken wrt
# the 248 parameters A (64), B (32), b (8) and H (144). mpc.pytorch's horizon has N + 1 = 21
# stages, the 21st control driving nothing (it stays 0); ours costs x_N by H's state block, the
# same problem. The problems are the script's own: numpy's legacy generator seeded 42 draws A, B,
# b and then x0 twice (its timing run, its sensitivity run) for umax = 1e4, then again for
# umax = 1.0; we solve the sensitivity run's x0.
#
# Our solver differentiates x_init and the cost's parameters (the KKT backward, diffstack.py §5);
# the dynamics' A, B, b take one more step from the same backward pass, the costates (Amos et al.
# 2018, eq. 8): with lambda the forward problem's costates and (dx, du, dlambda) the backward
# LQR's solution and costates,
#     dL/dA = sum_t dlambda_{t+1} x_t' + lambda_{t+1} dx_t'
#     dL/dB = sum_t dlambda_{t+1} u_t' + lambda_{t+1} du_t'
#     dL/db = sum_t dlambda_{t+1}
# (AffineLQR; test_bench.py holds them to central finite differences under active bounds).

LQR_UMAX = (1e4, 1.0)  # the two configurations, in the order the reference script draws them
LQR_N, LQR_NX, LQR_NU, LQR_BATCH = 20, 8, 4, 128
LQR_SETTINGS = {  # ours at ilqr's defaults; run until the step is below 1e-6; and with a finer
    "defaults": dict(iters=5, tol=0.05),  # line search (scales down to 2^-19, not 5^-4)
    "tight": dict(iters=100, tol=1e-6),
    "finer": dict(iters=100, tol=1e-6, ls_steps=20, ls_decay=2.0),
}
LQR_MPC = dict(lqr_iter=100, eps=1e-6)  # mpc.pytorch as the reference script runs it
LQR_PUBLISHED = (  # (umax, acados solve, acados solve + gradient (ms), mpc.pytorch x acados)
    (1e4, 7.6, 36.6, 9.22, 3.23),
    (1.0, 17.4, 58.4, 1460.0, 441.0),
)


def bounded_lqr_problem(umax: float, batch=LQR_BATCH, seed=42, horizon=LQR_N) -> dict:
    """The benchmark's problems for umax (one of LQR_UMAX), float64: A (8, 8), B (8, 4), b (8,),
    H (12, 12), x_init (batch, 8), lo, hi (4,), u_init (batch, horizon, 4) zeros (the horizon
    of u_init is the problems')."""
    rng = np.random.RandomState(seed)  # numpy's legacy generator, as npr.seed(42)
    for drawn in LQR_UMAX:
        A = np.eye(LQR_NX) + 0.2 * rng.randn(LQR_NX, LQR_NX)
        B = rng.randn(LQR_NX, LQR_NU)
        b = rng.randn(LQR_NX)
        rng.randn(batch, LQR_NX)  # the timing run's x0
        x0 = rng.randn(batch, LQR_NX)  # the sensitivity run's x0
        if drawn == umax:
            break
    else:
        raise ValueError(f"umax: {umax} is none of the benchmark's {LQR_UMAX}")
    P = dict(A=A, B=B, b=b, H=np.eye(LQR_NX + LQR_NU), x_init=x0)
    P = {k: torch.tensor(v, dtype=torch.float64) for k, v in P.items()}
    P["lo"] = torch.full((LQR_NU,), -umax, dtype=torch.float64)
    P["hi"] = torch.full((LQR_NU,), umax, dtype=torch.float64)
    P["u_init"] = torch.zeros(batch, horizon, LQR_NU, dtype=torch.float64)
    return P


class Affine:
    """x_{t+1} = A x_t + B u_t + b for x (..., n), u (..., m), with its Jacobians (A, B) and
    curvature (0) in closed form, as diffstack's solver takes dynamics."""

    def __init__(self, A, B, b):
        self.A, self.B, self.b = A, B, b

    def __call__(self, x, u):
        return x @ self.A.mT + u @ self.B.mT + self.b

    def jacobians(self, x, u):  # x (B, T, n) -> (B, T, n, n), (B, T, n, m)
        n, m = self.B.shape
        return self.A.expand(*x.shape[:-1], n, n), self.B.expand(*x.shape[:-1], n, m)

    def curvature(self, x, u, lam):  # (B, T, n+m, n+m): affine dynamics curve nowhere
        k = x.shape[-1] + u.shape[-1]
        return x.new_zeros(*x.shape[:-1], k, k)


class StageQuadratic:
    """The benchmark's cost: sum_{t<N} 1/2 tau_t' H tau_t + 1/2 x_N' H_xx x_N, tau_t = (x_t, u_t),
    x (B, N+1, n), u (B, N, m) -> (B,); its expansion in closed form (H's symmetric part)."""

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
    """lambda_N = g_x[N], lambda_t = g_x[t] + A_t' lambda_{t+1}: the costates of a problem whose
    stage gradients in x are g_x (B, N+1, n) along dynamics with Jacobians A (B, N, n, n)
    -> (B, N+1, n), lambda_0 .. lambda_N."""
    lam = [g_x[:, -1]]
    for t in reversed(range(A.shape[1])):
        lam.append(g_x[:, t] + (A[:, t].mT @ lam[-1][..., None])[..., 0])
    return torch.stack(lam[::-1], 1)


def outer_sum(a, b):
    """sum over the batch and the steps of a_t b_t': a (B, N, i), b (B, N, j) -> (i, j)."""
    return torch.einsum("bti,btj->ij", a, b)


class AffineLQR(torch.autograd.Function):
    """diffstack.ilqr on the bounded LQR, differentiable in x_init, A, B, b and H: the KKT backward
    of diffstack.py §5 (same active set held, same LQR), plus the dynamics' gradients from the
    costates (above). Scenarios that did not converge pass no gradient, as in diffstack."""

    @staticmethod
    def forward(ctx, settings, lo, hi, u_init, x_init, A, B, b, H):
        with torch.no_grad():
            x, u, info = ilqr(
                StageQuadratic(), Affine(A, B, b), x_init, u_init, (H,), lo, hi, **settings
            )
        ctx.save_for_backward(x, u, info.converged, lo.expand_as(u), hi.expand_as(u), A, B, b, H)
        ctx.mark_non_differentiable(info.converged, info.iters)
        return x, u, info.converged, info.iters

    @staticmethod
    def backward(ctx, grad_x, grad_u, _, __):
        x, u, converged, lo, hi, A, B, b, H = ctx.saved_tensors
        n, T = x.shape[-1], u.shape[1]
        free = ((u - lo).abs() > 1e-8) & ((hi - u).abs() > 1e-8)  # the active set, held
        keep = converged.to(x.dtype)[:, None, None]
        cost, dynamics = StageQuadratic(), Affine(A, B, b)
        g, Hz = cost.expansion(x, u, H)  # (B, N+1, n+m), (B, N+1, n+m, n+m)
        A_t, B_t = dynamics.jacobians(x[:, :-1], u)
        rhs = torch.cat([grad_x * keep, F.pad(grad_u * keep, (0, 0, 0, 1))], -1)
        k, K, _, p0 = diffstack.lqr_backward(A_t, B_t, Hz, rhs, free=free)
        dx, du = [torch.zeros_like(x[:, 0])], []  # the backward LQR's solution from dx_0 = 0
        for t in range(T):
            du.append(k[:, t] + (K[:, t] @ dx[-1][..., None])[..., 0])
            dx.append((A_t[:, t] @ dx[-1][..., None] + B_t[:, t] @ du[-1][..., None])[..., 0])
        dx, du = torch.stack(dx, 1), torch.stack(du, 1)
        d = torch.cat([dx, F.pad(du, (0, 0, 0, 1))], -1)  # (B, N+1, n+m)
        lam = costates(g[..., :n], A_t)[:, 1:]  # (B, N, n): lambda_1 .. lambda_N
        dlam = costates(((Hz @ d[..., None])[..., 0] + rhs)[..., :n], A_t)[:, 1:]
        (grad_H,) = diffstack.params_gradients(cost, x, u, (H.detach().requires_grad_(),), dx, du)
        # the gradients wrt the dynamics (above), summed over the batch and the steps
        grad_A = outer_sum(dlam, x[:, :-1]) + outer_sum(lam, dx[:, :-1])
        grad_B = outer_sum(dlam, u) + outer_sum(lam, du)
        grad_b = dlam.sum((0, 1))
        return None, None, None, None, p0, grad_A, grad_B, grad_b, grad_H


def condensed_qp(P) -> tuple:
    """The problems in the controls alone: with U = (u_0, ..., u_{N-1}) (N m,) the states are
    affine in U and the cost is 1/2 U'M U + q'U + const, M (N m, N m) shared, q (batch, N m)."""
    cost, dynamics = StageQuadratic(), Affine(P["A"], P["B"], P["b"])
    N = P["u_init"].shape[1]

    def of(U, x0):  # one problem's cost
        u = U.reshape(1, N, LQR_NU)
        return cost(diffstack.rollout(dynamics, x0[None], u), u, P["H"])[0]

    U0 = torch.zeros(N * LQR_NU, dtype=torch.float64)
    M = torch.func.hessian(of)(U0, P["x_init"][0])
    q = torch.func.vmap(torch.func.grad(of), (None, 0))(U0, P["x_init"])
    return M, q


def kkt_residual(u, M, q, lo, hi):
    """How far the controls u (batch, N, m) are from the box QP's solution, in units of controls:
    the largest move of a projected coordinate-Newton step, |U - clamp(U - (M U + q) / diag M)|,
    0 exactly at the solution -> (batch,). Scaled by diag M because the unstable system (spectral
    radius 1.8) makes the gradient wrt u_0 some 1e5 times that wrt u_19."""
    U = u.reshape(len(u), -1)
    grad = U @ M + q  # (batch, N m); M is symmetric
    lo, hi = lo.repeat(u.shape[1]), hi.repeat(u.shape[1])
    return (U - (U - grad / M.diagonal()).clamp(lo, hi)).abs().amax(-1)


def reference_controls(M, q, lo, hi) -> torch.Tensor:
    """The box QP solved another way: bounded-variable least squares (scipy's lsq_linear, 'bvls',
    an active-set method that ends at the exact solution) on 1/2 ||L'U + L^-1 q||^2, M = L L'
    -> (batch, N, m). Its default cap of N m iterations stops it short on some problems here."""
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


def ours_lqr(P, settings, grad=False):
    """Our solve of the benchmark: x (batch, N+1, n), u (batch, N, m), iterations (batch,), and
    the parameters (x_init, A, B, b, H), which with grad require it."""
    args = [P[k] for k in ("x_init", "A", "B", "b", "H")]
    if grad:
        args = [a.detach().clone().requires_grad_() for a in args]
    x, u, _, iters = AffineLQR.apply(settings, P["lo"], P["hi"], P["u_init"], *args)
    return x, u, iters, args


def mpc_lqr(P, grad=False, **settings):
    """mpc.pytorch's solve, as the reference script runs it: (x (batch, N+1, n), u (batch, N, m),
    iterations, the parameters); its 21st control is dropped (it drives nothing and stays 0)."""
    from mpc import mpc as mpc_lib
    from mpc.dynamics import AffineDynamics

    Bsz, T1 = len(P["x_init"]), LQR_N + 1
    args = [P[k] for k in ("x_init", "A", "B", "b", "H")]
    if grad:
        args = [a.detach().clone().requires_grad_() for a in args]
    x_init, A, B, b, H = args
    ctrl = mpc_lib.MPC(
        LQR_NX,
        LQR_NU,
        T1,
        P["lo"].expand(T1, Bsz, LQR_NU).contiguous(),
        P["hi"].expand(T1, Bsz, LQR_NU).contiguous(),
        None,
        backprop=grad,
        exit_unconverged=False,
        n_batch=Bsz,
        verbose=-1,
        **settings,
    )
    passes = [0]
    subproblem = ctrl.solve_lqr_subproblem

    def counted(*a, **kw):  # one LQR pass per iteration, and one more on the best iterate
        passes[0] += 1
        return subproblem(*a, **kw)

    ctrl.solve_lqr_subproblem = counted
    zero = torch.zeros(LQR_NX + LQR_NU, dtype=torch.float64)
    with contextlib.redirect_stdout(io.StringIO()):  # its inner QP's "did not converge" lines
        x, u, _ = ctrl(x_init, mpc_lib.QuadCost(H, zero), AffineDynamics(A, B, b))
    return x.transpose(0, 1), u.transpose(0, 1), passes[0] - 1, args


LQR_CONVERGED = 1e-6  # a solve has converged when no control would move by more (kkt_residual)


def lqr_check(name, settings, P, M, q, ref, solve) -> dict:
    """One untimed solve with gradients: iterations, how many problems converged (kkt_residual
    below LQR_CONVERGED), the largest distance to the reference controls, the largest relative
    objective gap, and the gradient of the sum of the first controls wrt (A, B, b, H), flattened
    (248,)."""
    x, u, iters, args = solve(P, grad=True)
    u = u[:, :LQR_N]  # mpc.pytorch's idle 21st control dropped
    u[:, 0].sum().backward()
    res = kkt_residual(u.detach(), M, q, P["lo"], P["hi"])

    def objective(u):
        U = u.reshape(len(u), -1)
        return 0.5 * ((U @ M) * U).sum(-1) + (q * U).sum(-1)

    gap = (objective(u.detach()) - objective(ref)) / objective(ref).abs()
    iters = torch.as_tensor(iters).double()
    return dict(
        solver=name,
        settings=settings,
        iterations_median=iters.median().item(),
        iterations_max=iters.max().item(),
        converged=int((res < LQR_CONVERGED).sum()),
        residual_max=res.max().item(),
        max_du=(u.detach() - ref).abs().max().item(),
        gap_max=gap.max().item(),
        grad=torch.cat([a.grad.flatten() for a in args[1:]]),
    )


def compare_bounded_lqr(batch=LQR_BATCH, reps=3, quick=False, log=print, hint=True) -> dict:
    """The bounded-LQR benchmark (above) at both umax: ours at ilqr's defaults and run tight,
    mpc.pytorch as the reference script runs it (skipped with its hint when not installed); one
    thread, float64, alternating runs. Returns {rows, table, gradient}; --quick caps the
    iterations at 20."""
    mpc_lib, why = import_peer("mpc.mpc")
    if mpc_lib is None:  # hint: with its install line (not when compare_mpc gave it already)
        log(
            mpc_hint(why).replace("comparison", "bounded-LQR comparison")
            if hint
            else f"mpc.pytorch: {why}, left out of the bounded-LQR comparison"
        )
    cap = 20 if quick else None
    ours_settings = {
        k: dict(v, iters=min(v["iters"], cap or v["iters"])) for k, v in LQR_SETTINGS.items()
    }
    mpc_settings = dict(LQR_MPC, lqr_iter=min(LQR_MPC["lqr_iter"], cap or LQR_MPC["lqr_iter"]))
    solvers = {
        f"diffstack, {k}": (s, functools.partial(ours_lqr, settings=s))
        for k, s in ours_settings.items()
    }
    if mpc_lib is not None:
        solvers["mpc.pytorch"] = (mpc_settings, functools.partial(mpc_lqr, **mpc_settings))
    rows, table, gradient = [], [], {}
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # mpc 0.0.6 uses deprecated torch APIs
            for umax in LQR_UMAX:
                P = bounded_lqr_problem(umax, batch)
                M, q = condensed_qp(P)
                ref = reference_controls(M, q, P["lo"], P["hi"])
                checks = {n: lqr_check(n, s, P, M, q, ref, f) for n, (s, f) in solvers.items()}
                fns = {}
                for n, (_, f) in solvers.items():
                    fns[n + " fwd"] = functools.partial(f, P)
                    fns[n + " fwd+bwd"] = functools.partial(lqr_forward_backward, f, P)
                m = measure(fns, reps, 1, f"bounded LQR, umax {umax:g}")
                for n, c in checks.items():
                    fwd, both = m[n + " fwd"], m[n + " fwd+bwd"]
                    key = "lqr_" + n.replace(".", "_").replace(", ", "_") + f"_umax{umax:g}"
                    rows += [
                        figure(
                            key + "_fwd",
                            f"bounded LQR umax {umax:g}: {n} forward",
                            fwd.times,
                            1,
                            "f64",
                            batch,
                        ),
                        figure(
                            key + "_fwd_bwd",
                            f"bounded LQR umax {umax:g}: {n} forward + backward",
                            both.times,
                            1,
                            "f64",
                            batch,
                        ),
                    ]
                    table.append(
                        dict(
                            {k: v for k, v in c.items() if k != "grad"},
                            umax=umax,
                            batch=batch,
                            forward_ms=1e3 * fwd.median,
                            forward_backward_ms=1e3 * both.median,
                            us_per_problem_stage=1e6 * both.median / (batch * LQR_N),
                        )
                    )
                if "mpc.pytorch" in checks:
                    ours, mpc = checks["diffstack, tight"], checks["mpc.pytorch"]
                    # each passes gradients from the problems it converged on only
                    both = ours["converged"] == mpc["converged"] == batch
                    rel = (ours["grad"] - mpc["grad"]).norm() / mpc["grad"].norm()
                    gradient[f"{umax:g}"] = dict(
                        relative_difference=rel.item() if both else None,
                        converged=[ours["converged"], mpc["converged"]],
                    )
    finally:
        torch.set_num_threads(before)
    log_bounded_lqr(table, gradient, batch, reps, log)
    return dict(rows=rows, table=table, gradient_vs_mpc=gradient)


def lqr_forward_backward(solve, P):
    """A solve with the parameters requiring grad and the backward of the sum of the first
    controls: what the published "solution + adjoint sensitivities" column times."""
    _, u, _, args = solve(P, grad=True)
    u[:, 0].sum().backward()


def log_bounded_lqr(table, gradient, batch, reps, log):
    """The bounded-LQR tables: ours and mpc.pytorch measured here, then the published rows."""
    log(
        f"\nBounded LQR (FreyJo/differentiable_nmpc, Table 1): {batch} problems, N = {LQR_N}, "
        f"8 states, 4 controls, float64, one thread; median of {reps} alternating runs; "
        f"converged: no control moves by more than {LQR_CONVERGED:g} (scipy's bvls gives the "
        "reference solution)"
    )
    lines = [
        [
            f"{t['umax']:g}",
            t["solver"],
            ", ".join(f"{k} {v:g}" for k, v in t["settings"].items()),
            f"{t['forward_ms']:.1f}",
            f"{t['forward_backward_ms']:.1f}",
            f"{t['us_per_problem_stage']:.2f}",
            f"{t['iterations_median']:g} / {t['iterations_max']:g}",
            f"{t['converged']} / {t['batch']}",
            f"{t['max_du']:.1e}",
            f"{t['gap_max']:.1e}",
        ]
        for t in table
    ]
    head = [
        "umax",
        "solver",
        "settings",
        "fwd (ms)",
        "fwd+bwd (ms)",
        "µs / problem-stage",
        "iterations (median / max)",
        "converged",
        "max Δu to u*",
        "max objective gap",
    ]
    log(markdown_table(head, lines))
    for umax, g in gradient.items():
        rel, (ours, mpc) = g["relative_difference"], g["converged"]
        log(
            f"umax {umax}: gradient of sum u_0 wrt (A, B, b, H), diffstack (tight) vs "
            + (
                f"mpc.pytorch: relative difference {rel:.1e}"
                if rel is not None
                else f"mpc.pytorch: not compared, each passes gradients only from the problems "
                f"it converged on ({ours} and {mpc} of {table[0]['batch']})"
            )
        )
    log("Published (i7-8665U laptop, up to 4 threads; not measured here):")
    pub = []
    for umax, ac_f, ac_fb, mp_f, mp_fb in LQR_PUBLISHED:
        for name, f, fb in (("acados", ac_f, ac_fb), ("mpc.pytorch", ac_f * mp_f, ac_fb * mp_fb)):
            pub.append(
                [
                    f"{umax:g}",
                    name,
                    f"{f:.1f}",
                    f"{fb:.1f}",
                    f"{1e3 * fb / (LQR_BATCH * LQR_N):.2f}",
                ]
            )
    log(markdown_table(["umax", "solver", "fwd (ms)", "fwd+bwd (ms)", "µs / problem-stage"], pub))


# ============================================================================================
# 5. Running, the tables, the JSON file, the command line
# ============================================================================================

QUICK = dict(batch=16, reps=2, scenes=2, sim_time=2.0)  # --quick: seconds, not minutes


def device_name(device: torch.device) -> str:
    """The device in words: 'cpu', or the GPU's name (e.g. 'cuda:0, NVIDIA H100 80GB HBM3')."""
    if device.type == "cuda":
        return f"{device}, {torch.cuda.get_device_name(device)}"
    return str(device)


def results_table(rows) -> str:
    """The figures as one markdown table."""

    def num(v):
        return f"{v:.1f}" if v < 100 else f"{v:.0f}"

    return markdown_table(
        ["benchmark", "B", "dtype", "threads", "median (ms)", "IQR (ms)", "runs", "note"],
        [
            [
                r["benchmark"],
                "" if r["batch"] is None else str(r["batch"]),
                r["dtype"],
                str(r["threads"]),
                num(r["median_ms"]),
                num(r["iqr_ms"]),
                str(r["runs"]),
                r["note"],
            ]
            for r in rows
        ],
    )


def run(
    threads=(1, 2),
    reps=5,
    batch_size=256,
    quick=False,
    closed_loop=True,
    log=print,
    progress=None,
    device=torch.device("cpu"),
) -> dict:
    """Every benchmark; returns the JSON document (the headline keys first, then every figure). On a
    device other than the CPU our modules run there (the data drawn on the CPU and moved); the
    closed loop and the peers, whose ratios are defined on the CPU, are left out."""
    progress = progress or (lambda s: print(s, file=sys.stderr, flush=True))
    on_cpu = device.type == "cpu"
    cfg = Config()
    if quick:  # a small dataset in memory: nothing written to the cache
        data = data_synth.make_dataset(max(2 * batch_size, 64), seed=0)
    else:
        data = data_synth.load_or_generate(max(2000, 2 * batch_size), seed=0, cache_dir=DATA_CACHE)
    assert len(data.train) >= batch_size, (
        "about 85 % of the samples are for training: 2 B samples are enough"
    )
    batch = data.train[:batch_size].to(device=device)
    rows = []
    for nt in threads:
        torch.set_num_threads(nt)  # for the untimed set-up too; the Timers set it for every run
        progress(
            f"threads {nt}: controller, planner, predictor, DiffStack step (B = {batch_size}, "
            f"{reps} runs each)"
        )
        for dtype in (torch.float64, torch.float32):
            rows += bench_controller(batch_size, dtype, reps, nt, device=device)
        rows += bench_candidates(batch, cfg, reps, nt) + bench_predictor(batch, cfg, reps, nt)
        rows += bench_stack_step(batch, cfg, reps, nt)
    progress(
        "controller scaling: B = "
        + ("%d and %d" % ((batch_size, 2 * batch_size) if quick else (1024, 4096)))
    )
    scaling, per_problem = bench_controller_scaling(
        (batch_size, 2 * batch_size) if quick else (1024, 4096), min(reps, 3), device=device
    )
    rows += scaling
    if closed_loop and on_cpu:
        n, sim_time, cl_reps = (
            (QUICK["scenes"], QUICK["sim_time"], 1) if quick else (100, 10.0, min(reps, 3))
        )
        progress(
            f"closed loop: {n} scenes x {sim_time:g} s, one thread, {cl_reps} timed run(s) per "
            "stack"
        )
        scenes = (
            data.val_scenes
            if quick
            else data_synth.load_or_generate(10000, seed=0, cache_dir=DATA_CACHE).val_scenes
        )
        rows += bench_closed_loop(scenes, cfg, n, sim_time, cl_reps)
    where = "" if on_cpu else f" on {device_name(device)}"
    log(
        f"\nDiffStack benchmarks{where}: B = {batch_size}, torch {torch.__version__}, "
        f"{os.cpu_count()} cores; median and IQR of the timed runs (torch.utils.benchmark), at "
        "the thread count of each row"
    )
    log(results_table(rows) + "\n")
    mpc_res = pp_res = lqr_res = None
    if on_cpu:
        progress("peers: mpc.pytorch side by side")
        mpc_res = compare_mpc(batch_size, threads, reps, log=log)
        pp_batches = (batch_size,) if quick else PYPOSE_BATCHES
        progress(f"peers: PyPose side by side, B in {pp_batches}, one thread")
        pp_res = compare_pypose(pp_batches, reps, log=log)
        lqr_res = run_bounded_lqr(quick, reps, batch_size, log, progress, hint=False)
        rows += lqr_res["rows"]
    else:
        log(f"--device {device}: the closed loop and the peers (compared on the CPU) are left out")
    step_1 = [r["median_ms"] for r in rows if r["key"] == "stack_step" and r["threads"] == 1]
    return dict(
        stack_step_ms_1thread=step_1[0] if step_1 else None,  # None when --threads leaves out 1
        speedup_vs_mpc_pytorch=None if mpc_res is None else mpc_res["speedup"],
        # at B = 256 (--quick: its B)
        speedup_vs_pypose=None if pp_res is None else pp_res["speedup"],
        # iLQR fwd + bwd, f64, box, 1 thread: slope from B = 1024 to 4096
        controller_ms_per_problem=per_problem,
        meta=run_meta(threads, reps, batch_size, quick, device),
        figures=rows,
        mpc_pytorch=None
        if mpc_res is None
        else dict(figures=mpc_res["rows"], gradient_error=mpc_res["gradient_error"]),
        pypose=None
        if pp_res is None
        else dict(
            figures=pp_res["rows"],
            table=pp_res["table"],
            speedup_batch=pp_res["speedup_batch"],
            agreement=pp_res["agreement"],
            gradient_error=pp_res["gradient_error"],
        ),
        bounded_lqr=None if lqr_res is None else lqr_summary(lqr_res),
    )


def run_meta(threads, reps, batch_size, quick, device) -> dict:
    """Where and how the figures were taken."""
    return dict(
        date=time.strftime("%Y-%m-%d %H:%M"),
        machine=machine(),
        cores=os.cpu_count(),
        torch=torch.__version__,
        threads=list(threads),
        reps=reps,
        batch=batch_size,
        quick=quick,
        device=str(device),
        device_name=device_name(device),
    )


def run_bounded_lqr(quick, reps, batch_size, log=print, progress=None, hint=True) -> dict:
    """compare_bounded_lqr at the published size (--quick: at --batch, iterations capped)."""
    progress = progress or (lambda s: print(s, file=sys.stderr, flush=True))
    batch = batch_size if quick else LQR_BATCH
    progress(f"bounded LQR (differentiable_nmpc): {batch} problems, umax {LQR_UMAX}, one thread")
    return compare_bounded_lqr(batch, min(reps, 3), quick, log, hint)


def lqr_summary(res: dict) -> dict:
    """The bounded LQR's part of the JSON document."""
    return dict(table=res["table"], gradient_vs_mpc=res["gradient_vs_mpc"])


# what made a --json file, now and before the move into lab/
BENCH_COMMANDS = ("python -m lab.bench", "python bench.py")


def bench_result(path) -> bool:
    """Whether path holds what --json writes (which a later run may replace)."""
    try:
        doc = json.loads(pathlib.Path(path).read_text())
        return str(doc["meta"]["command"]).startswith(BENCH_COMMANDS) and "figures" in doc
    except (OSError, ValueError, KeyError, TypeError, RecursionError):
        return False


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(
        description="DiffStack benchmarks (torch.utils.benchmark): controller, planner, "
        "predictor, a training step, the closed loop, and mpc.pytorch and PyPose side by side."
    )
    ap.add_argument(
        "--threads",
        type=bounded(int, 1, 256, "--threads"),
        nargs="+",
        default=[1, 2],
        help="torch thread counts (default 1 2)",
    )
    ap.add_argument(
        "--reps",
        type=bounded(int, 1, 10_000, "--reps"),
        help="timed runs per figure (default 5; closed loop at most 3; --quick 2)",
    )
    ap.add_argument(
        "--batch",
        type=bounded(int, 1, 1_000_000, "--batch"),
        help="scenarios / problems per batch (default 256; --quick 16)",
    )
    ap.add_argument(
        "--json",
        type=pathlib.Path,
        metavar="PATH",
        help="also write every figure to this JSON file",
    )
    ap.add_argument(
        "--overwrite",
        action="store_true",
        help="let --json replace a file that is not an earlier bench.py result",
    )
    ap.add_argument(
        "--skip-closed-loop", action="store_true", help="leave out the closed-loop log replay"
    )
    ap.add_argument("--quick", action="store_true", help="tiny sizes and reps: well under a minute")
    ap.add_argument(
        "--bounded-lqr",
        action="store_true",
        help="only the bounded-LQR benchmark of FreyJo/differentiable_nmpc, ours beside "
        "mpc.pytorch (a few minutes; --quick: seconds)",
    )
    ap.add_argument(
        "--device",
        type=device_arg,
        default="cpu",
        help="where our modules run (cpu, cuda, cuda:N; default cpu); off the CPU the closed "
        "loop and the peers are left out",
    )
    args = ap.parse_args(argv)
    # MPS has no float64: the controller's rows would fail after the set-up
    if args.device.type == "mps":
        ap.error(
            "argument --device: mps has no float64, which the controller's benchmarks use; use "
            "cpu or cuda"
        )
    # before the minutes of work, not after: a folder, or a place no file can go
    if args.json is not None:
        if args.json.is_dir():
            ap.error(f"argument --json: {args.json} is a folder, expected a file path")
        if args.json.exists() and not args.overwrite and not bench_result(args.json):
            ap.error(
                f"argument --json: {args.json} exists and is no bench.py result; to keep it, "
                "name another file; to replace it, add --overwrite"
            )
        try:
            check_writable(args.json.parent, "--json")
        except ValueError as e:
            ap.error(f"argument {e}")
    reps = args.reps or (QUICK["reps"] if args.quick else 5)
    batch_size = args.batch or (QUICK["batch"] if args.quick else 256)
    threads = list(dict.fromkeys(args.threads))  # in the order given, once each
    before = torch.get_num_threads()
    try:  # the project's errors and a file's (the data cache, --json) as one line
        with one_line(ap):
            if args.bounded_lqr:
                res = run_bounded_lqr(args.quick, reps, batch_size)
                meta = run_meta(
                    [1], min(reps, 3), res["table"][0]["batch"], args.quick, args.device
                )
                doc = dict(bounded_lqr=lqr_summary(res), figures=res["rows"], meta=meta)
            else:
                doc = run(
                    threads,
                    reps,
                    batch_size,
                    args.quick,
                    not args.skip_closed_loop,
                    device=args.device,
                )
            doc["meta"]["command"] = command_line(
                "python -m lab.bench", sys.argv[1:] if argv is None else argv
            )
            if args.json is not None:
                args.json.parent.mkdir(parents=True, exist_ok=True)
                write_atomic(args.json, json.dumps(doc, indent=1))
                print(f"\nwrote {args.json}")
    finally:
        torch.set_num_threads(before)  # main() may run inside another process (the tests)
    return doc


if __name__ == "__main__":
    main()
