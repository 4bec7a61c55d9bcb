"""DiffStack: a differentiable and modular autonomous-vehicle stack, in one readable module.

Karkus, Ivanovic, Mannor, Pavone, "DiffStack: A Differentiable and Modular Control Stack for
Autonomous Vehicles", CoRL 2022. The stack predicts the future of a nearby vehicle, plans with a
sampling planner, and refines the plan with a box-constrained iLQR controller. Planner and
controller are differentiable, so the predictor can be trained with the planning and control losses.

Map of the module (the order the data flows):
    1. Config                 every default of the paper, in one dataclass
    2. Dynamics               the dynamically-extended unicycle (exact integration)
    3. Cost                   eq. (2): collision, goal, lane, heading, control effort
    4. Planner                eq. (1): lane-centric spline candidates, argmin, relaxed argmin (L_plan)
    5. Controller             eq. (3): box-constrained iLQR, and its exact KKT backward (Amos et al. 2018)
    6. Predictor              Trajectron++-style CVAE over controls
    7. Stack                  predict -> plan -> control, L = a1 L_pred + a2 L_plan + a3 L_ctr
    8. Training, evaluation   the methods of Table 1 and their metrics
    9. Experiments, CLI       Tables 1-5, --quick, --bench

Shape letters used in comments:
    B scenarios (batch)   A other agents   K prediction modes   N planner candidates
    T time steps          L lanes          P points per lane    n = 4 state dims, m = 2 control dims
A state is s = (x, y, heading h, speed v); a control is u = (yaw rate w, acceleration a).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

# ============================================================================================
# 1. Config
# ============================================================================================


@dataclass
class Config:
    """Every default of the paper (REFERENCE.md); where the authors' code differs, a comment says so."""

    # --- time ---
    dt: float = 0.5
    """time step (s); nuScenes key frames are 2 Hz"""
    hist_len: int = 8
    """past steps of history (4 s); the current state makes 9"""
    horizon: int = 6
    """planning / prediction horizon T in steps (3 s)"""

    # --- cost, eq. (2) ---
    w_coll: float = 5.0
    """collision weight w1 (authors' code: 20)"""
    w_goal: float = 0.5
    """goal weight w2 (authors' code: 0.05)"""
    w_lat: float = 0.3
    """lateral lane deviation weight w3"""
    w_head: float = 0.3
    """lane heading deviation weight w4"""
    w_ctrl: float = 1.0
    """control effort weight w5"""
    rbf_var: float = 2.0
    """sigma^2 of the collision RBF phi(d2) = exp(-d2 / (2 sigma^2)) (m^2; authors' code: exp(-d^2/4))"""

    # --- planner, eq. (1), App. D ---
    goal_lane_dist: float = 4.5
    """a goal lane passes within this distance (m) of the goal"""
    goal_lane_heading: float = math.pi / 2
    """... and its heading differs from the goal's by less than this (rad) (authors' code: pi/4)"""
    max_goal_lanes: int = 2
    """candidate lanes kept per scenario (the closest to the goal); N = 24 * max_goal_lanes"""
    plan_accels: tuple = (-3.0, -2.0, -1.0, -0.5, 0.0, 0.5, 1.0, 2.0)
    """terminal accelerations (m/s^2)"""
    plan_offsets: tuple = (-0.5, 0.0, 0.5)
    """terminal lateral offsets from the lane centre (m)"""
    beta: float = 1.0
    """temperature of the relaxed argmin p_n = softmax(-beta C_n)"""
    feas_accel: tuple = (-6.0, 4.0)
    """feasible acceleration range of a candidate (m/s^2), authors' code"""
    feas_lat_accel: float = 8.0
    """feasible |w v| (m/s^2), authors' code"""
    feas_yaw_per_speed: float = 0.5
    """feasible |w| <= this * |v| (1/m), authors' code"""

    # --- controller, eq. (3), App. D ---
    u_lower: tuple = (-0.7, -5.0)
    """control lower bounds (yaw rate rad/s, acceleration m/s^2), authors' code"""
    u_upper: tuple = (0.7, 4.0)
    """control upper bounds"""
    ilqr_iters: int = 5
    """maximum iLQR iterations"""
    ilqr_tol: float = 0.05
    """converged when the norm of the full LQR control step is below this (paper: 0.05, authors' code: 0.01)"""
    line_search_steps: int = 5
    """step scales tried: 1, 1/5, 1/25, ..."""
    line_search_decay: float = 5.0
    """divide the step by this on failure"""

    # --- training, §3.2, App. E ---
    alpha_rl: tuple = (1.0, 100.0, 1000.0)
    """loss weights (L_pred, L_plan, L_ctr) in the RL setting"""
    alpha_il: tuple = (1.0, 10.0, 1000.0)
    """loss weights in the IL setting"""
    lr: float = 3e-3
    """Adam learning rate"""
    batch_size: int = 256
    """scenarios per training step"""


