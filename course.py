"""The checks of tutorial.ipynb's exercises.

Each check_* builds its own small problems (seeded, float64), runs the student's function on them and compares with
an independent answer (the module's function, autograd, or a closed form). A wrong answer raises AssertionError
with what differs and a hint; a stub that still raises NotImplementedError is reported as not done, so that
*Run All* goes on past an exercise the student has not tried yet. test_tutorial.py feeds every check known-wrong
answers and asserts that it catches each one.
"""

import torch

import diffstack as ds

F64 = torch.float64


def _close(name, mine, ref, tol, hint):
    """Assert mine ~ ref (same shape, finite, max abs difference <= tol * max(1, |ref|max))."""
    mine = torch.as_tensor(mine)
    assert mine.shape == ref.shape, f"{name}: shape {tuple(mine.shape)}, expected {tuple(ref.shape)}. {hint}"
    assert torch.isfinite(mine).all(), f"{name}: contains inf or NaN. {hint}"
    err = (mine.to(ref.dtype) - ref).abs().max().item()
    scale = max(1.0, ref.abs().max().item())
    assert err <= tol * scale, f"{name}: max |yours - reference| = {err:.3g} (allowed {tol * scale:.1g}). {hint}"
    return err


def exercise(number, check, fn):
    """Run one exercise's check from a notebook cell: PASS, not done yet (the stub raised NotImplementedError),
    or AssertionError (a wrong answer: the message says what differs). Returns True on PASS."""
    try:
        detail = check(fn)
    except NotImplementedError:
        print(f"EXERCISE {number}: not done yet: fill in `{fn.__name__}` in the cell above, run it, then this cell. "
              f"(The rest of the notebook does not need it.)")
        return False
    print(f"EXERCISE {number}: PASS ({detail})")
    return True


# --- exercise 1: the collision term ----------------------------------------------------------------------------


def collision_problem(seed=0, B=6, N=7, K=5, T=6, A=3):
    """Ego positions (B, N, T, 2) near a multi-mode prediction, and a CostContext in which some scenarios have no
    predicted agent (pred_mask 0) and some other agents are masked out."""
    g = torch.Generator().manual_seed(seed)
    preds = 3 * torch.randn(B, K, T, 2, generator=g, dtype=F64)
    probs = torch.softmax(2 * torch.randn(B, K, generator=g, dtype=F64), -1)  # far from uniform
    pred_mask = (torch.arange(B) % 3 != 1).to(F64)  # scenarios 1, 4: no predicted agent
    others = 3 * torch.randn(B, A, T, 2, generator=g, dtype=F64)
    others_mask = torch.ones(B, A, dtype=F64)
    others_mask[::2, 0] = 0  # some other agents absent
    lanes = torch.zeros(B, 1, 5, 3, dtype=F64)
    lanes[..., 0] = torch.linspace(-10, 30, 5, dtype=F64)
    ctx = ds.CostContext(preds, probs, pred_mask, others, others_mask, torch.zeros(B, 2, dtype=F64), lanes,
                         torch.ones(B, 1, 5, dtype=torch.bool))
    pos = 3 * torch.randn(B, N, T, 2, generator=g, dtype=F64)
    return pos, ctx


def check_collision(fn):
    hint = ("C_coll = pred_mask * sum_t phi(sum_k pi_k ||s_t - s^_kt||^2) + sum_a mask_a sum_t phi(||s_t - s_at||^2), "
            "phi(d2) = exp(-d2 / (2 rbf_var)); the expectation is over squared distances, not of positions.")
    worst = 0.0
    for seed, rbf_var in ((0, 2.0), (1, 3.5)):
        pos, ctx = collision_problem(seed)
        worst = max(worst, _close("my_collision", fn(pos, ctx, rbf_var), ds.collision_term(pos, ctx, rbf_var), 1e-9, hint))
    return f"max error {worst:.1e}, 2 problems, masks and rbf_var varied"


# --- exercise 2: the relaxed planner's loss ---------------------------------------------------------------------


def plan_problem(seed=0, B=8, N=12):
    """Candidate costs in the thousands (B, N), a valid mask with invalid candidates cheaper than every valid
    one (a softmax that ignores the mask picks them), and targets n* among the valid ones."""
    g = torch.Generator().manual_seed(seed)
    cost = 2000 + 3 * torch.randn(B, N, generator=g, dtype=F64)
    valid = torch.rand(B, N, generator=g) > 0.3
    valid[:, :2] = True  # at least two valid candidates
    cost = torch.where(valid, cost, cost - 20)
    target = torch.stack([torch.nonzero(v).flatten()[torch.randint(int(v.sum()), (1,), generator=g)][0] for v in valid])
    return cost, valid, target


