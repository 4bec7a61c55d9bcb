"""Training and evaluation of the DiffStack method (diffstack.py): one training loop for every
method of the paper (and for the cost weights), and the metrics. The lab hands it what a user runs
but need not read: data checks (lab/checks.py), many processes (lab/ddp.py); `python diffstack.py
--quick` and `--pretrain` are lab/quick.py's, the tables experiments.py's.

    1. Metrics          ADE/FDE, NLL, constant velocity; evaluation of a predictor
    2. Methods          Table 1's rows, their loss weights, the learned cost weights (App. A.2),
                        weighted L_pred (§4.1)
    3. Training         train_stack (the paper's loop), train_predictor; evaluation of the stack
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass

import torch
import torch.nn as nn
from torch.optim.lr_scheduler import ExponentialLR

from lab.checks import check_batch  # hand-over: data checked where it enters a run
from lab.ddp import Shard, wrap  # hand-over: training on many processes (DDP)

# hand-over: the lab's run machinery (files written whole, locks, provenance, workers)
from data_synth import (
    BEHAVIOURS,  # the synthetic predicted agent's manoeuvres (evaluation's breakdown by behaviour)
)
from diffstack import (
    Candidates,
    Config,
    Prediction,
    Predictor,
    ScenePlan,
    check_setting,
    collision_term,
    cost_contexts,
    cost_weights,
    gmm_log_prob,
    pred_loss,
    run_stack,
    scene_plan,
    stack_loss,
)

# --------------------------------------------------------------------------------------------
# 1. Metrics, and the constant-velocity baseline
# --------------------------------------------------------------------------------------------


def constant_velocity(batch, cfg: Config) -> torch.Tensor:
    """Positions t1..T (B, T, 2) keeping the tracked speed and heading of t0."""
    s = batch.agent_hist[:, -1]  # (B, 4)
    tt = cfg.dt * torch.arange(1, cfg.horizon + 1, dtype=s.dtype, device=s.device)  # (T,)
    v = torch.stack([s[:, 3] * torch.cos(s[:, 2]), s[:, 3] * torch.sin(s[:, 2])], -1)  # (B, 2)
    return s[:, None, :2] + tt[None, :, None] * v[:, None]  # (B, T, 2)


def prediction_metrics(pred: Prediction, batch, cfg: Config) -> dict[str, torch.Tensor]:
    """Per-scenario metrics (B,): ADE/FDE of the most likely mode (argmax of pred.probs),
    min-ADE/min-FDE over modes, GMM NLL = -mean_t max(log p(y_t), -20) with weights pred.probs; and
    constant velocity's ADE/FDE. Call with an eval-mode prediction and use_posterior=False for the
    paper's metrics (argmax p, mean controls)."""
    y = batch.agent_fut[..., :2]  # (B, T, 2)
    err = (pred.means - y[:, None]).norm(dim=-1)  # (B, K, T)
    best = pred.probs.argmax(-1)  # (B,)
    err_ml = err[torch.arange(len(best), device=best.device), best]  # (B, T)
    log_p = gmm_log_prob(pred, y, pred.probs.log(), cfg.pred_pos_std_min**2)  # (B, T)
    nll = -log_p.clamp(min=cfg.pred_nll_min).mean(-1)  # (B,)
    err_cv = (constant_velocity(batch, cfg) - y).norm(dim=-1)  # (B, T)
    return {
        "ade": err_ml.mean(-1),
        "fde": err_ml[:, -1],
        "min_ade": err.mean(-1).min(-1).values,
        "min_fde": err[..., -1].min(-1).values,
        "nll": nll,
        "cv_ade": err_cv.mean(-1),
        "cv_fde": err_cv[:, -1],
    }


