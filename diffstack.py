"""DiffStack (Karkus, Ivanovic, Mannor, Pavone, CoRL 2022): the method in one readable module.

The stack predicts the future of a nearby vehicle (eq. 1), plans with a sampling planner (eq. 2)
that minimises a hand-crafted cost (eq. 3), and refines the plan with a box-constrained iLQR
controller (eq. 4). Planner and controller are differentiable, so the predictor can be trained with
the planning and control losses. The sections run in the order of their dependencies, each using
only those above it (the checks, called by Config, stand last), not the paper's order:

    1. Config        every default of the paper, in one dataclass
    2. Dynamics      the dynamically-extended unicycle (exact integration)
    3. Cost          eq. (3): collision, goal, lane, heading, control effort
    4. Planner       eq. (2): lane-centric spline candidates, argmin, relaxed argmin (L_plan)
    5. Controller    eq. (4): box-constrained iLQR (eq. 3's closed-form expansion), its KKT backward
    6. Predictor     eq. (1): a Trajectron++-style CVAE over controls, and its InfoVAE loss
    7. Stack         predict -> plan -> control, L = a1 L_pred + a2 L_plan + a3 L_ctr
    8. Checks        every Config field in its range, refused by name at construction
Training and evaluation are in train.py (`python diffstack.py --quick` hands over to lab/quick.py).

Shapes in comments: B scenarios, A other agents, K prediction modes, N planner candidates,
T time steps, H history steps, L lanes, P points per lane, n = 4 state and m = 2 control dims (n
and m only in shapes); ... extra batch dims a function broadcasts over. Notation, one meaning per
letter (the paper's where it has one):
  s = (x, y, h, v)  state: position (x, y), heading h, speed v; s0 now; also a trajectory of
                    states, s (T+1, 4), as the paper's s_plan, s_ctr; s_gt the logged one
  u = (omega, a)    control: yaw rate omega, acceleration a; dt (tau) one step's duration
  f; f_s, f_u       dynamics s_t+1 = f(s_t, u_t); its Jacobians df/ds, df/du
  C, w, g           the cost of eq. (3), its weights w1..w5, the goal
  p_n; beta         the relaxed argmin's probability of candidate n; its temperature
  z; K, k, pi_k     the CVAE's latent; its K values (the modes), a mode, its weight
  c; p(z|c)         the CVAE's condition (the encoded histories); prior p(z|c), posterior
                    q(z|c,s_gt) given the predicted agent's logged future s_gt
  lambda; ff, G     costates (lambda_0 = dL/ds_init); iLQR's step du = ff + G ds (feed-forward,
                    feedback gain); delta the solution of a QP (box_qp, the KKT backward's LQR)
  a1..a3; b         the paper's alpha_i, L's weights (stack_loss); the KL weight of L_pred
  Sigma; sigma      covariances; the collision RBF's width
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass
from typing import NamedTuple

import torch
import torch.nn as nn


def wrap_angle(a):
    """Angle to (-pi, pi]: atan2(sin a, cos a), smooth away from +-pi."""
    return torch.atan2(torch.sin(a), torch.cos(a))


# ===== 1. Config ==================================================================================


@dataclass
class Config:
    """Every default of the paper (App. C, D; Trajectron++'s for the predictor); comments say where
    the authors' code differs."""

    dt: float = 0.5  # time step (s); nuScenes key frames are 2 Hz
    hist_len: int = 8  # past steps of history (4 s); the current state makes 9
    horizon: int = 6  # planning / prediction horizon T in steps (3 s)
    # --- cost, eq. (3) ---
    w_coll: float = 5.0  # collision weight w1 (authors' code: 20)
    w_goal: float = 0.5  # goal weight w2 (authors' code: 0.05)
    w_lat: float = 0.3  # lateral lane deviation weight w3
    w_head: float = 0.3  # lane heading deviation weight w4
    w_ctrl: float = 1.0  # control effort weight w5
    rbf_var: float = 2.0  # sigma^2 (m^2) of phi(d2) = exp(-d2 / 2 sigma^2) (authors': exp(-d2/4))
    # --- planner, eq. (2), App. C.1 ---
    goal: str = "logged"  # g of eq. (3): the GT ego state at T (App. C.3), or 'route' (route_goal)
    goal_lane_dist: float = 4.5  # a goal lane passes within this distance (m) of the goal
    goal_lane_heading: float = math.pi / 2  # and heading within this of the goal's (authors': pi/4)
    max_goal_lanes: int = 2  # lanes kept, closest to the goal first (paper: all); N = 8 x 3 x this
    plan_accels: tuple = (-3.0, -2.0, -1.0, -0.5, 0.0, 0.5, 1.0, 2.0)  # terminal accelerations
    plan_offsets: tuple = (-0.5, 0.0, 0.5)  # terminal lateral offsets from the lane centre (m)
    beta: float = 1.0  # temperature of the relaxed argmin p_n = softmax(-beta C)_n
    feas_lat_accel: float = 8.0  # feasible |omega v| (m/s^2), authors' code
    feas_yaw_per_speed: float = 0.5  # feasible |omega| <= this * |v| (1/m), authors' code
    # --- controller, eq. (4), App. C.2 ---
    u_lower: tuple = (-0.7, -5.0)  # control lower bounds (yaw rate rad/s, accel m/s^2), authors'
    u_upper: tuple = (0.7, 4.0)  # control upper bounds (the authors' box for a: [-6, 4])
    ilqr_iters: int = 5  # maximum iLQR iterations
    ilqr_tol: float = 0.05  # converged when the LQR step's norm is below this (authors': 0.01)
    line_search_steps: int = 5  # step scales tried: 1, 1/5, 1/25, ...
    line_search_decay: float = 5.0  # divide the step by this on failure
    # --- predictor, eq. (1), §3.1 (Trajectron++'s defaults, Salzmann et al. 2020) ---
    pred_modes: int = 25  # K values of the latent z (= GMM components = the planner's trajectories)
    pred_enc_hidden: int = 32  # widths: history LSTM, neighbour MLP, future BiLSTM (each direction)
    pred_latent_hidden: int = 32  # hidden width of the p(z|c) and q(z|c,s_gt) MLPs
    pred_dec_hidden: int = 64  # decoder GRU width (Trajectron++: 128; halved for CPU training)
    pred_radius: float = 30.0  # neighbours within this distance (m) at t0 are attended to
    pred_scales: tuple = (30.0, 15.0, 4.0, math.pi)  # input scales: pos, vel, acc, heading (rate)
    pred_min_speed: float = 0.5  # below it (m/s) the tracked heading replaces the velocity's at t0
    pred_pos_std_min: float = 0.05  # std (m) added to each component: at v = 0 no sideways spread
    pred_log_p_max: float = 6.0  # the loss's per-step log-likelihood is clamped above at this
    pred_kl_min: float = 0.07  # free bits: the batch-mean KL(q || p) is clamped below at this
    pred_beta: tuple = (100.0, 400.0, 100.0)  # KL weight b(step) = b0 sigmoid((step - b1) / b2)
    # logit clip lc(step) = lc0 + (lc1 - lc0) sigmoid((step - lc2) / lc3)
    pred_logit_clip: tuple = (0.05, 5.0, 300.0, 60.0)
    pred_nll_min: float = -20.0  # the NLL metric clamps each step's log p(pos_t) below at this
    pred_lr_decay: float = 0.9999  # learning rate multiplied by this after every iteration
    pred_grad_clip: float = 1.0  # gradients clipped to [-this, this] elementwise, as Trajectron++
    # --- training, §3.2, App. D ---
    alpha_rl: tuple = (1.0, 100.0, 1000.0)  # loss weights (L_pred, L_plan, L_ctr), RL setting
    alpha_il: tuple = (1.0, 10.0, 1000.0)  # loss weights in the IL setting
    lr: float = 3e-3  # Adam learning rate
    batch_size: int = 256  # scenarios per training step
    train_plan_weights: str = "posterior"  # mode weights in training: q (the authors') or 'prior'

    def __post_init__(self):
        check_config(self)


# ===== 2. Dynamics: the dynamically-extended unicycle =============================================
# The textbook's ODE, x. = v cos h, y. = v sin h, h. = omega, v. = a, is usually stepped by Euler:
#     s_t+1 = s_t + dt (v cos h, v sin h, omega, a).
# Here it is integrated exactly, with omega and a constant over the step tau = dt (the controls are
# zero-order held): one Euler step is over 1 m off at 10 m/s under the box's controls (0.7 rad/s,
# -5 m/s^2) over the paper's 0.5 s, and predictor, planner and controller share this f. Exactly:
#     h_t+1 = h + omega tau,   v_t+1 = v + a tau,   (x, y)_t+1 = (x, y) + R(h) (along, lateral),
#     along   = int_0^tau (v + a r) cos(omega r) dr = v cm_0 + a cm_1,
#     lateral = int_0^tau (v + a r) sin(omega r) dr = v sm_0 + a sm_1,
# with the moments cm_j = int_0^tau r^j cos(omega r) dr and sm_j = int_0^tau r^j sin(omega r) dr,
# whose derivatives are moments again, d cm_j/domega = -sm_j+1 and d sm_j/domega = cm_j+1: the
# Jacobians in closed form too. The closed forms divide by omega^(j+1); for |th| = |omega tau| < 0.3
# their Taylor series (seven terms, error < 1e-16: _moments) replaces them, and the closed forms get
# a safe omega = 1 there (a tiny omega inside torch.where would put NaN into the gradient).

_SERIES_SWITCH = 0.3  # |omega tau| below which the series replaces the closed forms
_SERIES_TERMS = 7  # i = 0 .. 6


@functools.lru_cache(maxsize=None)
def _series_coefficients(jmax, dtype, device):
    """a_ij = (-1)^i / ((2i)! (2i+j+1)) and b_ij = (-1)^i / ((2i+1)! (2i+j+2)) of the moments'
    series, side by side: (terms, 2 (jmax+1))."""
    fact = math.factorial
    rows = []
    for i in range(_SERIES_TERMS):
        a_i = [(-1) ** i / (fact(2 * i) * (2 * i + j + 1)) for j in range(jmax + 1)]
        b_i = [(-1) ** i / (fact(2 * i + 1) * (2 * i + j + 2)) for j in range(jmax + 1)]
        rows.append(a_i + b_i)
    return torch.tensor(rows, dtype=dtype, device=device)


def _moments(omega, tau, jmax):
    """[cm_0..cm_jmax], [sm_0..sm_jmax] for yaw rates omega (...,) over tau: exact, smooth at 0."""
    th = omega * tau
    small = th.abs() < _SERIES_SWITCH
    J = jmax + 1
    powers = torch.arange(1, J + 1, dtype=omega.dtype, device=omega.device)  # (J,) 1 .. j+1
    tau_pow = tau**powers  # (J,) tau^(j+1)
    # the series, term by term (th = 0 where the closed form is taken):
    #     cm_j = tau^(j+1) sum_i a_ij th^2i,   sm_j = tau^(j+1) th sum_i b_ij th^2i
    th_s = torch.where(small, th, 0.0)
    coef = _series_coefficients(jmax, omega.dtype, omega.device)  # (terms, 2J)
    th2 = th_s**2
    power = torch.ones_like(th_s)  # th^2i, from i = 0
    series = 0.0
    for i in range(_SERIES_TERMS):
        series = series + power[..., None] * coef[i]  # (..., 2J)
        power = power * th2
    cm_series = series[..., :J] * tau_pow
    sm_series = series[..., J:] * th_s[..., None] * tau_pow
    # the closed forms, by parts:
    #     cm_j = (tau^j sin - j sm_{j-1}) / omega,   sm_j = (j cm_{j-1} - tau^j cos) / omega
    om_safe = torch.where(small, 1.0, omega)
    sin = torch.sin(om_safe * tau)
    cos = torch.cos(om_safe * tau)
    cm = [sin / om_safe]
    sm = [(1.0 - cos) / om_safe]
    for i in range(1, J):
        cm.append((tau**i * sin - i * sm[-1]) / om_safe)
        sm.append((i * cm[-2] - tau**i * cos) / om_safe)
    small = small[..., None]
    cm = torch.where(small, cm_series, torch.stack(cm, -1))  # (..., J)
    sm = torch.where(small, sm_series, torch.stack(sm, -1))  # (..., J)
    return cm.unbind(-1), sm.unbind(-1)


def _rotate(h, along, lateral):
    """R(h) [along, lateral]: (x, y) of a vector given in the heading frame."""
    cos_h, sin_h = torch.cos(h), torch.sin(h)
    return cos_h * along - sin_h * lateral, sin_h * along + cos_h * lateral


def unicycle_step(s: torch.Tensor, u: torch.Tensor, dt: float) -> torch.Tensor:
    """f: one exact step, s (..., 4) = (x, y, h, v), u (..., 2) = (omega, a) -> s_t+1 (..., 4)."""
    x, y, h, v = s.unbind(-1)
    omega, a = u.unbind(-1)
    (cm0, cm1), (sm0, sm1) = _moments(omega, dt, 1)
    along, lateral = v * cm0 + a * cm1, v * sm0 + a * sm1
    cos_h, sin_h = torch.cos(h), torch.sin(h)
    x_next = x + cos_h * along - sin_h * lateral  # [x, y] + R(h) [along, lateral]
    y_next = y + sin_h * along + cos_h * lateral
    return torch.stack([x_next, y_next, h + omega * dt, v + a * dt], -1)


def _position_jacobians(h, v, omega, a, dt: float):
    """A unicycle step from h, v under omega, a (...): its displacement dx, dy (...) and the
    position rows of its Jacobians, Mq = d(x, y)/d(h, v), Mu = d(x, y)/d(omega, a) (..., 2, 2)."""
    (cm0, cm1, cm2), (sm0, sm1, sm2) = _moments(omega, dt, 2)
    dx, dy = _rotate(h, v * cm0 + a * cm1, v * sm0 + a * sm1)  # the displacement R(h) disp
    x_v, y_v = _rotate(h, cm0, sm0)  # d/dv
    # d/domega, by d cm_j/domega = -sm_{j+1}, d sm_j/domega = cm_{j+1}
    x_om, y_om = _rotate(h, -(v * sm1 + a * sm2), v * cm1 + a * cm2)
    x_a, y_a = _rotate(h, cm1, sm1)  # d/da
    # d/dh of R(h) disp is J R(h) disp = (-dy, dx)
    Mq = torch.stack([torch.stack([-dy, x_v], -1), torch.stack([dx, y_v], -1)], -2)  # (..., 2, 2)
    Mu = torch.stack([torch.stack([x_om, x_a], -1), torch.stack([y_om, y_a], -1)], -2)
    return dx, dy, Mq, Mu


def unicycle_jacobians(s: torch.Tensor, u: torch.Tensor, dt: float):
    """f_s = df/ds (..., 4, 4) and f_u = df/du (..., 4, 2) of unicycle_step, in closed form:
    f_s = [[I, Mq], [0, I]] and f_u = [[Mu], [dt I]] (only the controls move h and v)."""
    _, _, Mq, Mu = _position_jacobians(s[..., 2], s[..., 3], u[..., 0], u[..., 1], dt)
    eye = torch.eye(2, dtype=s.dtype, device=s.device).expand_as(Mq)  # (..., 2, 2)
    zero = torch.zeros_like(Mq)
    f_s = torch.cat([torch.cat([eye, Mq], -1), torch.cat([zero, eye], -1)], -2)  # (..., 4, 4)
    f_u = torch.cat([Mu, dt * eye], -2)  # (..., 4, 2)
    return f_s, f_u


def rollout(dynamics, s0, u):
    """Integrate controls u (..., T, m) from s0 (..., n) with a step function: (..., T+1, n)."""
    states = [s0]
    for t in range(u.shape[-2]):
        states.append(dynamics(states[-1], u[..., t, :]))
    return torch.stack(states, -2)


def unicycle_rollout(s0: torch.Tensor, u: torch.Tensor, dt: float) -> torch.Tensor:
    """Integrate controls u (..., T, 2) from s0 (..., 4): states (..., T+1, 4), s0 included."""
    return rollout(Unicycle(dt), s0, u)


class Unicycle:
    """The unicycle as the controller sees it: a step function with closed-form derivatives."""

    def __init__(self, dt: float):
        self.dt = dt

    def __call__(self, s, u):
        return unicycle_step(s, u, self.dt)

    def jacobians(self, s, u):
        return unicycle_jacobians(s, u, self.dt)

    def curvature(self, s, u, lam):
        return unicycle_curvature(s, u, lam, self.dt)


# ===== 3. Cost, eq. (3) and App. C.3 ==============================================================
#   C = w1 C_coll + w2 C_goal + w3 C_lat + w4 C_head + w5 C_u, a sum of per-step terms, each of one
#   step's state and control: the controller relies on the cost's Hessian being block-diagonal in
#   time. The terms by name, in the order of w (Config.w_<name>) and of every tensor of terms:
#   C_coll, the one a prediction enters, first; then those of the scene alone (scene_terms).
SCENE_TERMS = ("goal", "lat", "head", "ctrl")
COST_TERMS = ("coll", *SCENE_TERMS)


@dataclass
class CostContext:
    """What the cost knows about the world, as tensors so that gradients reach every one."""

    preds: torch.Tensor  # (B, K, T, 2)  predicted agent's mode positions, t1..T
    probs: torch.Tensor  # (B, K)        mode probabilities pi_k
    pred_mask: torch.Tensor  # (B,)      1 where the predicted agent counts (0: "No prediction")
    others: torch.Tensor  # (B, A, T, 2) other agents' GT future positions
    others_mask: torch.Tensor  # (B, A)
    goal: torch.Tensor  # (B, 2)         goal position at T
    lanes: torch.Tensor  # (B, L, P, 3)  lane centre lines (x, y, heading)
    lanes_mask: torch.Tensor  # (B, L, P)

    def tensors(self):
        return tuple(getattr(self, f.name) for f in dataclasses.fields(self))


def per_scenario(t: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """t (B, *rest) viewed as (B, 1, ..., 1, *rest), to broadcast over like's (B, ..., T, 2)."""
    return t.reshape(t.shape[0], *([1] * (like.dim() - 3)), *t.shape[1:])


def segment_projection(q, a, b):
    """The closest point to q (..., 2) on a -> b (..., 3) (x, y, heading): frac (...,) along the
    segment (clamped to [0, 1]), r = q - that point (..., 2), the lane heading there
    (interpolated) and dfrac/dq (..., 2) (0 where clamped)."""
    seg = b[..., :2] - a[..., :2]  # (..., 2)
    length2 = (seg * seg).sum(-1).clamp_min(1e-9)  # (...)
    raw = ((q - a[..., :2]) * seg).sum(-1) / length2  # the fraction before the clamp
    frac = raw.clamp(0, 1)
    r = q - a[..., :2] - frac[..., None] * seg
    lane_h = a[..., 2] + frac * wrap_angle(b[..., 2] - a[..., 2])
    on_segment = ((raw >= 0) & (raw <= 1))[..., None]
    dfrac = torch.where(on_segment, seg / length2[..., None], 0.0)  # as clamp's gradient
    return frac, r, lane_h, dfrac


# m^2: a lane point heading the other way at a distance r ranks as one at sqrt(r^2 + 100 m^2)
_SEARCH_LAM = 50.0


def nearest_lane_segment(pos, heading, lanes, lanes_mask):
    """The lane segment nearest each state: its ends a, b (B, Q, 3) (Q: the states, flattened)
    and has_lane (B, Q).

    First the nearest lane point (no gradient: it only picks an index), ranked by
        |q - l|^2 + lam (1 - cos(h_q - h_l)),   lam = 50 m^2 (q a state's position, l a lane point)
    so that an oncoming lane beside the state's own is not 'closest' (no lane within 90 degrees:
    no lane cost; the heading term is beyond the paper's "closest lane point"); then the closer of
    the two segments that meet there. As u(h_q).u(h_l) = cos(h_q - h_l), u(h) = (cos h, sin h),
        |q - l|^2 + lam (1 - cos(h_q - h_l))
            = |q|^2 + [-2q, -lam u(h_q), 1] . [l, u(h_l), |l|^2 + lam],
    one product of features for all pairs; |q|^2 drops out (a test holds the two to one point)."""
    B, L, P, _ = lanes.shape
    q = pos.reshape(B, -1, 2).detach()  # (B, Q, 2)
    hq = heading.reshape(B, -1).detach()  # (B, Q)
    pts = lanes.reshape(B, L * P, 3)
    lp = pts.detach()
    mask = lanes_mask.reshape(B, L * P)
    # 1. the nearest point, by the product above (padding ranks at 1e30, last)
    lp_norm = torch.where(mask, (lp[..., :2] ** 2).sum(-1) + _SEARCH_LAM, 1e30)  # (B, L*P)
    u_lp = torch.cat([torch.cos(lp[..., 2:]), torch.sin(lp[..., 2:])], -1)  # (B, L*P, 2)
    lp_feat = torch.cat([lp[..., :2], u_lp, lp_norm[..., None]], -1)  # (B, L*P, 5)
    u_q = torch.stack([torch.cos(hq), torch.sin(hq)], -1)  # (B, Q, 2)
    q_feat = torch.cat([-2 * q, -_SEARCH_LAM * u_q, torch.ones_like(q[..., :1])], -1)  # (B, Q, 5)
    j = (q_feat @ lp_feat.mT).argmin(-1)  # (B, Q) the nearest point's index
    near = pts.gather(1, j[..., None].expand(B, -1, 3))  # (B, Q, 3)
    has_lane = mask.gather(1, j) & (torch.cos(hq - near[..., 2].detach()) > 0)
    # 2. the closer of the segments before and after that point (a lane's valid points: a prefix)
    lane, i = j // P, j % P
    last = (lanes_mask.sum(-1).gather(1, lane) - 1).clamp_min(0)  # (B, Q) the lane's last point

    def point(idx):  # the lane's point idx (B, Q) -> (B, Q, 3)
        return pts.gather(1, (lane * P + idx)[..., None].expand(B, -1, 3))

    def dist2_to(a, b):  # squared distance from q to segment a -> b (B, Q)
        return segment_projection(q, a.detach(), b.detach())[1].square().sum(-1)

    prev, here, nxt = point((i - 1).clamp_min(0)), point(i), point(torch.minimum(i + 1, last))
    closer = (dist2_to(here, nxt) < dist2_to(prev, here))[..., None]  # (B, Q, 1)
    return torch.where(closer, here, prev), torch.where(closer, nxt, here), has_lane


def project_to_lanes(pos, heading, lanes, lanes_mask):
    """Squared distance to the closest lane point and heading error there, and has_lane, each
    (B, ...), for states pos (B, ..., 2), heading (B, ...); where no lane matches, both are 0."""
    B = lanes.shape[0]
    a, b, has_lane = nearest_lane_segment(pos, heading, lanes, lanes_mask)  # (B, Q, 3) x 2, (B, Q)
    _, r, lane_h, _ = segment_projection(pos.reshape(B, -1, 2), a, b)
    d2 = torch.where(has_lane, (r**2).sum(-1), 0.0)
    err = torch.where(has_lane, wrap_angle(heading.reshape(B, -1) - lane_h), 0.0)
    return d2.reshape(heading.shape), err.reshape(heading.shape), has_lane.reshape(heading.shape)


def rbf(d2: torch.Tensor, rbf_var: float) -> torch.Tensor:
    """phi(d2) = exp(-d2 / 2 sigma^2), its exponent floored at -60 (phi < 1e-26, nothing at the
    cost's precision): far agents would send exp into its underflow path, 10-25x slower."""
    return torch.exp((-d2 / (2 * rbf_var)).clamp_min(-60.0))


def prediction_moments(ctx: CostContext):
    """The prediction's per-step mean mu = sum_k pi_k s^_k (B, T, 2) and spread
    sum_k pi_k ||s^_k - mu||^2 (B, T)."""
    mu = (ctx.probs[:, :, None, None] * ctx.preds).sum(1)  # (B, T, 2)
    spread = (ctx.probs[:, :, None] * ((ctx.preds - mu[:, None]) ** 2).sum(-1)).sum(1)  # (B, T)
    return mu, spread


def collision_term(pos: torch.Tensor, ctx: CostContext, rbf_var: float = 2.0) -> torch.Tensor:
    """C_coll per trajectory: pos (B, ..., T, 2) positions t1..T -> (B, ...).

        C_coll = sum_t phi( sum_k pi_k ||s_t - s^_kt||^2 ) + sum_a sum_t phi(||s_t - s_at||^2)
    with phi(d2) = exp(-d2 / 2 sigma^2). The expected squared distance splits into the distance to
    the modes' mean and their spread:
        sum_k pi_k ||s - s^_k||^2 = ||s - mu||^2 + sum_k pi_k ||s^_k - mu||^2,
    with mu = sum_k pi_k s^_k: the planner sees a prediction only through its per-step mean and
    spread."""
    mu, spread = prediction_moments(ctx)  # (B, T, 2), (B, T)
    d2_mean = ((pos - per_scenario(mu, pos)) ** 2).sum(-1)  # (B, ..., T)
    d2_pred = d2_mean + per_scenario(spread, pos)  # (B, ..., T)
    coll = per_scenario(ctx.pred_mask, pos)[..., None] * rbf(d2_pred, rbf_var)
    others = per_scenario(ctx.others, pos)  # (B, ..., A, T, 2)
    d2_others = ((pos[..., None, :, :] - others) ** 2).sum(-1)  # (B, ..., A, T)
    others_mask = per_scenario(ctx.others_mask, pos)[..., None]  # (B, ..., A, 1)
    coll = coll + (others_mask * rbf(d2_others, rbf_var)).sum(-2)
    return coll.sum(-1)


def scene_terms(pos, head, u, goal, lanes, lanes_mask) -> torch.Tensor:
    """(C_goal, C_lat, C_head, C_u) per trajectory (B, ..., 4), the terms of eq. (3) no prediction
    enters: positions (B, ..., T, 2) and headings (B, ..., T) at t1..T, u (B, ..., T, 2),
    goal (B, 2), lanes (B, L, P, 3)."""
    # C_goal = ||s_T - g||^2
    to_goal = ((pos[..., -1, :] - per_scenario(goal, pos)) ** 2).sum(-1)
    # C_lat = sum_t ||s_t - s_lane||^2,   C_head = sum_t wrap(h_t - h_lane)^2
    lat, head_err, _ = project_to_lanes(pos, head, lanes, lanes_mask)
    # C_u = sum_t omega_t^2 + a_t^2
    effort = (u**2).sum((-1, -2))
    return torch.stack([to_goal, lat.sum(-1), (head_err**2).sum(-1), effort], -1)


def cost_terms(s: torch.Tensor, u: torch.Tensor, ctx: CostContext, rbf_var: float = 2.0):
    """The five unweighted terms of eq. (3) (B, ..., 5) of states s (B, ..., T+1, 4) (s0 first,
    not costed) and controls u (B, ..., T, 2): (C_coll, C_goal, C_lat, C_head, C_u)."""
    pos, head = s[..., 1:, :2], s[..., 1:, 2]  # (B, ..., T, 2), (B, ..., T): the cost skips t0
    coll = collision_term(pos, ctx, rbf_var)  # (B, ...)
    rest = scene_terms(pos, head, u, ctx.goal, ctx.lanes, ctx.lanes_mask)  # (B, ..., 4)
    return torch.cat([coll[..., None], rest], -1)


def cost_weights(cfg: Config, dtype=torch.float32, device=None) -> torch.Tensor:
    """The hand-tuned weights (w1..w5) of App. C.3, in COST_TERMS' order."""
    w = [getattr(cfg, f"w_{name}") for name in COST_TERMS]
    return torch.tensor(w, dtype=dtype, device=device)


def weigh(terms: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Eq. (3): C = sum_i w_i C_i. terms (B, ..., 5), w (5,) or per scenario (B, 5) -> (B, ...)."""
    if w.dim() == 2:
        w = w.reshape(w.shape[0], *([1] * (terms.dim() - 2)), len(COST_TERMS))
    return (terms * w).sum(-1)


def total_cost(s, u, ctx: CostContext, w: torch.Tensor, rbf_var: float = 2.0) -> torch.Tensor:
    """Eq. (3): s (B, ..., T+1, 4), u (B, ..., T, 2), w (5,) or (B, 5) -> (B, ...)."""
    return weigh(cost_terms(s, u, ctx, rbf_var), w)


# ===== 4. Planner: lane-centric spline candidates and the relaxed argmin, eq. (2), App. C.1 =======


@dataclass
class Candidates:
    """The planner's candidate trajectories for a batch."""

    s: torch.Tensor  # (B, N, T+1, 4) states along the splines, s0 first
    u: torch.Tensor  # (B, N, T, 2)   controls derived from the splines
    valid: torch.Tensor  # (B, N)     lane found, terminal on the lane, dynamically feasible


def _lane_arclength(lanes, lanes_mask):
    """Cumulative arc length along each lane, flat past its last valid point. -> (B, L, P)."""
    seg = (lanes[:, :, 1:, :2] - lanes[:, :, :-1, :2]).norm(dim=-1)
    seg = torch.where(lanes_mask[:, :, 1:] & lanes_mask[:, :, :-1], seg, 0.0)  # (B, L, P-1)
    return torch.cat([torch.zeros_like(seg[..., :1]), seg.cumsum(-1)], -1)


def _project_each_lane(pos, lanes, lanes_mask, cum):
    """Closest point of pos (B, 2) on every lane: squared distance, arc length and heading, each
    (B, L)."""
    seg_ok = lanes_mask[:, :, :-1] & lanes_mask[:, :, 1:]  # (B, L, P-1)
    q = pos[:, None, None, :]  # (B, 1, 1, 2)
    frac, r, lane_h, _ = segment_projection(q, lanes[:, :, :-1], lanes[:, :, 1:])  # (B, L, P-1)
    d2 = torch.where(seg_ok, (r**2).sum(-1), torch.full_like(r[..., 0], 1e9))
    best = d2.argmin(-1, keepdim=True)  # (B, L, 1) the closest segment of each lane
    arclength = cum[..., :-1] + frac * (cum[..., 1:] - cum[..., :-1])  # (B, L, P-1)
    return tuple(t.gather(-1, best).squeeze(-1) for t in (d2, arclength, lane_h))


def _point_at_arclength(lanes, cum, arc):
    """Lane points at arc lengths arc (B, G, Q) on lanes (B, G, P, 3), interpolated (B, G, Q, 3)."""
    i = torch.searchsorted(cum.contiguous(), arc.contiguous())  # the segment's end point
    i = i.clamp(1, cum.shape[-1] - 1)
    arc0, arc1 = cum.gather(-1, i - 1), cum.gather(-1, i)
    a = lanes.gather(-2, (i - 1)[..., None].expand(*i.shape, 3))
    b = lanes.gather(-2, i[..., None].expand(*i.shape, 3))
    f = ((arc - arc0) / (arc1 - arc0).clamp_min(1e-6)).clamp(0, 1)[..., None]
    xy = a[..., :2] + f * (b[..., :2] - a[..., :2])
    h = a[..., 2:] + f * wrap_angle(b[..., 2:] - a[..., 2:])
    return torch.cat([xy, h], -1)


def _hermite(p0, m0, p1, m1, tau):
    """Cubic Hermite curves p0 -> p1 with end tangents m0, m1 (..., 2) at tau (Q,) in [0, 1]:
    value, first and second derivative, each (..., Q, 2), as one product of the basis functions
    (3 Q, 4) with the control points."""
    t = tau[:, None]  # (Q, 1)
    # the Hermite basis h00, h10, h01, h11: p(t) = h00 p0 + h10 m0 + h01 p1 + h11 m1
    h = [2 * t**3 - 3 * t**2 + 1, t**3 - 2 * t**2 + t, -2 * t**3 + 3 * t**2, t**3 - t**2]
    dh = [6 * t**2 - 6 * t, 3 * t**2 - 4 * t + 1, -6 * t**2 + 6 * t, 3 * t**2 - 2 * t]
    ddh = [12 * t - 6, 6 * t - 4, -12 * t + 6, 6 * t - 2]
    basis = torch.cat([torch.cat(b, 1) for b in (h, dh, ddh)], 0)  # (3 Q, 4)
    ctrl = torch.stack([p0, m0, p1, m1]).reshape(4, -1)  # (4, ... * 2)
    out = (basis @ ctrl).reshape(3, len(tau), *p0.shape)  # (3, Q, ..., 2)
    return list(out.movedim(1, -2))  # value, first, second derivative, each (..., Q, 2)


def _goal_lanes(goal, lanes, lanes_mask, cum, cfg: Config):
    """The goal lanes: within goal_lane_dist of the goal and heading within goal_lane_heading of
    the goal's, up to max_goal_lanes, closest first. goal (B, 4) -> the lanes (B, G, P, 3), their
    arc lengths (B, G, P) and masks (B, G, P), and whether each is a goal lane at all (B, G)."""
    B, _, P, _ = lanes.shape
    d2_goal, _, h_goal = _project_each_lane(goal[:, :2], lanes, lanes_mask, cum)  # (B, L)
    near = d2_goal < cfg.goal_lane_dist**2
    aligned = wrap_angle(h_goal - goal[:, 2:3]).abs() < cfg.goal_lane_heading
    G = min(cfg.max_goal_lanes, lanes.shape[1])
    ranked = torch.where(near & aligned, d2_goal, math.inf)
    score, idx = ranked.topk(G, -1, largest=False)  # (B, G)
    g_lanes = lanes.gather(1, idx[:, :, None, None].expand(B, G, P, 3))  # (B, G, P, 3)
    g_cum = cum.gather(1, idx[:, :, None].expand(B, G, P))  # (B, G, P)
    g_mask = lanes_mask.gather(1, idx[:, :, None].expand(B, G, P))  # (B, G, P)
    return g_lanes, g_cum, g_mask, torch.isfinite(score)


def _terminal_states(s0, goal, lanes, lanes_mask, cfg: Config):
    """The candidates' terminal states on the goal lanes: each lane x 8 terminal accelerations x 3
    lateral offsets, flattened to N. s0, goal (B, 4) -> position (B, N, 2), heading (B, N),
    speed (B, N), valid (B, N): a goal lane and the terminal on it."""
    B, dur = len(s0), cfg.horizon * cfg.dt
    cum = _lane_arclength(lanes, lanes_mask)  # (B, L, P)
    g_lanes, g_cum, g_mask, lane_ok = _goal_lanes(goal, lanes, lanes_mask, cum, cfg)
    _, arc_ego, _ = _project_each_lane(s0[:, :2], g_lanes, g_mask, g_cum)  # (B, G) ego's arc length
    acc = s0.new_tensor(cfg.plan_accels)  # (n_acc,)
    off = s0.new_tensor(cfg.plan_offsets)  # (n_off,)
    v0 = s0[:, 3:4]  # (B, 1)
    # v_f = max(v0 + a T dt, 0), and the distance (v0 + v_f) / 2 * T dt along the lane
    v_f = (v0 + acc * dur).clamp_min(0)  # (B, n_acc)
    arc_end = arc_ego[:, :, None] + ((v0 + v_f) / 2 * dur)[:, None, :]  # (B, G, n_acc)
    on_lane = arc_end <= g_cum[..., -1:]  # the terminal lies on the lane
    lp = _point_at_arclength(g_lanes, g_cum, arc_end)  # (B, G, n_acc, 3)
    # then the lateral offset along the lane's normal
    normal = torch.stack([-torch.sin(lp[..., 2]), torch.cos(lp[..., 2])], -1)  # (B, G, n_acc, 2)
    p1 = lp[..., None, :2] + off[:, None] * normal[..., None, :]  # (B, G, n_acc, n_off, 2)
    h1 = lp[..., 2, None].expand(*p1.shape[:-1])  # (B, G, n_acc, n_off)
    v1 = v_f[:, None, :, None].expand_as(h1)
    valid = (lane_ok[:, :, None] & on_lane)[..., None].expand_as(h1)
    return p1.reshape(B, -1, 2), h1.reshape(B, -1), v1.reshape(B, -1), valid.reshape(B, -1)


def _heading_vector(h):
    """(cos h, sin h): the unit vector of heading h (...,) -> (..., 2)."""
    return torch.stack([torch.cos(h), torch.sin(h)], -1)


def _spline_trajectories(s0, p1, h1, v1, cfg: Config):
    """The cubic Hermite curve from s0 (B, 4) to each terminal state (p1 (B, N, 2), h1, v1 (B, N)),
    position and velocity matched at both ends, sampled at the T+1 steps: its states
    (B, N, T+1, 4), the controls derived from it (B, N, T, 2) and its speed (B, N, T+1)."""
    B, N = h1.shape
    T, dur = cfg.horizon, cfg.horizon * cfg.dt
    p0 = s0[:, None, :2].expand(B, N, 2)
    # the tangents scale with the duration
    m0 = (s0[:, 3:4] * _heading_vector(s0[:, 2]))[:, None].expand(B, N, 2) * dur
    m1 = v1[..., None] * _heading_vector(h1) * dur
    tau = torch.linspace(0, 1, T + 1, dtype=s0.dtype, device=s0.device)
    pos, dpos, ddpos = _hermite(p0, m0, p1, m1, tau)  # (B, N, T+1, 2) each
    vel, accel = dpos / dur, ddpos / dur**2
    speed = vel.norm(dim=-1)  # (B, N, T+1)
    # heading = direction of travel; below 0.1 m/s (5 cm a step) that direction is the spline's
    # rounding, so the heading blends from h0 to h1 there and the rates divide by at least 0.1
    h0 = s0[:, None, None, 2]  # (B, 1, 1)
    h_blend = h0 + tau * wrap_angle(h1 - s0[:, None, 2])[..., None]
    yaw = torch.where(speed > 0.1, torch.atan2(vel[..., 1], vel[..., 0]), h_blend)
    yaw = h0 + wrap_angle(yaw - h0)  # continuous from h0
    # yaw rate = (v x a) / |v|^2 (the path's curvature times speed), acceleration = v . a / |v|
    cross = vel[..., 0] * accel[..., 1] - vel[..., 1] * accel[..., 0]
    yaw_rate = cross / speed.clamp_min(0.1) ** 2
    lon_acc = (vel * accel).sum(-1) / speed.clamp_min(0.1)
    s = torch.stack([pos[..., 0], pos[..., 1], yaw, speed], -1)  # (B, N, T+1, 4)
    # controls of step t = average of the derived values at t and t+1
    both = torch.stack([yaw_rate, lon_acc], -1)  # (B, N, T+1, 2)
    u = (both[..., 1:, :] + both[..., :-1, :]) / 2  # (B, N, T, 2)
    return s, u, speed


def _feasible(u, speed, cfg: Config):
    """Dynamic feasibility (B, N) of controls u (B, N, T, 2) at speeds (B, N, T+1): the
    controller's box, the lateral acceleration, the yaw rate per unit speed."""
    lo, hi = u.new_tensor(cfg.u_lower), u.new_tensor(cfg.u_upper)
    v_mid = (speed[..., 1:] + speed[..., :-1]) / 2  # (B, N, T)
    in_box = ((u >= lo) & (u <= hi)).all(-1)
    lateral_ok = (u[..., 0] * v_mid).abs() <= cfg.feas_lat_accel
    yaw_ok = u[..., 0].abs() <= cfg.feas_yaw_per_speed * v_mid + 1e-3  # 1e-3: a stop's rounding
    return (in_box & lateral_ok & yaw_ok).all(-1)


def plan_candidates(s0, goal, lanes, lanes_mask, cfg: Config) -> Candidates:
    """Candidate trajectories (App. C.1) from the ego state s0 (B, 4) towards goal (B, 4): on up to
    max_goal_lanes goal lanes, 8 terminal accelerations x 3 lateral offsets, each joined to s0 by
    the cubic Hermite curve fixed by position and velocity at both ends (as the authors' code; the
    paper's spline "minimizes mean control effort")."""
    p1, h1, v1, valid = _terminal_states(s0, goal, lanes, lanes_mask, cfg)  # N = G x 8 x 3
    s, u, speed = _spline_trajectories(s0, p1, h1, v1, cfg)
    return Candidates(s, u, valid & _feasible(u, speed, cfg))


def plan_loss(cost: torch.Tensor, valid: torch.Tensor, target: torch.Tensor, beta: float):
    """The relaxed argmin (§3.1): p_n = exp(-beta C_n) / sum_valid exp(-beta C), and
    L_plan = -log p_n* (B,)."""
    log_p_n = torch.log_softmax(torch.where(valid, -beta * cost, -math.inf), -1)  # (B, N)
    return -log_p_n.gather(-1, target[:, None]).squeeze(-1)


def masked_argmin(values: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """argmin over the last dim among the valid entries: (B, N) -> (B,)."""
    return torch.where(valid, values, math.inf).argmin(-1)


class Plan(NamedTuple):
    """The planner's output for a batch."""

    cands: Candidates
    cost: torch.Tensor  # (B, N)       C_n, eq. (3) with the given weights
    best: torch.Tensor  # (B,)         the plan: argmin_n C_n over the valid candidates, eq. (2)
    plannable: torch.Tensor  # (B,)    bool: at least 2 valid candidates (others: flagged)
    terms: torch.Tensor  # (B, N, 5)   the unweighted terms of eq. (3) per candidate


def plan(s0, ctx: CostContext, goal_state, w, cfg: Config, scene: ScenePlan | None = None) -> Plan:
    """Eq. (2): the candidates, their costs C_n and the argmin, as Plan. s0 (B, 4), goal_state
    (B, 4), w (5,) or (B, 5); scene: the candidates and their prediction-free terms if already
    computed."""
    if scene is None:
        cands = plan_candidates(s0, goal_state, ctx.lanes, ctx.lanes_mask, cfg)
        terms = cost_terms(cands.s, cands.u, ctx, cfg.rbf_var)  # (B, N, 5)
    else:  # with the scene's terms known, C_coll is the one term a prediction moves
        cands = scene.cands
        coll = collision_term(cands.s[..., 1:, :2], ctx, cfg.rbf_var)  # (B, N)
        terms = torch.cat([coll[..., None], scene.terms], -1)  # (B, N, 5)
    cost = weigh(terms, w)  # (B, N)
    plannable = cands.valid.sum(-1) >= 2
    return Plan(cands, cost, masked_argmin(cost.detach(), cands.valid), plannable, terms)


# ===== 5. Controller: box-constrained iLQR, eq. (4) and App. C.2, and its exact KKT backward =====
#   min_{s, u}  sum_t l_t(s_t, u_t) + l_T(s_T)   s.t.  s_0 = s_init,  s_{t+1} = f(s_t, u_t),
#                                                      lo <= u_t <= hi
# The backward pass goes beyond the paper by default. The paper differentiates "the KKT conditions
# of the last LQR approximation" (as mpc.pytorch and the authors' code: kkt_backward's exact=False),
# whose Hessian lacks the dynamics' curvature sum_i lambda_i d2 f_i: exact on linear dynamics only;
# tracking with the unicycle, 45 % off. The default (exact=True) adds it, the Lagrangian's Hessian,
# and so differentiates the converged solution itself (test_diffstack.py: within 1e-6 of central
# differences). Where iLQR stalls on active bounds, active_set finishes the solve (refine).
# General: `cost_fn(s, u, *params) -> (B, ...)` any twice-differentiable sum of per-step terms,
# `dynamics(s_t, u_t) -> s_{t+1}` any twice-differentiable step; gradients reach s_init and every
# tensor in `params`. Closed forms where they bring them (`expansion`, `jacobians`, `curvature`).


def _stagewise_jacobian(fn, su: torch.Tensor, with_value=False):
    """d fn(su)[..., t, :] / d su[..., t, :] for every t, su (B, T, D) -> (B, T, out, D) (and
    fn(su) with_value). Step t's output depends on step t's input only, so one perturbation delta
    (D,) shared by all steps gives every block (has_aux: fn(su) comes back beside it)."""
    zero = su.new_zeros(su.shape[-1])  # (D,)
    jac = torch.func.jacfwd(lambda delta: (fn(su + delta),) * 2, has_aux=True)(zero)
    return jac if with_value else jac[0]


def cost_expansion(cost_fn, s, u, params):
    """Gradient (B, T+1, n+m) and block Hessian (B, T+1, n+m, n+m) of the cost, step by step."""
    if hasattr(cost_fn, "expansion"):
        return cost_fn.expansion(s, u, *params)
    n, T = s.shape[-1], u.shape[1]
    su = torch.cat([s, torch.cat([u, u.new_zeros(u[:, :1].shape)], 1)], -1)  # (B, T+1, n+m): u_T 0
    grad = torch.func.grad(lambda su: cost_fn(su[..., :n], su[:, :T, n:], *params).sum())
    H, g = _stagewise_jacobian(grad, su, with_value=True)
    return g, H


def _collision_expansion(pos, ctx: CostContext, rbf_var: float):
    """C_coll's gradient (B, T, 2) and Hessian (B, T, 2, 2) in pos (B, T, 2) (see below)."""
    eye = torch.eye(2, dtype=pos.dtype, device=pos.device)
    mu, spread = prediction_moments(ctx)  # (B, T, 2), (B, T)
    # the predicted mean first, then the other agents: (B, 1+A, ...)
    diff = pos[:, None] - torch.cat([mu[:, None], ctx.others], 1)  # (B, 1+A, T, 2)
    offset = torch.cat([spread[:, None], torch.zeros_like(ctx.others[..., 0])], 1)  # (B, 1+A, T)
    mask = torch.cat([ctx.pred_mask[:, None], ctx.others_mask], 1)[..., None]  # (B, 1+A, 1)
    phi = mask * rbf((diff**2).sum(-1) + offset, rbf_var)  # (B, 1+A, T)
    grad = -(phi[..., None] * diff).sum(1) / rbf_var  # (B, T, 2)
    hess = diff[..., :, None] * diff[..., None, :] / rbf_var**2 - eye / rbf_var  # (B, 1+A, T, 2, 2)
    return grad, (phi[..., None, None] * hess).sum(1)


def _lane_expansion(pos, h, ctx: CostContext):
    """C_lat's gradient, Hessian in pos (B, T, 2), C_head's in (pos, h) (B, T, 3) (see below)."""
    eye = torch.eye(2, dtype=pos.dtype, device=pos.device)
    a, b, has_lane = nearest_lane_segment(pos, h, ctx.lanes, ctx.lanes_mask)  # (B, T, 3) x 2
    _, r, lane_h, df = segment_projection(pos, a, b)  # (B, T, 2), (B, T), (B, T, 2)
    on = has_lane.to(pos.dtype)  # (B, T)
    J = eye - (b[..., :2] - a[..., :2])[..., :, None] * df[..., None, :]  # (B, T, 2, 2) dr/dpos
    g_lat = 2 * (J.mT @ r[..., None])[..., 0] * on[..., None]
    H_lat = 2 * J.mT @ J * on[..., None, None]
    e = wrap_angle(h - lane_h) * on  # (B, T)
    de_dpos = -wrap_angle(b[..., 2] - a[..., 2])[..., None] * df  # (B, T, 2)
    de = torch.cat([de_dpos, torch.ones_like(e)[..., None]], -1)  # (B, T, 3): d e / d(pos, h)
    g_head = 2 * e[..., None] * de
    H_head = 2 * de[..., :, None] * de[..., None, :] * on[..., None, None]
    return g_lat, H_lat, g_head, H_head


def cost_expansion_closed_form(s, u, ctx: CostContext, w, rbf_var: float = 2.0):
    """The gradient (B, T+1, 6) and block Hessian (B, T+1, 6, 6) of eq. (3) in (s_t, u_t) =
    (x, y, h, v, omega, a), step by step (s_0 costs nothing; u_T = 0 pads the last step), in closed
    form: cost_expansion's autodiff (held together by the tests). s (B, T+1, 4), u (B, T, 2), w (5,)
    or (B, 5). With pos, h a state's position and heading (sigma^2 = rbf_var):
      C_coll  phi = exp(-(|pos - mu|^2 + spread) / 2 sigma^2) per predicted mean mu = mu_t, and
              with spread 0 per other agent (mu its position): grad = -phi (pos - mu) / sigma^2,
              Hess = phi ((pos - mu)(pos - mu)' / sigma^4 - I / sigma^2)
      C_goal  |pos_T - g|^2:  grad = 2 (pos_T - g),  Hess = 2 I
      C_lat   |r|^2, r = pos - a - f (b - a) the offset from the closest point on the segment
              a -> b (f the fraction along it, linear in pos: df = (b - a) / |b - a|^2, or 0
              where clamped):  J = dr/dpos = I - (b - a) df',  grad = 2 J'r,  Hess = 2 J'J
      C_head  e^2, e = h - h_lane, h_lane = h_a + f (h_b - h_a):  de/dh = 1,
              de/dpos = -(h_b - h_a) df,  grad = 2 e de,  Hess = 2 de de'
      C_u     omega^2 + a^2:  grad = 2 u,  Hess = 2 I"""
    B, T = u.shape[:2]
    eye = torch.eye(2, dtype=s.dtype, device=s.device)
    w_coll, w_goal, w_lat, w_head, w_u = w.expand(B, -1)[:, :, None, None].unbind(1)  # (B, 1, 1)
    pos, h = s[:, 1:, :2], s[:, 1:, 2]  # (B, T, 2), (B, T): the states t1..T
    g_coll, H_coll = _collision_expansion(pos, ctx, rbf_var)
    g_lat, H_lat, g_head, H_head = _lane_expansion(pos, h, ctx)
    # the states t1..T in rows 1..T, the controls t0..T-1 in rows 0..T-1
    g, H = s.new_zeros(B, T + 1, 6), s.new_zeros(B, T + 1, 6, 6)
    g[:, 1:, :2] = w_coll * g_coll + w_lat * g_lat
    g[:, 1:, :3] += w_head * g_head
    g[:, T, :2] += 2 * w_goal[:, 0] * (pos[:, -1] - ctx.goal)
    g[:, :T, 4:] = 2 * w_u * u
    H[:, 1:, :2, :2] = w_coll[..., None] * H_coll + w_lat[..., None] * H_lat
    H[:, 1:, :3, :3] += w_head[..., None] * H_head
    H[:, T, :2, :2] += 2 * w_goal * eye
    H[:, :T, 4:, 4:] = 2 * w_u[..., None] * eye
    return g, H


class StackCost:
    """Eq. (3) as the controller sees it: cost(s, u, w, *ctx.tensors()) -> (B, ...), every
    argument per scenario, and its closed-form `expansion`, which the solver takes over autodiff."""

    def __init__(self, rbf_var: float):
        self.rbf_var = rbf_var

    def __call__(self, s, u, w, *context):
        return weigh(cost_terms(s, u, CostContext(*context), self.rbf_var), w)

    def expansion(self, s, u, w, *context):
        return cost_expansion_closed_form(s, u, CostContext(*context), w, self.rbf_var)


def dynamics_jacobians(dynamics, s, u):
    """f_s,t = df/ds (B, T, n, n), f_u,t = df/du (B, T, n, m) along s (B, T+1, n), u (B, T, m)."""
    if hasattr(dynamics, "jacobians"):
        return dynamics.jacobians(s[:, :-1], u)
    n = s.shape[-1]
    su = torch.cat([s[:, :-1], u], -1)  # (B, T, n+m)
    J = _stagewise_jacobian(lambda su: dynamics(su[..., :n], su[..., n:]), su)
    return J[..., :n], J[..., n:]


def solve_small(M, rhs):
    """M^-1 rhs for M (..., m, m), rhs (..., m, r); by Cramer's rule when m = 2: Table 4's imitation
    trainings, no seed of 14 above -13.5 with it, 4 of 10 above -3 with torch.linalg.solve."""
    if M.shape[-1] != 2:
        return torch.linalg.solve(M, rhs)
    m00, m01 = M[..., 0, 0, None], M[..., 0, 1, None]  # (..., 1) each
    m10, m11 = M[..., 1, 0, None], M[..., 1, 1, None]
    r0, r1 = rhs[..., 0, :], rhs[..., 1, :]  # (..., r) each
    det = (m00 * m11 - m01 * m10)[..., None]  # (..., 1, 1)
    return torch.stack([m11 * r0 - m01 * r1, m00 * r1 - m10 * r0], -2) / det


def solve_masked(Q, rhs, free):
    """Solve the free rows of Q sol = rhs, with sol = rhs on the others: Q (..., m, m),
    rhs (..., m, r), free (..., m)."""
    eye = torch.eye(Q.shape[-1], dtype=Q.dtype, device=Q.device)
    both_free = free[..., :, None] & free[..., None, :]
    return solve_small(torch.where(both_free, Q, eye), rhs)


def box_qp(Q, q, lo, hi):
    """min 1/2 delta'Q delta + q'delta  s.t. lo <= delta <= hi, exactly, for small m and Q > 0:
    the unconstrained minimiser where it is inside the box, else the best feasible one of the 3^m
    active sets (each control free, at lo or at hi). Q (B, m, m), q, lo, hi (B, m) -> delta (B, m),
    free (B, m) bool: the controls not held at a bound."""
    B, m = q.shape
    delta = solve_small(Q, -q[..., None])[..., 0]  # (B, m)
    inside = ((delta >= lo) & (delta <= hi)).all(-1)  # (B,)
    if inside.all():
        return delta, torch.ones_like(delta, dtype=torch.bool)
    assert m <= 4, "box_qp enumerates 3^m active sets: meant for few controls"
    # (3^m, m): each control free (0), at lo (1) or at hi (2)
    sets = torch.cartesian_prod(*[torch.arange(3, device=q.device)] * m).reshape(-1, m)
    free = sets == 0
    fixed_val = torch.where(sets[None] == 1, lo[:, None], hi[:, None])  # (B, 3^m, m)
    Qs, qs = Q[:, None], q[:, None]  # (B, 1, m, m), (B, 1, m)
    # free rows: Q_ff delta_f = -(q_f + Q_fc delta_c); fixed rows: delta_c = fixed value
    delta_fixed = torch.where(free, 0.0, fixed_val)[..., None]  # (B, 3^m, m, 1)
    rhs = torch.where(free, -(qs + (Qs @ delta_fixed)[..., 0]), fixed_val)  # (B, 3^m, m)
    Q_all = Qs.expand(-1, len(sets), m, m)
    deltas = solve_masked(Q_all, rhs[..., None], free.expand_as(rhs))[..., 0]  # (B, 3^m, m)
    feasible = ((deltas >= lo[:, None] - 1e-9) & (deltas <= hi[:, None] + 1e-9)).all(-1)
    obj = ((0.5 * (Qs @ deltas[..., None])[..., 0] + qs) * deltas).sum(-1)  # (B, 3^m)
    best = torch.where(feasible, obj, math.inf).argmin(-1)  # (B,)
    rows = torch.arange(B, device=q.device)
    delta_box, free_box = deltas[rows, best], free.expand(B, -1, -1)[rows, best]
    return torch.where(inside[:, None], delta, delta_box), free_box | inside[:, None]


def policy(Q_u, Q_us, Q_uu, lo, hi, pd_eps, free=None):
    """The step du = ff + G ds that minimises Q: [ff G] = -Q_uu^-1 [Q_u Q_us] on the free controls
    (free (B, m) bool, given), 0 on the held ones; iLQR's, control-limited DDP's (Tassa et al. 2014,
    §III.B), with Q_uu shifted to eigenvalues >= pd_eps (descent) and ff the box QP's solution
        min_ff 1/2 ff'Q_uu ff + Q_u'ff   s.t.  lo <= ff <= hi,    free: the controls it leaves free.
    Q_u (B, m, 1), Q_us, G (B, m, n), Q_uu (B, m, m), lo, hi, free (B, m) -> ff, G, free."""
    if box := free is None:
        shift = (pd_eps - torch.linalg.eigvalsh(Q_uu)[..., :1]).clamp_min(0.0)  # (B, 1)
        Q_uu = Q_uu + torch.diag_embed(shift.expand_as(Q_u[..., 0]))  # eigenvalues >= pd_eps
        ff, free = box_qp(Q_uu, Q_u[..., 0], lo, hi)  # (B, m), (B, m)
    rhs = torch.where(free[..., None], -torch.cat([Q_u, Q_us], -1), 0.0)  # (B, m, 1+n)
    ffG = solve_masked(Q_uu, rhs, free)
    return ff[..., None] if box else ffG[..., :1], ffG[..., 1:], free


def lqr_backward(f_s, f_u, H, g, lo=None, hi=None, pd_eps=0.0, free=None):
    """The backward pass of a time-varying LQR in the Q-function form of iLQR (Li, Todorov 2004;
    Tassa, Mansard, Todorov 2014). The stage cost of (ds_t, du_t) is 1/2 [ds; du]'H_t [ds; du] +
    g_t'[ds; du] (l_s, l_u = g's blocks, l_ss, l_us, l_uu = H's), the dynamics
    ds_{t+1} = f_s,t ds_t + f_u,t du_t. From V_T = l_T, for t = T-1 .. 0 (V+ is V_{t+1}, ' the
    transpose, f_s and f_u at t):
        Q_s  = l_s  + f_s'V+_s          Q_ss = l_ss + f_s'V+_ss f_s
        Q_u  = l_u  + f_u'V+_s          Q_uu = l_uu + f_u'V+_ss f_u     Q_us = l_us + f_u'V+_ss f_s
        du   = ff + G ds                the step that minimises Q (policy)
        V_s  = Q_s  + G'Q_uu ff + G'Q_u + Q_us'ff
        V_ss = Q_ss + G'Q_uu G + G'Q_us + Q_us'G
    iLQR's pass bounds du by lo, hi (B, T, m); the KKT backward's and active_set's hold the
    controls that are not free (B, T, m) at du = 0. f_s (B, T, n, n), f_u (B, T, n, m),
    H (B, T+1, n+m, n+m), g (B, T+1, n+m) (the last step has no control). Returns ff (B, T, m),
    G (B, T, m, n), free (B, T, m) and V_s at t = 0 (B, n): the costate lambda_0 = dV_0/ds_0."""
    T, n = f_s.shape[1], f_s.shape[-1]
    V_s, V_ss = g[:, T, :n, None], H[:, T, :n, :n]  # (B, n, 1), (B, n, n)
    steps = []  # (ff, G, free) of t = T-1 .. 0
    for t in reversed(range(T)):
        f_s_t, f_u_t = f_s[:, t], f_u[:, t]  # (B, n, n), (B, n, m)
        l_s, l_u = g[:, t, :n, None], g[:, t, n:, None]  # (B, n, 1), (B, m, 1)
        l_ss, l_us, l_uu = H[:, t, :n, :n], H[:, t, n:, :n], H[:, t, n:, n:]
        Q_s = l_s + f_s_t.mT @ V_s  # (B, n, 1)
        Q_u = l_u + f_u_t.mT @ V_s  # (B, m, 1)
        Q_ss = l_ss + f_s_t.mT @ V_ss @ f_s_t  # (B, n, n)
        Q_uu = l_uu + f_u_t.mT @ V_ss @ f_u_t  # (B, m, m)
        Q_us = l_us + f_u_t.mT @ V_ss @ f_s_t  # (B, m, n)
        box = (lo[:, t], hi[:, t], pd_eps) if free is None else (None, None, 0.0, free[:, t])
        ff, G, free_t = policy(Q_u, Q_us, Q_uu, *box)
        V_s = Q_s + G.mT @ Q_uu @ ff + G.mT @ Q_u + Q_us.mT @ ff  # (B, n, 1)
        V_ss = Q_ss + G.mT @ Q_uu @ G + G.mT @ Q_us + Q_us.mT @ G  # (B, n, n)
        V_ss = (V_ss + V_ss.mT) / 2  # symmetric up to rounding; kept exactly symmetric
        steps.append((ff[..., 0], G, free_t))
    ff, G, free_out = (torch.stack(v[::-1], 1) for v in zip(*steps))
    return ff, G, free_out, V_s[..., 0]


@dataclass
class ILQRInfo:
    """What the solver reports per scenario."""

    converged: torch.Tensor  # (B,) bool: the last full LQR step was below tol
    step_norm: torch.Tensor  # (B,) norm of the last full LQR control step
    iters: torch.Tensor  # (B,) iterations run
    costs: torch.Tensor  # (B, I+1) true cost after each iteration (the first: at u_init)


def ilqr(
    cost_fn, dynamics, s_init, u_init, params, lo, hi, iters=5, tol=0.05, ls_steps=5, ls_decay=5.0
):
    """iLQR with box controls (App. C.2); differentiable by unrolling (`ILQR` gives the exact KKT
    gradient instead). s_init (B, n), u_init (B, T, m), lo/hi (m,) or (B, T, m)
    -> s (B, T+1, n), u (B, T, m), ILQRInfo. Each iteration
        1. expands the cost to second and the dynamics to first order along (s, u),
        2. solves the box-constrained LQR of the step du = ff + G ds (lqr_backward),
        3. line-searches the step's scale (line_search);
    a scenario whose full step is below tol has converged and stops moving."""
    B, T, m = u_init.shape
    lo, hi = lo.expand(B, T, m), hi.expand(B, T, m)
    u = u_init.clamp(lo, hi)
    s = rollout(dynamics, s_init, u)
    cost = cost_fn(s, u, *params)  # (B,)
    # Q_uu's least eigenvalue: > 0 for a descent step, and in float32 well above the rounding
    # of Q_uu's entries (eps 1.2e-7 times up to ~1e3)
    pd_eps = 1e-6 if s.dtype == torch.float64 else 1e-3
    scales = ls_decay ** -torch.arange(ls_steps, dtype=s.dtype, device=s.device)  # 1, 1/5, ...
    moving = torch.ones_like(cost, dtype=torch.bool)  # not converged yet
    iters_run = torch.zeros_like(cost).long()
    step_norm = torch.full((B,), math.inf, dtype=s.dtype, device=s.device)
    costs = [cost]
    for _ in range(iters):
        g, H = cost_expansion(cost_fn, s, u, params)  # (B, T+1, n+m), (B, T+1, n+m, n+m)
        f_s, f_u = dynamics_jacobians(dynamics, s, u)  # (B, T, n, n), (B, T, n, m)
        ff, G, _, _ = lqr_backward(f_s, f_u, H, g, lo - u, hi - u, pd_eps)
        s, u, cost, full_step = line_search(  # a converged scenario stays where it is
            cost_fn, dynamics, s, u, cost, ff, G, lo, hi, params, scales, moving
        )
        step_norm = torch.where(moving, full_step, step_norm)
        iters_run = iters_run + moving.long()
        costs.append(cost)
        moving = moving & (step_norm >= tol)
        if not moving.any():
            break
    return s, u, ILQRInfo(step_norm < tol, step_norm, iters_run, torch.stack(costs, 1))


def active_set(cost_fn, dynamics, s, u, params, lo, hi, info, tol, iters, patience=3):
    """Where iLQR stalls, exact on a linear-quadratic problem: the primal-dual active-set method
    (Hintermueller, Ito, Kunisch 2002), block principal pivoting with Portugal, Judice, Vicente's
    (1994) backup rule. The held controls go to their bound, the free ones by the LQR with the held
    fixed, unclamped; then the violators flip: free controls outside the box are held at the bound
    they crossed, held ones whose dC/du points into the box (at lo: < 0) freed. None left and the
    step below tol: a KKT point. Where the violators have not become fewer than their least for
    `patience` iterations, the earliest step's alone flip (no cycling). Refines ilqr's s (B, T+1,
    n), u (B, T, m) where info has not converged; lo/hi (m,) or (B, T, m) -> s, u, ILQRInfo."""
    B, T, m = u.shape
    lo, hi = lo.expand(B, T, m), hi.expand(B, T, m)
    moving = ~info.converged  # (B,) the problems refined
    held_lo, held_hi = u <= lo, u >= hi  # (B, T, m) each
    grad = torch.func.grad(lambda u: cost_fn(rollout(dynamics, s[:, 0], u), u, *params).sum())
    least, tries = torch.full((B,), T * m + 1, device=u.device), torch.zeros(B, device=u.device)
    iters_run, step = info.iters, info.step_norm  # step: >= tol, or NaN
    s_in, u_in = s, u  # iLQR's, kept where this does not converge
    for k in range(iters + 1 if iters else 0):  # the last: the check alone
        dC_du = grad(u)  # (B, T, m): a held control's multiplier, up to its sign
        free = ~(held_lo | held_hi)  # (B, T, m)
        to_lo = (free & (u < lo)) | (held_lo & (dC_du < 0))  # the violators
        to_hi = (free & (u > hi)) | (held_hi & (dC_du > 0))
        count = (to_lo | to_hi).flatten(1).sum(-1)  # (B,)
        moving = moving & ((count > 0) | ~(step < tol))
        if k == iters or not moving.any():
            break
        tries, least = torch.where(count < least, patience, tries - 1), least.minimum(count)
        first = (to_lo | to_hi).any(-1).long().argmax(-1)  # (B,) the earliest step with one
        flip = (tries >= 0)[:, None] | (torch.arange(T, device=u.device) == first[:, None])
        held_lo = held_lo ^ (flip[..., None] & to_lo)  # (B, T, m): the flipped change sides
        held_hi = held_hi ^ (flip[..., None] & to_hi)
        held = held_lo | held_hi  # (B, T, m)
        go = moving[:, None, None]
        u = torch.where(go & held, torch.where(held_lo, lo, hi), u)
        s = rollout(dynamics, s[:, 0], u)
        g, H = cost_expansion(cost_fn, s, u, params)  # (B, T+1, n+m), (B, T+1, n+m, n+m)
        ff, G, _, _ = lqr_backward(*dynamics_jacobians(dynamics, s, u), H, g, free=~held)
        s_new, u_new = closed_loop_rollout(dynamics, s, u, ff, G, lo - math.inf, hi + math.inf)
        step = torch.where(moving, (u_new - u).flatten(1).norm(dim=-1), step)
        s, u = torch.where(go, s_new, s), torch.where(go, u_new, u)
        iters_run = iters_run + moving.long()
    back = moving[:, None, None]  # not converged: iLQR's s, u and step stand
    s, u = torch.where(back, s_in, s), torch.where(back, u_in, u)
    step = torch.where(moving, info.step_norm, step)
    return s, u, ILQRInfo(info.converged | ~moving, step, iters_run, info.costs)


def closed_loop_rollout(dynamics, s, u, ff, G, lo, hi):
    """The LQR step applied with feedback, from s_new,0 = s_0:
        u_new,t = clamp(u_t + ff_t + G_t (s_new,t - s_t), lo_t, hi_t),
        s_new,t+1 = f(s_new,t, u_new,t).
    s (B, T+1, n), u, ff, lo, hi (B, T, m), G (B, T, m, n) -> s_new (B, T+1, n), u_new (B, T, m)."""
    s_out, u_out = [s[:, 0]], []
    for t in range(u.shape[1]):
        feedback = (G[:, t] @ (s_out[-1] - s[:, t])[..., None])[..., 0]  # (B, m)
        u_out.append((u[:, t] + ff[:, t] + feedback).clamp(lo[:, t], hi[:, t]))
        s_out.append(dynamics(s_out[-1], u_out[-1]))
    return torch.stack(s_out, 1), torch.stack(u_out, 1)


def line_search(cost_fn, dynamics, s, u, cost, ff, G, lo, hi, params, scales, moving):
    """Backtracking (App. C.2): the closed-loop rollout of the step eta ff + G ds at eta = 1, then
    at 1/5, 1/25, ... where the true cost rose; the first scale that does not raise it is taken.
    s (B, T+1, n), u, ff, lo, hi (B, T, m), G (B, T, m, n), cost, moving (B,) -> the new s, u, cost
    (the old ones where no scale was accepted or not moving), the norm of the full step (B,)."""
    eps = torch.finfo(s.dtype).eps
    s_new, u_new, cost_new, accepted = s, u, cost, ~moving  # those not moving: not searched
    for i, eta in enumerate(scales):
        s_eta, u_eta = closed_loop_rollout(dynamics, s, u, eta * ff, G, lo, hi)
        cost_eta = cost_fn(s_eta, u_eta, *params)  # (B,)
        if i == 0:
            full_step = (u_eta - u).flatten(1).norm(dim=-1)  # (B,)
        # no rise up to rounding: the cost sums ~T (1 + A) terms, each rounded to eps
        no_rise = cost_eta <= cost + 100 * eps * (1 + cost.abs())
        take = no_rise & ~accepted  # (B,)
        s_new = torch.where(take[:, None, None], s_eta, s_new)
        u_new = torch.where(take[:, None, None], u_eta, u_new)
        cost_new = torch.where(take, cost_eta, cost_new)
        accepted = accepted | take
        if accepted.all():
            break
    return s_new, u_new, cost_new, full_step


def unicycle_curvature(s: torch.Tensor, u: torch.Tensor, lam: torch.Tensor, dt: float):
    """sum_i lam_i d2 f_i / d(s, u)^2 (..., 6, 6): the dynamics' curvature weighted by costates
    lam (..., 4). Only the displacement R(h) disp, disp = (along, lateral), is curved, in
    (h, v, omega, a). With nu = R(h)' lam_xy (the costate in the heading frame) and J the 90-degree
    rotation:
        d2/dh2 = -nu'disp,   d2/dh dq = (J'nu)' ddisp/dq,   d2/dq dr = nu' d2disp/dq dr
    (q, r in (v, omega, a)); the moments' rule above gives every derivative of disp."""
    h, v = s[..., 2], s[..., 3]
    omega, a = u.unbind(-1)
    (cm0, cm1, cm2, cm3), (sm0, sm1, sm2, sm3) = _moments(omega, dt, 3)
    cos_h, sin_h = torch.cos(h), torch.sin(h)
    nu_x = cos_h * lam[..., 0] + sin_h * lam[..., 1]  # nu = R(h)' lam_xy
    nu_y = -sin_h * lam[..., 0] + cos_h * lam[..., 1]
    disp = (v * cm0 + a * cm1, v * sm0 + a * sm1)
    # first derivatives of disp, by q
    ddisp = {"v": (cm0, sm0), "omega": (-(v * sm1 + a * sm2), v * cm1 + a * cm2), "a": (cm1, sm1)}
    # second derivatives of disp that are not zero, by (q, r)
    d2disp = {
        ("v", "omega"): (-sm1, cm1),
        ("omega", "a"): (-sm2, cm2),
        ("omega", "omega"): (-(v * cm2 + a * cm3), -(v * sm2 + a * sm3)),
    }
    index = {"h": 2, "v": 3, "omega": 4, "a": 5}  # positions in (s, u) = (x, y, h, v, omega, a)
    H = torch.zeros(*h.shape, 6, 6, dtype=s.dtype, device=s.device)
    H[..., 2, 2] = -(nu_x * disp[0] + nu_y * disp[1])  # -nu'disp
    for q, e in ddisp.items():
        H[..., 2, index[q]] = H[..., index[q], 2] = nu_y * e[0] - nu_x * e[1]  # (J'nu)' e
    for (q, r), e in d2disp.items():
        H[..., index[q], index[r]] = H[..., index[r], index[q]] = nu_x * e[0] + nu_y * e[1]
    return H


def lagrangian_curvature(dynamics, s, u, g, f_s):
    """The dynamics' part of the Lagrangian's Hessian, sum_i lambda_{t+1, i} d2 f_i / d(s_t, u_t)^2
    (B, T+1, n+m, n+m) (0 at t = T), with the costates of stationarity in s:
        lambda_T = dl_T/ds_T,   lambda_t = dl_t/ds_t + f_s,t' lambda_{t+1}.
    g (B, T+1, n+m) the cost's gradient along s (B, T+1, n), u (B, T, m); f_s (B, T, n, n)."""
    n, T = s.shape[-1], u.shape[1]
    lam = [g[:, T, :n]]  # lambda_T .. lambda_1
    for t in reversed(range(1, T)):
        lam.append(g[:, t, :n] + (f_s[:, t].mT @ lam[-1][..., None])[..., 0])
    lam = torch.stack(lam[::-1], 1)  # (B, T, n): lambda_1 .. lambda_T
    if hasattr(dynamics, "curvature"):  # closed form (Unicycle)
        Hf = dynamics.curvature(s[:, :-1], u, lam)  # (B, T, n+m, n+m)
    else:  # autodiff: the Hessian of sum_t lambda_{t+1}' f(s_t, u_t)
        grad = torch.func.grad(lambda su: (lam * dynamics(su[..., :n], su[..., n:])).sum())
        Hf = _stagewise_jacobian(grad, torch.cat([s[:, :-1], u], -1))
    return torch.cat([Hf, torch.zeros_like(Hf[:, :1])], 1)


def kkt_backward(cost_fn, dynamics, s, u, params, free, grad_s, grad_u, exact=True):
    """Gradients of a loss on the solution tau = (s, u) wrt s_init and params (Amos et al. 2018).
    At the solution the KKT conditions F(s, u, lambda; params) = 0 hold; by the implicit function
    theorem dloss/dparams = delta' dF/dparams, where delta solves the KKT system with the incoming
    gradient as right-hand side, an LQR problem:
        min_delta 1/2 delta'H delta + (dloss/dtau)'delta   s.t.  ds_0 = 0, du_active = 0,
                                                                 ds_{t+1} = f_s ds_t + f_u du_t,
    H the Hessian of the Lagrangian C + sum_t lambda_{t+1}' (f(s_t, u_t) - s_{t+1}):
        H_t = d2 l_t + sum_i lambda_{t+1, i} d2 f_i(s_t, u_t) (lagrangian_curvature; exact=False: 0)
    Amos et al.'s, for their LQR's cost 1/2 tau'C tau + c'tau, with delta their d*_tau:
        dloss/dc = delta,  dloss/dC = (delta tau' + tau delta') / 2,  dloss/ds_init = lambda_0,
    the LQR's costate at t = 0: the gradient of <grad_tau cost, delta> = <C tau + c, delta> in
    (C, c), tau and delta fixed; for any cost(tau; params), by the chain rule through C and c:
        dloss/dparams = d/dparams [ sum_t dl_t/dtau_t(params) . delta_t ]     (delta fixed)
    s (B, T+1, n), u (B, T, m), free (B, T, m) bool, grad_s, grad_u like s, u."""
    g, H = cost_expansion(cost_fn, s, u, params)
    f_s, f_u = dynamics_jacobians(dynamics, s, u)
    H = H + lagrangian_curvature(dynamics, s, u, g, f_s) if exact else H
    grad_u_padded = torch.cat([grad_u, torch.zeros_like(grad_u[:, :1])], 1)
    rhs = torch.cat([grad_s, grad_u_padded], -1)  # (B, T+1, n+m)
    ff, G, _, lam0 = lqr_backward(f_s, f_u, H, rhs, free=free)
    # the LQR's solution delta = (ds, du) from ds_0 = 0
    ds, du = [torch.zeros_like(s[:, 0])], []
    for t in range(u.shape[1]):
        du.append(ff[:, t] + (G[:, t] @ ds[-1][..., None])[..., 0])
        ds.append((f_s[:, t] @ ds[-1][..., None] + f_u[:, t] @ du[-1][..., None])[..., 0])
    ds, du = torch.stack(ds, 1), torch.stack(du, 1)
    return lam0, params_gradients(cost_fn, s, u, params, ds, du)


def params_gradients(cost_fn, s, u, params, ds, du):
    """d/dparams [ sum_t dl_t/dtau_t(params) . delta_t ], delta = (ds, du) fixed: one gradient per
    entry of params (None where it is no tensor that requires grad)."""
    needs = [i for i, p in enumerate(params) if torch.is_tensor(p) and p.requires_grad]
    if not needs:
        return [None] * len(params)
    with torch.enable_grad():
        ps = [p.detach().requires_grad_() if i in needs else p for i, p in enumerate(params)]
        sg, ug = s.detach().requires_grad_(), u.detach().requires_grad_()
        gs, gu = torch.autograd.grad(cost_fn(sg, ug, *ps).sum(), (sg, ug), create_graph=True)
        inner = (gs * ds).sum() + (gu * du).sum()  # < dC/dtau (params), delta >
        found = torch.autograd.grad(inner, [ps[i] for i in needs], allow_unused=True)
    return [dict(zip(needs, found)).get(i) for i in range(len(params))]


class ILQR(torch.autograd.Function):
    """iLQR with the KKT backward (use `ilqr_solve`); the unconverged pass no gradient (§3.1)."""

    @staticmethod
    def forward(fctx, cost_fn, dynamics, settings, exact, s_init, u_init, *params):
        refine = settings.pop("refine", 100)  # active_set's iterations where iLQR has not converged
        with torch.no_grad():
            s, u, info = ilqr(cost_fn, dynamics, s_init, u_init, params, **settings)
            a = (settings["lo"], settings["hi"], info, settings.get("tol", 0.05), refine)
            s, u, info = active_set(cost_fn, dynamics, s, u, params, *a)
        fctx.fns = (cost_fn, dynamics, exact)
        lo, hi = settings["lo"].expand_as(u), settings["hi"].expand_as(u)
        fctx.save_for_backward(s, u, info.converged, lo, hi, *params)
        fctx.mark_non_differentiable(info.converged)
        return s, u, info.converged

    @staticmethod
    def backward(fctx, grad_s, grad_u, _):
        cost_fn, dynamics, exact = fctx.fns
        s, u, converged, lo, hi, *params = fctx.saved_tensors
        # held fixed: the controls at a bound, where clamp() put them exactly (1e-8: rounding)
        free = ((u - lo).abs() > 1e-8) & ((hi - u).abs() > 1e-8)
        keep = converged.to(s.dtype)[:, None, None]  # the unconverged pass no gradient
        grads_in = (grad_s * keep, grad_u * keep)
        lam0, grads = kkt_backward(cost_fn, dynamics, s, u, params, free, *grads_in, exact)
        return (None, None, None, None, lam0, None, *grads)


def ilqr_solve(cost_fn, dynamics, s_init, u_init, params, lo, hi, exact=True, **settings):
    """The differentiable controller, eq. (4): s (B, T+1, n), u (B, T, m), converged (B,), where not
    a zero gradient (no solution to differentiate); settings `ilqr`'s, refine active_set's (100)."""
    settings["lo"] = torch.as_tensor(lo, dtype=s_init.dtype, device=s_init.device)
    settings["hi"] = torch.as_tensor(hi, dtype=s_init.dtype, device=s_init.device)
    return ILQR.apply(cost_fn, dynamics, settings, exact, s_init, u_init, *params)


# ===== 6. Predictor, eq. (1): a Trajectron++-style CVAE over controls (§3.1, Salzmann et al.) ====
# From 4 s of history of the predicted vehicle and its neighbours (the others and the ego), K = 25
# futures, one per value of a discrete latent z: p(s_gt | c) = sum_k p(z=k | c) p(s_gt | c, z=k).
# For each k a GRU emits per step a bivariate Gaussian over the controls u = (omega, a); the mean
# controls are integrated by the planner's unicycle and the control covariances pushed through its
# Jacobians (EKF): a K-component GMM over positions per step. Training maximises Trajectron++'s
# InfoVAE objective, q(z | c, s_gt) from a bidirectional LSTM over the true future; all K values of
# z are enumerated, none sampled. The GRU's next input is the reparameterised sample of u_t in
# training (Trajectron++), the mean at evaluation; the modes are the integrated mean controls,
# weighted by q(z|c,s_gt) in training (the authors' code), p(z|c) at evaluation. Where this differs
# from Trajectron++ (no map, no ego-future conditioning, ...): docs/method.md.

# ---- 6.1 Inputs: the 8-D state history, by backward differences ------------------------------


def backward_diff(track: torch.Tensor, first: torch.Tensor, dt: float) -> torch.Tensor:
    """rate_t = (track_t - track_{t-1}) / dt for a track (..., H, D); steps t <= first (...,) (the
    first observed step) copy rate_{first+1}. Backward, never central: a central difference at t0
    would read track_{t1}, the future."""
    H = track.shape[-2]
    diff = (track[..., 1:, :] - track[..., :-1, :]) / dt  # (..., H-1, D)
    rate = torch.cat([torch.zeros_like(track[..., :1, :]), diff], -2)  # (..., H, D)
    idx = (first + 1).clamp(max=H - 1)[..., None, None]  # (..., 1, 1)
    rate_first = torch.take_along_dim(rate, idx, dim=-2)  # (..., 1, D)
    t = torch.arange(H, device=track.device)
    return torch.where((t <= first[..., None])[..., None], rate_first, rate)  # (..., H, D)


def state_features(hist, origin, first, cfg: Config) -> torch.Tensor:
    """Trajectron++'s 8-D state (position - origin, velocity, acceleration, heading, heading rate),
    scaled by 30 m, 15 m/s, 4 m/s^2, pi, from (x, y, h, v) tracks: hist (..., H, 4), origin
    (..., 2), first (...,) the first observed step -> (..., H, 8)."""
    sp, sv, sa, sh = cfg.pred_scales
    pos = hist[..., :2]  # (..., H, 2)
    vel = backward_diff(pos, first, cfg.dt)  # (..., H, 2)
    # the velocity's first difference is at first + 1
    acc = backward_diff(vel, (first + 1).clamp(max=hist.shape[-2] - 1), cfg.dt)  # (..., H, 2)
    dh = wrap_angle(hist[..., 1:, 2] - hist[..., :-1, 2])  # (..., H-1)
    h_unwrapped = torch.cat([hist[..., :1, 2], hist[..., :1, 2] + dh.cumsum(-1)], -1)  # (..., H)
    h_rate = backward_diff(h_unwrapped[..., None], first, cfg.dt)  # (..., H, 1)
    heading = wrap_angle(hist[..., 2:3])  # (..., H, 1)
    rel = pos - origin[..., None, :]
    return torch.cat([rel / sp, vel / sv, acc / sa, heading / sh, h_rate / sh], -1)  # (..., H, 8)


# ---- 6.2 The model ----------------------------------------------------------------------------


@dataclass
class Prediction:
    """What the predictor hands to the planner, its loss and metrics; differentiable in theta."""

    s0: torch.Tensor  # (B, 4) the agent's state at t0, the modes' start (Predictor.initial_state)
    states: torch.Tensor  # (B, K, T, 4) mode trajectories t1..T: mean controls integrated
    controls: torch.Tensor  # (B, K, T, 2) mean controls (yaw rate, acceleration) of each mode
    pos_cov: torch.Tensor  # (B, K, T, 2, 2) position covariance of each GMM component
    log_p: torch.Tensor  # (B, K) log p(z|c) (logits clipped when a training step is given)
    log_q: torch.Tensor | None  # (B, K) log q(z|c,s_gt), or None when the future was not used
    probs: torch.Tensor  # (B, K) the mode weights: q(z|c,s_gt) with use_posterior, else p(z|c)

    @property
    def means(self) -> torch.Tensor:
        """(B, K, T, 2) the GMM components' means: the modes' positions."""
        return self.states[..., :2]


# The decoder's correlation rho = tanh(.) is kept this far inside (-1, 1), as Trajectron++: at
# |rho| = 1 the covariance is singular and the training sample's sqrt(1 - rho^2) has an infinite
# derivative (NaN gradients).
RHO_MARGIN = 1e-5


def bounded_correlation(pre_tanh: torch.Tensor) -> torch.Tensor:
    """tanh clamped to 1 - RHO_MARGIN, which float32 reaches at |pre_tanh| ~ 9; inside, the clamp
    is the identity."""
    return torch.tanh(pre_tanh).clamp(-1 + RHO_MARGIN, 1 - RHO_MARGIN)


def clip_logits(logits: torch.Tensor, step: int | None, cfg: Config) -> torch.Tensor:
    """Trajectron++'s z-logit clipping, in training only: zero-mean logits clamped to +-lc(step)."""
    if step is None:
        return logits
    lc0, lc1, centre, width = cfg.pred_logit_clip
    lc = lc0 + (lc1 - lc0) / (1 + math.exp(-(step - centre) / width))
    return (logits - logits.mean(-1, keepdim=True)).clamp(-lc, lc)


def control_sample(out: torch.Tensor, eps: torch.Tensor) -> torch.Tensor:
    """The reparameterised sample u = mu + L eps of the decoder's Gaussian over controls, out
    (..., 5) = (mu_om, mu_a, log sd_om, log sd_a, rho before tanh), eps (..., 2) standard normal,
    with L = [[sd_om, 0], [rho sd_a, sd_a sqrt(1 - rho^2)]] the Cholesky factor of Sigma_u."""
    mu = out[..., :2]
    sd_om, sd_a = out[..., 2].exp(), out[..., 3].exp()
    rho = bounded_correlation(out[..., 4])  # inside (-1, 1): the sqrt below stays finite
    e1, e2 = eps.unbind(-1)
    return mu + torch.stack([sd_om * e1, sd_a * (rho * e1 + torch.sqrt(1 - rho**2) * e2)], -1)


def control_covariance(out: torch.Tensor) -> torch.Tensor:
    """Sigma_u = [[sd_om^2, rho sd_om sd_a], [rho sd_om sd_a, sd_a^2]] (..., 2, 2) of the decoder's
    output out (..., 5); the same rho as the sample's."""
    sd_om, sd_a = out[..., 2].exp(), out[..., 3].exp()
    off = bounded_correlation(out[..., 4]) * sd_om * sd_a  # the off-diagonal
    return torch.stack([torch.stack([sd_om**2, off], -1), torch.stack([off, sd_a**2], -1)], -2)


class Predictor(nn.Module):
    """Trajectron++-style CVAE over unicycle controls: pred = predictor(batch, use_posterior)."""

    def __init__(self, cfg: Config):
        super().__init__()
        self.cfg = cfg
        K = cfg.pred_modes
        E = cfg.pred_enc_hidden  # the encoders' width
        Hz = cfg.pred_latent_hidden  # the latent MLPs' width
        Hd = cfg.pred_dec_hidden  # the decoder's width
        Dc = 2 * E  # the condition c = (history encoding, neighbour context)
        n_hist = cfg.hist_len + 1  # steps of history
        self.hist_lstm = nn.LSTMCell(8, E)
        self.nbr_mlp = nn.Sequential(nn.Linear(n_hist * 8 + 2, E), nn.ReLU(), nn.Linear(E, E))
        self.att_q = nn.Linear(E, E, bias=False)
        self.att_k = nn.Linear(E, E, bias=False)
        self.fut_lstm = nn.LSTM(8, E, batch_first=True, bidirectional=True)
        self.p_z = nn.Sequential(nn.Linear(Dc, Hz), nn.ReLU(), nn.Linear(Hz, K))
        self.q_z = nn.Sequential(nn.Linear(Dc + 2 * E, Hz), nn.ReLU(), nn.Linear(Hz, K))
        # the decoder GRU (see decode): h_0 = dec_h0([z; c]), input [z; c; u_prev]
        self.dec_h0 = nn.Linear(K + Dc, Hd)
        self.dec_u0 = nn.Linear(8, 2)  # u_prev at t0 from the current state (Trajectron++'s)
        self.dec_in = nn.Linear(K + Dc + 2, 3 * Hd)  # W_i, b_i: the gates' rows r, z, n
        self.dec_hh = nn.Linear(Hd, 3 * Hd)  # W_h, b_h
        self.dec_out = nn.Linear(Hd, 5)
        self.heading_fix = nn.Linear(Dc + 1, 1)  # Trajectron++'s Unicycle p0_model (initial_state)

    def encode(self, batch) -> tuple[torch.Tensor, torch.Tensor]:
        """The condition c (B, 2E) = (history LSTM state, attention over neighbours), and the
        agent's features (B, H, 8)."""
        cfg = self.cfg
        hist, mask = batch.agent_hist, batch.agent_hist_mask  # (B, H, 4), (B, H)
        B, H = mask.shape
        first = (~mask).sum(-1)  # (B,) the first observed step (missing steps are a prefix)
        origin = hist[:, -1, :2]  # (B, 2) the agent's current position
        f = state_features(hist, origin, first, cfg)  # (B, H, 8)
        # history LSTM over the 9 steps; an unobserved step leaves its state untouched
        h = c = f.new_zeros(B, cfg.pred_enc_hidden)  # (B, E)
        for t in range(H):
            h_t, c_t = self.hist_lstm(f[:, t], (h, c))
            seen = mask[:, t, None]  # (B, 1)
            h = torch.where(seen, h_t, h)
            c = torch.where(seen, c_t, c)
        # neighbours = other agents + the ego, with (is pedestrian, is ego) flags
        nbr = torch.cat([batch.others_hist, batch.ego_hist[:, None]], 1)  # (B, A+1, H, 4)
        nbr_valid = torch.cat([batch.others_mask, mask.new_ones(B, 1)], 1)  # (B, A+1)
        is_ped = torch.cat([batch.others_is_ped, mask.new_zeros(B, 1)], 1)  # (B, A+1)
        is_ego = torch.cat([torch.zeros_like(batch.others_mask), mask.new_ones(B, 1)], 1)
        distance = (nbr[:, :, -1, :2] - origin[:, None]).norm(dim=-1)  # (B, A+1)
        near = nbr_valid & (distance < cfg.pred_radius)  # (B, A+1)
        all_observed = torch.zeros_like(near, dtype=torch.long)  # first observed step: 0
        nbr_origin = origin[:, None].expand(-1, nbr.shape[1], -1)  # (B, A+1, 2)
        nf = state_features(nbr, nbr_origin, all_observed, cfg)  # (B, A+1, H, 8)
        flags = torch.stack([is_ped, is_ego], -1).to(f.dtype)  # (B, A+1, 2)
        e = self.nbr_mlp(torch.cat([nf.flatten(-2), flags], -1))  # (B, A+1, E)
        # masked dot-product attention, query = the agent's history encoding
        scores = (self.att_k(e) @ self.att_q(h)[:, :, None])[..., 0] / math.sqrt(e.shape[-1])
        att_w = torch.softmax(scores.masked_fill(~near, -1e9), -1) * near  # all masked: all 0
        att = (att_w[..., None] * e).sum(1)  # (B, E); zero for an agent without neighbours
        return torch.cat([h, att], -1), f  # (B, 2E), (B, H, 8)

    def encode_future(self, batch, c: torch.Tensor) -> torch.Tensor:
        """The q(z|c,s_gt) logits (B, K): a bidirectional LSTM over the GT future's 8-D states."""
        cur_fut = torch.cat([batch.agent_hist[:, -1:], batch.agent_fut], 1)  # (B, 1+T, 4)
        zero = torch.zeros(len(cur_fut), dtype=torch.long, device=cur_fut.device)
        fy = state_features(cur_fut, batch.agent_hist[:, -1, :2], zero, self.cfg)[:, 1:]
        _, (h_n, _) = self.fut_lstm(fy)  # h_n (2, B, E): the last state of each direction
        y_enc = torch.cat([h_n[0], h_n[1]], -1)  # (B, 2E)
        return self.q_z(torch.cat([c, y_enc], -1))  # (B, K)

    def decode(self, c: torch.Tensor, f0: torch.Tensor, noise=None):
        """Per mode k and step t a Gaussian over controls: means (B, K, T, 2), covariances
        (B, K, T, 2, 2). A GRU (Cho et al. 2014) over the steps, all K values of z at once as B*K
        rows, with input i = [one_hot(z); c; u_prev] and h_0 = W_0 [one_hot(z); c] + b_0:
            r  = sigmoid(W_ir i + b_ir + W_hr h + b_hr)
            g  = sigmoid(W_ig i + b_ig + W_hg h + b_hg)   (Cho's update gate z: z is the latent)
            n  = tanh(W_in i + b_in + r * (W_hn h + b_hn))
            h' = (1 - g) * n + g * h
        noise: the training sample's standard normal draws, a tensor (T, B, K, 2), or a
        torch.Generator to draw them from (None: torch's)."""
        K, T, Hd = self.cfg.pred_modes, self.cfg.horizon, self.cfg.pred_dec_hidden
        B, Dc = c.shape
        # the input's constant part: W_i [one_hot(k); c] + b_i = W_ik[:, k] + W_ic c + b_i, per gate
        W_ik, W_ic, W_iu = self.dec_in.weight.split([K, Dc, 2], 1)  # (3Hd, K), (3Hd, X), (3Hd, 2)
        zc = ((c @ W_ic.T + self.dec_in.bias)[:, None] + W_ik.T).reshape(B * K, 3 * Hd)
        zc_r, zc_g, zc_n = zc.chunk(3, 1)  # (B*K, Hd) each
        W_ur, W_ug, W_un = W_iu.chunk(3, 0)  # (Hd, 2) each: the input's u_prev part
        W_hr, W_hg, W_hn = self.dec_hh.weight.chunk(3, 0)  # (Hd, Hd) each
        b_hr, b_hg, b_hn = self.dec_hh.bias.chunk(3)  # (Hd,) each
        W_0k, W_0c = self.dec_h0.weight.split([K, Dc], 1)  # (Hd, K), (Hd, X)
        h = ((c @ W_0c.T + self.dec_h0.bias)[:, None] + W_0k.T).reshape(B * K, Hd)  # h_0
        u_prev = self.dec_u0(f0).repeat_interleave(K, 0)  # (B*K, 2)
        outs = []
        for t in range(T):
            # W_h h + b_h, gate by gate (as nn.Linear computes it: addmm)
            r = torch.sigmoid(zc_r + u_prev @ W_ur.T + torch.addmm(b_hr, h, W_hr.T))  # (B*K, Hd)
            g = torch.sigmoid(zc_g + u_prev @ W_ug.T + torch.addmm(b_hg, h, W_hg.T))  # (B*K, Hd)
            n = torch.tanh(zc_n + u_prev @ W_un.T + r * torch.addmm(b_hn, h, W_hn.T))  # (B*K, Hd)
            h = torch.lerp(n, h, g)  # (B*K, Hd)  = (1 - g) * n + g * h
            out = self.dec_out(h)  # (B*K, 5) = (mu_om, mu_a, log sd_om, log sd_a, rho before tanh)
            outs.append(out)
            if self.training:  # the sample of u_t is the next input (Trajectron++)
                u_prev = control_sample(out, self._noise(noise, t, out))
            else:
                u_prev = out[:, :2]
        out = torch.stack(outs, 1).reshape(B, K, T, 5)
        return out[..., :2], control_covariance(out)

    @staticmethod
    def _noise(noise, t: int, out: torch.Tensor) -> torch.Tensor:
        """Step t's standard normal draws (B*K, 2): from the tensor noise (T, B, K, 2), or drawn
        from the generator noise (None: torch's)."""
        if torch.is_tensor(noise):
            return noise[t].reshape(-1, 2)
        return torch.randn(out.shape[0], 2, generator=noise, dtype=out.dtype, device=out.device)

    def initial_state(self, batch, c: torch.Tensor) -> torch.Tensor:
        """s0 = (x0, y0, heading, v0) (B, 4): heading = velocity direction + a learned correction
        in (-1, 1) rad; the tracked speed."""
        hist = batch.agent_hist  # (B, H, 4)
        vel = (hist[:, -1, :2] - hist[:, -2, :2]) / self.cfg.dt  # (B, 2) backward difference
        moving = vel.norm(dim=-1) > self.cfg.pred_min_speed  # (B,)
        phi = torch.where(moving, torch.atan2(vel[:, 1], vel[:, 0]), hist[:, -1, 2])  # (B,)
        phi = phi + torch.tanh(self.heading_fix(torch.cat([c, phi[:, None]], -1)))[:, 0]  # (B,)
        return torch.stack([hist[:, -1, 0], hist[:, -1, 1], phi, hist[:, -1, 3]], -1)  # (B, 4)

    def forward(self, batch, use_posterior: bool, step: int | None = None, noise=None):
        """K mode trajectories, their probabilities and the position GMM, as Prediction.
        use_posterior: weigh the modes by q(z|c,s_gt) (needs batch.agent_fut) instead of p(z|c).
        step: the training iteration, for clip_logits. noise: see decode."""
        cfg = self.cfg
        c, f = self.encode(batch)  # (B, 2E), (B, H, 8)
        log_p = torch.log_softmax(clip_logits(self.p_z(c), step, cfg), -1)  # (B, K)
        log_q = None
        if use_posterior:
            log_q = torch.log_softmax(clip_logits(self.encode_future(batch, c), step, cfg), -1)
        s0 = self.initial_state(batch, c)  # (B, 4)
        mu, cov_u = self.decode(c, f[:, -1], noise)  # (B, K, T, 2), (B, K, T, 2, 2)
        s0_modes = s0[:, None].expand(-1, cfg.pred_modes, -1)  # (B, K, 4)
        traj, pos_cov = integrate_modes(s0_modes, mu, cov_u, cfg)  # (B, K, T+1, 4), (B, K, T, 2, 2)
        probs = (log_q if use_posterior else log_p).exp()  # (B, K)
        return Prediction(s0, traj[:, :, 1:], mu, pos_cov, log_p, log_q, probs)


def integrate_modes(s0, u, cov_u, cfg: Config):
    """unicycle_rollout(s0, u) and the EKF's position covariances along it: s0 (..., 4),
    u (..., T, 2), cov_u (..., T, 2, 2) -> states (..., T+1, 4), covariances (..., T, 2, 2) (plus
    pred_pos_std_min^2 I). The covariance is the EKF's recursion, Sigma_0 = 0 and
        Sigma_{t+1} = f_s Sigma_t f_s' + f_u Sigma_u,t f_u',   f_s = df/ds, f_u = df/du at the mean,
    in 2x2 blocks: f_s = [[I, Mq], [0, I]], f_u = [[Mu], [dt I]] (the controls move q = (h, v)), so
    with Sigma = [[Spp, Spq], [Spq', Sqq]] (subscript p: the position) each step updates (<-: the
    next value)
        Spp <- Spp + Mq Spq' + Spq Mq' + Mq Sqq Mq' + Mu Su Mu'
        Spq <- Spq + Mq Sqq + dt Mu Su
        Sqq <- Sqq + dt^2 Su"""
    dt = cfg.dt
    omega, a = u.unbind(-1)  # (..., T) each
    h = torch.cat([s0[..., 2:3], s0[..., 2:3] + (omega * dt).cumsum(-1)], -1)  # (..., T+1)
    v = torch.cat([s0[..., 3:4], s0[..., 3:4] + (a * dt).cumsum(-1)], -1)  # (..., T+1)
    # the displacements dx, dy (..., T) and the Jacobians' blocks Mq, Mu (..., T, 2, 2)
    dx, dy, Mq, Mu = _position_jacobians(h[..., :-1], v[..., :-1], omega, a, dt)
    x = torch.cat([s0[..., 0:1], s0[..., 0:1] + dx.cumsum(-1)], -1)  # (..., T+1)
    y = torch.cat([s0[..., 1:2], s0[..., 1:2] + dy.cumsum(-1)], -1)  # (..., T+1)
    # B Su B' of every step at once (it does not depend on Sigma): Mu Su Mu' and dt Mu Su
    MuSuMu = Mu @ cov_u @ Mu.mT  # (..., T, 2, 2)
    MuSu = dt * Mu @ cov_u  # (..., T, 2, 2)
    Spp = Spq = Sqq = torch.zeros_like(Mq[..., 0, :, :])  # (..., 2, 2) Sigma_0 = 0
    pos_cov = []
    for t in range(u.shape[-2]):
        Mq_t = Mq[..., t, :, :]  # (..., 2, 2)
        MqSqq = Mq_t @ Sqq
        MqSpq = Mq_t @ Spq.mT
        Spp = Spp + MqSpq + MqSpq.mT + MqSqq @ Mq_t.mT + MuSuMu[..., t, :, :]
        Spq = Spq + MqSqq + MuSu[..., t, :, :]
        Sqq = Sqq + dt**2 * cov_u[..., t, :, :]
        pos_cov.append(Spp)
    floor = cfg.pred_pos_std_min**2 * torch.eye(2, dtype=Mq.dtype, device=Mq.device)
    return torch.stack([x, y, h, v], -1), torch.stack(pos_cov, -3) + floor


# ---- 6.3 Loss: Trajectron++'s InfoVAE objective -----------------------------------------------


def gaussian2_log_prob(pt, mean, cov, min_var: float = 0.0) -> torch.Tensor:
    """log N(pt; mean, cov) of 2-D Gaussians: pt, mean (..., 2), cov (..., 2, 2) -> (...); cov is
    known to be positive semi-definite plus min_var I."""
    ex, ey = (pt - mean).unbind(-1)  # (...) each: e = pt - mean
    vxx, vxy, vyy = cov[..., 0, 0], cov[..., 0, 1], cov[..., 1, 1]
    # det(P0 + eps I) = det P0 + eps tr P0 + eps^2 >= eps tr - eps^2 (eps = min_var): for a long
    # thin ellipse vxx vyy - vxy^2 cancels to 0 or below in float32 (NaN log); the bound restores it
    det = torch.maximum(vxx * vyy - vxy * vxy, min_var * (vxx + vyy) - min_var**2)  # (...)
    # e' Sigma^-1 e with Sigma^-1 = [[vyy, -vxy], [-vxy, vxx]] / det
    maha = (vyy * ex**2 - 2 * vxy * ex * ey + vxx * ey**2) / det
    return -0.5 * maha - 0.5 * torch.log(det) - math.log(2 * math.pi)


def gmm_log_prob(pred: Prediction, pos, log_w, min_var: float = 0.0) -> torch.Tensor:
    """log sum_k w_k N(pos_t; mu_kt, Sigma_kt) per step: pos (B, T, 2), log_w (B, K) -> (B, T)."""
    log_n = gaussian2_log_prob(pos[:, None], pred.means, pred.pos_cov, min_var)  # (B, K, T)
    return torch.logsumexp(log_w[..., None] + log_n, 1)  # (B, T)


def batch_average(v: torch.Tensor) -> torch.Tensor:
    """v (B, ...) -> (...): the mean over the batch (pred_loss's default batch_mean)."""
    return v.mean(0)


def pred_loss(pred: Prediction, batch, step: int, cfg: Config, batch_mean=batch_average):
    """L_pred per scenario (B,) (its mean is Trajectron++'s loss), and its parts (floats):
        L = -(LL - b KL + I_p)   (InfoVAE variant, Zhao et al. 2019, as in Trajectron++)
        LL   = sum_t min(log sum_k q_k N(pos_gt,t; mu_kt, Sigma_kt), 6)
        KL   = max(mean_batch KL(q || p), 0.07)   free bits: below 0.07 the term is a constant
        I_p  = H(mean_batch p) - mean_batch H(p)   mutual information of z and c under p
    Beside the ELBO, log p(s_gt|c) >= E_q[log p(s_gt|c,z)] - KL(q || p): LL takes the log of the
    q-weighted mixture instead (>= the ELBO's first term, by Jensen) and clamps each step's (no
    reward past a near-exact fit), KL is weighted by b, annealed from 0 (the decoder learns first),
    with free bits, and I_p (InfoVAE) keeps p(z|c) from collapsing onto one mode. batch_mean: the
    batch's mean (B, ...) -> (...); under DDP the global batch's (train.py passes one)."""
    if pred.log_q is None:
        raise ValueError("pred: pred_loss needs the posterior (the predictor's use_posterior=True)")
    pos_gt = batch.agent_fut[..., :2]  # (B, T, 2)
    log_p_y = gmm_log_prob(pred, pos_gt, pred.log_q, cfg.pred_pos_std_min**2)  # (B, T)
    ll = log_p_y.clamp(max=cfg.pred_log_p_max).sum(-1)  # (B,)
    q = pred.log_q.exp()  # (B, K)
    kl = (q * (pred.log_q - pred.log_p)).sum(-1)  # (B,)
    kl_fb = torch.where(batch_mean(kl) > cfg.pred_kl_min, kl, torch.full_like(kl, cfg.pred_kl_min))
    p = pred.log_p.exp()  # (B, K)
    p_bar = batch_mean(p)  # (K,)
    mi = -(p_bar * torch.log(p_bar)).sum() + batch_mean((p * pred.log_p).sum(-1))  # scalar
    b0, centre, width = cfg.pred_beta
    kl_w = b0 / (1 + math.exp(-(step - centre) / width))  # b0 sigmoid((step - b1) / b2)
    loss = -(ll - kl_w * kl_fb + mi)  # (B,)
    parts = {name: v.mean().item() for name, v in dict(loss=loss, ll=ll, kl=kl, mi=mi).items()}
    return loss, {**parts, "beta": kl_w}


# ===== 7. The stack: predict -> plan -> control, §3.2 ============================================
#   L = a1 L_pred + a2 L_plan + a3 L_ctr (stack_loss; a_i the paper's alpha_i, Config.alpha_rl/il)
#   RL: L_ctr = C_H(s_ctr, u_ctr), the hindsight cost (eq. 3, GT futures), target n* = argmin C_H
#   IL: L_ctr = sum_t ||s_ctr,t - s_gt,t||^2, target n* = the candidate closest to the GT
# It reads a `batch` (data_synth.Scenarios) of B scenarios: the (x, y, h, v) tracks ego_hist,
# agent_hist (B, H, 4), others_hist (B, A, H, 4), the futures ego_fut, agent_fut (B, T, 4),
# others_fut (B, A, T, 4), masks, lanes (B, L, P, 3), the goal (B, 4); and a `method` (train.Method,
# a row of Table 1): its `predictor` ('learned', 'gt': the GT future, 'none'), `train_plan_weights`.

SETTINGS = ("rl", "il")  # the planner target and L_ctr: hindsight cost (RL) or imitation (IL)


@dataclass
class StackOutput:
    """Per-scenario results of one pass through the stack (all (B,) unless noted)."""

    l_pred: torch.Tensor  # InfoVAE loss (0 without a learned predictor)
    l_plan: torch.Tensor  # cross-entropy of the relaxed planner with the target candidate
    l_ctr: torch.Tensor  # RL: hindsight cost of the controller's trajectory; IL: its error to GT
    hindsight: torch.Tensor  # hindsight cost of the final trajectory
    mse: torch.Tensor  # sum_t ||s_t - s_gt,t||^2 of the final trajectory
    plannable: torch.Tensor  # bool: at least 2 planner candidates
    converged: torch.Tensor  # bool: iLQR converged
    s: torch.Tensor  # (B, T+1, 4) the final ego trajectory
    u: torch.Tensor  # (B, T, 2) its controls
    cands: Candidates | None = None
    cand_cost: torch.Tensor | None = None  # (B, N)
    pred: object = None  # the predictor's output


# ---- 7.1 The planner's clock: the paper's is the prediction step dt; the ablation's finer -------
# The dt = 0.1 s ablation (plan_dt) plans and controls `substeps` times per prediction step: the
# futures interpolated (upsample), the horizon in fine steps (planner_config), the per-step terms of
# eq. (3) divided by substeps (clock_weights). With substeps = 1, the paper's, each is the identity.


def upsample(now: torch.Tensor, fut: torch.Tensor, substeps: int) -> torch.Tensor:
    """A future on a clock `substeps` times finer, by linear interpolation from the present:
    now (..., D) at t0, fut (..., T, D) at t1..T -> (..., T * substeps, D)."""
    if substeps == 1:
        return fut
    knots = torch.cat([now[..., None, :], fut], -2)  # (..., T+1, D)
    a, b = knots[..., :-1, None, :], knots[..., 1:, None, :]  # (..., T, 1, D)
    steps = torch.arange(1, substeps + 1, dtype=fut.dtype, device=fut.device)
    f = steps[:, None] / substeps  # (substeps, 1) the fractions of a step
    return (a + (b - a) * f).flatten(-3, -2)


def planner_substeps(cfg: Config, plan_dt) -> int:
    """Planner/controller steps of plan_dt per prediction step cfg.dt (1 for plan_dt None)."""
    if plan_dt is None:
        return 1
    substeps = round(cfg.dt / plan_dt) if plan_dt > 0 else 0
    if substeps < 1 or abs(substeps * plan_dt - cfg.dt) > 1e-9:
        raise ValueError(f"plan_dt: must divide dt = {cfg.dt} s into whole steps, got {plan_dt}")
    return substeps


def planner_config(cfg: Config, substeps: int) -> Config:
    """cfg on the planner's and the controller's clock: substeps per prediction step."""
    return dataclasses.replace(cfg, dt=cfg.dt / substeps, horizon=cfg.horizon * substeps)


def clock_weights(cfg: Config, w, substeps: int, like: dict):
    """The weights (5,) of eq. (3) on the planner's clock: the hand-tuned ones and w (or those)."""
    per_step = torch.tensor([1 / substeps, 1, 1 / substeps, 1 / substeps, 1 / substeps], **like)
    w_fixed = cost_weights(cfg, **like) * per_step
    return w_fixed, w_fixed if w is None else w * per_step


# ---- 7.2 The three stages and their losses -----------------------------------------------------


def cost_contexts(batch, preds, probs, pred_mask, plan_others=True, substeps=1, goal=None):
    """The cost's view of a batch with the given predictions (already on the planner's clock,
    substeps per step), and in hindsight (the agent's GT future). plan_others=False: the others
    count in hindsight only (App. D.3)."""
    others_mask = batch.others_mask.to(preds.dtype)
    others_now = batch.others_hist[:, :, -1, :2]  # (B, A, 2)
    others = upsample(others_now, batch.others_fut[..., :2], substeps)  # (B, A, T, 2)
    goal = batch.goal if goal is None else goal
    common = dict(others=others, goal=goal[:, :2], lanes=batch.lanes, lanes_mask=batch.lanes_mask)
    ctx = CostContext(preds, probs, pred_mask, others_mask=others_mask * plan_others, **common)
    ones = torch.ones_like(pred_mask)
    agent = upsample(batch.agent_hist[:, -1, :2], batch.agent_fut[..., :2], substeps)  # (B, T, 2)
    hctx = CostContext(agent[:, None], ones[:, None], ones, others_mask=others_mask, **common)
    return ctx, hctx


def route_goal(s0, lanes, lanes_mask, cfg: Config) -> torch.Tensor:
    """The 'route' goal (Config.goal), which unlike the logged one holds no reaction of the driver
    to the others: where the ego reaches at T keeping its speed along its lane (the nearest heading
    its way, within 40 degrees). (B, 4)."""
    B = s0.shape[0]
    cum = _lane_arclength(lanes, lanes_mask)  # (B, L, P)
    d2, arc_on, h_lane = _project_each_lane(s0[:, :2], lanes, lanes_mask, cum)  # (B, L) each
    # 40 degrees: a lane through a bend is still the ego's, a crossing one (~90) is not
    heading_ok = wrap_angle(h_lane - s0[:, 2:3]).abs() < math.radians(40)
    lane = torch.where(heading_ok, d2, math.inf).argmin(-1)  # (B,) the nearest such lane
    rows = torch.arange(B, device=s0.device)
    distance = s0[:, 3] * cfg.horizon * cfg.dt  # (B,) at its speed until T
    ahead = arc_on[rows, lane] + distance  # (B,) arc length at T
    p = _point_at_arclength(lanes[rows, lane, None], cum[rows, lane, None], ahead[:, None, None])
    route = torch.cat([p[:, 0, 0], s0[:, 3:4]], -1)  # (B, 4): x, y, lane heading, speed
    # no lane heading the ego's way (real data can lack one): straight ahead at its speed
    direction = _heading_vector(s0[:, 2])  # (B, 2)
    straight = torch.cat([s0[:, :2] + direction * distance[:, None], s0[:, 2:]], -1)
    return torch.where(heading_ok.any(-1, keepdim=True), route, straight)


@dataclass
class ScenePlan:
    """What the planner computes from the scene alone: the goal g, the candidates and every term of
    eq. (3) but C_coll for each. A prediction reaches the plan through C_coll only, so training
    computes these once."""

    goal: torch.Tensor  # (B, 4)       the goal state
    cands: Candidates
    terms: torch.Tensor  # (B, N, 4)   (C_goal, C_lat, C_head, C_u) per candidate, unweighted

    def __getitem__(self, rows):
        """The scenarios `rows` (a slice or an index tensor), as a Scenarios batch is indexed."""
        cands = Candidates(self.cands.s[rows], self.cands.u[rows], self.cands.valid[rows])
        return ScenePlan(self.goal[rows], cands, self.terms[rows])


def scene_plan(batch, cfg: Config, plan_dt=None) -> ScenePlan:
    """A batch's ScenePlan on the planner's clock: the goal (Config.goal), the candidates, their
    prediction-free terms."""
    sub = planner_substeps(cfg, plan_dt)
    s0 = batch.ego_hist[:, -1]  # (B, 4)
    route = cfg.goal == "route"
    goal = route_goal(s0, batch.lanes, batch.lanes_mask, cfg) if route else batch.goal
    pcfg = planner_config(cfg, sub)
    cands = plan_candidates(s0, goal, batch.lanes, batch.lanes_mask, pcfg)
    pos, head = cands.s[..., 1:, :2], cands.s[..., 1:, 2]
    terms = scene_terms(pos, head, cands.u, goal[:, :2], batch.lanes, batch.lanes_mask)
    return ScenePlan(goal, cands, terms)


def predict(batch, model, method, cfg: Config, train=False, step=None, substeps=1, **options):
    """The stack's first stage, eq. (1): what the planner sees of the predicted agent, on the
    planner's clock: the modes' positions (B, K, T, 2), their weights (B, K) and whether the agent
    counts (B,); and the predictor's output and its loss L_pred (B,) (0 unless learned and
    training). options: pred_target, noise, batch_mean (run_stack's)."""
    B, T = len(batch), cfg.horizon * substeps
    like = dict(dtype=batch.ego_hist.dtype, device=batch.ego_hist.device)
    pred, l_pred = None, torch.zeros(B, **like)
    now = batch.agent_hist[:, -1, :2]  # (B, 2)
    if method.predictor == "learned":
        pred = model(batch, use_posterior=train, step=step, noise=options.get("noise"))
        K = pred.probs.shape[1]
        preds = upsample(now[:, None].expand(B, K, 2), pred.states[..., :2], substeps).contiguous()
        probs = pred.probs  # (B, K) q(z|c,s_gt) in training, p(z|c) otherwise
        if train and (method.train_plan_weights or cfg.train_plan_weights) == "prior":
            # the planner sees what it will see at evaluation, and its losses reach p(z|c)
            probs = pred.log_p.exp()
        if train:
            target = batch
            if options.get("pred_target") is not None:
                target = dataclasses.replace(batch, agent_fut=options["pred_target"])
            l_pred, _ = pred_loss(pred, target, step, cfg, options.get("batch_mean", batch_average))
        return preds, probs, torch.ones(B, **like), pred, l_pred
    if method.predictor == "gt":
        preds = upsample(now, batch.agent_fut[..., :2], substeps)[:, None]  # (B, 1, T, 2)
        return preds, torch.ones(B, 1, **like), torch.ones(B, **like), pred, l_pred
    # no prediction: the agent does not count
    preds = torch.zeros(B, 1, T, 2, **like)
    return preds, torch.ones(B, 1, **like), torch.zeros(B, **like), pred, l_pred


def plan_with_target(batch, s0, ctx, hctx, scene, w, w_fixed, setting, cfg, substeps=1):
    """The stack's second stage, eq. (2): the plan, and L_plan (B,) against the planner's target
    n*: RL, the candidate cheapest in hindsight (the agent's GT future in the collision term, the
    other terms as planned); IL, the candidate closest to the GT ego trajectory."""
    plan_out = plan(s0, ctx, scene.goal, w, planner_config(cfg, substeps), scene)
    cands = plan_out.cands
    if setting == "rl":
        h_coll = collision_term(cands.s[..., 1:, :2], hctx, cfg.rbf_var)  # (B, N)
        h_terms = torch.cat([h_coll[..., None], plan_out.terms[..., 1:]], -1)  # (B, N, 5)
        target = masked_argmin((h_terms.detach() * w_fixed).sum(-1), cands.valid)
    else:
        gt_pos = upsample(s0[:, :2], batch.ego_fut[..., :2], substeps)  # (B, T, 2)
        error = ((cands.s[..., 1:, :2] - gt_pos[:, None]) ** 2).sum(-1).mean(-1)  # (B, N)
        target = masked_argmin(error, cands.valid)
    valid = cands.valid | ~plan_out.plannable[:, None]  # the softmax finite where nothing plans
    l_plan = plan_loss(plan_out.cost, valid, target, cfg.beta)
    return plan_out, torch.where(plan_out.plannable, l_plan, 0.0)


def control(s0, plan_out: Plan, ctx, w, cfg: Config, substeps=1, planner=True, controller=True):
    """The stack's third stage, eq. (4): iLQR from the plan (from zero controls without a
    planner), gradients by the KKT backward; without a controller the plan is final.
    -> s (B, T+1, 4), u (B, T, 2), converged (B,)."""
    B = len(s0)
    rows = torch.arange(B, device=s0.device)
    s_plan = plan_out.cands.s[rows, plan_out.best]  # (B, T+1, 4)
    u_plan = plan_out.cands.u[rows, plan_out.best]  # (B, T, 2)
    if not controller:
        return s_plan, u_plan, torch.ones(B, dtype=torch.bool, device=s0.device)
    u_init = u_plan if planner else torch.zeros_like(u_plan)
    params = (w.expand(B, -1), *ctx.tensors())  # every parameter per scenario
    cost = StackCost(cfg.rbf_var)
    dynamics = Unicycle(cfg.dt / substeps)
    settings = dict(iters=cfg.ilqr_iters, tol=cfg.ilqr_tol, refine=0)  # App. C.2: a fixed limit
    settings.update(ls_steps=cfg.line_search_steps, ls_decay=cfg.line_search_decay)
    return ilqr_solve(cost, dynamics, s0, u_init, params, cfg.u_lower, cfg.u_upper, **settings)


def run_stack(
    batch,
    model,
    method,
    cfg: Config,
    setting: str = "rl",
    step=None,
    train=False,
    w=None,
    planner=True,
    controller=True,
    plan_others=True,
    plan_dt=None,
    scene: ScenePlan | None = None,
    **pred_options,
) -> StackOutput:
    """One pass of the stack over a batch: predict, plan, control. setting: 'rl' or 'il' (L_ctr
    and the planner's target). train: the modes weighted by q(z|c,s_gt), the schedules at `step`
    (the authors' code); else p(z|c). w: the cost weights (5,), default the hand-tuned ones.
    Ablations: planner=False, iLQR from zero controls; controller=False, the plan is final;
    plan_others=False, planner and controller ignore the others; plan_dt, 7.1. scene: the batch's
    scene_plan, if computed. pred_options: pred_target (Table 2 shifts it), noise, batch_mean."""
    check_setting(setting)
    sub = planner_substeps(cfg, plan_dt)  # 1: the paper's clock
    like = dict(dtype=batch.ego_hist.dtype, device=batch.ego_hist.device)
    s0 = batch.ego_hist[:, -1]  # (B, 4)
    w_fixed, w = clock_weights(cfg, w, sub, like)  # (5,) the hand-tuned weights, those planned with
    # 1. predict, eq. (1)
    preds, probs, pred_mask, pred, l_pred = predict(
        batch, model, method, cfg, train, step, sub, **pred_options
    )
    # 2. plan, eq. (2): costs of all candidates with the predictions; the plan is their argmin
    scene = scene_plan(batch, cfg, plan_dt) if scene is None else scene
    ctx, hctx = cost_contexts(batch, preds, probs, pred_mask, plan_others, sub, scene.goal)
    plan_out, l_plan = plan_with_target(batch, s0, ctx, hctx, scene, w, w_fixed, setting, cfg, sub)
    # 3. control, eq. (4)
    s, u, converged = control(s0, plan_out, ctx, w, cfg, sub, planner, controller)
    hindsight = total_cost(s, u, hctx, w_fixed, cfg.rbf_var)  # (B,)
    mse = ((s[:, sub::sub, :2] - batch.ego_fut[..., :2]) ** 2).sum((-1, -2))  # at the logged steps
    l_ctr = hindsight if setting == "rl" else mse
    losses = dict(l_pred=l_pred, l_plan=l_plan, l_ctr=l_ctr)
    metrics = dict(hindsight=hindsight, mse=mse, plannable=plan_out.plannable, converged=converged)
    results = dict(s=s, u=u, cands=plan_out.cands, cand_cost=plan_out.cost, pred=pred)
    return StackOutput(**losses, **metrics, **results)


def stack_loss(out: StackOutput, alphas, pred_weights=1.0, count=None):
    """The training loss of §3.2, L = a1 L_pred + a2 L_plan + a3 L_ctr, and its terms, each a mean
    over the plannable scenarios (the others are flagged, not trained on): (L, (L_pred, L_plan,
    L_ctr)). alphas (a1, a2, a3): Config.alpha_rl or alpha_il switched by the method; pred_weights:
    L_pred's per-scenario weights (B,) (§4.1); count: what the sums divide by (default: this batch's
    plannable scenarios; under DDP train.py passes the global batch's over the ranks)."""
    keep = out.plannable.to(out.l_plan.dtype)  # (B,)
    count = keep.sum().clamp_min(1) if count is None else count
    per_scenario = (out.l_pred * pred_weights, out.l_plan, out.l_ctr)  # (B,) each
    terms = tuple((term * keep).sum() / count for term in per_scenario)
    return sum(a * term for a, term in zip(alphas, terms)), terms


# ===== 8. Config's checks: every field in its range, refused by name at construction =============
# The math does not check its input again: Config, the command lines and the loaders (train.py,
# data_synth.py, lab/nuscenes.py) do. Every number of Config has an inclusive range.
CONFIG_RANGES = {
    "dt": (1e-3, 10),
    **dict.fromkeys(["hist_len", "horizon"], (1, 100)),
    **dict.fromkeys([*[f"w_{name}" for name in COST_TERMS], "pred_kl_min"], (0, 1e6)),
    **dict.fromkeys(["rbf_var", "beta"], (1e-6, 1e6)),
    **dict.fromkeys(["goal_lane_dist", "feas_lat_accel", "feas_yaw_per_speed"], (1e-6, 1e4)),
    "pred_radius": (1e-6, 1e4),
    "goal_lane_heading": (1e-6, 7),
    "max_goal_lanes": (1, 64),
    "ilqr_iters": (1, 1000),
    **dict.fromkeys(["ilqr_tol", "pred_grad_clip"], (1e-12, 1e6)),
    "line_search_steps": (1, 60),
    "line_search_decay": (1.01, 1e6),
    "pred_modes": (1, 1024),
    **dict.fromkeys(["pred_enc_hidden", "pred_latent_hidden", "pred_dec_hidden"], (1, 4096)),
    **dict.fromkeys(["pred_min_speed", "pred_pos_std_min"], (0, 1e3)),
    **dict.fromkeys(["pred_log_p_max", "pred_nll_min"], (-1e6, 1e6)),
    "pred_lr_decay": (1e-9, 1),
    "lr": (1e-12, 1e3),
    "batch_size": (1, 100_000),
}
CONFIG_SIZES = dict(
    u_lower=2, u_upper=2, pred_scales=4, pred_beta=3, pred_logit_clip=4, alpha_rl=3, alpha_il=3
)
CONFIG_CHOICES = dict(train_plan_weights=("posterior", "prior"), goal=("logged", "route"))


def _finite(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _config_field_error(name: str, kind: str, v):
    """What is wrong with Config field `name` of type kind ('int', 'float', 'tuple', ...) holding
    v, or None."""
    if name in CONFIG_CHOICES:
        return v not in CONFIG_CHOICES[name] and f"one of {CONFIG_CHOICES[name]}"
    if kind == "tuple":
        n = CONFIG_SIZES.get(name)
        ok = isinstance(v, tuple) and v and len(v) == (n or len(v)) and all(map(_finite, v))
        return not ok and f"a tuple of {n or 'one or more'} finite numbers"
    lo, hi = CONFIG_RANGES[name]
    whole = kind == "int"
    ok = _finite(v) and (isinstance(v, int) or not whole) and lo <= v <= hi
    return not ok and f"{'a whole' if whole else 'a finite'} number from {lo:g} to {hi:g}"


def check_config(cfg: Config) -> None:
    """Refuse, naming the field, any value out of its range."""
    for f in dataclasses.fields(cfg):
        v = getattr(cfg, f.name)
        bad = _config_field_error(f.name, f.type, v)
        if bad:
            raise ValueError(f"Config.{f.name}: must be {bad}, got {v!r}")
    if any(lo >= hi for lo, hi in zip(cfg.u_lower, cfg.u_upper)):
        raise ValueError(f"Config.u_lower: must be below u_upper {cfg.u_upper}, got {cfg.u_lower}")
    if any(x <= 0 for x in cfg.pred_scales) or any(x < 0 for x in cfg.alpha_rl + cfg.alpha_il):
        raise ValueError("Config.pred_scales must be > 0 and Config.alpha_rl, alpha_il >= 0")


def check_setting(setting) -> str:
    if setting not in SETTINGS:
        raise ValueError(f"setting: expected 'rl' (hindsight) or 'il' (imitation), got {setting!r}")
    return setting


if __name__ == "__main__":
    from lab import quick  # the method ends here; --quick and --pretrain are lab/quick.py's

    quick.main()
