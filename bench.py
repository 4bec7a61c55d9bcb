"""Benchmarks of the DiffStack reference: every timing of the project, in one module.

    python bench.py                                   # everything at 1 and 2 threads, B = 256 (a few minutes)
    python bench.py --threads 1 --reps 3 --skip-closed-loop
    python bench.py --quick                           # tiny sizes and reps, well under a minute (test_bench.py)
    python bench.py --json results/bench.json         # also every figure, in a JSON file

What is timed (B = --batch scenarios or problems, default 256):
    controller    ilqr_solve's forward (box-constrained iLQR, up to 5 iterations, tol 0.01) and its KKT backward on
                  tracking_problem (B unicycle tracking problems, T = 6, dt 0.5), in float64 and float32
    planner       plan_candidates: the planner's spline candidates (48 per scenario)
    predictor     a training iteration (forward, InfoVAE loss, backward, Adam step) and an eval forward (K = 25)
    stack         one DiffStack training step (RL): run_stack and the backward of L = a1 L_pred + a2 L_plan + a3 L_ctr;
                  its parts predict / plan / control / backward are run_stack's `timings` laps (perf_counter)
    closed loop   log replay of 100 scenes x 10 s (20 replanning steps) with each stack of Table 5, one thread
    peers         the controller side by side with mpc.pytorch on the same problems, with the same solver settings,
                  and both gradients against finite differences; PyPose: not implemented yet (a later issue)

How: every figure is a torch.utils.benchmark.Timer measurement at a stated torch thread count (Timer's num_threads):
the median and the interquartile range (IQR) of --reps timed runs. Each timed run follows an untimed run of the same
code (blocked_autorange(min_run_time=0) runs the statement once to size its block, then times one block of one run),
and the benchmarks measured together take turns, so that a change in the machine's load hits them alike.

--json PATH writes (atomically) stack_step_ms_1thread (the whole DiffStack step at one thread; null when --threads
leaves out 1), speedup_vs_mpc_pytorch (mpc.pytorch time / ours, iLQR forward + backward, 5 iterations, float64, box
controls, at the fewest threads; null without mpc), speedup_vs_pypose (null: not implemented yet), meta, figures
(every row of the table: key, benchmark, dtype, threads, batch, median_ms, iqr_ms, runs, note) and mpc_pytorch.

Peers are no dependencies of the project. Without one, its part is skipped with a one-line hint; to compare, install
it in a throwaway venv (--no-deps keeps the torch of requirements.txt):
    python3 -m venv /tmp/peers && /tmp/peers/bin/pip install -r requirements.txt && /tmp/peers/bin/pip install --no-deps mpc==0.0.6
    /tmp/peers/bin/python bench.py

Map of the module:
    1. Measuring     measure(): Timer measurements taking turns; figure(): one row of the results
    2. The problem   tracking_problem, tracking_cost: the controller's benchmark, shared with the peers
    3. Our modules   controller, planner, predictor, a DiffStack training step, the closed loop
    4. Peers         mpc.pytorch side by side (skipped with a hint when it is not installed)
    5. Running       run(), the tables, the JSON file, the command line
"""
from __future__ import annotations

import argparse
import importlib
import itertools
import json
import math
import os
import pathlib
import platform
import statistics
import sys
import time
import warnings

import torch
import torch.utils.benchmark as benchmark

import data_synth
from diffstack import (Config, Method, Predictor, Unicycle, alphas, bounded, markdown_table, ilqr, ilqr_solve, plan_candidates, pred_loss,
                       run_stack, unicycle_jacobians, unicycle_rollout)
from experiments import CLOSED_LOOP_METHODS, closed_loop_scenes, simulate, stack_policy, write_atomic

DATA_CACHE = pathlib.Path(__file__).resolve().parent / "data_cache"

# ============================================================================================
# 1. Measuring
# ============================================================================================