@torch.no_grad()
def evaluate_predictor(
    model: Predictor, data, cfg: Config, batch_size: int = 1024
) -> dict[str, float]:
    """Mean metrics over a Scenarios set, in eval mode (prior weights, mean controls), constant
    velocity beside.

    cv_nll is constant velocity made a distribution: an isotropic Gaussian per step whose variance
    is fit to this very set (sigma_t^2 = mean squared error / 2), an oracle calibration that favours
    the baseline.
    """
    was_training = model.training
    model.eval()
    sums = {}
    cv_sq = 0.0
    n = 0
    for i in range(0, len(data), batch_size):
        batch = data[i : i + batch_size]
        check_batch(batch, cfg, need_future=True)
        m = prediction_metrics(model(batch, use_posterior=False), batch, cfg)
        for k, v in m.items():
            sums[k] = sums.get(k, 0.0) + v.sum().item()
        cv_err = constant_velocity(batch, cfg) - batch.agent_fut[..., :2]  # (B, T, 2)
        cv_sq = cv_sq + (cv_err**2).sum((0, 2))  # (T,)
        n += len(batch)
    model.train(was_training)
    out = {k: v / n for k, v in sums.items()}
    var = cv_sq / (2 * n)  # (T,) ML variance per axis
    # -mean_t log N(e_t; 0, var_t I) = mean_t [log(2 pi var_t) + E e^2 / (2 var_t)]
    #                                = mean_t [log(2 pi var_t) + 1]
    out["cv_nll"] = (torch.log(2 * math.pi * var) + 1).mean().item()  # (no per-step clamp here)
    return out


# --------------------------------------------------------------------------------------------
# 2. The methods of Table 1, their loss weights and the planning-aware weights of L_pred
#    (§4.1, App. A.2)
# --------------------------------------------------------------------------------------------


@dataclass
class Method:
    """A row of Table 1: where predictions come from and how the predictor is trained (run_stack
    reads `predictor` and `train_plan_weights`)."""

    name: str
    # 'learned', 'gt' (oracle: the GT future) or 'none' (the predicted agent is ignored)
    predictor: str = "learned"
    # which of (L_pred, L_plan, L_ctr) train the predictor, times the setting's alphas
    losses: tuple = (1, 0, 0)
    # L_pred's per-scenario weights: 'standard', 'distance', 'grad_cost' (§4.1), a callable
    weighting: str = "standard"
    train_plan_weights: str | None = None  # as Config.train_plan_weights; None: the Config's

    def __post_init__(self):
        if self.predictor not in PREDICTORS:
            raise ValueError(
                f"Method.predictor: expected one of {PREDICTORS}, got {self.predictor!r}"
            )
        if (
            not isinstance(self.losses, tuple)
            or len(self.losses) != 3
            or not all(
                isinstance(a, (int, float)) and math.isfinite(a) and a >= 0 for a in self.losses
            )
        ):
            raise ValueError(
                "Method.losses: expected 3 finite numbers >= 0 (L_pred, L_plan, L_ctr), got "
                f"{self.losses!r}"
            )
        if not callable(self.weighting) and self.weighting not in WEIGHTINGS:
            raise ValueError(
                f"Method.weighting: expected one of {tuple(WEIGHTINGS)} or a callable, got "
                f"{self.weighting!r}"
            )
        if self.train_plan_weights not in (None, "posterior", "prior"):
            raise ValueError(
                "Method.train_plan_weights: expected None, 'posterior' or 'prior', got "
                f"{self.train_plan_weights!r}"
            )


PREDICTORS = ("learned", "gt", "none")


def alphas(method: Method, setting: str, cfg: Config):
    """The loss weights (a1, a2, a3) a method trains with: the setting's defaults, switched by the
    method."""
    base = cfg.alpha_rl if check_setting(setting) == "rl" else cfg.alpha_il
    return tuple(a * on for a, on in zip(base, method.losses))


