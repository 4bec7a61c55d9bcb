"""DiffStack (Karkus, Ivanovic, Mannor, Pavone, CoRL 2022): the method in one readable module.

The stack predicts the future of a nearby vehicle (eq. 1), plans with a sampling planner (eq. 2) that minimises a
hand-crafted cost (eq. 3), and refines the plan with a box-constrained iLQR controller (eq. 4). Planner and
controller are differentiable, so the predictor can be trained with the planning and control losses.

    1. Config        every default of the paper, in one dataclass
    2. Dynamics      the dynamically-extended unicycle (exact integration)
    3. Cost          eq. (3): collision, goal, lane, heading, control effort
    4. Planner       eq. (2): lane-centric spline candidates, argmin, relaxed argmin (L_plan)
    5. Controller    eq. (4): box-constrained iLQR, and its exact KKT backward (Amos et al. 2018)
    6. Predictor     eq. (1): a Trajectron++-style CVAE over controls, and its InfoVAE loss
    7. Stack         predict -> plan -> control, L = a1 L_pred + a2 L_plan + a3 L_ctr
    8. Input checks  what the public entry points refuse, in one place
Training and evaluation are in train.py (`python diffstack.py --quick` hands over to it).

Shapes in comments: B scenarios, A other agents, K prediction modes, N planner candidates, T time steps, L lanes,
P points per lane, n = 4 state and m = 2 control dims; ... extra batch dims a function broadcasts over.
A state is s = (x, y, heading h, speed v); a control is u = (yaw rate w, acceleration a).
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

# ===== 1. Config ====================================================================================================

@dataclass
class Config:
    """Every default of the paper (App. C, D; Trajectron++'s for the predictor); comments say where the authors' code differs."""

    dt: float = 0.5  # time step (s); nuScenes key frames are 2 Hz
    hist_len: int = 8  # past steps of history (4 s); the current state makes 9
    horizon: int = 6  # planning / prediction horizon T in steps (3 s)
    # --- cost, eq. (3) ---
    w_coll: float = 5.0  # collision weight w1 (authors' code: 20)
    w_goal: float = 0.5  # goal weight w2 (authors' code: 0.05)
    w_lat: float = 0.3  # lateral lane deviation weight w3
    w_head: float = 0.3  # lane heading deviation weight w4
    w_ctrl: float = 1.0  # control effort weight w5
    rbf_var: float = 2.0  # sigma^2 (m^2) of the collision RBF phi(d2) = exp(-d2 / 2 sigma^2) (the authors' exp(-d^2/4))
    # --- planner, eq. (2), App. C.1 ---
    goal: str = "logged"  # g of eq. (3): the GT ego state at T (App. C.3), or 'route' (see route_goal)
    goal_lane_dist: float = 4.5  # a goal lane passes within this distance (m) of the goal
    goal_lane_heading: float = math.pi / 2  # ... and its heading differs from the goal's by less (authors' code: pi/4)
    max_goal_lanes: int = 2  # lanes kept, closest to the goal first (the paper: every goal lane); N = 8 x 3 x this
    plan_accels: tuple = (-3.0, -2.0, -1.0, -0.5, 0.0, 0.5, 1.0, 2.0)  # terminal accelerations (m/s^2)
    plan_offsets: tuple = (-0.5, 0.0, 0.5)  # terminal lateral offsets from the lane centre (m)
    beta: float = 1.0  # temperature of the relaxed argmin p_n = softmax(-beta C_n)
    feas_lat_accel: float = 8.0  # feasible |w v| (m/s^2), authors' code; and the controller's box (authors': a in [-6, 4])
    feas_yaw_per_speed: float = 0.5  # feasible |w| <= this * |v| (1/m), authors' code
    # --- controller, eq. (4), App. C.2 ---
    u_lower: tuple = (-0.7, -5.0)  # control lower bounds (yaw rate rad/s, acceleration m/s^2), authors' code
    u_upper: tuple = (0.7, 4.0)  # control upper bounds
    ilqr_iters: int = 5  # maximum iLQR iterations
    ilqr_tol: float = 0.05  # converged when the full LQR control step's norm is below this (authors' code: 0.01)
    line_search_steps: int = 5  # step scales tried: 1, 1/5, 1/25, ...
    line_search_decay: float = 5.0  # divide the step by this on failure
    # --- predictor, eq. (1), §3.1 (Trajectron++'s defaults, Salzmann et al. 2020) ---
    pred_modes: int = 25  # K, the values of the discrete latent z (= GMM components = trajectories for the planner)
    pred_enc_hidden: int = 32  # width of the history LSTM, the neighbour encoder and each direction of the future BiLSTM
    pred_latent_hidden: int = 32  # hidden width of the p(z|x) and q(z|x,y) MLPs
    pred_dec_hidden: int = 64  # decoder GRU width (Trajectron++: 128; halved for CPU training)
    pred_radius: float = 30.0  # neighbours within this distance (m) of the predicted agent at t0 are attended to
    pred_scales: tuple = (30.0, 15.0, 4.0, math.pi)  # input scales: position, velocity, acceleration, heading (and rate)
    pred_min_speed: float = 0.5  # below this speed (m/s) the tracked heading replaces the velocity direction at t0
    pred_pos_std_min: float = 0.05  # std (m) added to every GMM component: at v = 0 the controls cannot move sideways
    pred_log_p_max: float = 6.0  # the loss's per-step log-likelihood is clamped above at this (Trajectron++)
    pred_kl_min: float = 0.07  # free bits: the batch-mean KL(q || p) is clamped below at this
    pred_beta: tuple = (100.0, 400.0, 100.0)  # KL weight beta(step) = b0 sigmoid((step - b1) / b2)
    pred_logit_clip: tuple = (0.05, 5.0, 300.0, 60.0)  # logit clip c(step) = c0 + (c1 - c0) sigmoid((step - c2) / c3)
    pred_nll_min: float = -20.0  # the NLL metric clamps each step's log p(y_t) below at this
    pred_lr_decay: float = 0.9999  # learning rate multiplied by this after every iteration
    pred_grad_clip: float = 1.0  # gradients clipped to [-c, c] elementwise (value clipping, as Trajectron++)
    # --- training, §3.2, App. D ---
    alpha_rl: tuple = (1.0, 100.0, 1000.0)  # loss weights (L_pred, L_plan, L_ctr) in the RL setting
    alpha_il: tuple = (1.0, 10.0, 1000.0)  # loss weights in the IL setting
    lr: float = 3e-3  # Adam learning rate
    batch_size: int = 256  # scenarios per training step
    train_plan_weights: str = "posterior"  # the planner's mode weights in training: q(z|x,y) (authors' code) or 'prior'

    def __post_init__(self):
        check_config(self)

# ===== 2. Dynamics: the dynamically-extended unicycle ===============================================================
#
# With constant yaw rate w and acceleration a over one step tau = dt, starting from (x, y, h, v):
#     h' = h + w tau,   v' = v + a tau,   [x', y'] = [x, y] + R(h) [along, lateral],
#     along   = int_0^tau (v + a s) cos(w s) ds = v c_0 + a c_1,
#     lateral = int_0^tau (v + a s) sin(w s) ds = v s_0 + a s_1,
# with the moments c_j = int_0^tau s^j cos(w s) ds and s_j = int_0^tau s^j sin(w s) ds, whose derivatives are
# moments again, d c_j / dw = -s_{j+1} and d s_j / dw = c_{j+1}: the Jacobians in closed form too.
# The closed forms divide by w^(j+1); for |th| = |w tau| < 0.3 the Taylor series (seven terms, error < 1e-16)
#     c_j = tau^(j+1) sum_k (-1)^k th^2k / ((2k)! (2k+j+1)),  s_j = tau^(j+1) sum_k (-1)^k th^(2k+1) / ((2k+1)! (2k+j+2))
# replaces them, and they get a safe w = 1 there (a tiny w inside torch.where would put NaN into the gradient).

_SERIES_SWITCH = 0.3  # |w tau| below which the series replaces the closed forms

@functools.lru_cache(maxsize=None)
def _series_coefficients(jmax, tau, dtype, device):
    """The series' coefficients in powers of th^2, highest first (rows (2 (jmax+1),)), and tau^(j+1) (jmax+1,)."""
    f = math.factorial
    coef = [[(-1) ** k / (f(2 * k) * (2 * k + j + 1)) for j in range(jmax + 1)]
            + [(-1) ** k / (f(2 * k + 1) * (2 * k + j + 2)) for j in range(jmax + 1)] for k in range(7)]
    tau_pow = torch.tensor(tau, dtype=dtype, device=device) ** torch.arange(1, jmax + 2, dtype=dtype, device=device)
    return tuple(torch.tensor(coef[::-1], dtype=dtype, device=device).unbind(0)), tau_pow

def _moments(w, tau, jmax):
    """[c_0..c_jmax], [s_0..s_jmax] for yaw rates w (...,) over tau: exact and smooth at w = 0."""
    th = w * tau
    small = th.abs() < _SERIES_SWITCH
    # series, all moments at once by Horner's rule in th^2: (..., 2 (jmax+1))
    thz = torch.where(small, th, 0.0)[..., None]
    th2 = thz * thz
    coef, tau_pow = _series_coefficients(jmax, tau, w.dtype, w.device)  # terms x (2 (jmax+1),), (jmax+1,) tau^(j+1)
    series = coef[0]
    for c in coef[1:]:
        series = torch.addcmul(c, series, th2)  # series th^2 + c
    series = series * torch.cat([tau_pow.expand(*th.shape, -1), tau_pow * thz], -1)
    # closed forms, by parts: c_j = (tau^j sin - j s_{j-1}) / w,  s_j = (j c_{j-1} - tau^j cos) / w; w = 1 where small
    ws = torch.where(small, 1.0, w)
    ths = ws * tau
    sin, cos = torch.sin(ths), torch.cos(ths)
    c, s = [sin / ws], [(1.0 - cos) / ws]
    for j in range(1, jmax + 1):
        c.append((tau**j * sin - float(j) * s[-1]) / ws)
        s.append((float(j) * c[-2] - tau**j * cos) / ws)
    moments = torch.where(small[..., None], series, torch.stack(c + s, -1)).unbind(-1)
    return moments[: jmax + 1], moments[jmax + 1 :]

def unicycle_step(s: torch.Tensor, u: torch.Tensor, dt: float) -> torch.Tensor:
    """One exact step of the unicycle: s (..., 4) = (x, y, h, v), u (..., 2) = (w, a) -> s' (..., 4)."""
    check_tensor("s", s, (..., 4)), check_tensor("u", u, (..., 2), s.dtype)
    return _unicycle_step(s, u, check_positive("dt", dt))

def _unicycle_step(s: torch.Tensor, u: torch.Tensor, dt: float) -> torch.Tensor:
    x, y, h, v = s.unbind(-1)
    w, a = u.unbind(-1)
    (c0, c1), (s0, s1) = _moments(w, dt, 1)
    along, lateral = torch.addcmul(v * c0, a, c1), torch.addcmul(v * s0, a, s1)  # v c0 + a c1, v s0 + a s1
    cos_h, sin_h = torch.cos(h), torch.sin(h)
    return torch.stack([x.addcmul(cos_h, along).addcmul(sin_h, lateral, value=-1.0),  # x + cos along - sin lateral
                        y.addcmul(sin_h, along).addcmul(cos_h, lateral),  # y + sin along + cos lateral
                        h.add(w, alpha=dt), v.add(a, alpha=dt)], -1)  # h + w dt, v + a dt

def _position_jacobians(h, v, w, a, dt: float):
    """A unicycle step from h, v under w, a (...): its displacement dx, dy and the position rows of its Jacobians,
    M = d(x, y)/d(h, v) and N = d(x, y)/d(w, a), (2, 2, ...), matrix indices first."""
    (c0, c1, c2), (s0, s1, s2) = _moments(w, dt, 2)
    cos_h, sin_h = torch.cos(h), torch.sin(h)
    rot = lambda al, la: (cos_h * al - sin_h * la, sin_h * al + cos_h * la)  # noqa: E731  R(h) [al, la]
    dx, dy = rot(v * c0 + a * c1, v * s0 + a * s1)  # the displacement
    xv, yv = rot(c0, s0)  # d/dv
    xw, yw = rot(-(v * s1 + a * s2), v * c1 + a * c2)  # d/dw, by d c_j/dw = -s_{j+1}, d s_j/dw = c_{j+1}
    xa, ya = rot(c1, s1)  # d/da
    M = torch.stack([torch.stack([-dy, xv]), torch.stack([dx, yv])])  # (2, 2, ...); d/dh of R(h) d is J R(h) d
    N = torch.stack([torch.stack([xw, xa]), torch.stack([yw, ya])])  # (2, 2, ...)
    return dx, dy, M, N

def unicycle_jacobians(s: torch.Tensor, u: torch.Tensor, dt: float):
    """A = df/ds (..., 4, 4) and B = df/du (..., 4, 2) of unicycle_step, in closed form."""
    _, _, M, N = _position_jacobians(s[..., 2], s[..., 3], *u.unbind(-1), dt)  # (2, 2, ...) each
    one, zero = torch.ones_like(s[..., 2]), torch.zeros_like(s[..., 2])
    rows = lambda *r: torch.stack([torch.stack(row, -1) for row in r], -2)  # noqa: E731
    A = rows([one, zero, *M[0]], [zero, one, *M[1]], [zero, zero, one, zero], [zero, zero, zero, one])
    B = rows([*N[0]], [*N[1]], [dt * one, zero], [zero, dt * one])
    return A, B

def unicycle_curvature(s: torch.Tensor, u: torch.Tensor, lam: torch.Tensor, dt: float) -> torch.Tensor:
    """sum_i lam_i d2 f_i / d(s, u)^2 (..., 6, 6): the dynamics' curvature weighted by costates lam (..., 4).

    Only the displacement D = R(h) d, d = (along, lateral), is curved, in (h, v, w, a). With
    mu = R(h)' lam_xy (the costate in the heading frame) and J the 90-degree rotation:
        d2/dh2 = -mu'd,   d2/dh dq = (J'mu)' dd/dq,   d2/dq dr = mu' d2d/dq dr,   q, r in (v, w, a),
    and the moments' rule d c_j/dw = -s_{j+1}, d s_j/dw = c_{j+1} gives every derivative of d."""
    h, v = s[..., 2], s[..., 3]
    w, a = u.unbind(-1)
    (c0, c1, c2, c3), (s0, s1, s2, s3) = _moments(w, dt, 3)
    cos_h, sin_h = torch.cos(h), torch.sin(h)
    mu_x = cos_h * lam[..., 0] + sin_h * lam[..., 1]  # mu = R(h)' lam_xy
    mu_y = -sin_h * lam[..., 0] + cos_h * lam[..., 1]
    dot = lambda e: mu_x * e[0] + mu_y * e[1]  # noqa: E731  mu' e
    dot_j = lambda e: mu_y * e[0] - mu_x * e[1]  # noqa: E731  (J' mu)' e
    d = (v * c0 + a * c1, v * s0 + a * s1)
    dd = {"v": (c0, s0), "w": (-(v * s1 + a * s2), v * c1 + a * c2), "a": (c1, s1)}  # first derivatives of d
    d2 = {("v", "w"): (-s1, c1), ("w", "a"): (-s2, c2), ("w", "w"): (-(v * c2 + a * c3), -(v * s2 + a * s3))}
    index = {"h": 2, "v": 3, "w": 4, "a": 5}  # positions in z = (x, y, h, v, w, a)
    H = torch.zeros(*h.shape, 6, 6, dtype=s.dtype, device=s.device)
    H[..., 2, 2] = -dot(d)
    for q, e in dd.items():
        H[..., 2, index[q]] = H[..., index[q], 2] = dot_j(e)
    for (q, r), e in d2.items():
        H[..., index[q], index[r]] = H[..., index[r], index[q]] = dot(e)
    return H

def rollout(dynamics, x0, u):
    """Integrate controls u (..., T, m) from x0 (..., n) with a step function: x (..., T+1, n), x0 first."""
    xs = [x0]
    for t in range(u.shape[-2]):
        xs.append(dynamics(xs[-1], u[..., t, :]))
    return torch.stack(xs, -2)

def unicycle_rollout(s0: torch.Tensor, u: torch.Tensor, dt: float) -> torch.Tensor:
    """Integrate controls u (..., T, 2) from s0 (..., 4): states (..., T+1, 4), s0 included."""
    return rollout(Unicycle(dt), s0, u)

class Unicycle:
    """The unicycle as the controller sees it: a step function with closed-form derivatives."""

    def __init__(self, dt: float):
        self.dt = check_positive("dt", dt)

    def __call__(self, s, u):
        return _unicycle_step(s, u, self.dt)

    def jacobians(self, s, u):
        return unicycle_jacobians(s, u, self.dt)

    def curvature(self, s, u, lam):
        return unicycle_curvature(s, u, lam, self.dt)

# ===== 3. Cost, eq. (3) and App. C.3 ================================================================================
#   C = w1 C_coll + w2 C_goal + w3 C_lat + w4 C_head + w5 C_u, a sum of per-step terms, each of one step's state and
#   control: the controller relies on the cost's Hessian being block-diagonal in time.

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

def segment_projection(q, a, b):
    """The closest point to q (..., 2) on a -> b (..., 3) (x, y, heading): frac (...,) along the segment (clamped to
    [0, 1]), r = q - that point (..., 2), the lane heading there (interpolated) and dfrac/dq (..., 2) (0 where clamped)."""
    d = b[..., :2] - a[..., :2]  # (..., 2)
    raw = ((q - a[..., :2]) * d).sum(-1) / (d * d).sum(-1).clamp_min(1e-9)  # the fraction before the clamp
    frac = raw.clamp(0, 1)
    r = q - a[..., :2] - frac[..., None] * d
    lane_h = a[..., 2] + frac * wrap_angle(b[..., 2] - a[..., 2])
    on_segment = ((raw >= 0) & (raw <= 1))[..., None]
    dfrac = torch.where(on_segment, d / (d * d).sum(-1, keepdim=True).clamp_min(1e-9), 0.0)  # as clamp's gradient
    return frac, r, lane_h, dfrac

_SEARCH_LAM = 50.0  # m^2: a lane point heading the other way at distance d ranks as one at sqrt(d^2 + 100 m^2)

def nearest_lane_segment(pos, heading, lanes, lanes_mask):
    """The lane segment nearest each state: its ends a, b (B, Q, 3) (Q: the states, flattened) and has_lane (B, Q).

    First the nearest lane point (no gradient: it only picks an index), ranked by |q - p|^2 + lam (1 - cos(h_q - h_p)),
    lam = 50 m^2, so that an oncoming lane beside the state's own is not 'closest' (no lane within 90 degrees: no
    lane cost); then the closer of the two segments that meet there."""
    B, L, P, _ = lanes.shape
    q, hq = pos.reshape(B, -1, 2), heading.reshape(B, -1)  # (B, Q, 2), (B, Q)
    pts = lanes.reshape(B, L * P, 3)
    # 1. nearest point: |q|^2 is the same for every p and drops out of the ranking, and the rest is one
    #    product of features: [-2 q, -lam u(h_q), 1] . [p, u(h_p), |p|^2 + lam] (|p|^2 = 1e30 for padding)
    qd, hd, pd = q.detach(), hq.detach(), pts.detach()
    p_norm = torch.where(lanes_mask.reshape(B, L * P), (pd[..., :2] ** 2).sum(-1) + _SEARCH_LAM, 1e30)  # (B, L*P)
    search = torch.cat([pd[..., :2], torch.cos(pd[..., 2:]), torch.sin(pd[..., 2:]), p_norm[..., None]], -1).mT  # (B, 5, L*P)
    feat_q = torch.cat([-2 * qd, -_SEARCH_LAM * torch.stack([torch.cos(hd), torch.sin(hd)], -1), torch.ones_like(qd[..., :1])], -1)
    j = (feat_q @ search).min(-1).indices  # (B, Q): min's indices are argmin's (the first minimum)
    near = pts.gather(1, j[..., None].expand(B, -1, 3))
    has_lane = lanes_mask.reshape(B, L * P).gather(1, j) & (torch.cos(hd - near[..., 2].detach()) > 0)
    # 2. the closer of the segments before and after that point (a lane's valid points are a prefix)
    lane, i = j // P, j % P
    n_valid = lanes_mask.sum(-1).gather(1, lane)  # (B, Q)
    point = lambda k: pts.gather(1, (lane * P + k)[..., None].expand(B, -1, 3))  # noqa: E731  (B, Q, 3)
    prev, here, nxt = point((i - 1).clamp_min(0)), point(i), point(torch.minimum(i + 1, (n_valid - 1).clamp_min(0)))
    d2 = lambda a, b: segment_projection(qd, a.detach(), b.detach())[1].square().sum(-1)  # noqa: E731  (B, Q)
    closer = d2(here, nxt) < d2(prev, here)  # (B, Q)
    return torch.where(closer[..., None], here, prev), torch.where(closer[..., None], nxt, here), has_lane

def project_to_lanes(pos, heading, lanes, lanes_mask):
    """Squared distance to the closest lane point and heading error there, and has_lane, each (B, ...), for states pos
    (B, ..., 2), heading (B, ...); where no lane matches, both are 0."""
    B = lanes.shape[0]
    a, b, has_lane = nearest_lane_segment(pos, heading, lanes, lanes_mask)  # (B, Q, 3) x 2, (B, Q)
    _, r, lane_h, _ = segment_projection(pos.reshape(B, -1, 2), a, b)
    d2 = torch.where(has_lane, (r**2).sum(-1), 0.0)
    err = torch.where(has_lane, wrap_angle(heading.reshape(B, -1) - lane_h), 0.0)
    return d2.reshape(heading.shape), err.reshape(heading.shape), has_lane.reshape(heading.shape)

def rbf(d2: torch.Tensor, rbf_var: float) -> torch.Tensor:
    """phi(d2) = exp(-d2 / 2 sigma^2), its exponent floored at -60 (phi < 1e-26, nothing at the cost's precision;
    docs/performance.md says why)."""
    return torch.exp((-d2 / (2 * rbf_var)).clamp_min(-60.0))

def collision_term(pos: torch.Tensor, ctx: CostContext, rbf_var: float = 2.0) -> torch.Tensor:
    """C_coll per trajectory: pos (B, ..., T, 2) positions t1..T -> (B, ...).

    C_coll = sum_t phi( sum_k pi_k ||s_t - s^_kt||^2 ) + sum_a sum_t phi(||s_t - s_at||^2),  phi(d2) = exp(-d2 / 2 sigma^2)
    The expected squared distance splits into the distance to the modes' mean and their spread:
        sum_k pi_k ||s - s^_k||^2 = ||s - mu||^2 + sum_k pi_k ||s^_k - mu||^2,   mu = sum_k pi_k s^_k,
    so the planner sees a prediction only through its per-step mean and spread."""
    B = pos.shape[0]
    view = lambda t: t.reshape(B, *([1] * (pos.dim() - 3)), *t.shape[1:])  # noqa: E731  broadcast over ...
    mu = (ctx.probs[:, :, None, None] * ctx.preds).sum(1)  # (B, T, 2)
    spread = (ctx.probs[:, :, None] * ((ctx.preds - mu[:, None]) ** 2).sum(-1)).sum(1)  # (B, T)
    d2_pred = ((pos - view(mu)) ** 2).sum(-1) + view(spread)  # (B, ..., T)
    coll = view(ctx.pred_mask)[..., None] * rbf(d2_pred, rbf_var)
    d2_others = ((pos[..., None, :, :] - view(ctx.others)) ** 2).sum(-1)  # (B, ..., A, T)
    coll = coll + (view(ctx.others_mask)[..., None] * rbf(d2_others, rbf_var)).sum(-2)
    return coll.sum(-1)

def scene_terms(pos: torch.Tensor, head: torch.Tensor, u: torch.Tensor, goal: torch.Tensor, lanes, lanes_mask) -> torch.Tensor:
    """(C_goal, C_lat, C_head, C_u) per trajectory (B, ..., 4), the terms of eq. (3) no prediction enters: positions
    (B, ..., T, 2) and headings (B, ..., T) at t1..T, u (B, ..., T, 2), goal (B, 2), lanes (B, L, P, 3)."""
    B = pos.shape[0]
    view = lambda t: t.reshape(B, *([1] * (pos.dim() - 3)), *t.shape[1:])  # noqa: E731  broadcast over ...
    # C_goal = ||s_T - g||^2
    to_goal = ((pos[..., -1, :] - view(goal)) ** 2).sum(-1)
    # C_lat = sum_t ||s_t - s_lane||^2,   C_head = sum_t wrap(h_t - h_lane)^2
    lat, head_err, _ = project_to_lanes(pos, head, lanes, lanes_mask)
    # C_u = sum_t w_t^2 + a_t^2
    effort = (u**2).sum((-1, -2))
    return torch.stack([to_goal, lat.sum(-1), (head_err**2).sum(-1), effort], -1)

def cost_terms(x: torch.Tensor, u: torch.Tensor, ctx: CostContext, rbf_var: float = 2.0) -> torch.Tensor:
    """The five unweighted terms of eq. (3) (B, ..., 5) of states x (B, ..., T+1, 4) (s0 first, not costed) and
    controls u (B, ..., T, 2): (C_coll, C_goal, C_lat, C_head, C_u)."""
    pos, head = x[..., 1:, :2], x[..., 1:, 2]  # (B, ..., T, 2), (B, ..., T): the cost skips t0
    coll = collision_term(pos, ctx, rbf_var)  # (B, ...)
    rest = scene_terms(pos, head, u, ctx.goal, ctx.lanes, ctx.lanes_mask)  # (B, ..., 4)
    return torch.cat([coll[..., None], rest], -1)

def cost_weights(cfg: Config, dtype=torch.float32, device=None) -> torch.Tensor:
    """The hand-tuned weights (w1..w5) of App. C.3."""
    return torch.tensor([cfg.w_coll, cfg.w_goal, cfg.w_lat, cfg.w_head, cfg.w_ctrl], dtype=dtype, device=device)

def weigh(terms: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Eq. (3): C = sum_i w_i C_i. terms (B, ..., 5), w (5,) or per scenario (B, 5) -> (B, ...)."""
    w = w if w.dim() == 1 else w.reshape(w.shape[0], *([1] * (terms.dim() - 2)), 5)
    return (terms * w).sum(-1)

def total_cost(x, u, ctx: CostContext, w: torch.Tensor, rbf_var: float = 2.0) -> torch.Tensor:
    """Eq. (3) of a trajectory: x (B, ..., T+1, 4), u (B, ..., T, 2), w (5,) or (B, 5) -> (B, ...)."""
    check_cost_inputs(x, u, ctx, w, rbf_var)
    return weigh(cost_terms(x, u, ctx, rbf_var), w)

def cost_expansion_closed_form(x, u, ctx: CostContext, w, rbf_var: float = 2.0):
    """The gradient (B, T+1, 6) and block Hessian (B, T+1, 6, 6) of eq. (3) in z_t = (x, y, h, v, w, a), step by
    step (x_0 costs nothing; u_T = 0 pads the last step), in closed form: what cost_expansion computes by
    autodiff (the tests hold the two together). x (B, T+1, 4), u (B, T, 2), w (5,) or (B, 5).

    With p, h a state's position and heading (sigma^2 = rbf_var):
      C_coll   phi = c exp(-|p - m|^2 / 2 sigma^2) per predicted mean m = mu_t (c = exp(-spread / 2 sigma^2)) and
               per other agent:  grad = -phi (p - m) / sigma^2,  Hess = phi ((p - m)(p - m)' / sigma^4 - I / sigma^2)
      C_goal   |p_T - g|^2:  grad = 2 (p_T - g),  Hess = 2 I
      C_lat    |r|^2, r = p - a - f d the offset from the closest point on the segment a -> b (d = b - a, f the fraction
               along it, linear in p: df = d / |d|^2, or 0 where clamped):  J = dr/dp = I - d df',  grad = 2 J'r,  Hess = 2 J'J
      C_head   e^2, e = h - h_lane, h_lane = h_a + f (h_b - h_a):  de/dh = 1,  de/dp = -(h_b - h_a) df,
               grad = 2 e de,  Hess = 2 de de'
      C_u      w^2 + a^2:  grad = 2 u,  Hess = 2 I"""
    B, T = u.shape[:2]
    dtype, dev = x.dtype, x.device
    wc, wg, wl, wh, wu = w.expand(B, 5)[:, :, None].unbind(1)  # (B, 1) each: broadcast over the steps
    p, h = x[:, 1:, :2], x[:, 1:, 2]  # (B, T, 2), (B, T): the states t1..T
    eye = torch.eye(2, dtype=dtype, device=dev)
    outer = lambda a, b: a[..., :, None] * b[..., None, :]  # noqa: E731
    # C_coll: the predicted mean first, then the other agents
    mu = (ctx.probs[:, :, None, None] * ctx.preds).sum(1)  # (B, T, 2)
    spread = (ctx.probs[:, :, None] * ((ctx.preds - mu[:, None]) ** 2).sum(-1)).sum(1)  # (B, T)
    diff = p[:, None] - torch.cat([mu[:, None], ctx.others], 1)  # (B, 1+A, T, 2)
    offset = torch.cat([spread[:, None], torch.zeros_like(ctx.others[..., 0])], 1)  # (B, 1+A, T)
    mask = torch.cat([ctx.pred_mask[:, None], ctx.others_mask], 1)[..., None]  # (B, 1+A, 1)
    phi = mask * rbf((diff**2).sum(-1) + offset, rbf_var)  # (B, 1+A, T)
    g_coll = -(phi[..., None] * diff).sum(1) / rbf_var  # (B, T, 2)
    H_coll = (phi[..., None, None] * (outer(diff, diff) / rbf_var**2 - eye / rbf_var)).sum(1)  # (B, T, 2, 2)
    # C_lat and C_head, on the nearest lane segment
    a, b, has_lane = nearest_lane_segment(p, h, ctx.lanes, ctx.lanes_mask)  # (B, T, 3) x 2, (B, T)
    _, r, lane_h, df = segment_projection(p, a, b)  # (B, T, 2), (B, T), (B, T, 2)
    on = has_lane.to(dtype)  # (B, T)
    J = eye - outer(b[..., :2] - a[..., :2], df)  # (B, T, 2, 2)
    g_lat = 2 * (J.transpose(-1, -2) @ r[..., None])[..., 0] * on[..., None]
    H_lat = 2 * J.transpose(-1, -2) @ J * on[..., None, None]
    e = wrap_angle(h - lane_h) * on  # (B, T)
    de = torch.cat([-wrap_angle(b[..., 2] - a[..., 2])[..., None] * df, torch.ones_like(e)[..., None]], -1)  # (B, T, 3)
    g_head = 2 * e[..., None] * de  # (B, T, 3): d/d(p, h)
    H_head = 2 * outer(de, de) * on[..., None, None]  # (B, T, 3, 3)
    # assemble per step: the states t1..T in rows 1..T, the controls t0..T-1 in rows 0..T-1
    g = torch.zeros(B, T + 1, 6, dtype=dtype, device=dev)
    H = torch.zeros(B, T + 1, 6, 6, dtype=dtype, device=dev)
    g[:, 1:, :2] = wc[..., None] * g_coll + wl[..., None] * g_lat
    g[:, 1:, :3] += wh[..., None] * g_head
    g[:, T, :2] += 2 * wg * (p[:, -1] - ctx.goal)
    g[:, :T, 4:] = 2 * wu[..., None] * u
    H[:, 1:, :2, :2] = wc[..., None, None] * H_coll + wl[..., None, None] * H_lat
    H[:, 1:, :3, :3] += wh[..., None, None] * H_head
    H[:, T, :2, :2] += 2 * wg[..., None] * eye
    H[:, :T, 4:, 4:] = 2 * wu[..., None, None] * eye
    return g, H

class StackCost:
    """Eq. (3) as the controller sees it: cost(x, u, w, *ctx.tensors()) -> (B, ...), every argument per scenario,
    with its closed-form `expansion`, which the solver takes instead of autodiff."""

    def __init__(self, rbf_var: float):
        self.rbf_var = rbf_var

    def __call__(self, x, u, w, *context):
        return weigh(cost_terms(x, u, CostContext(*context), self.rbf_var), w)

    def expansion(self, x, u, w, *context):
        return cost_expansion_closed_form(x, u, CostContext(*context), w, self.rbf_var)

# ===== 4. Planner: lane-centric spline candidates and the relaxed argmin, eq. (2) and App. C.1 ======================

@dataclass
class Candidates:
    """The planner's candidate trajectories for a batch."""
    x: torch.Tensor  # (B, N, T+1, 4) states along the splines, s0 first
    u: torch.Tensor  # (B, N, T, 2)   controls derived from the splines
    valid: torch.Tensor  # (B, N)     lane found, terminal on the lane, dynamically feasible

def _lane_arclength(lanes, lanes_mask):
    """Cumulative arc length along each lane, flat past its last valid point. -> (B, L, P)."""
    seg = (lanes[:, :, 1:, :2] - lanes[:, :, :-1, :2]).norm(dim=-1)
    seg = torch.where(lanes_mask[:, :, 1:] & lanes_mask[:, :, :-1], seg, 0.0)  # (B, L, P-1)
    return torch.cat([torch.zeros_like(seg[..., :1]), seg.cumsum(-1)], -1)

def _project_each_lane(p, lanes, lanes_mask, cum):
    """Closest point of p (B, 2) on every lane: squared distance, arc length and heading, each (B, L)."""
    seg_ok = lanes_mask[:, :, :-1] & lanes_mask[:, :, 1:]  # (B, L, P-1)
    frac, r, lane_h, _ = segment_projection(p[:, None, None, :], lanes[:, :, :-1], lanes[:, :, 1:])  # (B, L, P-1)
    d2 = torch.where(seg_ok, (r**2).sum(-1), torch.full_like(r[..., 0], 1e9))
    best = d2.argmin(-1, keepdim=True)  # (B, L, 1)
    pick = lambda t: t.gather(-1, best).squeeze(-1)  # noqa: E731
    seg_len = cum[..., 1:] - cum[..., :-1]
    return pick(d2), pick(cum[..., :-1] + frac * seg_len), pick(lane_h)

def _point_at_arclength(lanes, cum, s):
    """Interpolate lane points at arc lengths s (B, G, Q) on lanes (B, G, P, 3) -> (B, G, Q, 3)."""
    i = torch.searchsorted(cum.contiguous(), s.contiguous()).clamp(1, cum.shape[-1] - 1)  # segment end index
    s0, s1 = cum.gather(-1, i - 1), cum.gather(-1, i)
    a = lanes.gather(-2, (i - 1)[..., None].expand(*i.shape, 3))
    b = lanes.gather(-2, i[..., None].expand(*i.shape, 3))
    f = ((s - s0) / (s1 - s0).clamp_min(1e-6)).clamp(0, 1)[..., None]
    xy = a[..., :2] + f * (b[..., :2] - a[..., :2])
    h = a[..., 2:] + f * wrap_angle(b[..., 2:] - a[..., 2:])
    return torch.cat([xy, h], -1)

def _hermite(p0, m0, p1, m1, tau):
    """Cubic Hermite curves p0 -> p1 with end tangents m0, m1 (..., 2) at tau (Q,) in [0, 1]: value, first and second
    derivative, each (..., Q, 2), as one product of the basis functions (3 Q, 4) with the control points."""
    t = tau[:, None]  # (Q, 1)
    h = [2 * t**3 - 3 * t**2 + 1, t**3 - 2 * t**2 + t, -2 * t**3 + 3 * t**2, t**3 - t**2]
    dh = [6 * t**2 - 6 * t, 3 * t**2 - 4 * t + 1, -6 * t**2 + 6 * t, 3 * t**2 - 2 * t]
    ddh = [12 * t - 6, 6 * t - 4, -12 * t + 6, 6 * t - 2]
    basis = torch.cat([torch.cat(b, 1) for b in (h, dh, ddh)], 0)  # (3 Q, 4)
    ctrl = torch.stack([p0, m0, p1, m1]).reshape(4, -1)  # (4, ... * 2)
    out = (basis @ ctrl).reshape(3, len(tau), *p0.shape)  # (3, Q, ..., 2)
    return list(out.movedim(1, -2))  # value, first, second derivative, each (..., Q, 2)

def plan_candidates(s0, goal, lanes, lanes_mask, cfg: Config) -> Candidates:
    """Candidate trajectories (App. C.1) from the ego state s0 (B, 4) towards goal (B, 4): on up to max_goal_lanes goal
    lanes, 8 terminal accelerations x 3 lateral offsets, each joined to s0 by the cubic Hermite curve fixed by position
    and velocity at both ends (as the authors' code; the paper's spline "minimizes mean control effort")."""
    B = check_plan_inputs(s0, goal, lanes, lanes_mask)
    T, dur = cfg.horizon, cfg.horizon * cfg.dt
    cum = _lane_arclength(lanes, lanes_mask)  # (B, L, P)
    # goal lanes: within goal_lane_dist of the goal, heading within goal_lane_heading of the goal's
    d2_goal, _, h_goal = _project_each_lane(goal[:, :2], lanes, lanes_mask, cum)  # (B, L)
    is_goal_lane = (d2_goal < cfg.goal_lane_dist**2) & (wrap_angle(h_goal - goal[:, 2:3]).abs() < cfg.goal_lane_heading)
    G = min(cfg.max_goal_lanes, lanes.shape[1])
    score, lane_idx = torch.where(is_goal_lane, d2_goal, torch.full_like(d2_goal, math.inf)).topk(G, -1, largest=False)
    lane_ok = torch.isfinite(score)  # (B, G)
    g_lanes = lanes.gather(1, lane_idx[:, :, None, None].expand(B, G, *lanes.shape[2:]))  # (B, G, P, 3)
    g_cum = cum.gather(1, lane_idx[:, :, None].expand(B, G, cum.shape[-1]))  # (B, G, P)
    g_mask = lanes_mask.gather(1, lane_idx[:, :, None].expand(B, G, lanes_mask.shape[-1]))
    _, s_ego, _ = _project_each_lane(s0[:, :2], g_lanes, g_mask, g_cum)  # (B, G) ego's arc length on each
    # terminal states: v_f = max(v0 + a T dt, 0), distance (v0 + v_f) / 2 * T dt along the lane, then offset
    acc, off, v0 = s0.new_tensor(cfg.plan_accels), s0.new_tensor(cfg.plan_offsets), s0[:, 3:4]  # (n_acc,), (n_off,), (B, 1)
    v_f = (v0 + acc * dur).clamp_min(0)  # (B, n_acc)
    s_end = s_ego[:, :, None] + ((v0 + v_f) / 2 * dur)[:, None, :]  # (B, G, n_acc)
    on_lane = s_end <= g_cum[..., -1:]  # the terminal lies on the lane
    lp = _point_at_arclength(g_lanes, g_cum, s_end)  # (B, G, n_acc, 3)
    normal = torch.stack([-torch.sin(lp[..., 2]), torch.cos(lp[..., 2])], -1)  # (B, G, n_acc, 2)
    p1 = lp[..., None, :2] + off[:, None] * normal[..., None, :]  # (B, G, n_acc, n_off, 2)
    h1 = lp[..., 2, None].expand(*p1.shape[:-1])  # (B, G, n_acc, n_off)
    v1 = v_f[:, None, :, None].expand_as(h1)
    p1, h1, v1 = p1.reshape(B, -1, 2), h1.reshape(B, -1), v1.reshape(B, -1)
    N = p1.shape[1]  # G * n_acc * n_off, 48 by default
    valid = (lane_ok[:, :, None] & on_lane)[..., None].expand(B, G, len(acc), len(off)).reshape(B, N)
    # cubic Hermite x(t), y(t): position and velocity matched at both ends, sampled at the T+1 steps
    heading_vec = lambda h: torch.stack([torch.cos(h), torch.sin(h)], -1)  # noqa: E731
    p0 = s0[:, None, :2].expand(B, N, 2)
    m0 = (s0[:, 3:4] * heading_vec(s0[:, 2]))[:, None].expand(B, N, 2) * dur  # tangents scale with the duration
    m1 = v1[..., None] * heading_vec(h1) * dur
    tau = torch.linspace(0, 1, T + 1, dtype=s0.dtype, device=s0.device)
    pos, dpos, ddpos = _hermite(p0, m0, p1, m1, tau)  # (B, N, T+1, 2) each
    vel, accel = dpos / dur, ddpos / dur**2
    speed = vel.norm(dim=-1)  # (B, N, T+1)
    # heading = direction of travel; near standstill it is undefined, so blend from h0 to the terminal heading
    h_blend = s0[:, None, None, 2] + tau * wrap_angle(h1 - s0[:, None, 2])[..., None]
    yaw = torch.where(speed > 0.1, torch.atan2(vel[..., 1], vel[..., 0]), h_blend)
    yaw = s0[:, None, None, 2] + wrap_angle(yaw - s0[:, None, None, 2])  # continuous from h0
    yaw_rate = (vel[..., 0] * accel[..., 1] - vel[..., 1] * accel[..., 0]) / speed.clamp_min(0.1) ** 2
    lon_acc = (vel * accel).sum(-1) / speed.clamp_min(0.1)
    x = torch.stack([pos[..., 0], pos[..., 1], yaw, speed], -1)  # (B, N, T+1, 4)
    # controls of step t = average of the derived values at t and t+1
    both = torch.stack([yaw_rate, lon_acc], -1)  # (B, N, T+1, 2)
    u = (both[..., 1:, :] + both[..., :-1, :]) / 2  # (B, N, T, 2)
    # dynamic feasibility: the controller's box, lateral acceleration, yaw rate per unit speed
    lo, hi = s0.new_tensor(cfg.u_lower), s0.new_tensor(cfg.u_upper)
    v_mid = (speed[..., 1:] + speed[..., :-1]) / 2
    feasible = (((u >= lo) & (u <= hi)).all(-1) & ((u[..., 0] * v_mid).abs() <= cfg.feas_lat_accel)
                & (u[..., 0].abs() <= cfg.feas_yaw_per_speed * v_mid + 1e-3)).all(-1)
    return Candidates(x, u, valid & feasible)

def route_goal(s0, lanes, lanes_mask, cfg: Config) -> torch.Tensor:
    """The 'route' goal (Config.goal), which unlike the logged one holds no reaction of the driver to the others: where
    the ego reaches at T keeping its speed along its lane (the nearest heading its way, within 40 degrees). (B, 4)."""
    B = s0.shape[0]
    cum = _lane_arclength(lanes, lanes_mask)  # (B, L, P)
    d2, s_on, h_lane = _project_each_lane(s0[:, :2], lanes, lanes_mask, cum)  # (B, L) each
    heading_ok = wrap_angle(h_lane - s0[:, 2:3]).abs() < math.radians(40)
    lane = torch.where(heading_ok, d2, torch.full_like(d2, math.inf)).min(-1).indices  # (B,) nearest such lane
    rows = torch.arange(B, device=s0.device)
    ahead = s_on[rows, lane] + s0[:, 3] * cfg.horizon * cfg.dt  # arc length at T
    p = _point_at_arclength(lanes[rows, lane][:, None], cum[rows, lane][:, None], ahead[:, None, None])[:, 0, 0]
    route = torch.cat([p, s0[:, 3:4]], -1)  # (B, 4): x, y, lane heading, speed
    # no lane heading the ego's way (real data can lack one): straight ahead at its speed
    zero = torch.zeros_like(s0[:, 2])
    straight = s0 + torch.stack([torch.cos(s0[:, 2]), torch.sin(s0[:, 2]), zero, zero], -1) * (s0[:, 3:4] * cfg.horizon * cfg.dt)
    return torch.where(heading_ok.any(-1, keepdim=True), route, straight)

def plan_loss(cost: torch.Tensor, valid: torch.Tensor, target: torch.Tensor, beta: float) -> torch.Tensor:
    """The relaxed argmin (§3.1): p_n = exp(-beta C_n) / Z over the valid candidates, L_plan = -log p_{n*}: (B,)."""
    logp = torch.log_softmax(torch.where(valid, -beta * cost, -math.inf), -1)  # (B, N)
    return -logp.gather(-1, target[:, None]).squeeze(-1)

def masked_argmin(values: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """argmin over the last dim among the valid entries: (B, N) -> (B,)."""
    return torch.where(valid, values, math.inf).argmin(-1)

class Plan(NamedTuple):
    """The planner's output for a batch."""
    cands: Candidates
    cost: torch.Tensor  # (B, N)       C_n, eq. (3) with the given weights
    best: torch.Tensor  # (B,)         the plan: argmin_n C_n over the valid candidates, eq. (2)
    plannable: torch.Tensor  # (B,)    bool: at least 2 valid candidates (others are flagged, not crashed on)
    terms: torch.Tensor  # (B, N, 5)   the unweighted terms of eq. (3) per candidate

@dataclass
class ScenePlan:
    """What the planner computes from the scene alone: the goal g, the candidates and every term of eq. (3) but
    C_coll for each. A prediction reaches the plan through C_coll only, so training computes these once."""
    goal: torch.Tensor  # (B, 4)       the goal state
    cands: Candidates
    terms: torch.Tensor  # (B, N, 4)   (C_goal, C_lat, C_head, C_u) per candidate, unweighted

    def __getitem__(self, rows):  # the scenarios `rows` (a slice or an index tensor), as a Scenarios batch is indexed
        c = self.cands
        return ScenePlan(self.goal[rows], Candidates(c.x[rows], c.u[rows], c.valid[rows]), self.terms[rows])

def plan(s0, ctx: CostContext, goal_state, w, cfg: Config, scene: ScenePlan | None = None) -> Plan:
    """Eq. (2): the candidates, their costs C_n and the argmin, as Plan. s0 (B, 4), goal_state (B, 4), w (5,) or (B, 5);
    scene: the candidates and their prediction-free terms if already computed."""
    check_plan_inputs(s0, goal_state, ctx.lanes, ctx.lanes_mask, "goal_state")
    cands = plan_candidates(s0, goal_state, ctx.lanes, ctx.lanes_mask, cfg) if scene is None else scene.cands
    check_cost_inputs(cands.x, cands.u, ctx, w, cfg.rbf_var)
    # (B, N, 5): with the scene's terms known, C_coll is the one term a prediction moves
    terms = (cost_terms(cands.x, cands.u, ctx, cfg.rbf_var) if scene is None else
             torch.cat([collision_term(cands.x[..., 1:, :2], ctx, cfg.rbf_var)[..., None], scene.terms], -1))
    cost = weigh(terms, w)  # (B, N)
    plannable = cands.valid.sum(-1) >= 2
    return Plan(cands, cost, masked_argmin(cost.detach(), cands.valid), plannable, terms)

# ===== 5. Controller: box-constrained iLQR, eq. (4) and App. C.2, and its exact KKT backward ========================
#   min_{x, u}  sum_t l_t(x_t, u_t) + l_T(x_T)   s.t.  x_0 = x_init,  x_{t+1} = f(x_t, u_t),  lo <= u_t <= hi
# General: `cost_fn(x, u, *params) -> (B, ...)` is any twice-differentiable sum of per-step terms (x (B, ..., T+1, n)
# with x_0 first, u (B, ..., T, m); ... are extra dims), `dynamics(x_t, u_t) -> x_{t+1}` any twice-differentiable
# step. Gradients reach x_init and every tensor in `params`. Closed forms where the cost or dynamics bring them
# (`expansion`, `jacobians`, `curvature`: StackCost, Unicycle; the tests hold each to autodiff), autodiff otherwise.

def _stagewise_jacobian(fn, z: torch.Tensor, with_value=False):
    """d fn(z)[..., t, :] / d z[..., t, :] for every t, z (B, T, k) -> (B, T, out, k) (and fn(z) with_value).
    Step t's output depends on step t's input only, so one perturbation d shared by all steps gives every block."""
    jac = torch.func.jacfwd(lambda d: (fn(z + d),) * 2, has_aux=True)(z.new_zeros(z.shape[-1]))
    return jac if with_value else jac[0]

def cost_expansion(cost_fn, x, u, params):
    """Gradient (B, T+1, n+m) and block Hessian (B, T+1, n+m, n+m) of the cost, step by step."""
    if hasattr(cost_fn, "expansion"):
        return cost_fn.expansion(x, u, *params)
    n, T = x.shape[-1], u.shape[1]
    z = torch.cat([x, torch.cat([u, u.new_zeros(u[:, :1].shape)], 1)], -1)  # (B, T+1, n+m); u_T is padding
    grad = torch.func.grad(lambda z: cost_fn(z[..., :n], z[:, :T, n:], *params).sum())
    H, g = _stagewise_jacobian(grad, z, with_value=True)
    return g, H

def dynamics_jacobians(dynamics, x, u):
    """A_t = df/dx (B, T, n, n), B_t = df/du (B, T, n, m) along a trajectory x (B, T+1, n), u (B, T, m)."""
    if hasattr(dynamics, "jacobians"):
        return dynamics.jacobians(x[:, :-1], u)
    n = x.shape[-1]
    J = _stagewise_jacobian(lambda z: dynamics(z[..., :n], z[..., n:]), torch.cat([x[:, :-1], u], -1))
    return J[..., :n], J[..., n:]

def solve_small(M, rhs):
    """M^-1 rhs for M (..., m, m), rhs (..., m, r); by Cramer's rule when m = 2 (why: docs/results.md, Table 4)."""
    if M.shape[-1] != 2:
        return torch.linalg.solve(M, rhs)
    (a, b, c, d), (r0, r1) = M.reshape(*M.shape[:-2], 4, 1).unbind(-2), rhs.unbind(-2)  # (..., 1) each, (..., r) each
    return torch.stack([d * r0 - b * r1, a * r1 - c * r0], -2) / (a * d - b * c)[..., None]

def solve_masked(Q, rhs, free):
    """Solve the free rows of Q y = rhs, with y = rhs on the others: Q (..., m, m), rhs (..., m, r), free (..., m)."""
    return solve_small(torch.where(free[..., :, None] & free[..., None, :], Q, torch.eye(Q.shape[-1], dtype=Q.dtype, device=Q.device)), rhs)

def box_qp(Q, q, lo, hi):
    """min_d 1/2 d'Q d + q'd  s.t. lo <= d <= hi, exactly, for small m and Q positive definite: the unconstrained
    minimiser where it is inside the box, else the best feasible one of the 3^m active sets (each control free, at
    lo or at hi). Q (B, m, m), q, lo, hi (B, m) -> d (B, m), free (B, m) bool: the controls not held at a bound."""
    B, m = q.shape
    d = solve_small(Q, -q[..., None])[..., 0]  # (B, m)
    inside = ((d >= lo) & (d <= hi)).all(-1)  # (B,)
    if inside.all():
        return d, torch.ones_like(d, dtype=torch.bool)
    assert m <= 4, "box_qp enumerates 3^m active sets: meant for few controls"
    sets = torch.cartesian_prod(*[torch.arange(3, device=q.device)] * m).reshape(-1, m)  # (3^m, m): free, lo, hi
    free = sets == 0
    fixed_val = torch.where(sets[None] == 1, lo[:, None], hi[:, None])  # (B, 3^m, m)
    Qs, qs = Q[:, None], q[:, None]  # (B, 1, m, m), (B, 1, m)
    Qv = lambda v: (Qs @ v[..., None])[..., 0]  # noqa: E731  Q v for v (B, 3^m, m)
    # free rows: Q_ff d_f = -(q_f + Q_fc d_c); fixed rows: d_c = fixed value
    rhs = torch.where(free, -(qs + Qv(torch.where(free, 0.0, fixed_val))), fixed_val)
    ds = solve_masked(Qs.expand(-1, len(sets), m, m), rhs[..., None], free.expand_as(rhs))[..., 0]  # (B, 3^m, m)
    feasible = ((ds >= lo[:, None] - 1e-9) & (ds <= hi[:, None] + 1e-9)).all(-1)
    obj = ((0.5 * Qv(ds) + qs) * ds).sum(-1)  # (B, 3^m) = 1/2 d'Q d + q'd
    best = torch.where(feasible, obj, math.inf).argmin(-1)  # (B,)
    rows = torch.arange(B, device=q.device)
    d_box, free_box = ds[rows, best], free.expand(B, -1, -1)[rows, best]
    return torch.where(inside[:, None], d, d_box), free_box | inside[:, None]

def make_pd(Q, eps):
    """Shift a symmetric Q (B, m, m) by a multiple of I until its smallest eigenvalue is >= eps."""
    lam = torch.linalg.eigvalsh(Q)[..., 0]  # (B,)
    return Q + (eps - lam).clamp_min(0.0)[:, None, None] * torch.eye(Q.shape[-1], dtype=Q.dtype, device=Q.device)

def riccati_backward(A, B, H, g, n, stage):
    """The Riccati recursion of a time-varying LQR: cost blocks H (B, T+1, n+m, n+m), linear terms g (B, T+1, n+m),
    dynamics dx_{t+1} = A_t dx_t + B_t du_t.

    In homogeneous coordinates a quadratic with a linear term is one matrix,
        1/2 z'H z + g'z = 1/2 [1; z]' Ht [1; z],   Ht = [[0, g'], [g, H]],
    so V_t(dx) = 1/2 dx'P dx + p'dx + const is Pt = [[., p'], [p, P]] over X = [1; dx], the dynamics are
    [1; dx'] = Ft [1; dx; du] with Ft = [[1, 0, 0], [0, A, B]], and the policy is du = k + K dx = W X, W = [k K]:
        Qt = Ht_t + Ft' Pt_{t+1} Ft                      (Q = H_t + F'PF and q = g_t + F'p at once, F = [A B])
        W  from Qt's control rows [Q_uX Q_uu]            (W = -Q_uu^-1 Q_uX where nothing is clamped)
        Pt_t = Q_XX + Q_Xu W + W'(Q_uX + Q_uu W)          (V_t(dx) = Q_t(dx, k + K dx): P and p at once)
    stage(t, Q_uu (B, m, m), Q_uX (B, m, 1+n)) -> (W (B, m, 1+n), free (B, m) bool) picks the policy. Returns
    k (B, T, m), K (B, T, m, n), free (B, T, m) and p_0 = dV_0/dx_0 (B, n)."""
    T, nX = A.shape[1], 1 + n  # nX: the size of [1; dx]; the controls follow it
    Ht_0, Ht_z = nn.functional.pad(g, (1, 0))[..., None, :], torch.cat([g[..., None], H], -1)  # Ht's first row, the others
    F = torch.cat([A, B], -1)  # (B, T, n, n+m); the products skip Ft's first row and column
    Pt = torch.cat([Ht_0[:, T], Ht_z[:, T, :n]], 1)[..., :nX]  # (B, 1+n, 1+n): V_T = l_T, which has no control
    Ws, frees = [], []
    for t in reversed(range(T)):
        PF = torch.cat([Pt[:, :, :1], torch.bmm(Pt[:, :, 1:], F[:, t])], -1)  # (B, 1+n, 1+n+m) = Pt Ft
        Qt = torch.cat([Ht_0[:, t] + PF[:, :1], Ht_z[:, t] + torch.bmm(F[:, t].mT, PF[:, 1:])], 1)  # Ht_t + Ft' Pt Ft
        Q_uu, Q_uX = Qt[:, nX:, nX:], Qt[:, nX:, :nX]
        W, free = stage(t, Q_uu, Q_uX)  # (B, m, 1+n)
        Pt = Qt[:, :nX, :nX] + torch.bmm(Qt[:, :nX, nX:], W) + torch.bmm(W.mT, Q_uX + torch.bmm(Q_uu, W))  # (B, 1+n, 1+n)
        Pt = (Pt + Pt.mT) * 0.5  # symmetric up to rounding; kept exactly symmetric
        Ws.append(W), frees.append(free)
    W, free = torch.stack(Ws[::-1], 1), torch.stack(frees[::-1], 1)  # (B, T, m, 1+n), (B, T, m)
    return W[..., 0], W[..., 1:], free, Pt[:, 1:, 0]

def lqr_backward_box(A, B, H, g, n, lo, hi, pd_eps):
    """iLQR's Riccati pass: k solves the box QP with Quu shifted to eigenvalues >= pd_eps (a descent direction); K
    solves the same Quu on the free controls, 0 on the clamped ones. lo, hi (B, T, m) bound du."""
    def stage(t, Q_uu, Q_uX):
        Q_uu = make_pd(Q_uu, pd_eps)
        k, free = box_qp(Q_uu, Q_uX[..., 0], lo[:, t], hi[:, t])
        K = solve_masked(Q_uu, torch.where(free[..., None], -Q_uX[..., 1:], 0.0), free)  # (B, m, n)
        return torch.cat([k[..., None], K], -1), free
    return riccati_backward(A, B, H, g, n, stage)

def lqr_backward_fixed(A, B, H, g, n, free):
    """The KKT backward's LQR: controls at a bound in the solution (free False, (B, T, m)) are held at du = 0,
    the others solve the exact Quu: [k K]_f = -Quu_ff^-1 [qu Qux]_f."""
    def stage(t, Q_uu, Q_uX):
        f = free[:, t]
        return solve_masked(Q_uu, torch.where(f[..., None], -Q_uX, 0.0), f), f
    return riccati_backward(A, B, H, g, n, stage)

@dataclass
class ILQRInfo:
    """What the solver reports per scenario."""
    converged: torch.Tensor  # (B,) bool: the last full LQR step was below tol
    step_norm: torch.Tensor  # (B,) norm of the last full LQR control step
    iters: torch.Tensor  # (B,) iterations run
    costs: torch.Tensor  # (B, I+1) true cost after each iteration (the first: at u_init)

def ilqr(cost_fn, dynamics, x_init, u_init, params, lo, hi, iters=5, tol=0.05, ls_steps=5, ls_decay=5.0, batched_params=False):
    """iLQR with box controls (App. C.2); differentiable by unrolling (`ILQR` gives the exact KKT gradient instead).

    x_init (B, n), u_init (B, T, m), lo/hi (m,) or (B, T, m) -> x (B, T+1, n), u (B, T, m), ILQRInfo. Each iteration
    expands the cost to second and the dynamics to first order, solves the box-constrained LQR and line-searches
    the step; a scenario whose full step is below tol has converged and stops moving. batched_params: every tensor
    in params is per scenario, (B, ...), and the iterations work on the scenarios still moving only."""
    (Bsz, T, m), n = u_init.shape, x_init.shape[-1]
    lo, hi = lo.expand(Bsz, T, m), hi.expand(Bsz, T, m)
    u = u_init.clamp(lo, hi)
    x = rollout(dynamics, x_init, u)
    cost, pd_eps = cost_fn(x, u, *params), 1e-6 * (1 if x.dtype == torch.float64 else 1e3)
    scales = ls_decay ** -torch.arange(ls_steps, dtype=x.dtype, device=x.device)  # (ls_steps,) 1, 1/5, ...
    active, n_iter = torch.ones(Bsz, dtype=torch.bool, device=x.device), torch.zeros(Bsz, dtype=torch.long, device=x.device)
    step_norm, costs = torch.full((Bsz,), math.inf, dtype=x.dtype, device=x.device), [cost]
    for _ in range(iters):
        # the scenarios this iteration works on (b of them): those still moving, or all of them (no gathers)
        if batched_params and not active.all():
            i = active.nonzero()[:, 0]  # (b,)
            take, put = (lambda t: t[i]), (lambda full, part: full.index_put((i,), part))  # noqa: E731
            pi = tuple(p[i] if torch.is_tensor(p) else p for p in params)
        else:
            take, put, pi = (lambda t: t), (lambda full, part: part), params  # noqa: E731
        xi, ui, ci, lo_i, hi_i, act = (take(t) for t in (x, u, cost, lo, hi, active))
        g, H = cost_expansion(cost_fn, xi, ui, pi)
        A, Bm = dynamics_jacobians(dynamics, xi, ui)
        k, K, _, _ = lqr_backward_box(A, Bm, H, g, n, lo_i - ui, hi_i - ui, pd_eps)
        x_new, u_new, c_new, accept, full_step = line_search(cost_fn, dynamics, xi, ui, ci, k, K, lo_i, hi_i, pi, scales, batched_params)
        accept = act & accept  # (b,)
        step_norm = put(step_norm, torch.where(act, full_step, take(step_norm)))
        n_iter = put(n_iter, take(n_iter) + act.long())
        sel = lambda new, old: torch.where(accept.reshape(-1, *[1] * (old.dim() - 1)), new, old)  # noqa: E731
        x, u, cost = put(x, sel(x_new, xi)), put(u, sel(u_new, ui)), put(cost, sel(c_new, ci))
        costs.append(cost)
        active = active & (step_norm >= tol)
        if not active.any():
            break
    return x, u, ILQRInfo(step_norm < tol, step_norm, n_iter, torch.stack(costs, 1))

def line_search(cost_fn, dynamics, x, u, cost, k, K, lo, hi, params, scales, batched_params):
    """Backtracking on the closed-loop rollouts u_t' = clamp(u_t + s k_t + K_t (x_t' - x_t)), x_{t+1}' = f(x_t', u_t'):
    s = 1 for every scenario, then 1/5, 1/25, ... at once (a dim S) where it raised the true cost (everywhere without
    batched_params); the largest scale that does not is taken. x (b, T+1, n), u, k, lo, hi (b, T, m), K (b, T, m, n),
    cost (b,) -> the new x, u, cost, whether a scale was accepted (b,), the norm of the full step (b,)."""
    eps = torch.finfo(x.dtype).eps
    no_rise = lambda c, c0: c <= c0 + 100 * eps * (1 + c0.abs())  # noqa: E731  up to rounding

    def rollouts(r, s):  # scenarios r, scales s (S,) -> x' (b, S, T+1, n), u' (b, S, T, m), cost (b, S)
        xr, ur, kr, Kr, lor, hir = (t[r] for t in (x, u, k, K, lo, hi))
        xs, us = [xr[:, None, 0].expand(-1, len(s), -1)], []  # (b, S, n)
        for t in range(u.shape[1]):
            du_fb = torch.bmm(xs[-1] - xr[:, None, t], Kr[:, t].mT)  # (b, S, m): K_t (x_t' - x_t), as row vectors
            us.append((ur[:, None, t] + s[:, None] * kr[:, None, t] + du_fb).clamp(lor[:, None, t], hir[:, None, t]))
            xs.append(dynamics(xs[-1], us[-1]))
        xs, us = torch.stack(xs, 2), torch.stack(us, 2)
        return xs, us, cost_fn(xs, us, *(p[r] if batched_params and torch.is_tensor(p) else p for p in params))

    every = torch.arange(len(x), device=x.device)
    x1, u1, c1 = rollouts(every, scales[:1])
    x_new, u_new, c_new, accept = x1[:, 0], u1[:, 0], c1[:, 0], no_rise(c1[:, 0], cost)
    r = (~accept).nonzero()[:, 0] if batched_params else every[: 0 if accept.all() else len(x)]
    if len(scales) > 1 and len(r):
        xs, us, cs = rollouts(r, scales[1:])
        ok = no_rise(cs, cost[r, None])  # (len(r), S-1)
        first = torch.where(ok, torch.arange(ok.shape[1], device=x.device), ok.shape[1]).min(-1).values
        use, pick = (first < ok.shape[1]) & ~accept[r], first.clamp(max=ok.shape[1] - 1)  # a smaller scale, where
        sel = lambda new, old: torch.where(use.reshape(-1, *[1] * (old.dim() - 1)), new, old)  # noqa: E731
        rows = torch.arange(len(r), device=x.device)
        x_new, u_new, c_new = (v.index_put((r,), sel(n[rows, pick], v[r])) for v, n in ((x_new, xs), (u_new, us), (c_new, cs)))
        accept = accept.index_put((r,), accept[r] | use)
    return x_new, u_new, c_new, accept, (u1[:, 0] - u).flatten(1).norm(dim=-1)

def kkt_backward(cost_fn, dynamics, x, u, params, free, grad_x, grad_u, exact=True):
    """Gradients of a loss on the solution (x, u) wrt x_init and params (Amos et al. 2018).

    At the solution the KKT conditions F(x, u, lambda; params) = 0 hold; by the implicit function theorem
    dloss/dparams = d' dF/dparams, where d solves the KKT system with the incoming gradient as right-hand side,
    an LQR problem:
        min_d 1/2 d' H d + (dloss/dz)' d   s.t.  dx_0 = 0, dx_{t+1} = A_t dx_t + B_t du_t, du_active = 0,
    H the Hessian of the Lagrangian L = C + sum_t lambda_{t+1}' (f(x_t, u_t) - x_{t+1}):
        H_t = d2 l_t + sum_i lambda_{t+1, i} d2 f_i(x_t, u_t)      (the dynamics' curvature)
    with costates from stationarity in x: lambda_T = dl_T/dx_T, lambda_t = dl_t/dx_t + A_t' lambda_{t+1}.
    mpc.pytorch and the authors' code drop the curvature (exact=False): exact on linear dynamics only. Then
        dloss/dparams = d/dparams [ sum_t dl_t/dz_t(params) . d_t ]     (d fixed)
        dloss/dx_init = p_0, the gradient at dx_0 = 0 of the LQR's value function.
    x (B, T+1, n), u (B, T, m), free (B, T, m) bool, grad_x, grad_u like x, u."""
    n, T = x.shape[-1], u.shape[1]
    g, H = cost_expansion(cost_fn, x, u, params)
    A, Bm = dynamics_jacobians(dynamics, x, u)
    if exact:
        lam = [g[:, T, :n]]  # costates lambda_T .. lambda_1
        for t in reversed(range(1, T)):
            lam.append(g[:, t, :n] + (A[:, t].transpose(-1, -2) @ lam[-1][..., None])[..., 0])
        lam = torch.stack(lam[::-1], 1)  # (B, T, n): lambda_1 .. lambda_T
        if hasattr(dynamics, "curvature"):  # closed form (Unicycle)
            Hf = dynamics.curvature(x[:, :-1], u, lam)  # (B, T, n+m, n+m)
        else:
            z = torch.cat([x[:, :-1], u], -1)  # (B, T, n+m)
            lam_f = lambda z: (lam * dynamics(z[..., :n], z[..., n:])).sum()  # noqa: E731
            Hf = _stagewise_jacobian(torch.func.grad(lam_f), z)
        H = H + torch.cat([Hf, torch.zeros_like(H[:, :1])], 1)
    rhs = torch.cat([grad_x, torch.cat([grad_u, torch.zeros_like(grad_u[:, :1])], 1)], -1)  # (B, T+1, n+m)
    k, K, _, p0 = lqr_backward_fixed(A, Bm, H, rhs, n, free)
    dx, du = [torch.zeros_like(x[:, 0])], []  # the LQR's solution d = (dx, du)
    for t in range(T):
        du.append(k[:, t] + (K[:, t] @ dx[-1][..., None])[..., 0])
        dx.append((A[:, t] @ dx[-1][..., None] + Bm[:, t] @ du[-1][..., None])[..., 0])
    dx, du = torch.stack(dx, 1), torch.stack(du, 1)
    needs, grads = [i for i, p in enumerate(params) if torch.is_tensor(p) and p.requires_grad], [None] * len(params)
    if needs:
        with torch.enable_grad():
            ps = [p.detach().requires_grad_(i in needs) if torch.is_tensor(p) else p for i, p in enumerate(params)]
            xg, ug = x.detach().requires_grad_(), u.detach().requires_grad_()
            gx, gu = torch.autograd.grad(cost_fn(xg, ug, *ps).sum(), (xg, ug), create_graph=True)
            inner = (gx * dx).sum() + (gu * du).sum()  # < dC/dz (params), d >
            for i, gi in zip(needs, torch.autograd.grad(inner, [ps[i] for i in needs], allow_unused=True)):
                grads[i] = gi
    return p0, grads

class ILQR(torch.autograd.Function):
    """iLQR with the KKT backward (use `ilqr_solve`); scenarios that did not converge pass no gradient (§3.1)."""
    @staticmethod
    def forward(ctx, cost_fn, dynamics, settings, exact, x_init, u_init, *params):
        with torch.no_grad():
            x, u, info = ilqr(cost_fn, dynamics, x_init, u_init, params, **settings)
        ctx.fns = (cost_fn, dynamics, exact)
        ctx.save_for_backward(x, u, info.converged, settings["lo"].expand_as(u), settings["hi"].expand_as(u), *params)
        ctx.mark_non_differentiable(info.converged)
        return x, u, info.converged

    @staticmethod
    def backward(ctx, grad_x, grad_u, _):
        cost_fn, dynamics, exact = ctx.fns
        x, u, converged, lo, hi, *params = ctx.saved_tensors
        free = ((u - lo).abs() > 1e-8) & ((hi - u).abs() > 1e-8)  # active bounds are held fixed
        keep = converged.to(x.dtype)[:, None, None]  # scenarios that did not converge pass no gradient
        p0, grads = kkt_backward(cost_fn, dynamics, x, u, params, free, grad_x * keep, grad_u * keep, exact)
        return (None, None, None, None, p0, None, *grads)

def ilqr_solve(cost_fn, dynamics, x_init, u_init, params, lo, hi, iters=5, tol=0.05, ls_steps=5, ls_decay=5.0, exact=True,
               batched_params=False):
    """The differentiable controller, eq. (4): x (B, T+1, n), u (B, T, m), converged (B,); arguments as `ilqr`'s."""
    lo, hi = check_solver_inputs(x_init, u_init, params, lo, hi, batched_params)
    settings = dict(lo=lo, hi=hi, iters=iters, tol=tol, ls_steps=ls_steps, ls_decay=ls_decay, batched_params=batched_params)
    return ILQR.apply(cost_fn, dynamics, settings, exact, x_init, u_init, *params)

# ===== 6. Predictor, eq. (1): a Trajectron++-style CVAE over controls (§3.1, Salzmann et al. 2020) ==================
# From 4 s of history of the predicted vehicle and its neighbours (the other agents and the ego), K = 25 futures,
# one per value of a discrete latent z:   p(y | x) = sum_k p(z = k | x) p(y | x, z = k).
# For each k a GRU emits per step a bivariate Gaussian over the controls u = (yaw rate w, accel a); the mean
# controls are integrated by the planner's unicycle and the control covariances pushed through its Jacobians (EKF):
# a K-component GMM over positions per step. Training maximises Trajectron++'s InfoVAE objective, q(z | x, y) from
# a bidirectional LSTM over the true future; all K values of z are enumerated, none sampled. The GRU's next input
# is the reparameterised sample of u_t in training (Trajectron++), the mean at evaluation; the modes are the
# integrated mean controls either way, weighted by q(z|x,y) in training (the authors' code), p(z|x) at evaluation.
# Where this differs from Trajectron++ (no map, no ego-future conditioning, ...): docs/method.md.

# ---- 6.1 Inputs: the 8-D state history, by backward differences ---------------------------

def backward_diff(x: torch.Tensor, first: torch.Tensor, dt: float) -> torch.Tensor:
    """d_t = (x_t - x_{t-1}) / dt for x (..., H, D); steps t <= first (...,) (the first observed step) copy
    d_{first+1}. Backward, never central: a central difference at t0 would read x_{t1}, the future."""
    H = x.shape[-2]
    d = torch.cat([torch.zeros_like(x[..., :1, :]), (x[..., 1:, :] - x[..., :-1, :]) / dt], -2)  # (..., H, D)
    idx = (first + 1).clamp(max=H - 1)[..., None, None]  # (..., 1, 1)
    d_first = torch.take_along_dim(d, idx, dim=-2)  # (..., 1, D)
    t = torch.arange(H, device=x.device)
    return torch.where((t <= first[..., None])[..., None], d_first, d)  # (..., H, D)

def state_features(hist: torch.Tensor, origin: torch.Tensor, first: torch.Tensor, cfg: Config) -> torch.Tensor:
    """Trajectron++'s 8-D state (position - origin, velocity, acceleration, heading, heading rate), scaled by
    30 m, 15 m/s, 4 m/s^2, pi, from (x, y, h, v) tracks: hist (..., H, 4), origin (..., 2) -> (..., H, 8)."""
    sp, sv, sa, sh = cfg.pred_scales
    pos = hist[..., :2]  # (..., H, 2)
    vel = backward_diff(pos, first, cfg.dt)  # (..., H, 2)
    acc = backward_diff(vel, (first + 1).clamp(max=hist.shape[-2] - 1), cfg.dt)  # (..., H, 2); vel starts at first+1
    dh = wrap_angle(hist[..., 1:, 2] - hist[..., :-1, 2])  # (..., H-1)
    h_unwrapped = torch.cat([hist[..., :1, 2], hist[..., :1, 2] + dh.cumsum(-1)], -1)  # (..., H)
    h_rate = backward_diff(h_unwrapped[..., None], first, cfg.dt)  # (..., H, 1)
    return torch.cat(
        [(pos - origin[..., None, :]) / sp, vel / sv, acc / sa, wrap_angle(hist[..., 2:3]) / sh, h_rate / sh], -1
    )  # (..., H, 8)

# ---- 6.2 The model ------------------------------------------------------------------------
@dataclass
class Prediction:
    """What the predictor hands to the planner, its loss and metrics; all differentiable in theta."""
    s0: torch.Tensor  # (B, 4) the agent's state at t0, the modes' start (see Predictor.initial_state)
    states: torch.Tensor  # (B, K, T, 4) mode trajectories t1..T: each mode's mean controls integrated
    controls: torch.Tensor  # (B, K, T, 2) mean controls (yaw rate, acceleration) of each mode
    pos_cov: torch.Tensor  # (B, K, T, 2, 2) position covariance of each GMM component
    log_p: torch.Tensor  # (B, K) log p(z|x) (logits clipped when a training step is given)
    log_q: torch.Tensor | None  # (B, K) log q(z|x,y), or None when the future was not used
    probs: torch.Tensor  # (B, K) the mode weights: q(z|x,y) with use_posterior, p(z|x) otherwise

    @property
    def means(self) -> torch.Tensor:  # (B, K, T, 2) the GMM components' means: the modes' positions
        return self.states[..., :2]

# The decoder's correlation rho = tanh(.) is kept this far inside (-1, 1), as Trajectron++: at |rho| = 1 the covariance
# is singular and the training sample's sqrt(1 - rho^2) has an infinite derivative (NaN gradients).
RHO_MARGIN = 1e-5

def bounded_correlation(pre_tanh: torch.Tensor) -> torch.Tensor:
    """tanh clamped to 1 - RHO_MARGIN, which float32 reaches at |pre_tanh| ~ 9; inside, the clamp is the identity."""
    return torch.tanh(pre_tanh).clamp(-1 + RHO_MARGIN, 1 - RHO_MARGIN)

def clip_logits(logits: torch.Tensor, step: int | None, cfg: Config) -> torch.Tensor:
    """Trajectron++'s z-logit clipping, in training only: zero-mean logits clamped to +-c(step)."""
    if step is None:
        return logits
    c0, c1, centre, width = cfg.pred_logit_clip
    c = c0 + (c1 - c0) / (1 + math.exp(-(step - centre) / width))  # c(step) = c0 + (c1 - c0) sigmoid((step - b) / w)
    return (logits - logits.mean(-1, keepdim=True)).clamp(-c, c)

class Predictor(nn.Module):
    """Trajectron++-style CVAE over unicycle controls. pred = predictor(batch, use_posterior, step)."""

    def __init__(self, cfg: Config):
        super().__init__()
        self.cfg = cfg
        E, Hd, K, Z = cfg.pred_enc_hidden, cfg.pred_dec_hidden, cfg.pred_modes, cfg.pred_latent_hidden
        X, n_hist = 2 * E, cfg.hist_len + 1  # x = (history encoding, neighbour context); steps of history
        self.hist_lstm = nn.LSTMCell(8, E)
        self.nbr_mlp = nn.Sequential(nn.Linear(n_hist * 8 + 2, E), nn.ReLU(), nn.Linear(E, E))
        self.att_q, self.att_k = nn.Linear(E, E, bias=False), nn.Linear(E, E, bias=False)
        self.fut_lstm = nn.LSTM(8, E, batch_first=True, bidirectional=True)
        self.p_z = nn.Sequential(nn.Linear(X, Z), nn.ReLU(), nn.Linear(Z, K))
        self.q_z = nn.Sequential(nn.Linear(X + 2 * E, Z), nn.ReLU(), nn.Linear(Z, K))
        # the decoder GRU: input cat(z, x, u_prev) (dec_in), h_0 = dec_h0(cat(z, x)); see decode
        self.dec_h0 = nn.Linear(K + X, Hd)
        self.dec_u0 = nn.Linear(8, 2)  # u_prev at t0 from the current state (Trajectron++'s state_action)
        self.dec_in = nn.Linear(K + X + 2, 3 * Hd)
        self.dec_hh = nn.Linear(Hd, 3 * Hd)
        self.dec_out = nn.Linear(Hd, 5)
        self.heading_fix = nn.Linear(X + 1, 1)  # Trajectron++'s Unicycle p0_model, see initial_state

    def encode(self, batch) -> tuple[torch.Tensor, torch.Tensor]:
        """x (B, 2E) = (history LSTM state, attention over neighbours), and the agent's features (B, H, 8)."""
        cfg = self.cfg
        hist, mask = batch.agent_hist, batch.agent_hist_mask  # (B, H, 4), (B, H)
        B, H = mask.shape
        first = (~mask).sum(-1)  # (B,) index of the first observed step (missing steps are a prefix)
        origin = hist[:, -1, :2]  # (B, 2) the agent's current position
        f = state_features(hist, origin, first, cfg)  # (B, H, 8)
        # history LSTM over the 9 steps; an unobserved step leaves its state untouched
        h = c = f.new_zeros(B, cfg.pred_enc_hidden)  # (B, E)
        for t in range(H):
            h_t, c_t = self.hist_lstm(f[:, t], (h, c))
            seen = mask[:, t, None]  # (B, 1)
            h, c = torch.where(seen, h_t, h), torch.where(seen, c_t, c)
        # neighbours = other agents + the ego, with (is pedestrian, is ego) flags
        nbr = torch.cat([batch.others_hist, batch.ego_hist[:, None]], 1)  # (B, A+1, H, 4)
        nbr_valid = torch.cat([batch.others_mask, mask.new_ones(B, 1)], 1)  # (B, A+1)
        is_ped = torch.cat([batch.others_is_ped, mask.new_zeros(B, 1)], 1)  # (B, A+1)
        is_ego = torch.cat([torch.zeros_like(batch.others_mask), mask.new_ones(B, 1)], 1)  # (B, A+1)
        near = nbr_valid & ((nbr[:, :, -1, :2] - origin[:, None]).norm(dim=-1) < cfg.pred_radius)  # (B, A+1)
        all_observed = torch.zeros_like(near, dtype=torch.long)  # (B, A+1) first observed step: 0
        nf = state_features(nbr, origin[:, None].expand(-1, nbr.shape[1], -1), all_observed, cfg)  # (B, A+1, H, 8)
        flags = torch.stack([is_ped, is_ego], -1).to(f.dtype)  # (B, A+1, 2)
        e = self.nbr_mlp(torch.cat([nf.flatten(-2), flags], -1))  # (B, A+1, E)
        # masked dot-product attention, query = the agent's history encoding
        scores = (self.att_k(e) @ self.att_q(h)[:, :, None])[..., 0] / math.sqrt(e.shape[-1])  # (B, A+1)
        alpha = torch.softmax(scores.masked_fill(~near, -1e9), -1) * near  # (B, A+1); all masked -> all zero
        ctx = (alpha[..., None] * e).sum(1)  # (B, E); zero for an agent without neighbours
        return torch.cat([h, ctx], -1), f  # (B, 2E), (B, H, 8)

    def encode_future(self, batch, x: torch.Tensor) -> torch.Tensor:
        """The q(z|x,y) logits (B, K): a bidirectional LSTM over the GT future's 8-D states."""
        cur_fut = torch.cat([batch.agent_hist[:, -1:], batch.agent_fut], 1)  # (B, 1+T, 4)
        zero = torch.zeros(len(cur_fut), dtype=torch.long, device=cur_fut.device)
        fy = state_features(cur_fut, batch.agent_hist[:, -1, :2], zero, self.cfg)[:, 1:]  # (B, T, 8)
        _, (h_n, _) = self.fut_lstm(fy)  # h_n (2, B, E): last state of each direction
        y_enc = torch.cat([h_n[0], h_n[1]], -1)  # (B, 2E)
        return self.q_z(torch.cat([x, y_enc], -1))  # (B, K)

    def decode(self, x: torch.Tensor, f0: torch.Tensor, shard=None) -> tuple[torch.Tensor, torch.Tensor]:
        """Per mode k and step t a Gaussian over controls: means (B, K, T, 2), covariances (B, K, T, 2, 2).

        All K values of z at once, as B*K rows, by a GRU (Cho et al. 2014) written out gate by gate:
            r = sigma(W_ir [z; x; u] + b_ir + W_hr h + b_hr),   z_gate likewise,
            n = tanh(W_in [z; x; u] + b_in + r * (W_hn h + b_hn)),   h' = (1 - z_gate) n + z_gate h.
        The (z, x) part of the input, W_z[:, k] + W_x x + b, is the same at every step (a column lookup plus a (B, 2E)
        matmul), computed once. shard: under DDP (train.Shard) the samples' noise is drawn for the global batch and
        this rank keeps its rows, so a scenario gets the same sample whichever rank holds it."""
        cfg = self.cfg
        K, T, Hd = cfg.pred_modes, cfg.horizon, cfg.pred_dec_hidden
        B, X = x.shape
        W, b = self.dec_in.weight, self.dec_in.bias  # (3Hd, K+X+2), (3Hd,); rows: gates r, z, n
        W_u, W_h, b_h = W[:, K + X :], self.dec_hh.weight, self.dec_hh.bias  # (3Hd, 2), (3Hd, Hd), (3Hd,)
        # W [one_hot(k); x] + b_i + b_h for r and z (plain sums); b_hn stays inside r * (W_hn h + b_hn)
        b_i = b + torch.cat([b_h[: 2 * Hd], b_h.new_zeros(Hd)])  # (3Hd,)
        gi_zx = ((x @ W[:, K : K + X].T + b_i)[:, None] + W[:, :K].T.contiguous()).reshape(B * K, 3 * Hd)
        W0 = self.dec_h0.weight  # (Hd, K+X): h_0 = dec_h0([one_hot(k); x]), by the same column lookup
        h = ((x @ W0[:, K:].T + self.dec_h0.bias)[:, None] + W0[:, :K].T.contiguous()).reshape(B * K, Hd)
        c_r, c_z, c_n = (c.contiguous() for c in gi_zx.split(Hd, 1))  # (B*K, Hd) each
        (W_hr, W_hz, W_hn), (W_ur, W_uz, W_un) = (w.T for w in W_h.split(Hd)), (w.T for w in W_u.split(Hd))
        b_hn = b_h[2 * Hd :]  # (Hd,)
        u_prev = self.dec_u0(f0).repeat_interleave(K, 0)  # (B*K, 2)
        outs = []
        for t in range(T):
            r = torch.addmm(c_r, h, W_hr).addmm_(u_prev, W_ur).sigmoid_()  # (B*K, Hd)
            z = torch.addmm(c_z, h, W_hz).addmm_(u_prev, W_uz).sigmoid_()  # (B*K, Hd)
            n = torch.addmm(c_n, u_prev, W_un).addcmul_(r, torch.addmm(b_hn, h, W_hn)).tanh_()  # (B*K, Hd)
            h = torch.lerp(n, h, z)  # (B*K, Hd); lerp(n, h, z) = n + z (h - n)
            out = self.dec_out(h)  # (B*K, 5) = (mu_w, mu_a, log s_w, log s_a, rho before tanh)
            outs.append(out)
            mu = out[:, :2]  # (B*K, 2)
            if self.training:  # u_t = mu + L eps, L = [[s_w, 0], [rho s_a, s_a sqrt(1 - rho^2)]] the Cholesky factor
                s_w, s_a = out[:, 2].exp(), out[:, 3].exp()  # (B*K,) each
                rho = bounded_correlation(out[:, 4])  # (B*K,) inside (-1, 1): the sqrt below stays finite
                eps = torch.randn_like(mu) if shard is None else shard.randn_rows(mu, K)  # (B*K, 2)
                e1, e2 = eps.unbind(1)  # (B*K,) each
                u_prev = mu + torch.stack([s_w * e1, s_a * (rho * e1 + torch.sqrt(1 - rho**2) * e2)], -1)  # (B*K, 2)
            else:
                u_prev = mu
        # Sigma_u = [[s_w^2, rho s_w s_a], [rho s_w s_a, s_a^2]]
        mu, log_s, rho = torch.stack(outs, 1).split([2, 2, 1], -1)  # (B*K, T, 2), (B*K, T, 2), (B*K, T, 1)
        s_w, s_a = log_s[..., 0].exp(), log_s[..., 1].exp()  # (B*K, T) each
        c = bounded_correlation(rho[..., 0]) * s_w * s_a  # (B*K, T); the same rho as the sample's
        cov = torch.stack([s_w**2, c, c, s_a**2], -1)  # (B*K, T, 4)
        return mu.reshape(B, K, T, 2), cov.reshape(B, K, T, 2, 2)

    def initial_state(self, batch, x: torch.Tensor) -> torch.Tensor:
        """s0 = (x0, y0, heading, v0) (B, 4): heading = velocity direction + a learned correction in (-1, 1) rad."""
        hist = batch.agent_hist  # (B, H, 4)
        vel = (hist[:, -1, :2] - hist[:, -2, :2]) / self.cfg.dt  # (B, 2) backward difference at t0
        moving = vel.norm(dim=-1) > self.cfg.pred_min_speed  # (B,)
        phi = torch.where(moving, torch.atan2(vel[:, 1], vel[:, 0]), hist[:, -1, 2])  # (B,)
        phi = phi + torch.tanh(self.heading_fix(torch.cat([x, phi[:, None]], -1)))[:, 0]  # (B,)
        return torch.stack([hist[:, -1, 0], hist[:, -1, 1], phi, hist[:, -1, 3]], -1)  # (B, 4); tracked speed

    def forward(self, batch, use_posterior: bool, step: int | None = None, shard=None) -> Prediction:
        """K mode trajectories, their probabilities and the position GMM. use_posterior: weigh the modes by q(z|x,y)
        (needs batch.agent_fut) instead of p(z|x). step: the training iteration, for clip_logits. shard: see decode."""
        cfg = self.cfg
        check_batch(batch, cfg, need_future=use_posterior)
        x, f = self.encode(batch)  # (B, 2E), (B, H, 8)
        log_p = torch.log_softmax(clip_logits(self.p_z(x), step, cfg), -1)  # (B, K)
        log_q = torch.log_softmax(clip_logits(self.encode_future(batch, x), step, cfg), -1) if use_posterior else None
        s0 = self.initial_state(batch, x)  # (B, 4)
        mu, cov_u = self.decode(x, f[:, -1], shard)  # (B, K, T, 2), (B, K, T, 2, 2)
        traj, pos_cov = integrate_modes(s0[:, None].expand(-1, cfg.pred_modes, -1), mu, cov_u, cfg)  # s0 first; (B, K, T, 2, 2)
        probs = (log_q if use_posterior else log_p).exp()  # (B, K)
        return Prediction(s0, traj[:, :, 1:], mu, pos_cov, log_p, log_q, probs)

def _covariance_unrolled(M: torch.Tensor, N: torch.Tensor, Su: torch.Tensor, cfg: Config) -> torch.Tensor:
    """The EKF's position covariances through the unicycle (..., T, 2, 2), plus pred_pos_std_min^2 I, from the position
    Jacobians M, N and the control covariances Su, each (2, 2, ..., T), matrix indices first. Step by step they are
        Sigma_0 = 0,   Sigma_{t+1} = A_t Sigma_t A_t^T + B_t Su_t B_t^T,   A = df/ds, B = df/du at the mean;
    here unrolled, all steps at once. The unicycle's A is a shear, A_t = [[I, M_t], [0, I]] (only the controls move h
    and v), and shears compose by adding their corners: A_t ... A_{r+1} = [[I, C_t - C_r], [0, I]], C_t = M_0 + ...
    + M_t. With B_r = [[N_r], [dt I]] the recursion unrolls to the position block
        P_{t+1} = sum_{r <= t} G_tr Su_r G_tr^T,   G_tr = N_r + dt (C_t - C_r) = D_r + dt C_t,   D_r = N_r - dt C_r
    (G_tr: how u_r moves (x, y)_{t+1}), and expanding the product makes each sum over r <= t a cumsum:
        P_{t+1} = cumsum(D Su D^T)_t + dt (cumsum(D Su)_t C_t^T + C_t cumsum(Su D^T)_t) + dt^2 C_t cumsum(Su)_t C_t^T."""
    def mm(X, Y):  # (2, 2, ...) x (2, 2, ...) -> (2, 2, ...)
        (x00, x01), (x10, x11) = (row.unbind(0) for row in X.unbind(0))
        (y00, y01), (y10, y11) = (row.unbind(0) for row in Y.unbind(0))
        return torch.stack([torch.stack([x00 * y00 + x01 * y10, x00 * y01 + x01 * y11]),
                            torch.stack([x10 * y00 + x11 * y10, x10 * y01 + x11 * y11])])
    tr = lambda X: X.transpose(0, 1)  # noqa: E731
    C = M.cumsum(-1)  # (2, 2, ..., T)
    D = N - cfg.dt * C  # (2, 2, ..., T)
    DSu = mm(D, Su)  # (2, 2, ..., T)
    P = (mm(DSu, tr(D)).cumsum(-1) + cfg.dt * (mm(DSu.cumsum(-1), tr(C)) + mm(C, mm(Su, tr(D)).cumsum(-1)))
         + cfg.dt**2 * mm(mm(C, Su.cumsum(-1)), tr(C)))  # (2, 2, ..., T)
    return P.movedim((0, 1), (-2, -1)) + cfg.pred_pos_std_min**2 * torch.eye(2, dtype=M.dtype, device=M.device)

def integrate_modes(s0: torch.Tensor, u: torch.Tensor, cov_u: torch.Tensor, cfg: Config) -> tuple[torch.Tensor, torch.Tensor]:
    """unicycle_rollout(s0, u) and the EKF covariances along it, all steps at once (headings, speeds and positions are
    cumsums): s0 (..., 4), u (..., T, 2), cov_u (..., T, 2, 2) -> states (..., T+1, 4), covariances (..., T, 2, 2)."""
    dt = cfg.dt
    w, a = u.unbind(-1)  # (..., T) each
    h = torch.cat([s0[..., 2:3], s0[..., 2:3] + (w * dt).cumsum(-1)], -1)  # (..., T+1): h_{t+1} = h_t + w_t dt
    v = torch.cat([s0[..., 3:4], s0[..., 3:4] + (a * dt).cumsum(-1)], -1)  # (..., T+1): v_{t+1} = v_t + a_t dt
    dx, dy, M, N = _position_jacobians(h[..., :-1], v[..., :-1], w, a, dt)  # (..., T), (..., T), (2, 2, ..., T) x2
    x = torch.cat([s0[..., 0:1], s0[..., 0:1] + dx.cumsum(-1)], -1)  # (..., T+1)
    y = torch.cat([s0[..., 1:2], s0[..., 1:2] + dy.cumsum(-1)], -1)  # (..., T+1)
    return torch.stack([x, y, h, v], -1), _covariance_unrolled(M, N, cov_u.movedim((-2, -1), (0, 1)).contiguous(), cfg)

# ---- 6.3 Loss: Trajectron++'s InfoVAE objective -------------------------------------------
def gaussian2_log_prob(y: torch.Tensor, mean: torch.Tensor, cov: torch.Tensor, min_var: float = 0.0) -> torch.Tensor:
    """log N(y; mean, cov) of 2-D Gaussians: y, mean (..., 2), cov (..., 2, 2) -> (...); cov is known to be positive
    semi-definite plus min_var I."""
    d = y - mean  # (..., 2)
    a, b, c = cov[..., 0, 0], cov[..., 0, 1], cov[..., 1, 1]
    # det(P0 + s I) = det P0 + s tr P0 + s^2 >= s (a + c) - s^2: for a long thin ellipse a c - b^2 cancels to 0 or
    # below in float32 (NaN log), and the bound restores the floor
    det = torch.maximum(a * c - b * b, min_var * (a + c) - min_var**2)  # (...)
    # d^T Sigma^-1 d with Sigma^-1 = [[c, -b], [-b, a]] / det
    maha = (c * d[..., 0] ** 2 - 2 * b * d[..., 0] * d[..., 1] + a * d[..., 1] ** 2) / det
    return -0.5 * maha - 0.5 * torch.log(det) - math.log(2 * math.pi)

def gmm_log_prob(pred: Prediction, y: torch.Tensor, log_w: torch.Tensor, min_var: float = 0.0) -> torch.Tensor:
    """log sum_k w_k N(y_t; mu_kt, Sigma_kt) per step: y (B, T, 2), log_w (B, K) -> (B, T)."""
    log_n = gaussian2_log_prob(y[:, None], pred.means, pred.pos_cov, min_var)  # (B, K, T)
    return torch.logsumexp(log_w[..., None] + log_n, 1)  # (B, T)

def pred_loss(pred: Prediction, batch, step: int, cfg: Config, shard=None) -> tuple[torch.Tensor, dict]:
    """L_pred per scenario (B,) (its mean is Trajectron++'s loss), and its parts (floats) for logging:
        L = -(LL - beta KL + I_p)   (InfoVAE variant, Zhao et al. 2019, as in Trajectron++)
        LL   = sum_t min(log sum_k q_k N(y_t; mu_kt, Sigma_kt), 6)
        KL   = max(mean_batch KL(q || p), 0.07)   free bits: below 0.07 the term is a constant
        I_p  = H(mean_batch p) - mean_batch H(p)   mutual information of z and x under p
    shard: under DDP (train.Shard) the batch of these means is the global one, and beta anneals with the step."""
    if pred.log_q is None:
        raise ValueError("pred: pred_loss needs the posterior, call the predictor with use_posterior=True")
    y = batch.agent_fut[..., :2]  # (B, T, 2)
    ll = gmm_log_prob(pred, y, pred.log_q, cfg.pred_pos_std_min**2).clamp(max=cfg.pred_log_p_max).sum(-1)  # (B,)
    batch_mean = (lambda x: x.mean(0)) if shard is None else shard.mean  # noqa: E731  over the (global) batch
    q = pred.log_q.exp()  # (B, K)
    kl = (q * (pred.log_q - pred.log_p)).sum(-1)  # (B,)
    kl_fb = torch.where(batch_mean(kl) > cfg.pred_kl_min, kl, torch.full_like(kl, cfg.pred_kl_min))  # (B,)
    p = pred.log_p.exp()  # (B, K)
    p_bar = batch_mean(p)  # (K,)
    mi = -(p_bar * torch.log(p_bar)).sum() + batch_mean((p * pred.log_p).sum(-1))  # scalar
    b0, centre, width = cfg.pred_beta
    beta = b0 / (1 + math.exp(-(step - centre) / width))  # beta(step) = b0 sigmoid((step - b1) / b2), ~0 -> 100
    loss = -(ll - beta * kl_fb + mi)  # (B,)
    parts = {"loss": loss.mean().item(), "ll": ll.mean().item(), "kl": kl.mean().item(), "mi": mi.item(), "beta": beta}
    return loss, parts

# ===== 7. The stack: predict -> plan -> control, §3.2 ===============================================================
#   L = a1 L_pred + a2 L_plan + a3 L_ctr
#   RL: L_ctr = hindsight cost C_H(s_ctr, u_ctr) (eq. 3 with GT futures, fixed weights), planner target argmin_n C_H
#   IL: L_ctr = sum_t ||s_ctr,t - s_gt,t||^2, planner target n* = the candidate closest to the GT

SETTINGS = ("rl", "il")  # the planner target and L_ctr: hindsight cost (RL) or imitation (IL), §3.2

@dataclass
class StackOutput:
    """Per-scenario results of one pass through the stack (all (B,) unless noted)."""
    l_pred: torch.Tensor  # InfoVAE loss (0 without a learned predictor)
    l_plan: torch.Tensor  # cross-entropy of the relaxed planner with the target candidate
    l_ctr: torch.Tensor  # RL: hindsight cost of the controller's trajectory; IL: its squared error to the GT
    hindsight: torch.Tensor  # hindsight cost of the final trajectory
    mse: torch.Tensor  # sum_t ||s_t - s_gt,t||^2 of the final trajectory
    plannable: torch.Tensor  # bool: at least 2 planner candidates
    converged: torch.Tensor  # bool: iLQR converged
    x: torch.Tensor  # (B, T+1, 4) the final ego trajectory
    u: torch.Tensor  # (B, T, 2) its controls
    cands: Candidates | None = None
    cand_cost: torch.Tensor | None = None  # (B, N)
    pred: object = None  # the predictor's output

def upsample(now: torch.Tensor, fut: torch.Tensor, substeps: int) -> torch.Tensor:
    """A future on a clock `substeps` times finer, by linear interpolation from the present: now (..., D) at t0, fut
    (..., T, D) at t1..T -> (..., T * substeps, D)."""
    if substeps == 1:
        return fut
    knots = torch.cat([now[..., None, :], fut], -2)  # (..., T+1, D)
    a, b = knots[..., :-1, None, :], knots[..., 1:, None, :]  # (..., T, 1, D)
    f = torch.arange(1, substeps + 1, dtype=fut.dtype, device=fut.device)[:, None] / substeps  # (substeps, 1) the fractions of a step
    return (a + (b - a) * f).flatten(-3, -2)

def planner_substeps(cfg: Config, plan_dt) -> int:
    """How many planner/controller steps of plan_dt make one prediction step cfg.dt (1 for plan_dt None)."""
    if plan_dt is None:
        return 1
    substeps = round(cfg.dt / plan_dt) if plan_dt > 0 else 0
    if substeps < 1 or abs(substeps * plan_dt - cfg.dt) > 1e-9:
        raise ValueError(f"plan_dt: must divide the prediction step dt = {cfg.dt} s into whole steps, got {plan_dt}")
    return substeps

def cost_contexts(batch, preds, probs, pred_mask, plan_others=True, substeps=1, goal=None):
    """The cost's view of a batch with the given predictions (already on the planner's clock, substeps per step), and
    in hindsight (the agent's GT future). plan_others=False: the others count in hindsight only (App. D.3)."""
    others_mask = batch.others_mask.to(preds.dtype)
    others = upsample(batch.others_hist[:, :, -1, :2], batch.others_fut[..., :2], substeps)  # (B, A, T, 2)
    goal = batch.goal if goal is None else goal
    common = dict(others=others, goal=goal[:, :2], lanes=batch.lanes, lanes_mask=batch.lanes_mask)
    ctx = CostContext(preds, probs, pred_mask, others_mask=others_mask * plan_others, **common)
    ones = torch.ones_like(pred_mask)
    agent = upsample(batch.agent_hist[:, -1, :2], batch.agent_fut[..., :2], substeps)  # (B, T, 2)
    hctx = CostContext(agent[:, None], ones[:, None], ones, others_mask=others_mask, **common)
    return ctx, hctx

def scene_plan(batch, cfg: Config, plan_dt=None) -> ScenePlan:
    """A batch's ScenePlan on the planner's clock: the goal (Config.goal), the candidates, their prediction-free terms."""
    sub = planner_substeps(cfg, plan_dt)
    s0 = batch.ego_hist[:, -1]  # (B, 4)
    goal = batch.goal if cfg.goal == "logged" else route_goal(s0, batch.lanes, batch.lanes_mask, cfg)  # (B, 4)
    pcfg = cfg if sub == 1 else dataclasses.replace(cfg, dt=cfg.dt / sub, horizon=cfg.horizon * sub)
    cands = plan_candidates(s0, goal, batch.lanes, batch.lanes_mask, pcfg)
    terms = scene_terms(cands.x[..., 1:, :2], cands.x[..., 1:, 2], cands.u, goal[:, :2], batch.lanes, batch.lanes_mask)
    return ScenePlan(goal, cands, terms)

def run_stack(batch, model, method, cfg: Config, setting: str = "rl", step=None, train=False,
              w=None, planner=True, controller=True, plan_others=True, pred_target=None, plan_dt=None,
              shard=None, scene: ScenePlan | None = None) -> StackOutput:
    """One pass of the stack over a batch of Scenarios.

    setting: 'rl' or 'il' (which L_ctr and planner target). train: the modes weighted by q(z|x,y) and the schedules at
    `step` (as the authors' code); otherwise p(z|x). w: cost weights (5,), default the hand-tuned ones.
    planner=False: iLQR starts from zero controls; controller=False: the plan is final; plan_others=False: planner and
    controller ignore the others (ablations). pred_target: what the predictor is trained towards (Table 2 shifts it).
    plan_dt: a finer planner and controller step (ablation: 0.1 s); the per-step cost terms (all but the goal's) are
    then scaled by 1/substeps, so that eq. (3) sums the same costs per second. shard: see Predictor.decode.
    scene: the batch's scene_plan, if already computed."""
    check_setting(setting)
    check_batch(batch, cfg, need_future=train, stack=True)
    sub = planner_substeps(cfg, plan_dt)
    B, T, dt = len(batch), cfg.horizon * sub, cfg.dt / sub  # the planner's and the controller's clock
    dtype, device = batch.ego_hist.dtype, batch.ego_hist.device  # every tensor made here: the batch's dtype and device
    like = dict(dtype=dtype, device=device)
    s0 = batch.ego_hist[:, -1]  # (B, 4)
    per_step = torch.tensor([1 / sub, 1, 1 / sub, 1 / sub, 1 / sub], **like)  # the goal term is terminal
    w_fixed = cost_weights(cfg, dtype, device) * per_step
    w = w_fixed if w is None else w * per_step
    # --- predict, eq. (1) ---
    pred, l_pred = None, torch.zeros(B, **like)
    if method.predictor == "learned":
        pred = model(batch, use_posterior=train, step=step, shard=shard)
        now = batch.agent_hist[:, None, -1, :2].expand(B, pred.probs.shape[1], 2)  # (B, K, 2) every mode starts here
        preds = upsample(now, pred.states[..., :2], sub).contiguous()
        probs, pred_mask = pred.probs, torch.ones(B, **like)  # (B, K) q(z|x,y) in training, p(z|x) otherwise; (B,)
        if train and (method.train_plan_weights or cfg.train_plan_weights) == "prior":
            probs = pred.log_p.exp()  # the planner sees what it will see at evaluation, and its losses reach p(z|x)
        if train:
            target = batch if pred_target is None else dataclasses.replace(batch, agent_fut=pred_target)
            l_pred, _ = pred_loss(pred, target, step, cfg, shard)
    elif method.predictor == "gt":
        preds = upsample(batch.agent_hist[:, -1, :2], batch.agent_fut[..., :2], sub)[:, None]  # (B, 1, T, 2)
        probs, pred_mask = torch.ones(B, 1, **like), torch.ones(B, **like)
    else:
        preds, probs, pred_mask = torch.zeros(B, 1, T, 2, **like), torch.ones(B, 1, **like), torch.zeros(B, **like)
    # --- plan, eq. (2): costs of all candidates with the predictions; the plan is their argmin ---
    scene = scene_plan(batch, cfg, plan_dt) if scene is None else scene  # goal, candidates: the scene's alone
    ctx, hctx = cost_contexts(batch, preds, probs, pred_mask, plan_others, sub, scene.goal)  # goal (B, 4)
    gt_pos = upsample(s0[:, :2], batch.ego_fut[..., :2], sub)  # (B, T, 2)
    pcfg = cfg if sub == 1 else dataclasses.replace(cfg, dt=dt, horizon=T)
    cands, cost, best, plannable, terms = plan(s0, ctx, scene.goal, w, pcfg, scene)  # (B, N) costs, (B,) plan
    # the planner's target n*: RL, the candidate cheapest in hindsight (the agent's GT future in the collision
    # term, the other terms as planned); IL, the candidate closest to the GT ego trajectory
    if setting == "rl":
        h_terms = torch.cat([collision_term(cands.x[..., 1:, :2], hctx, cfg.rbf_var)[..., None], terms[..., 1:]], -1)
        target = masked_argmin((h_terms.detach() * w_fixed).sum(-1), cands.valid)
    else:
        target = masked_argmin(((cands.x[..., 1:, :2] - gt_pos[:, None]) ** 2).sum(-1).mean(-1), cands.valid)
    valid = cands.valid | ~plannable[:, None]  # keep the softmax finite where nothing can be planned
    l_plan = torch.where(plannable, plan_loss(cost, valid, target, cfg.beta), 0.0)
    idx = torch.arange(B, device=device)
    # --- control, eq. (4): iLQR from the plan, gradients by the KKT backward ---
    converged = torch.ones(B, dtype=torch.bool, device=device)
    if controller:
        u_init = cands.u[idx, best] if planner else torch.zeros(B, T, 2, **like)
        # every parameter per scenario (w (5,) too, as a view), so that the solver can set converged scenarios aside
        params = (w.expand(B, 5), *ctx.tensors())
        x, u, converged = ilqr_solve(StackCost(cfg.rbf_var), Unicycle(dt), s0, u_init, params, cfg.u_lower, cfg.u_upper,
                                     cfg.ilqr_iters, cfg.ilqr_tol, cfg.line_search_steps, cfg.line_search_decay, batched_params=True)
    else:
        x, u = cands.x[idx, best], cands.u[idx, best]
    hindsight = total_cost(x, u, hctx, w_fixed, cfg.rbf_var)  # (B,)
    mse = ((x[:, sub::sub, :2] - batch.ego_fut[..., :2]) ** 2).sum((-1, -2))  # (B,) at the logged steps
    l_ctr = hindsight if setting == "rl" else mse
    return StackOutput(l_pred, l_plan, l_ctr, hindsight, mse, plannable, converged, x, u, cands, cost, pred)

# ===== 8. Input checks: what Config and the public entry points refuse, naming the argument ========================
# The entry points a user calls (unicycle_step, total_cost, plan_candidates, plan, ilqr_solve, Predictor.forward,
# run_stack) call one of these on their input; the math inside them is not checked again.

def check_config(cfg: Config) -> None:
    """Refuse, naming the field, any value out of its range (inclusive; every number has one): no NaN or petabyte later."""
    ranges = dict(dt=(1e-3, 10), hist_len=(1, 100), horizon=(1, 100), w_coll=(0, 1e6), w_goal=(0, 1e6), w_lat=(0, 1e6),
                  w_head=(0, 1e6), w_ctrl=(0, 1e6), rbf_var=(1e-6, 1e6), goal_lane_dist=(1e-6, 1e4), goal_lane_heading=(1e-6, 7),
                  max_goal_lanes=(1, 64), beta=(1e-6, 1e6), feas_lat_accel=(1e-6, 1e4), feas_yaw_per_speed=(1e-6, 1e4),
                  ilqr_iters=(1, 1000), ilqr_tol=(1e-12, 1e6), line_search_steps=(1, 60), line_search_decay=(1.01, 1e6),
                  pred_modes=(1, 1024), pred_enc_hidden=(1, 4096), pred_latent_hidden=(1, 4096), pred_dec_hidden=(1, 4096),
                  pred_radius=(1e-6, 1e4), pred_min_speed=(0, 1e3), pred_pos_std_min=(0, 1e3), pred_log_p_max=(-1e6, 1e6),
                  pred_kl_min=(0, 1e6), pred_nll_min=(-1e6, 1e6), pred_lr_decay=(1e-9, 1), pred_grad_clip=(1e-12, 1e6),
                  lr=(1e-12, 1e3), batch_size=(1, 100_000))
    sizes = dict(u_lower=2, u_upper=2, pred_scales=4, pred_beta=3, pred_logit_clip=4, alpha_rl=3, alpha_il=3)
    choices = dict(train_plan_weights=("posterior", "prior"), goal=("logged", "route"))
    finite = lambda x: isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)  # noqa: E731
    for f in dataclasses.fields(cfg):
        v, n, (lo, hi) = getattr(cfg, f.name), sizes.get(f.name), ranges.get(f.name, (None, None))
        if f.name in choices:
            bad = v not in choices[f.name] and f"one of {choices[f.name]}"
        elif f.type == "tuple":
            bad = ((not isinstance(v, tuple) or not v or len(v) != (n or len(v)) or not all(map(finite, v)))
                   and f"a tuple of {n or 'one or more'} finite numbers")
        else:
            whole = f.type == "int"
            bad = ((not finite(v) or whole and not isinstance(v, int) or not lo <= v <= hi)
                   and f"{'a whole' if whole else 'a finite'} number from {lo:g} to {hi:g}")
        if bad:
            raise ValueError(f"Config.{f.name}: must be {bad}, got {v!r}")
    if any(lo >= hi for lo, hi in zip(cfg.u_lower, cfg.u_upper)):
        raise ValueError(f"Config.u_lower: must be below u_upper, got {cfg.u_lower} and {cfg.u_upper}")
    if any(x <= 0 for x in cfg.pred_scales) or any(x < 0 for x in cfg.alpha_rl + cfg.alpha_il):
        raise ValueError("Config.pred_scales must be > 0 and Config.alpha_rl, alpha_il >= 0")

def check_setting(setting) -> str:
    if setting not in SETTINGS:
        raise ValueError(f"setting: expected 'rl' (hindsight cost) or 'il' (imitation), got {setting!r}")
    return setting

def check_tensor(name: str, t, shape=None, dtype=None):
    """ValueError naming `name` unless t is a tensor of the given shape (None: any size there) and dtype, and finite."""
    if not torch.is_tensor(t):
        raise ValueError(f"{name}: expected a tensor, got {type(t).__name__}")
    tail = shape is not None and shape[0] is ...  # (..., n): any leading dims
    dims = t.shape[t.dim() - len(shape) + 1:] if tail else t.shape
    if shape is not None and (t.dim() < len(shape) - tail or len(dims) != len(shape) - tail
                              or any(s is not None and s != d for s, d in zip(shape[tail:], dims))):
        want = "(" + ", ".join("..." if s is ... else "*" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"{name}: expected shape {want}, got {tuple(t.shape)}")
    if dtype is not None and t.dtype != dtype:
        raise ValueError(f"{name}: expected dtype {dtype}, got {t.dtype}")
    try:
        bad = t.is_floating_point() and not torch.isfinite(t).all()
    except RuntimeError:  # inside torch.func's transforms a value cannot steer Python: checked outside them
        bad = False
    if bad:
        raise ValueError(f"{name}: contains NaN or inf")
    return t

def check_positive(name: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        raise ValueError(f"{name}: expected a finite number > 0, got {value!r}")
    return value

def check_plan_inputs(s0, goal, lanes, lanes_mask, goal_name="goal") -> int:
    """The planner's inputs; returns the batch size B."""
    B = check_tensor("s0", s0, (None, 4)).shape[0]
    if B == 0:
        raise ValueError("s0: no scenarios (a batch of size 0)")
    check_tensor(goal_name, goal, (B, 4), s0.dtype)
    check_tensor("lanes", lanes, (B, None, None, 3), s0.dtype)
    check_tensor("lanes_mask", lanes_mask, (B, *lanes.shape[1:3]), torch.bool)
    return B

def check_cost_inputs(x, u, ctx: CostContext, w, rbf_var) -> None:
    check_tensor("x", x)
    if x.dim() < 3 or x.shape[-1] != 4 or x.shape[-2] < 2:
        raise ValueError(f"x: expected states (B, ..., T+1, 4) with T >= 1, got {tuple(x.shape)}")
    B, T = x.shape[0], x.shape[-2] - 1
    check_tensor("u", u, (B, *x.shape[1:-2], T, 2), x.dtype)
    if tuple(check_tensor("w", w, dtype=x.dtype).shape) not in ((5,), (B, 5)):
        raise ValueError(f"w: expected the 5 weights of eq. (3), shape (5,) or ({B}, 5), got {tuple(w.shape)}")
    for name, shape in (("preds", (B, None, T, 2)), ("probs", (B, ctx.preds.shape[1])), ("others", (B, None, T, 2)),
                        ("goal", (B, 2)), ("lanes", (B, None, None, 3))):
        check_tensor(f"ctx.{name}", getattr(ctx, name), shape, x.dtype)
    check_positive("rbf_var", rbf_var)

def check_solver_inputs(x_init, u_init, params, lo, hi, batched_params):
    """The controller's inputs; returns the bounds lo, hi as tensors."""
    B = check_tensor("x_init", x_init, (None, None)).shape[0]
    check_tensor("u_init", u_init, (B, None, None), x_init.dtype)
    lo, hi = (check_tensor(n, torch.as_tensor(b, dtype=x_init.dtype, device=x_init.device)) for n, b in (("lo", lo), ("hi", hi)))
    if (lo > hi).any():
        raise ValueError("lo: a lower control bound is above its upper bound")
    for i, p in enumerate(params):
        if torch.is_tensor(p) and p.is_floating_point():
            check_tensor(f"params[{i}]", p, dtype=x_init.dtype)
        if batched_params and torch.is_tensor(p) and (p.dim() == 0 or p.shape[0] != B):
            raise ValueError(f"params[{i}]: batched_params needs per-scenario tensors ({B}, ...), got {tuple(p.shape)}")
    return lo, hi

def check_batch(batch, cfg: Config, need_future: bool, stack: bool = False) -> None:
    """A batch of Scenarios: not empty, the history and future lengths of cfg, finite. need_future: the agent's GT
    future is read (training); stack: the ego's future, the other agents, the goal and the lanes too."""
    if len(batch) == 0:
        raise ValueError("batch: no scenarios (a batch of size 0)")
    H, T = cfg.hist_len + 1, cfg.horizon
    expect = dict(agent_hist=H, ego_hist=H, others_hist=H, **({"agent_fut": T} if need_future or stack else {}),
                  **(dict(ego_fut=T, others_fut=T) if stack else {}))
    for name, steps in expect.items():
        x = getattr(batch, name)
        if tuple(x.shape[-2:]) != (steps, 4):
            raise ValueError(f"{name}: expected shape (..., {steps}, 4), got {tuple(x.shape)}")
        if not torch.isfinite(x).all():
            raise ValueError(f"{name} contains NaN or inf")
    if stack:
        check_tensor("goal", batch.goal, (len(batch), 4), batch.ego_hist.dtype)
        check_tensor("lanes", batch.lanes, (len(batch), None, None, 3), batch.ego_hist.dtype)
    m = batch.agent_hist_mask
    if tuple(m.shape) != tuple(batch.agent_hist.shape[:2]):
        raise ValueError(f"agent_hist_mask: expected shape {tuple(batch.agent_hist.shape[:2])}, got {tuple(m.shape)}")
    if not m[:, -1].all() or (m[:, 1:].int() < m[:, :-1].int()).any():
        raise ValueError("agent_hist_mask: the current step must be observed and missing steps must be the earliest")

if __name__ == "__main__":
    import train  # the method ends here; --quick (training, evaluation) is train.py's
    train.main()