def measure(fns: dict, reps: int, threads: int, label: str = "") -> dict:
    """{name: torch.utils.benchmark Measurement of fns[name]()}: reps timed runs of each callable at `threads`
    torch threads. The callables take turns, one run each per round (a drift in load hits them alike); each timed
    run follows an untimed one of the same callable, which blocked_autorange(min_run_time=0) makes to size its
    block (one run for anything slower than microseconds) -- so no callable inherits another's warm caches."""
    timers = {name: benchmark.Timer("fn()", globals={"fn": fn}, label=label, description=name, num_threads=threads)
              for name, fn in fns.items()}
    runs = {name: [] for name in fns}
    for _ in range(reps):
        for name, timer in timers.items():
            runs[name].append(timer.blocked_autorange(min_run_time=0))
    return {name: benchmark.Measurement.merge(ms)[0] for name, ms in runs.items()}  # one Measurement per callable


def figure(key: str, name: str, times, threads: int, dtype="", batch=None, note="") -> dict:
    """One row of the results: median and IQR (ms) of run times (s; a Measurement's .times, or perf_counter laps),
    quartiles interpolated linearly as Measurement.iqr does."""
    times = sorted(times)
    q1, q3 = statistics.quantiles(times, n=4, method="inclusive")[::2] if len(times) > 1 else (times[0], times[0])
    return dict(key=key, benchmark=name, dtype=dtype, threads=threads, batch=batch,
                median_ms=1e3 * statistics.median(times),
                iqr_ms=1e3 * (q3 - q1), runs=len(times), note=note)


# ============================================================================================
# 2. The problem: unicycle tracking, shared with the peers
# ============================================================================================


def tracking_problem(B=256, T=6, dtype=torch.float64, seed=0):
    """B unicycle tracking problems, the benchmark shared with mpc.pytorch (section 4):
        min sum_t 1/2 (s_t - r_t)' Q (s_t - r_t) + 1/2 (u_t - ur_t)' R (u_t - ur_t),  box controls,
    the reference rolled out from smooth random controls (some outside the box), the start perturbed."""
    g = torch.Generator().manual_seed(seed)
    U = lambda lo, hi, *shape: lo + (hi - lo) * torch.rand(*shape, generator=g, dtype=dtype)  # noqa: E731
    x0 = torch.stack([U(-20, 20, B), U(-20, 20, B), U(-math.pi, math.pi, B), U(2.0, 15.0, B)], -1)
    tt = torch.arange(T, dtype=dtype) / (T - 1)
    u_ref = torch.stack([U(-0.5, 0.5, B, 1) + U(-0.6, 0.6, B, 1) * tt, U(-3.0, 2.5, B, 1) + U(-3.5, 3.5, B, 1) * tt], -1)
    x_ref = unicycle_rollout(x0, u_ref, 0.5)  # (B, T+1, 4)
    x_init = x0 + torch.randn(B, 4, generator=g, dtype=dtype) * torch.tensor([1.0, 1.0, 0.15, 1.0], dtype=dtype)
    Q, R = torch.tensor([1.0, 1.0, 1.0, 0.2], dtype=dtype), torch.tensor([0.5, 0.1], dtype=dtype)
    cfg = Config()
    lo, hi = torch.tensor(cfg.u_lower, dtype=dtype), torch.tensor(cfg.u_upper, dtype=dtype)
    return dict(x_init=x_init, x_ref=x_ref, u_ref=u_ref, Q=Q, R=R, lo=lo, hi=hi, u_init=u_ref.clamp(lo, hi))


def tracking_cost(x, u, x_ref, u_ref, Q, R):
    """The tracking benchmark's cost: x (B, *S, T+1, 4), u (B, *S, T, 2) -> (B, *S)."""
    view = lambda t: t.reshape(t.shape[0], *([1] * (x.dim() - 3)), *t.shape[1:])  # noqa: E731
    return 0.5 * ((x - view(x_ref)) ** 2 * Q).sum((-1, -2)) + 0.5 * ((u - view(u_ref)) ** 2 * R).sum((-1, -2))


# ============================================================================================
# 3. Our modules
# ============================================================================================