def grad_cost_weights(batch, cfg: Config) -> torch.Tensor:
    """Grad-cost weighting (§4.1, Ivanovic et al. 2021): ||dC/d(agent GT future)|| for the expert's
    (GT) ego trajectory, i.e. how much the planning cost reacts to this agent. (B,)"""
    fut = batch.agent_fut[..., :2].detach().clone().requires_grad_(True)  # (B, T, 2)
    B = len(batch)
    ones = torch.ones(B, dtype=fut.dtype, device=fut.device)
    ctx, _ = cost_contexts(batch, fut[:, None], ones[:, None], ones)
    ego = batch.ego_fut[..., :2]  # (B, T, 2) the expert's positions t1..T
    with torch.enable_grad():
        (g,) = torch.autograd.grad(collision_term(ego, ctx, cfg.rbf_var).sum() * cfg.w_coll, fut)
    return g.flatten(1).norm(dim=-1)


def offset_targets(batch, offset: float) -> torch.Tensor:
    """The agent's GT future shifted `offset` metres to its left (its heading at t0): Table 2's
    interface error."""
    h = batch.agent_hist[:, -1, 2]  # (B,)
    shift = offset * torch.stack([-torch.sin(h), torch.cos(h)], -1)  # (B, 2)
    fut = batch.agent_fut.clone()
    fut[..., :2] += shift[:, None]
    return fut


class CostWeights(nn.Module):
    """The cost weights of eq. (3), reparameterised as in App. A.2, with the collision weight fixed:

        w_i = alpha w'_i,   w'_1 = w_1 (collision, fixed),
        w'_i = c exp(psi_i) / sum_{j=2..5} exp(psi_j),  i = 2..5

    alpha and psi_2..5 are trained; c = w_2 + .. + w_5 of the hand-tuned weights. Fixing psi_1 "to
    ensure safety" means w'_1 does not move: the softmax runs over the trainable terms only, so the
    paper's learned row keeps w'_1 = 5.00 and w'_2..5 summing to 2.10 (0.5 + 0.3 + 0.3 + 1.0). At
    initialisation psi = log w and alpha = 1 recover the hand-tuned weights exactly.

    alpha is trained as log alpha, so it stays positive: the paper only says it is trainable, and a
    cost times a negative alpha is a cost to maximise. Note what alpha cannot do: the minimiser of
    alpha C is the same for every alpha > 0, so the loss does not depend on it; its gradient comes
    only from iLQR stopping short of the exact minimum (at tol), where the KKT backward sees a
    residual gradient of C. Trained unconstrained, that drift carried alpha through zero by 20
    epochs, after which the controller maximised the cost.
    """

    def __init__(self, cfg: Config):
        super().__init__()
        w0 = cost_weights(cfg, torch.float32)  # (5,)
        self.register_buffer("w_coll", w0[:1].clone())  # (1,) w'_1, fixed: not a parameter
        self.register_buffer("c", w0[1:].sum())  # the sum of w'_2..5
        self.psi = nn.Parameter(w0[1:].log())  # (4,) the SCENE_TERMS' weights
        # alpha = exp(0) = 1
        self.log_alpha = nn.Parameter(torch.zeros((), dtype=w0.dtype, device=w0.device))

    @property
    def alpha(self) -> torch.Tensor:
        """The scale alpha = exp(log alpha) > 0 (a 0-dim tensor)."""
        return self.log_alpha.exp()

    def normalised(self) -> torch.Tensor:
        """w' = [w_1, c softmax(psi_2..5)] (5,): the weights before the scale alpha
        (the columns of Table 3)."""
        return torch.cat([self.w_coll, self.c * torch.softmax(self.psi, 0)])

    def forward(self) -> torch.Tensor:
        """w = alpha w' (5,), what the planner and the controller use."""
        return self.alpha * self.normalised()


def standard_weights(batch, cfg: Config | None = None) -> torch.Tensor:
    """Standard: every scenario weighs 1 (B,)."""
    return torch.ones(len(batch), dtype=batch.agent_fut.dtype, device=batch.agent_fut.device)


def distance_weights(batch, cfg: Config | None = None) -> torch.Tensor:
    """Distance weighted (§4.1): 1 / mean_t ||ego GT_t - agent GT_t|| (B,), distances floored
    at 1 m."""
    d = (batch.ego_fut[..., :2] - batch.agent_fut[..., :2]).norm(dim=-1).mean(-1)  # (B,)
    return 1.0 / d.clamp(min=1.0)


