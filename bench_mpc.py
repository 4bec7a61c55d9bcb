"""diffstack's iLQR against locuslab/mpc.pytorch (`mpc` 0.0.6), side by side, on the same problems.

mpc.pytorch is no dependency of this project: install it in a throwaway venv,
    python3 -m venv /tmp/mpcvenv && /tmp/mpcvenv/bin/pip install torch==2.13.0 mpc==0.0.6 numpy
    /tmp/mpcvenv/bin/python bench_mpc.py
The problem is `diffstack.tracking_problem`: B = 256 unicycle tracking problems, 6 controls, dt 0.5,
box controls, float64. mpc.pytorch's T = 7 convention adds a 7th control that drives nothing; it gets
weight R and reference 0, so it stays 0 and costs nothing. Timings alternate between the two solvers
in one process (medians); gradients are compared with central finite differences of a tight solve.
"""
import statistics
import sys
import time
import warnings

import torch
from mpc import mpc as mpc_lib

import diffstack as ds

warnings.filterwarnings("ignore")  # mpc 0.0.6 uses deprecated torch.lu / uint8 masks


class UnicycleDx(torch.nn.Module):
    """The unicycle as mpc.pytorch wants it, with the exact closed-form Jacobians (GradMethods.ANALYTIC)."""

    def forward(self, x, u):
        return ds.unicycle_step(x, u, 0.5)

    def grad_input(self, x, u):
        return ds.unicycle_jacobians(x, u, 0.5)


def mpc_solve(P, x_init, x_ref, iters, eps):
    """One mpc.MPC solve of the tracking problem: x (B, T+1, 4), u (B, T, 2)."""
    B, T1, _ = x_ref.shape
    C = torch.diag(torch.cat([P["Q"], P["R"]])).expand(T1, B, 6, 6)
    u_ref = torch.cat([P["u_ref"], torch.zeros_like(P["u_ref"][:, :1])], 1)
    c = torch.cat([-P["Q"] * x_ref, -P["R"] * u_ref], -1).transpose(0, 1)  # (T+1, B, 6)
    lo, hi = P["lo"].expand(T1, B, 2).contiguous(), P["hi"].expand(T1, B, 2).contiguous()
    u0 = torch.cat([P["u_init"], torch.zeros_like(P["u_init"][:, :1])], 1).transpose(0, 1).contiguous()
    ctrl = mpc_lib.MPC(4, 2, T1, u_lower=lo, u_upper=hi, u_init=u0, lqr_iter=iters, eps=eps,
                       grad_method=mpc_lib.GradMethods.ANALYTIC, exit_unconverged=False, backprop=True,
                       verbose=-1, n_batch=B, linesearch_decay=0.2, max_linesearch_iter=5)
    x, u, _ = ctrl(x_init, mpc_lib.QuadCost(C, c), UnicycleDx())
    return x.transpose(0, 1), u.transpose(0, 1)[:, :-1]


def ours_solve(P, x_init, x_ref, iters, eps):
    x, u, _ = ds.ilqr_solve(ds.tracking_cost, ds.Unicycle(0.5), x_init, P["u_init"],
                            (x_ref, P["u_ref"], P["Q"], P["R"]), P["lo"], P["hi"], iters=iters, tol=eps)
    return x, u


def timings(P, solve, iters, eps):
    """(forward, backward) seconds of one solve + backward of sum of final positions wrt x_init and x_ref."""
    x_init, x_ref = P["x_init"].clone().requires_grad_(), P["x_ref"].clone().requires_grad_()
    t0 = time.perf_counter()
    x, _ = solve(P, x_init, x_ref, iters, eps)
    t1 = time.perf_counter()
    x[:, -1, :2].sum().backward()
    return t1 - t0, time.perf_counter() - t1


def gradient_errors(P, solve, idx, iters):
    """Relative error of d(x_T + y_T)/dx_init per problem in idx against central finite differences of our
    tight solve (which tests/test_diffstack.py checks against finite differences and unrolled autograd)."""
    sub = {k: (v[idx] if torch.is_tensor(v) and v.dim() > 1 else v) for k, v in P.items()}
    x_init = sub["x_init"].clone().requires_grad_()
    x, _ = solve(sub, x_init, sub["x_ref"], iters, 1e-9)
    (g,) = torch.autograd.grad((x[:, -1, 0] + x[:, -1, 1]).sum(), x_init)

    def loss(xi):
        x, u, _ = ds.ilqr(ds.tracking_cost, ds.Unicycle(0.5), xi, sub["u_init"], (sub["x_ref"], sub["u_ref"], sub["Q"], sub["R"]),
                          sub["lo"], sub["hi"], iters=200, tol=1e-12)
        return x[:, -1, 0] + x[:, -1, 1]

    h, fd = 1e-5, torch.zeros_like(g)
    for j in range(4):
        e = torch.zeros_like(sub["x_init"])
        e[:, j] = h
        fd[:, j] = (loss(sub["x_init"] + e) - loss(sub["x_init"] - e)) / (2 * h)
    return ((g - fd).norm(dim=-1) / fd.norm(dim=-1))


def main(reps=7, threads=(1, 2)):
    P = ds.tracking_problem(256, dtype=torch.float64)
    print("B = 256 unicycle tracking problems, T = 6, dt = 0.5, float64; medians of", reps, "alternating runs")
    print("| threads | iterations, tol | mpc.pytorch fwd / bwd (ms) | diffstack fwd / bwd (ms) | speed-up fwd / fwd+bwd |")
    print("|---|---|---|---|---|")
    for nt in threads:
        torch.set_num_threads(nt)
        for iters, eps in ((5, 0.01), (10, 1e-3)):
            runs = {"mpc": [], "ours": []}
            for k in range(reps + 1):
                for name, solve in (("mpc", mpc_solve), ("ours", ours_solve)):
                    t = timings(P, solve, iters, eps)
                    if k:  # the first round warms up
                        runs[name].append(t)
            med = {n: [1e3 * statistics.median(r[i] for r in v) for i in (0, 1)] for n, v in runs.items()}
            (mf, mb), (of, ob) = med["mpc"], med["ours"]
            print(f"| {nt} | {iters}, {eps} | {mf:.0f} / {mb:.1f} | {of:.0f} / {ob:.1f} | {mf / of:.2f}x / {(mf + mb) / (of + ob):.2f}x |")
    torch.set_num_threads(1)
    idx = torch.arange(0, 256, 16)
    for name, solve in (("mpc.pytorch", mpc_solve), ("diffstack", ours_solve)):
        err = gradient_errors(P, solve, idx, 100)
        q = err.quantile(torch.tensor([0.5, 0.9], dtype=err.dtype))
        print(f"{name:12s} d(x_T + y_T)/d x_init vs finite differences, {len(idx)} problems: median {q[0]:.1e}, "
              f"90th percentile {q[1]:.1e}, max {err.max():.1e}")


if __name__ == "__main__":
    main(reps=int(sys.argv[1]) if len(sys.argv) > 1 else 7)