def bench_controller(B=256, dtype=torch.float64, reps=5, threads=1, iters=5, tol=0.01) -> list:
    """iLQR forward and KKT backward on the tracking problem; the note gives the converged share."""
    P = tracking_problem(B, dtype=dtype)
    params = (P["x_ref"], P["u_ref"], P["Q"], P["R"])

    def solve(x_init, params):
        return ilqr_solve(tracking_cost, Unicycle(0.5), x_init, P["u_init"], params, P["lo"], P["hi"],
                          iters=iters, tol=tol)

    # the backward alone: one solve with x_init and x_ref requiring grad builds the graph, each run walks it
    # again (retain_graph keeps ILQR's saved tensors; the gradients accumulating in .grad cost a few additions)
    x_init, x_ref = P["x_init"].clone().requires_grad_(), P["x_ref"].clone().requires_grad_()
    x, u, converged = solve(x_init, (x_ref, *params[1:]))  # (B, T+1, 4), (B, T, 2), (B,)
    loss = x.sum()
    m = measure({"forward": lambda: solve(P["x_init"], params), "backward": lambda: loss.backward(retain_graph=True)},
                reps, threads, "controller")
    dt, conv = str(dtype).replace("torch.float", "f"), f"converged {converged.float().mean().item():.2f}"
    return [figure(f"ilqr_forward_{dt}", f"iLQR forward ({iters} iterations, tol {tol})", m["forward"].times, threads,
                   dt, B, conv),
            figure(f"kkt_backward_{dt}", "KKT backward", m["backward"].times, threads, dt, B)]


def bench_candidates(batch, cfg: Config, reps=5, threads=1) -> list:
    """The planner's candidate splines (plan_candidates) for every scenario of the batch."""
    s0 = batch.ego_hist[:, -1]  # (B, 4)
    m = measure({"candidates": lambda: plan_candidates(s0, batch.goal, batch.lanes, batch.lanes_mask, cfg)},
                reps, threads, "planner")
    n = 24 * cfg.max_goal_lanes  # 8 accelerations x 3 offsets per goal lane
    return [figure("candidates", f"planner: candidates (up to {n} per scenario)", m["candidates"].times, threads, "f32",
                   len(batch))]


def bench_predictor(batch, cfg: Config | None = None, reps=5, threads=1) -> list:
    """A training iteration (forward with q(z|x,y), InfoVAE loss, backward, Adam step) and an eval forward."""
    cfg = cfg or Config()
    torch.manual_seed(0)
    model = Predictor(cfg).to(batch.agent_hist.dtype)
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
    return [figure("predictor_train", f"predictor: training iteration ({what})", m["train"].times, threads, "f32",
                   len(batch)),
            figure("predictor_eval", "predictor: eval forward", m["eval"].times, threads, "f32", len(batch))]


def bench_stack_step(batch, cfg: Config, reps=5, threads=1) -> list:
    """One DiffStack training step (RL): run_stack with train=True, then the backward of the weighted losses.
    The whole step is a Timer measurement; its parts are run_stack's perf_counter laps over the same runs (the
    untimed ones too, all but the very first, which pays for first-call allocations)."""
    torch.manual_seed(0)
    model = Predictor(cfg)
    method = Method("DiffStack", losses=(1, 1, 1))
    a1, a2, a3 = alphas(method, "rl", cfg)
    laps = []

    def step():
        t = {}
        out = run_stack(batch, model, method, cfg, "rl", step=0, train=True, timings=t)  # fills predict, plan, control
        t0 = time.perf_counter()
        (a1 * out.l_pred.mean() + a2 * out.l_plan.mean() + a3 * out.l_ctr.mean()).backward()
        t["backward"] = time.perf_counter() - t0
        laps.append(t)

    m = measure({"step": step}, reps, threads, "DiffStack step")
    rows = [figure("stack_step", "DiffStack training step (RL)", m["step"].times, threads, "f32", len(batch))]
    for part in ("predict", "plan", "control", "backward"):
        rows.append(figure(f"stack_{part}", f"DiffStack step: {part} (perf_counter lap)", [t[part] for t in laps[1:]],
                           threads, "f32", len(batch)))
    return rows