def scenario_weights(batch, weighting, cfg: Config, shard: Shard | None = None) -> torch.Tensor:
    """Per-scenario weights of L_pred (B,), normalised to mean 1 in the batch (under DDP, shard: in
    the global batch of all processes, lab/ddp.py).

    weighting: a name in WEIGHTINGS, or a callable batch -> (B,) raw weights.
    """
    raw = WEIGHTINGS[weighting](batch, cfg) if isinstance(weighting, str) else weighting(batch)
    raw = raw.detach().to(batch.agent_fut.dtype)  # (B,)
    if raw.shape != (len(batch),) or not torch.isfinite(raw).all() or (raw < 0).any():
        raise ValueError(
            f"weighting: expected finite non-negative weights of shape ({len(batch)},)"
        )
    mean = raw.mean(0) if shard is None else shard.mean(raw)
    return raw / mean if mean > 0 else torch.ones_like(raw)


# L_pred's per-scenario weightings by name (§4.1): (batch, cfg) -> raw weights (B,)
WEIGHTINGS = {
    "standard": standard_weights,
    "distance": distance_weights,
    "grad_cost": grad_cost_weights,
}


# The two reference rows every table of the planner is read against, by name
NO_PREDICTION = Method("No prediction", "none")
GT_PREDICTION = Method("GT prediction", "gt")


# ============================================================================================
# 3. Training and evaluation, §3.2, §4.1, App. A.2, App. D.2
# ============================================================================================
#
#   L = a1 L_pred + a2 L_plan + a3 L_ctr
#
# One loop, train_stack, trains every method of the paper: the predictor, with the loss weights
# (a1, a2, a3) of its method and setting, or (Table 3, App. A.2) the cost weights w of eq. (3) with
# the predictor frozen. Each step draws a batch, runs the stack (the Objective), forms L, and takes
# an Adam step (lr 0.003, gradient clipping, App. D.2; the lr's x0.9999 per step and clipping by
# value are Trajectron++'s; learning the cost weights keeps the lr constant). L_plan and L_ctr (and
# L_pred with them) are means over the plannable scenarios of the batch; methods with a2 = a3 = 0
# (Standard and the weighted baselines) skip planning and control. pred_offset: metres added to
# the GT prediction targets, to the left of the agent (Table 2). Training runs on the model's
# device (the cost weights must be there too): the data stays on the CPU, each batch is moved as
# it is drawn. Under torchrun each rank trains on its cfg.batch_size / world scenarios of every
# global batch, with the gradient of the single-process loss on the global batch (lab/ddp.py);
# only rank 0 logs, and every rank returns the same per-step log. A loss, gradient or parameter
# that is no longer finite stops the training at that step (TrainingDiverged).


def to_device(obj, device):
    """obj with every tensor in it moved to `device`: a tensor, or a dataclass, NamedTuple, tuple,
    list or dict holding them (nested; a StackOutput, a Prediction); anything else as it is. E.g.
    results to the CPU to plot."""
    if torch.is_tensor(obj):
        return obj.to(device)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return dataclasses.replace(
            obj,
            **{
                f.name: to_device(getattr(obj, f.name), device)
                for f in dataclasses.fields(obj)
                if f.init
            },
        )
    if isinstance(obj, tuple) and hasattr(obj, "_fields"):
        return type(obj)(*(to_device(v, device) for v in obj))
    if isinstance(obj, (tuple, list)):
        return type(obj)(to_device(v, device) for v in obj)
    if isinstance(obj, dict):
        return {k: to_device(v, device) for k, v in obj.items()}
    return obj


