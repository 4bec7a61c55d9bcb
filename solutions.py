"""Reference answers to the exercises of tutorial.ipynb. Try the exercises before reading this file.

The notebook does not show this file. `DIFFSTACK_SOLUTIONS=1` (what CI and test_tutorial.py set)
makes the notebook import these functions in place of the student's stubs, so that every exercise
check runs on a known-right answer.
"""

import math

import torch


# Exercise 1: the collision term of eq. (3), the expectation over modes taken directly
def my_collision(pos, ctx, rbf_var):
    def phi(d2):
        return torch.exp(-d2 / (2 * rbf_var))

    # d2: (B, N, K, T) squared distance to every mode
    d2 = ((pos[:, :, None] - ctx.preds[:, None]) ** 2).sum(-1)
    expected = (ctx.probs[:, None, :, None] * d2).sum(2)  # (B, N, T) its expectation over the modes
    pred_term = ctx.pred_mask[:, None] * phi(expected).sum(-1)  # (B, N)
    d2_others = ((pos[:, :, None] - ctx.others[:, None]) ** 2).sum(-1)  # (B, N, A, T)
    others_term = (ctx.others_mask[:, None] * phi(d2_others).sum(-1)).sum(-1)  # (B, N)
    return pred_term + others_term


# Exercise 2: the relaxed planner's loss, -log p_{n*} with p the softmax of -beta C over the
# valid candidates
def my_plan_loss(cost, valid, target, beta):
    # invalid: p = 0
    logits = torch.where(valid, -beta * cost, torch.tensor(-math.inf, dtype=cost.dtype))
    logp = logits - torch.logsumexp(logits, -1, keepdim=True)  # (B, N) a stable log-softmax
    return -logp.gather(-1, target[:, None])[:, 0]


# Exercise 5: one step of the unconstrained Riccati recursion
def my_riccati_step(P, p, H_t, g_t, A_t, B_t, n):
    F = torch.cat([A_t, B_t], -1)  # (B, n, n+m)
    Q = H_t + F.transpose(-1, -2) @ P @ F  # (B, n+m, n+m)
    q = g_t + (F.transpose(-1, -2) @ p[..., None])[..., 0]  # (B, n+m)
    Qss, Qsu, Qus, Quu = Q[:, :n, :n], Q[:, :n, n:], Q[:, n:, :n], Q[:, n:, n:]
    qs, qu = q[:, :n], q[:, n:]
    k = -torch.linalg.solve(Quu, qu)  # (B, m) feed-forward
    K = -torch.linalg.solve(Quu, Qus)  # (B, m, n) feedback gain
    KT = K.transpose(-1, -2)
    P_new = Qss + KT @ Quu @ K + KT @ Qus + Qsu @ K
    p_new = (
        qs
        + (KT @ Quu @ k[..., None])[..., 0]
        + (KT @ qu[..., None])[..., 0]
        + (Qsu @ k[..., None])[..., 0]
    )
    return k, K, P_new, p_new


# Exercise 3: the gradient of L_plan = -log p_{n*} with respect to the candidate costs C_n.
#   log p_n = -beta C_n - log sum_{n' valid} exp(-beta C_n'),  so
#   dL_plan/dC_n = beta (1[n = n*] - p_n) on valid candidates, 0 on invalid ones.
def my_plan_loss_grad(cost, valid, target, beta):
    # p: (B, N)
    p = torch.softmax(
        torch.where(valid, -beta * cost, torch.tensor(-math.inf, dtype=cost.dtype)), -1
    )
    onehot = torch.nn.functional.one_hot(target, cost.shape[-1]).to(cost.dtype)  # (B, N)
    return beta * (onehot - p)


# Exercise 6: the controller's gradient. At the solution, the KKT conditions hold; differentiating
# them gives the same LQR with the incoming gradient as its linear term (Amos et al. 2018):
#   d = argmin 1/2 d'Hd + [grad_x; grad_u]'d  s.t.  dx_0 = 0, dx_{t+1} = A_t dx_t + B_t du_t,
# held controls du = 0. Then dL/dg_t = d_t and dL/dx_init = p_0.
def my_kkt_backward(A, B, H, grad_x, grad_u, free, n):
    import diffstack as ds

    # (B, T+1, n+m)
    rhs = torch.cat([grad_x, torch.cat([grad_u, torch.zeros_like(grad_u[:, :1])], 1)], -1)
    k, K, _, p0 = ds.lqr_backward(A, B, H, rhs, free=free)
    dx, du = [torch.zeros_like(grad_x[:, 0])], []
    for t in range(A.shape[1]):
        du.append(k[:, t] + (K[:, t] @ dx[-1][..., None])[..., 0])
        dx.append((A[:, t] @ dx[-1][..., None] + B[:, t] @ du[-1][..., None])[..., 0])
    du.append(torch.zeros_like(du[0]))  # the last stage has no control
    return p0, torch.cat([torch.stack(dx, 1), torch.stack(du, 1)], -1)


# Exercise 4 (find the bug): buggy_plan_loss takes the softmax over every candidate and then
# renormalises it over the valid ones. When an invalid candidate is far cheaper, exp(-beta C) of
# every valid candidate underflows next to it (exp(-200) is 0 in float32), the renormalisation is
# 0/0 and the loss NaN; float64 only moves the cliff further out. The fix: mask the logits, so the
# invalid candidates never enter the softmax, and take the log-softmax in one stable step.
def my_plan_loss_fixed(cost, valid, target, beta):
    logits = torch.where(valid, -beta * cost, torch.tensor(-math.inf, dtype=cost.dtype))  # (B, N)
    logp = torch.log_softmax(logits, -1)  # (B, N), 0 probability (-inf) on invalid candidates
    return -logp.gather(-1, target[:, None])[:, 0]