def bench_closed_loop(scenes, cfg: Config | None = None, n=100, sim_time=10.0, reps=3) -> list:
    """Log replay of n scenes for sim_time with each stack of Table 5, one thread. The predictor is untrained:
    the time does not depend on its weights."""
    cfg = cfg or Config()
    scenes = closed_loop_scenes(scenes, cfg, sim_time)[:n]
    torch.manual_seed(0)
    model = Predictor(cfg)

    def replay(method):
        policy = stack_policy(model if method.predictor == "learned" else None, method, cfg)
        return lambda: simulate(scenes, policy, cfg, sim_time)

    m = measure({meth.name: replay(meth) for meth in CLOSED_LOOP_METHODS}, reps, 1, "closed loop")
    what = f"{len(scenes)} scenes x {sim_time:g} s"
    return [figure("closed_loop_" + name.lower().replace(" ", "_"), f"closed loop, {name} ({what})", mm.times, 1, "f32")
            for name, mm in m.items()]


# ============================================================================================
# 4. Peers: mpc.pytorch (locuslab, `mpc` 0.0.6), side by side
# ============================================================================================
#
# The same problems (tracking_problem, float64), the same initial controls, iterations, tolerance, line search
# (decay 1/5, 5 steps) and box; runs alternate in one process. mpc.pytorch's T = 7 convention adds a 7th control
# that drives nothing: it gets weight R and reference 0, so it stays 0 and costs nothing.

PEER_VENV = ("python3 -m venv /tmp/peers && /tmp/peers/bin/pip install -r requirements.txt && "
             "/tmp/peers/bin/pip install --no-deps mpc==0.0.6")
PYPOSE_NOTE = "pypose: skipped, the PyPose comparison is not implemented yet (speedup_vs_pypose: null)"


def import_peer(name: str):
    """(module, None), or (None, why) when it cannot be imported: a missing peer is a skip, never a traceback."""
    try:
        return importlib.import_module(name), None
    except ImportError:
        return None, "not installed"
    except Exception as e:  # noqa: BLE001  (a peer built for another torch may fail any way on import)
        return None, f"import failed: {type(e).__name__}: {' '.join(str(e).split())}"


def mpc_hint(why: str) -> str:
    """The one line printed instead of the mpc.pytorch comparison."""
    return (f"mpc.pytorch: {why}, comparison skipped (speedup_vs_mpc_pytorch: null). To run it: {PEER_VENV} "
            "then /tmp/peers/bin/python bench.py")


class UnicycleDx(torch.nn.Module):
    """The unicycle as mpc.pytorch wants it, with the exact closed-form Jacobians (GradMethods.ANALYTIC)."""

    def forward(self, x, u):
        return Unicycle(0.5)(x, u)  # the unchecked step our solver uses too, so both pay the same

    def grad_input(self, x, u):
        return unicycle_jacobians(x, u, 0.5)


def mpc_solve(P, x_init, x_ref, iters, eps):
    """One mpc.MPC solve of the tracking problem: x (B, T+1, 4), u (B, T, 2)."""
    from mpc import mpc as mpc_lib  # a dictionary look-up after the first import

    B, T1, _ = x_ref.shape
    C = torch.diag(torch.cat([P["Q"], P["R"]])).expand(T1, B, 6, 6)
    u_ref = torch.cat([P["u_ref"], torch.zeros_like(P["u_ref"][:, :1])], 1)  # (B, T+1, 2) the idle 7th control
    c = torch.cat([-P["Q"] * x_ref, -P["R"] * u_ref], -1).transpose(0, 1)  # (T+1, B, 6)
    lo, hi = P["lo"].expand(T1, B, 2).contiguous(), P["hi"].expand(T1, B, 2).contiguous()
    u0 = torch.cat([P["u_init"], torch.zeros_like(P["u_init"][:, :1])], 1).transpose(0, 1).contiguous()  # (T+1, B, 2)
    ctrl = mpc_lib.MPC(4, 2, T1, u_lower=lo, u_upper=hi, u_init=u0, lqr_iter=iters, eps=eps,
                       grad_method=mpc_lib.GradMethods.ANALYTIC, exit_unconverged=False, backprop=True,
                       verbose=-1, n_batch=B, linesearch_decay=0.2, max_linesearch_iter=5)
    x, u, _ = ctrl(x_init, mpc_lib.QuadCost(C, c), UnicycleDx())  # time-major: (T+1, B, 4), (T+1, B, 2)
    return x.transpose(0, 1), u.transpose(0, 1)[:, :-1]