def scene_plans(data, cfg: Config, plan_dt=None, chunk=1024) -> ScenePlan:
    """scene_plan of a whole set of Scenarios, checked and computed in chunks; it is indexed as the
    set is: scene_plans(data)[rows] equals scene_plan(data[rows]) bit for bit (every number is one
    scenario's own)."""
    parts = []
    for i in range(0, len(data), chunk):
        batch = data[i : i + chunk]
        check_batch(batch, cfg, need_future=True, stack=True)
        parts.append(scene_plan(batch, cfg, plan_dt))

    def cat(get):
        return torch.cat([get(p) for p in parts])

    return ScenePlan(
        cat(lambda p: p.goal),
        Candidates(
            cat(lambda p: p.cands.s), cat(lambda p: p.cands.u), cat(lambda p: p.cands.valid)
        ),
        cat(lambda p: p.terms),
    )


class TrainingDiverged(ValueError):
    """A training whose loss, gradient or parameters became NaN or infinite (train_stack stops at
    that step)."""


LOSS_NAMES = ("L_pred", "L_plan", "L_ctr")


def stop_if_diverged(where: str, shard: Shard, terms=None, grads=None, params=None) -> None:
    """TrainingDiverged, saying where, once training has diverged: a loss term that is not finite
    (it would make every parameter NaN at this step; every rank sees the flags of all, so they stop
    together), a NaN gradient under finite losses (an infinite one is clipped), or a parameter made
    infinite by a step that overflowed (a huge learning rate)."""
    if terms is not None:
        finite = torch.isfinite(torch.stack(terms))  # (3,)
        bad = shard.total((~finite).to(terms[0].dtype)[None])  # (3,)
        if bad.any():
            which = ", ".join(n for n, b in zip(LOSS_NAMES, bad.tolist()) if b)
            raise TrainingDiverged(f"{where}: {which} is not finite")
    if grads is not None and torch.isnan(torch.nn.utils.get_total_norm(grads)):
        raise TrainingDiverged(f"{where}: a gradient is NaN")
    if params is not None and not torch.isfinite(torch.nn.utils.get_total_norm(params)):
        raise TrainingDiverged(f"{where}: a parameter is not finite")


@dataclass
class Objective:
    """What a training step minimises on a batch: L = a1 L_pred + a2 L_plan + a3 L_ctr (stack_loss),
    its terms, means over the batch's plannable scenarios (the predictor alone, over all, when
    a2 = a3 = 0), and iLQR's convergence rate among them. alphas: (a1, a2, a3).

    predictor, cost_w: what the forward pass calls (under DDP the wrapped modules); cost_w None:
    the hand-tuned weights. scenes: the data's scene_plans (None without planning)."""

    predictor: torch.nn.Module
    cost_w: torch.nn.Module | None
    method: Method
    cfg: Config
    setting: str
    shard: Shard
    scenes: ScenePlan | None
    pred_offset: float
    stack_kw: dict
    alphas: tuple

    def __call__(self, batch, rows, step: int) -> tuple[torch.Tensor, tuple, float]:
        target = offset_targets(batch, self.pred_offset) if self.pred_offset else None
        noise = self.shard.decoder_noise(self.predictor, len(batch), self.cfg, batch.ego_hist)
        if self.scenes is None:
            return self.prediction_terms(batch, target, noise, step)
        return self.stack_terms(batch, rows, target, noise, step)

    def prediction_terms(self, batch, target, noise, step):
        """a1 L_pred and (L_pred, 0, 0): the predictor alone (Standard, the weighted baselines)."""
        pred = self.predictor(batch, use_posterior=True, step=step, noise=noise)
        truth = batch if target is None else dataclasses.replace(batch, agent_fut=target)
        l_pred_b, _ = pred_loss(pred, truth, step, self.cfg, self.shard.mean)
        # a mean over this rank's b scenarios: every rank holds b, so DDP's mean over the ranks is
        # the mean over the global batch
        weights = scenario_weights(batch, self.method.weighting, self.cfg, self.shard)
        l_pred = (l_pred_b * weights).mean()
        zero = torch.zeros((), dtype=l_pred.dtype, device=l_pred.device)
        return self.alphas[0] * l_pred, (l_pred, zero, zero), float("nan")

    def stack_terms(self, batch, rows, target, noise, step):
        """L and (L_pred, L_plan, L_ctr) of the whole stack, means over the plannable scenarios."""
        learn_cost = self.cost_w is not None
        out = run_stack(
            batch,
            self.predictor,
            self.method,
            self.cfg,
            self.setting,
            step=None if learn_cost else step,
            train=not learn_cost,
            w=self.cost_w() if learn_cost else None,
            pred_target=target,
            noise=noise,
            batch_mean=self.shard.mean,
            scene=to_device(self.scenes[rows], batch.ego_hist.device),
            **self.stack_kw,
        )
        keep = out.plannable.to(out.l_plan.dtype)
        # this rank's sums divided by the global number of plannable scenarios / world (lab/ddp.py)
        m = self.shard.total(keep).clamp_min(1) / self.shard.world
        weights = scenario_weights(batch, self.method.weighting, self.cfg, self.shard)
        loss, terms = stack_loss(out, self.alphas, weights, m)
        if self.shard.world == 1:
            conv = out.converged[out.plannable].float().mean().item()
        else:  # converged among the plannable scenarios of the global batch
            converged = (out.converged & out.plannable).to(keep.dtype)
            conv = (self.shard.total(converged) / self.shard.total(keep)).item()
        return loss, terms, conv