# ============================================================================================
# 2. Dynamics: the dynamically-extended unicycle
# ============================================================================================
#
# With constant yaw rate w and acceleration a over one step tau = dt, starting from (x, y, h, v):
#     h' = h + w tau,   v' = v + a tau,
#     [x', y'] = [x, y] + R(h) [along, lateral],
#     along   = int_0^tau (v + a s) cos(w s) ds = v c0 + a c1,
#     lateral = int_0^tau (v + a s) sin(w s) ds = v s0 + a s1,
# with c0 = sin(th)/w, s0 = (1 - cos th)/w, c1 = tau sin(th)/w + (cos th - 1)/w^2,
#      s1 = sin(th)/w^2 - tau cos(th)/w, th = w tau.
# These divide by w. For |th| < 0.3 we use their Taylor series instead (error < 1e-16 with seven
# terms), and feed the closed form a safe w = 1 there: a division by a tiny w inside torch.where
# would still put NaN into the gradient of the branch that is not selected.

_SERIES_TERMS = 7
_SERIES_SWITCH = 0.3


def _motion_integrals(w, tau):
    """c0, s0, c1, s1 above, for yaw rates w (...,), step tau: exact and smooth at w = 0."""
    th = w * tau
    small = th.abs() < _SERIES_SWITCH
    # closed form, with w = 1 where it is not used
    ws = torch.where(small, torch.ones_like(w), w)
    ths = ws * tau
    sin, cos = torch.sin(ths), torch.cos(ths)
    c0, s0 = sin / ws, (1 - cos) / ws
    c1 = tau * sin / ws + (cos - 1) / ws**2
    s1 = sin / ws**2 - tau * cos / ws
    # series in th:  c0/tau = sum (-1)^n th^2n / (2n+1)!       s0/tau = sum (-1)^n th^(2n+1) / (2n+2)!
    #                c1/tau^2 = sum (-1)^n th^2n / ((2n)! (2n+2))   s1/tau^2 = sum (-1)^n th^(2n+1) / ((2n+1)! (2n+3))
    thz = torch.where(small, th, torch.zeros_like(th))
    sc0 = ss0 = sc1 = ss1 = torch.zeros_like(th)
    for k in range(_SERIES_TERMS):
        even, odd = (-1) ** k * thz ** (2 * k), (-1) ** k * thz ** (2 * k + 1)
        sc0 = sc0 + even / math.factorial(2 * k + 1)
        ss0 = ss0 + odd / math.factorial(2 * k + 2)
        sc1 = sc1 + even / (math.factorial(2 * k) * (2 * k + 2))
        ss1 = ss1 + odd / (math.factorial(2 * k + 1) * (2 * k + 3))
    pick = lambda series, closed, scale: torch.where(small, series * scale, closed)  # noqa: E731
    return pick(sc0, c0, tau), pick(ss0, s0, tau), pick(sc1, c1, tau**2), pick(ss1, s1, tau**2)


def unicycle_step(s: torch.Tensor, u: torch.Tensor, dt: float) -> torch.Tensor:
    """One exact step of the unicycle. s (..., 4) = (x, y, h, v), u (..., 2) = (w, a) -> s' (..., 4)."""
    x, y, h, v = s.unbind(-1)
    w, a = u.unbind(-1)
    c0, s0, c1, s1 = _motion_integrals(w, dt)
    along, lateral = v * c0 + a * c1, v * s0 + a * s1
    cos_h, sin_h = torch.cos(h), torch.sin(h)
    return torch.stack(
        [x + cos_h * along - sin_h * lateral, y + sin_h * along + cos_h * lateral, h + w * dt, v + a * dt], -1
    )


def unicycle_rollout(s0: torch.Tensor, u: torch.Tensor, dt: float) -> torch.Tensor:
    """Integrate controls u (..., T, 2) from s0 (..., 4): states (..., T+1, 4), s0 included."""
    states = [s0]
    for t in range(u.shape[-2]):  # T is 6: a loop over time, never over scenarios
        states.append(unicycle_step(states[-1], u[..., t, :], dt))
    return torch.stack(states, -2)


def unicycle_jacobians(s: torch.Tensor, u: torch.Tensor, dt: float):
    """A = df/ds (..., 4, 4) and B = df/du (..., 4, 2), exact, by forward-mode autodiff.

    Every step depends only on its own (s, u), so one forward-mode pass per input direction,
    shared by all steps and scenarios at once, gives every Jacobian: 6 passes in all.
    """
    n = s.shape[-1]
    z = torch.cat([s, u], -1)
    step = lambda d: unicycle_step((z + d)[..., :n], (z + d)[..., n:], dt)  # noqa: E731
    J = torch.func.jacfwd(step)(torch.zeros(z.shape[-1], dtype=z.dtype))  # (..., 4, 6)
    return J[..., :n], J[..., n:]