def ours_solve(P, x_init, x_ref, iters, eps):
    """The same solve with diffstack's controller: x (B, T+1, 4), u (B, T, 2)."""
    x, u, _ = ilqr_solve(tracking_cost, Unicycle(0.5), x_init, P["u_init"], (x_ref, P["u_ref"], P["Q"], P["R"]),
                         P["lo"], P["hi"], iters=iters, tol=eps)
    return x, u


def solver_runs(P, solve, iters, eps):
    """(forward, backward) callables: a solve with x_init and x_ref requiring grad (both solvers build their graph
    in the forward), and the backward of the final positions' sum wrt them on one prebuilt graph."""
    x_init, x_ref = P["x_init"].clone().requires_grad_(), P["x_ref"].clone().requires_grad_()
    x, _ = solve(P, x_init, x_ref, iters, eps)
    loss = x[:, -1, :2].sum()  # the final positions depend on every control: the gradient crosses every step
    return (lambda: solve(P, x_init, x_ref, iters, eps)), (lambda: loss.backward(retain_graph=True))


def gradient_errors(P, solve, idx, iters):
    """Relative error of d(x_T + y_T)/dx_init per problem in idx against central finite differences of our
    tight solve (which test_diffstack.py checks against finite differences and unrolled autograd)."""
    sub = {k: (v[idx] if torch.is_tensor(v) and v.dim() > 1 else v) for k, v in P.items()}
    x_init = sub["x_init"].clone().requires_grad_()
    x, _ = solve(sub, x_init, sub["x_ref"], iters, 1e-9)
    (g,) = torch.autograd.grad((x[:, -1, 0] + x[:, -1, 1]).sum(), x_init)  # (b, 4)

    def loss(xi):
        x, u, _ = ilqr(tracking_cost, Unicycle(0.5), xi, sub["u_init"], (sub["x_ref"], sub["u_ref"], sub["Q"], sub["R"]),
                       sub["lo"], sub["hi"], iters=200, tol=1e-12)
        return x[:, -1, 0] + x[:, -1, 1]

    h, fd = 1e-5, torch.zeros_like(g)
    for j in range(4):
        e = torch.zeros_like(sub["x_init"])
        e[:, j] = h
        fd[:, j] = (loss(sub["x_init"] + e) - loss(sub["x_init"] - e)) / (2 * h)
    return (g - fd).norm(dim=-1) / fd.norm(dim=-1)  # (b,)