def batch_rows(n: int, cfg: Config, shard: Shard, order: torch.Generator, total: int):
    """The rows of this rank's share of every training batch, `total` batches: each epoch a new
    permutation of the n scenarios, the same on every rank (drawn on the CPU by `order`), cut into
    batches of cfg.batch_size (the last partial one dropped)."""
    b = cfg.batch_size // shard.world  # scenarios per step on this rank
    mine = shard.positions(n)  # (n // world,) this rank's positions (all of them: one process)
    steps_per_epoch, step = max(1, n // cfg.batch_size), 0
    while step < total:
        perm = torch.randperm(n, generator=order, device="cpu")
        for i in range(min(steps_per_epoch, total - step)):
            yield perm[mine[i * b : (i + 1) * b]]  # one process: perm[i B:(i + 1) B]
            step += 1


def train_stack(
    model,
    data,
    method: Method,
    cfg: Config,
    setting="rl",
    epochs=1.0,
    seed=0,
    log=print,
    pred_offset=0.0,
    weights: CostWeights | None = None,
    on_epoch=None,
    **stack_kw,
):
    """Train the predictor of a method (or, given `weights`, the cost weights, the predictor
    frozen) for `epochs` (a fraction too) on data: L = a1 L_pred + a2 L_plan + a3 L_ctr, Adam.
    on_epoch(epochs done, steps done): called before the first step and after every epoch, in a
    fork of the random state. Returns the per-step log (list of dicts: the global batch's
    values)."""
    shard = Shard.of_process_group()  # one process, or this rank's rows under torchrun
    shard.check_split(cfg.batch_size)
    log = log if shard.rank == 0 else None  # the other ranks stay quiet
    torch.manual_seed(seed)  # the decoder's sampled controls, the same on every rank
    order = torch.Generator().manual_seed(seed)  # the order of the scenarios, on the CPU
    params, objective = objective_for(
        model, data, method, cfg, setting, shard, weights, pred_offset, stack_kw
    )
    opt = torch.optim.Adam(params, lr=cfg.lr)
    sched = None if weights is not None else ExponentialLR(opt, cfg.pred_lr_decay)
    steps_per_epoch = max(1, len(data) // cfg.batch_size)
    total = max(1, round(epochs * steps_per_epoch))
    epoch_done = epoch_callback(on_epoch, model, weights is None, steps_per_epoch)
    history, t0 = [], time.time()
    epoch_done(0)
    try:
        for step, rows in enumerate(batch_rows(len(data), cfg, shard, order, total), 1):
            batch = to_device(data[rows], next(model.parameters()).device)
            # L = a1 L_pred + a2 L_plan + a3 L_ctr (§3.2) and its terms
            loss, terms, conv = objective(batch, rows, step - 1)
            where = f"{method.name}, seed {seed}: training diverged at step {step} of {total}"
            stop_if_diverged(where, shard, terms=terms)
            opt.zero_grad()
            loss.backward()
            stop_if_diverged(where, shard, grads=[p.grad for p in params if p.grad is not None])
            torch.nn.utils.clip_grad_value_(params, cfg.pred_grad_clip)
            opt.step()
            stop_if_diverged(where, shard, params=params)
            if sched is not None:
                sched.step()
            history.append(step_record(step, loss, terms, conv, shard, weights))
            if step % steps_per_epoch == 0 or step == total:
                epoch_done(step)
            if log and (step % max(1, total // 10) == 0 or step == total):
                log(progress_line(method, history[-1], step, total, time.time() - t0))
    finally:
        shard.close()
    return history


def objective_for(model, data, method, cfg, setting, shard, weights, pred_offset, stack_kw):
    """(the parameters to train, the Objective) of a training: the predictor's (train mode), or
    with `weights` the cost weights' (the predictor frozen, in eval mode: it weighs its modes by
    p(z|x) as at evaluation, and dL/dw comes from the controller's KKT backward). Under DDP the
    trained module is wrapped (lab/ddp.py). Without planning (a2 = a3 = 0) the data
    is checked here; with it, the goal, the candidates and every term of eq. (3) but C_coll depend
    on the scenes alone (not on the predictor nor on the weights): computed once for the data here,
    not at every step of every epoch (about a sixth of a step), the same numbers either way."""
    if weights is not None:
        model.eval().requires_grad_(False)
        params, predictor, cost_w = list(weights.parameters()), model, wrap(weights, shard)
    else:
        model.train()
        params, predictor, cost_w = list(model.parameters()), wrap(model, shard), None
    a = alphas(method, setting, cfg)
    scenes = None
    if a[1] > 0 or a[2] > 0:
        scenes = scene_plans(data, cfg, stack_kw.get("plan_dt"))
    else:
        for i in range(0, len(data), 1024):
            check_batch(data[i : i + 1024], cfg, need_future=True)
    objective = Objective(
        predictor, cost_w, method, cfg, setting, shard, scenes, pred_offset, stack_kw, a
    )
    return params, objective


def epoch_callback(on_epoch, model, train_mode: bool, steps_per_epoch: int):
    """step -> None: on_epoch(epochs done, step) in a fork of the random state (training draws
    the same numbers with it or without it), the model put back in its training mode after."""

    def epoch_done(step: int) -> None:
        if on_epoch is None:
            return
        device = next(model.parameters()).device
        with torch.random.fork_rng(devices=[device] if device.type == "cuda" else []):
            on_epoch(step / steps_per_epoch, step)
        model.train(train_mode)

    return epoch_done


def step_record(step: int, loss, terms, conv: float, shard: Shard, weights) -> dict:
    """The log of a step: the global batch's loss and terms (the mean over the ranks of theirs;
    one process: its own), iLQR's convergence rate and, when learned, the cost weights."""
    values = torch.stack([loss, *terms])[None]  # (1, 4)
    loss_v, l_pred, l_plan, l_ctr = shard.total(values).div(shard.world).tolist()
    record = dict(step=step, loss=loss_v, l_pred=l_pred, l_plan=l_plan, l_ctr=l_ctr, converged=conv)
    if weights is not None:
        record["w"] = weights().tolist()
    return record


def progress_line(method: Method, rec: dict, step: int, total: int, elapsed: float) -> str:
    """One line of training progress (about ten per training)."""
    w = "  w " + " ".join(f"{v:.3f}" for v in rec["w"]) if "w" in rec else ""
    return (
        f"  [{method.name}] step {step}/{total}  loss {rec['loss']:9.3f}  L_pred "
        f"{rec['l_pred']:7.3f}  L_plan {rec['l_plan']:6.3f}  L_ctr {rec['l_ctr']:7.4f}{w}  "
        f"{elapsed:5.0f}s  ETA {elapsed / step * (total - step):4.0f}s"
    )


def train_predictor(
    method: Method,
    data,
    cfg: Config,
    setting="rl",
    epochs=1.0,
    seed=0,
    log=print,
    pred_offset=0.0,
    device="cpu",
    curve_samples=0,
    **stack_kw,
) -> Predictor:
    """A fresh predictor, initialised from `seed` (on the CPU, so that every device starts from the
    same weights), moved to `device` and trained there on data.train_for(seed) (the seed's own draw)
    by train_stack. curve_samples > 0: its learning curve, evaluate_stack on the first curve_samples
    validation scenarios before training and after every epoch, is kept in model.learning_curve (a
    list of {epoch, step, metrics})."""
    torch.manual_seed(seed)  # the predictor's initialisation
    model = Predictor(cfg).to(device)
    curve = []
    on_epoch = None
    if curve_samples > 0:
        subset = data.val[:curve_samples]

        def on_epoch(epoch, step):  # a point of the learning curve
            metrics = evaluate_stack(model, subset, method, cfg, setting, device=device, **stack_kw)
            curve.append(dict(epoch=epoch, step=step, **metrics))

    train_stack(
        model,
        data.train_for(seed),
        method,
        cfg,
        setting,
        epochs,
        seed,
        log,
        pred_offset,
        on_epoch=on_epoch,
        **stack_kw,
    )
    if curve_samples > 0:
        model.learning_curve = curve
    return model


def evaluate_stack(
    model, data, method: Method, cfg: Config, setting="rl", batch_size=512, device=None, **stack_kw
) -> dict:
    """Mean metrics over the plannable scenarios of a set (prior mode weights p(z|x), §3.2):
    ADE/FDE/NLL of the predictor, planning loss, hindsight cost, MSE to the GT ego trajectory, and
    iLQR's convergence rate. Each batch runs on `device` (default: the model's; the CPU without a
    model)."""
    if device is None:
        device = next(model.parameters()).device if model is not None else "cpu"
    if model is not None:
        model.eval()
    sums = {}
    n, n_all = 0, 0
    by_behaviour = {}
    for i in range(0, len(data), batch_size):
        batch = to_device(data[i : i + batch_size], device)
        check_batch(batch, cfg, need_future=True, stack=True)
        out = run_stack(batch, model, method, cfg, setting, **stack_kw)
        keep = out.plannable
        vals = dict(
            plan_loss=out.l_plan,
            hindsight=out.hindsight,
            mse=out.mse,
            converged=out.converged.to(out.mse.dtype),
        )
        if out.pred is not None:
            metrics = prediction_metrics(out.pred, batch, cfg)
            vals.update(
                {
                    k: v
                    for k, v in metrics.items()
                    if k in ("ade", "fde", "min_ade", "nll", "cv_ade")
                }
            )
        for k, v in vals.items():
            sums[k] = sums.get(k, 0.0) + v.detach()[keep].sum().item()
        # the same sums per behaviour of the predicted agent (synthetic data; real data is
        # labelled -1)
        for b in batch.behaviour[keep].unique().tolist():
            if b >= 0:
                rows = keep & (batch.behaviour == b)
                acc = by_behaviour.setdefault(BEHAVIOURS[b], dict(n=0))
                acc["n"] += rows.sum().item()
                for k in ("hindsight", "mse", "plan_loss"):
                    acc[k] = acc.get(k, 0.0) + vals[k].detach()[rows].sum().item()
        n, n_all = n + keep.sum().item(), n_all + len(batch)
    if n == 0:  # means over nothing would read as a table of zeros
        raise ValueError(
            f"{method.name}: none of the {n_all} scenarios is plannable (fewer than 2 feasible "
            "candidates on a goal lane in each): check the data's lanes and goals, or the "
            "Config's planner settings"
        )
    out = {k: v / n for k, v in sums.items()}
    out.update(n=n, skipped=n_all - n)
    if by_behaviour:  # means per behaviour, and how many scenarios each has
        out["by_behaviour"] = {
            name: {k: (v if k == "n" else v / acc["n"]) for k, v in acc.items()}
            for name, acc in sorted(by_behaviour.items())
        }
    return out