def check_plan_loss(fn):
    hint = ("L_plan = -log p_{n*}, p_n = exp(-beta C_n) / sum over the *valid* n' of exp(-beta C_n'); use a stable "
            "log-softmax (logsumexp): exp(-2000) underflows.")
    worst = 0.0
    for seed, beta in ((0, 1.0), (1, 0.3), (2, 2.5)):
        cost, valid, target = plan_problem(seed)
        c1, c2 = cost.clone().requires_grad_(), cost.clone().requires_grad_()
        mine, ref = fn(c1, valid, target, beta), ds.plan_loss(c2, valid, target, beta)
        worst = max(worst, _close(f"my_plan_loss (beta = {beta})", mine, ref, 1e-9, hint))
        ref.sum().backward()
        assert mine.requires_grad, f"my_plan_loss: the result has no gradient (keep it a torch expression). {hint}"
        mine.sum().backward()
        _close(f"gradient of my_plan_loss wrt the costs (beta = {beta})", c1.grad, c2.grad, 1e-9, hint)
    return f"values and gradients, max error {worst:.1e}, beta in (0.3, 1, 2.5), masked candidates"


# --- exercise 3: one step of the Riccati recursion --------------------------------------------------------------


def riccati_problem(seed=0, B=6, n=4, m=2):
    """A random one-step LQR (positive definite cost), as ds.lqr_backward_fixed takes it: H (B, 2, n+m, n+m),
    g (B, 2, n+m), A (B, 1, n, n), B (B, 1, n, m)."""
    g = torch.Generator().manual_seed(seed)
    R = torch.randn(B, 2, n + m, n + m, generator=g, dtype=F64)
    H = R @ R.transpose(-1, -2) + 0.5 * torch.eye(n + m, dtype=F64)
    gv = torch.randn(B, 2, n + m, generator=g, dtype=F64)
    A = torch.randn(B, 1, n, n, generator=g, dtype=F64)
    Bm = torch.randn(B, 1, n, m, generator=g, dtype=F64)
    return H, gv, A, Bm


def check_riccati(fn):
    hint = "see the formulas above the iLQR cell: Q = H_t + F'PF, q = g_t + F'p with F = [A_t B_t]."
    n, m = 4, 2
    worst = 0.0
    for seed in (0, 1):
        H, gv, A, Bm = riccati_problem(seed, n=n, m=m)
        B = len(H)
        k_ref, K_ref, _, p0_ref = ds.lqr_backward_fixed(A, Bm, H, gv, n, torch.ones(B, 1, m, dtype=torch.bool))
        # P_new independently: the Schur complement of Q's control block, Q_ss - Q_su Q_uu^-1 Q_us
        F = torch.cat([A[:, 0], Bm[:, 0]], -1)
        Q = H[:, 0] + F.transpose(-1, -2) @ H[:, 1, :n, :n] @ F
        P_ref = Q[:, :n, :n] - Q[:, :n, n:] @ torch.linalg.solve(Q[:, n:, n:], Q[:, n:, :n])
        k, K, P_new, p_new = fn(H[:, 1, :n, :n], gv[:, 1, :n], H[:, 0], gv[:, 0], A[:, 0], Bm[:, 0], n)
        for name, mine, ref in (("k (feed-forward)", k, k_ref[:, 0]), ("K (feedback gain)", K, K_ref[:, 0]),
                                ("P_new", P_new, P_ref), ("p_new", p_new, p0_ref)):
            worst = max(worst, _close(f"my_riccati_step: {name}", mine, ref, 1e-8, hint))
    return f"k, K, P_new, p_new, max error {worst:.1e}"


# --- exercise 4: the gradient through the relaxed argmin --------------------------------------------------------


def check_plan_grad(fn):
    hint = ("differentiate -log p_{n*} = beta C_{n*} + log sum_{n' valid} exp(-beta C_n') with respect to C_n; "
            "invalid candidates get 0.")
    worst = 0.0
    for seed, beta in ((0, 1.0), (1, 0.3), (2, 2.5)):
        cost, valid, target = plan_problem(seed)
        c = cost.clone().requires_grad_()
        (ref,) = torch.autograd.grad(ds.plan_loss(c, valid, target, beta).sum(), c)  # autograd's answer
        worst = max(worst, _close(f"my_plan_loss_grad (beta = {beta})", fn(cost, valid, target, beta), ref, 1e-9, hint))
    return f"against autograd, max error {worst:.1e}, beta in (0.3, 1, 2.5), masked candidates"


CHECKS = {1: check_collision, 2: check_plan_loss, 3: check_riccati, 4: check_plan_grad}