def compare_mpc(B=256, threads=(1, 2), reps=5, log=print) -> dict | None:
    """diffstack's iLQR against mpc.pytorch on tracking_problem(B), float64, at 5 iterations / tol 0.01 and 10 /
    1e-3. Returns {rows, speedup (mpc time / ours, forward + backward, 5 iterations, the fewest threads),
    gradient_error}, or None after one line of hint when mpc cannot be imported."""
    mpc_lib, why = import_peer("mpc.mpc")
    if mpc_lib is None:
        log(mpc_hint(why))
        return None
    P = tracking_problem(B, dtype=torch.float64)
    head = ["threads", "iterations, tol", "mpc.pytorch fwd / bwd (ms)", "diffstack fwd / bwd (ms)",
            "speed-up fwd / fwd+bwd"]
    rows, lines, speedup = [], [], None
    ms = lambda m: f"{1e3 * m.median:.1f} (±{1e3 * m.iqr:.1f})"  # noqa: E731
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # mpc 0.0.6 uses deprecated torch APIs (torch.lu, uint8 masks)
        for nt in sorted(threads):
            for iters, eps in ((5, 0.01), (10, 1e-3)):
                fns = {}
                for name, solve in (("mpc", mpc_solve), ("ours", ours_solve)):
                    fns[name + " fwd"], fns[name + " bwd"] = solver_runs(P, solve, iters, eps)
                m = measure(fns, reps, nt, f"iLQR vs mpc.pytorch, {iters} iterations")
                med = {k: v.median for k, v in m.items()}
                fwd = med["mpc fwd"] / med["ours fwd"]
                total = (med["mpc fwd"] + med["mpc bwd"]) / (med["ours fwd"] + med["ours bwd"])
                if speedup is None:  # the headline: the controller's default settings, the fewest threads
                    speedup = total
                for k, v in m.items():
                    rows.append(figure(f"{k.replace(' ', '_')}_{iters}it", f"{k}, {iters} iterations, tol {eps}",
                                       v.times, nt, "f64", B))
                lines.append([str(nt), f"{iters}, {eps}", f"{ms(m['mpc fwd'])} / {ms(m['mpc bwd'])}",
                              f"{ms(m['ours fwd'])} / {ms(m['ours bwd'])}", f"{fwd:.2f}x / {total:.2f}x"])
        idx = torch.arange(0, B, 16)  # 16 problems at B = 256
        errors = {}
        for name, solve in (("mpc.pytorch", mpc_solve), ("diffstack", ours_solve)):
            err = gradient_errors(P, solve, idx, 100)
            q = err.quantile(torch.tensor([0.5, 0.9], dtype=err.dtype))
            errors[name] = dict(median=q[0].item(), p90=q[1].item(), max=err.max().item(), problems=len(idx))
    log(f"mpc.pytorch side by side: B = {B} unicycle tracking problems, T = 6, dt 0.5, float64, box controls; "
        f"median (IQR) of {reps} alternating runs")
    log(markdown_table(head, lines))
    for name, e in errors.items():
        log(f"{name:12s} d(x_T + y_T)/d x_init vs finite differences, {e['problems']} problems: median {e['median']:.1e}, "
            f"90th percentile {e['p90']:.1e}, max {e['max']:.1e}")
    return dict(rows=rows, speedup=speedup, gradient_error=errors)


# ============================================================================================
# 5. Running, the tables, the JSON file, the command line
# ============================================================================================

QUICK = dict(batch=16, reps=2, scenes=2, sim_time=2.0)  # --quick: seconds, not minutes


def results_table(rows) -> str:
    """The figures as one markdown table."""
    num = lambda v: f"{v:.1f}" if v < 100 else f"{v:.0f}"  # noqa: E731
    return markdown_table(["benchmark", "B", "dtype", "threads", "median (ms)", "IQR (ms)", "runs", "note"],
                    [[r["benchmark"], "" if r["batch"] is None else str(r["batch"]), r["dtype"], str(r["threads"]),
                      num(r["median_ms"]), num(r["iqr_ms"]), str(r["runs"]), r["note"]] for r in rows])


def run(threads=(1, 2), reps=5, batch_size=256, quick=False, closed_loop=True, log=print, progress=None) -> dict:
    """Every benchmark; returns the JSON document (the headline keys first, then every figure)."""
    progress = progress or (lambda s: print(s, file=sys.stderr, flush=True))
    cfg = Config()
    if quick:  # a small dataset in memory: nothing written to the cache
        data = data_synth.make_dataset(max(2 * batch_size, 64), seed=0)
    else:
        data = data_synth.load_or_generate(max(2000, 2 * batch_size), seed=0, cache_dir=DATA_CACHE)
    assert len(data.train) >= batch_size, "about 85 % of the samples are for training: 2 B samples are enough"
    batch = data.train[:batch_size]
    rows = []
    for nt in threads:
        torch.set_num_threads(nt)  # for the untimed set-up too; the Timers set it for every run
        progress(f"threads {nt}: controller, planner, predictor, DiffStack step (B = {batch_size}, {reps} runs each)")
        for dtype in (torch.float64, torch.float32):
            rows += bench_controller(batch_size, dtype, reps, nt)
        rows += bench_candidates(batch, cfg, reps, nt) + bench_predictor(batch, cfg, reps, nt)
        rows += bench_stack_step(batch, cfg, reps, nt)
    if closed_loop:
        n, sim_time, cl_reps = (QUICK["scenes"], QUICK["sim_time"], 1) if quick else (100, 10.0, min(reps, 3))
        progress(f"closed loop: {n} scenes x {sim_time:g} s, one thread, {cl_reps} timed run(s) per stack")
        scenes = data.val_scenes if quick else data_synth.load_or_generate(10000, seed=0, cache_dir=DATA_CACHE).val_scenes
        rows += bench_closed_loop(scenes, cfg, n, sim_time, cl_reps)
    log(f"\nDiffStack benchmarks: B = {batch_size}, torch {torch.__version__}, {os.cpu_count()} cores; median and IQR "
        f"of the timed runs (torch.utils.benchmark), at the thread count of each row")
    log(results_table(rows) + "\n")
    progress("peers: mpc.pytorch side by side")
    mpc_res = compare_mpc(batch_size, threads, reps, log=log)
    log(PYPOSE_NOTE)
    step_1 = [r["median_ms"] for r in rows if r["key"] == "stack_step" and r["threads"] == 1]
    return dict(
        stack_step_ms_1thread=step_1[0] if step_1 else None,  # None when --threads leaves out 1
        speedup_vs_mpc_pytorch=None if mpc_res is None else mpc_res["speedup"],
        speedup_vs_pypose=None,  # not implemented yet
        meta=dict(date=time.strftime("%Y-%m-%d %H:%M"), machine=platform.machine(), cores=os.cpu_count(),
                  torch=torch.__version__, threads=list(threads), reps=reps, batch=batch_size, quick=quick),
        figures=rows,
        mpc_pytorch=None if mpc_res is None else dict(figures=mpc_res["rows"], gradient_error=mpc_res["gradient_error"]),
    )


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description="DiffStack benchmarks (torch.utils.benchmark): controller, planner, "
                                             "predictor, a training step, the closed loop, and mpc.pytorch side by side.")
    ap.add_argument("--threads", type=bounded(int, 1, 256, "--threads"), nargs="+", default=[1, 2], help="torch thread counts (default 1 2)")
    ap.add_argument("--reps", type=bounded(int, 1, 10_000, "--reps"), help="timed runs per figure (default 5; closed loop at most 3; --quick 2)")
    ap.add_argument("--batch", type=bounded(int, 1, 1_000_000, "--batch"), help="scenarios / problems per batch (default 256; --quick 16)")
    ap.add_argument("--json", type=pathlib.Path, metavar="PATH", help="also write every figure to this JSON file")
    ap.add_argument("--skip-closed-loop", action="store_true", help="leave out the closed-loop log replay")
    ap.add_argument("--quick", action="store_true", help="tiny sizes and reps: well under a minute")
    args = ap.parse_args(argv)
    if args.json is not None and args.json.is_dir():
        ap.error(f"argument --json: {args.json} is a folder, expected a file path")
    reps = args.reps or (QUICK["reps"] if args.quick else 5)
    batch_size = args.batch or (QUICK["batch"] if args.quick else 256)
    threads = list(dict.fromkeys(args.threads))  # in the order given, once each
    before = torch.get_num_threads()
    try:
        doc = run(threads, reps, batch_size, args.quick, not args.skip_closed_loop)
    finally:
        torch.set_num_threads(before)  # main() may run inside another process (the tests)
    doc["meta"]["command"] = " ".join(["python bench.py", *(sys.argv[1:] if argv is None else argv)])
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        write_atomic(args.json, json.dumps(doc, indent=1))
        print(f"\nwrote {args.json}")
    return doc


if __name__ == "__main__":
    main()
