"""The paper's experiments on diffstack.py: Tables 1-5, the ablations of App. A.1, the report.

    python experiments.py --experiment rl     # Table 1 (10 seeds) -> results/rl.json, results/rl.md
    python experiments.py --experiment all    # every table, results/report.md (40 epochs a method)
    python experiments.py --experiment all --seeds 5 --epochs 20 --out runs/epochs20
                                              # at the paper's length

Each table of the paper is a declarative TableSpec (specs.py: its methods, setting, loss weights,
metrics and the paper's own numbers); the functions here compute its numbers, and lab/tables.py
runs any of them (cut into pieces, in worker processes, kept and resumed; `main` hands over to it)
and lab/report.py writes their text.

Map of the module:
    1. Training       trained_predictor: a predictor is trained once per (method, seed, ...) and
                      shared by the tables; the tables' data
    2. Cost learning  Table 3, the learned cost weights (App. A.2, Table 7)
    3. Closed loop    log replay (§4.3, Table 5, App. D.3): the simulation and its metrics
    4. Ablations      App. A.1; the goal table (what a perfect prediction is worth, by behaviour)

Shape letters as in diffstack.py; in the closed loop, as in data_synth.py, S counts scenes and N
simulation steps.
"""

from __future__ import annotations

import functools
import json
import math
import os
import pickle
import statistics
import sys
import time
from dataclasses import dataclass

import torch

import lab.data  # hand-over: load_data, the data made or read (lab/data.py)
import data_synth
from diffstack import (
    COST_TERMS,
    Config,
    Predictor,
    cost_contexts,
    cost_terms,
    cost_weights,
    project_to_lanes,
    route_goal,
    run_stack,
    unicycle_step,
    wrap_angle,
)
from specs import (
    CLOSE,
    CLOSED_LOOP_METHODS,
    COST_WEIGHTS_ROW,
    CURVE_SAMPLES,
    GOALS,
    RELATIVE_SCALE,
    STANDARD,
    TABLE1_METHODS,
    TableSpec,
)
from specs import TABLES as TABLES  # tutorial.py reads them as experiments.TABLES
from train import (
    GT_PREDICTION,
    NO_PREDICTION,
    CostWeights,
    Method,
    TrainingDiverged,
    alphas,
    evaluate_stack,
    to_device,
    train_predictor,
    train_stack,
)

# hand-over to the lab: files written whole and JSON read safely (lab/runs.py), the table formatter
# (lab/stats.py), the tables' text (lab/report.py: the notebook and the course read three of its
# functions as experiments')
from lab.report import behaviour_markdown as behaviour_markdown
from lab.report import claim_line as claim_line
from lab.report import gap_closed as gap_closed
from lab.runs import load_json, save_atomic, write_atomic
from lab.stats import markdown_table


# ---- 1. Training, shared between tables ----------------------------------------------------------


def method_key(m: Method) -> tuple:
    """A method by what it trains with, in names and numbers (a callable weighting by its
    qualified name, never the object: an object's text holds its address)."""
    w = m.weighting
    weighting = w if isinstance(w, str) else f"{w.__module__}.{w.__qualname__}"
    return (m.name, m.predictor, tuple(m.losses), weighting, m.train_plan_weights)


def spec_key(spec: TableSpec) -> dict:
    """What a table's spec sets that moves its numbers, by value: its kind, setting, target
    offset, rows and ablation sections, the learning curves' size (and the goal table's goals and
    distance); not its title, columns, claims or the paper's numbers, which are text."""
    return dict(
        kind=spec.kind,
        setting=spec.setting,
        pred_offset=spec.pred_offset,
        methods=[method_key(m) for m in spec.methods],
        sections=[
            (title, sorted(kw.items()), [method_key(m) for m in methods])
            for title, kw, methods in spec.sections
        ],
        goals=list(GOALS) if spec.kind == "goal" else None,
        close=CLOSE if spec.kind == "goal" else None,
        curve_samples=CURVE_SAMPLES,
    )


def training_key(
    m: Method, cfg: Config, setting, epochs, seed, pred_offset=0.0, device="cpu", **stack_kw
) -> tuple:
    """What tells method m's predictor apart from another (trained_predictor): its loss weights,
    scenario weighting, seed, epochs, target offset and device, and only where training runs the
    stack (L_plan or L_ctr on) the setting and the stack options, less the controller's when
    L_ctr is off."""
    a = alphas(m, setting, cfg)
    runs_stack = a[1:] != (0, 0)
    kw = {k: v for k, v in stack_kw.items() if runs_stack and (a[2] != 0 or k != "controller")}
    weighting = method_key(m)[3]  # by name
    key = (a, weighting, seed, epochs, pred_offset, str(device))
    key += (setting if runs_stack else None, tuple(sorted(kw.items())))
    plan_weights = (m.train_plan_weights or cfg.train_plan_weights) if runs_stack else None
    # (the default, the posterior, adds nothing)
    return key + ((plan_weights,) if plan_weights == "prior" else ())


def stored_predictor(path, cfg: Config, device):
    """The predictor an earlier piece of this run stored at path (with its learning curve), or None
    when there is none; one that cannot be read (a damaged file, an earlier version) is named on
    stderr, set aside as .corrupt beside it and trained again."""
    if not path.exists():
        return None
    model = Predictor(cfg).to(device)
    curve = path.with_suffix(".curve.json")
    try:
        model.load_state_dict(torch.load(path, map_location=device, weights_only=True))
        if curve.exists():
            model.learning_curve = load_json(curve, "a learning curve")
            if not isinstance(model.learning_curve, list):
                raise ValueError(f"{curve}: not a learning curve (a list)")
    except (RuntimeError, ValueError, OSError, EOFError, pickle.UnpicklingError) as e:
        print(
            f"{path}: not a stored predictor ({' '.join(str(e).split())[:200]}); set aside as "
            f"{path.name}.corrupt, trained again",
            file=sys.stderr,
        )
        for f in (path, curve):
            if f.exists():
                os.replace(f, f.with_name(f.name + ".corrupt"))
        return None
    return model


def trained_predictor(
    m: Method,
    data,
    cfg: Config,
    setting,
    epochs,
    seed,
    log=print,
    pred_offset=0.0,
    models=None,
    device="cpu",
    store=None,
    **stack_kw,
):
    """Method m's predictor trained with `seed` (its learning curve on CURVE_SAMPLES scenarios), or
    the one trained before with the same training_key (Standard once per seed for Tables 1, 3, 4, 5
    and the ablations): from models (a dict the tables of one run share), else from store (a
    RunStore: a resumed run or a worker loads an earlier piece's)."""
    key = training_key(m, cfg, setting, epochs, seed, pred_offset, device, **stack_kw)
    if models is not None and key in models:
        if log:
            log(f"  [{m.name}] seed {seed}: trained above, reused")
        return models[key]
    path = store.model_path(key) if store is not None else None
    model = stored_predictor(path, cfg, device) if path is not None else None
    if model is not None:
        if log:
            log(f"  [{m.name}] seed {seed}: loaded from {path}, trained by an earlier piece")
    else:
        kw = dict(device=device, curve_samples=CURVE_SAMPLES, **stack_kw)
        model = train_predictor(m, data, cfg, setting, epochs, seed, log, pred_offset, **kw)
        try:  # neither file is written: a result is never written with NaN
            curve = json.dumps(getattr(model, "learning_curve", None), allow_nan=False)
        except ValueError:
            raise TrainingDiverged(
                f"{m.name}, seed {seed}: its learning curve holds NaN or infinity"
            ) from None
        if path is not None:  # the curve first: a model file on disk always has its curve beside it
            path.parent.mkdir(parents=True, exist_ok=True)
            write_atomic(path.with_suffix(".curve.json"), curve)
            save_atomic(model.state_dict(), path)
    if models is not None:
        models[key] = model
    return model


def open_loop_experiment(
    data,
    cfg: Config,
    setting="rl",
    methods=TABLE1_METHODS,
    seeds=(0,),
    epochs=1.0,
    pred_offset=0.0,
    log=print,
    models=None,
    device="cpu",
    store=None,
    **stack_kw,
) -> dict:
    """compare_methods with predictors shared through `models` and kept in `store`, a RunStore
    (trained_predictor), run on `device`."""
    train = functools.partial(trained_predictor, models=models, store=store)
    args = (data, cfg, setting, methods, tuple(seeds), epochs, pred_offset, log, train, device)
    return compare_methods(*args, **stack_kw)


VAL_SEED = 1000
"""The data seed of the tables' common validation set. Training seed s trains on the draw of data
seed s, and seeds are 0..99 (--seeds <= 100): no training draw is this one, and distinct draws hold
distinct random scenes."""


VAL_N = 10_000
"""Samples in the common validation set: at 1,500 which scenes land in validation decides a row of
Table 1 (a few near-collisions among ~46 cut-in scenes carry the signal); at 10,000 the rows hold
from draw to draw."""


def experiment_data(
    n=10000, seeds=range(5), n_val=VAL_N, cache_dir="data_cache", log=print
) -> data_synth.Dataset:
    """The tables' synthetic data: training seed s trains on the training scenes of its own draw
    (load_data(n, seed=s).train), and every method of every seed is evaluated on one common
    validation set, all n_val samples of the draw of data seed VAL_SEED, whose scenes no training
    draw contains; that draw's validation scenes are the closed loop's. Each draw is generated once,
    then read from cache_dir."""
    seeds = tuple(seeds)
    if not seeds or max(seeds) >= VAL_SEED:
        raise ValueError(
            f"--seeds: training seeds must be 0..{VAL_SEED - 1} (data seed {VAL_SEED} is the "
            f"validation set's), got {seeds}"
        )
    common = lab.data.load_data(None, n_val, VAL_SEED, cache_dir, log)
    draws = tuple(
        lab.data.load_data(None, n, s, cache_dir, log).train for s in range(max(seeds) + 1)
    )
    return data_synth.Dataset(
        draws[0], data_synth.Scenarios.cat([common.train, common.val]), common.val_scenes, draws
    )


def compare_methods(
    data,
    cfg: Config,
    setting="rl",
    methods=TABLE1_METHODS,
    seeds=(0,),
    epochs=1.0,
    pred_offset=0.0,
    log=print,
    train=train_predictor,
    device="cpu",
    **stack_kw,
) -> dict:
    """Train every method for every seed on data.train, evaluate on data.val (Tables 1, 2, 4, the
    ablations): {method name: [metrics dict per seed]}, with 'rel_<metric>' (add_relative).
    train(method, data, cfg, setting, epochs, seed, log, pred_offset, device=device, **stack_kw) ->
    a trained predictor on `device`, where training and evaluation run; the data stays on the CPU
    and the metrics come back as Python numbers."""
    results = {}
    for m in methods:
        runs = []
        for seed in seeds if m.predictor == "learned" else seeds[:1]:
            t0 = time.time()
            model = None
            if m.predictor == "learned":
                model = train(
                    m, data, cfg, setting, epochs, seed, log, pred_offset, device=device, **stack_kw
                )
            r = evaluate_stack(model, data.val, m, cfg, setting, device=device, **stack_kw)
            predicted = [k for k in ("ade", "fde", "min_ade", "min_fde", "nll") if k in r]
            bad = [k for k in predicted if not math.isfinite(r[k])]
            if bad:  # a predictor that trained to finite losses can still predict NaN
                raise TrainingDiverged(
                    f"{m.name}, seed {seed}: its evaluation is not finite ({', '.join(bad)})"
                )
            r["seconds"] = time.time() - t0
            if getattr(model, "learning_curve", None) is not None:
                r["curve"] = model.learning_curve
            runs.append(r)
            if log:
                log(f"{m.name:24s} seed {seed}: {metrics_line(r)}")
        results[m.name] = runs
    return add_relative(results, setting)


def metrics_line(r: dict) -> str:
    """A run's numbers on one line of the log."""
    return "  ".join(f"{k} {v:.4f}" for k, v in r.items() if isinstance(v, float))


def add_relative(results: dict, setting: str) -> dict:
    """Add the planning metrics relative to No prediction's first run ('rel_<metric>', scaled as
    RELATIVE_SCALE) to every run of {method name: [metrics dict per seed]}, in place; nothing
    without a No prediction row. Returns it."""
    base = results["No prediction"][0] if "No prediction" in results else None
    for runs in results.values():
        for r in runs:
            for key, scale in RELATIVE_SCALE[setting].items():
                if base is not None and key in r:  # (a diverged training's run has no metrics)
                    r["rel_" + key] = (r[key] - base[key]) / scale
    return results


# ---- 2. Cost learning (§4.2, Table 3; App. A.2, Table 7) -----------------------------------------


def cost_learning_experiment(
    data, cfg: Config, seeds=(0,), epochs=1.0, log=print, models=None, device="cpu"
) -> dict:
    """Table 3: per seed a Standard predictor, then the cost weights learned with it frozen
    (train.train_stack with `weights`: L = a3 L_ctr, the MSE to the GT ego trajectory); both
    evaluated on data.val, IL. {'Hand-tuned': [per seed], 'Learned': [...]}, each with w'
    (normalised weights), alpha, plan_loss and mse (absolute, m^2 over T)."""
    runs = [cost_learning_seed(data, cfg, seed, epochs, log, models, device) for seed in seeds]
    return {name: [r[name] for r in runs] for name in ("Hand-tuned", "Learned")}


def cost_learning_seed(
    data, cfg: Config, seed=0, epochs=1.0, log=print, models=None, device="cpu", store=None
) -> dict:
    """One seed of Table 3: {'Hand-tuned': metrics, 'Learned': metrics}
    (cost_learning_experiment)."""
    res = {}
    kw = dict(models=models, device=device, store=store)
    model = trained_predictor(STANDARD, data, cfg, "il", epochs, seed, log, **kw)
    weights = CostWeights(cfg).to(device)

    def evaluate(name):  # the stack under the weights as they stand, IL, on data.val
        with torch.no_grad():
            w, w_norm, alpha = weights(), weights.normalised().tolist(), weights.alpha.item()
        res[name] = r = evaluate_stack(model, data.val, STANDARD, cfg, "il", w=w, device=device)
        r.update(w=w_norm, alpha=alpha)
        if log:
            terms = " ".join(f"{v:.3f}" for v in w_norm)
            losses = f"plan_loss {r['plan_loss']:.4f}  mse {r['mse']:.4f}"
            log(f"{name:10s} seed {seed}: w' {terms}  alpha {alpha:.3f}  {losses}")

    evaluate("Hand-tuned")
    train_stack(
        model, data.train_for(seed), COST_WEIGHTS_ROW, cfg, "il", epochs, seed, log, weights=weights
    )
    evaluate("Learned")
    return res


# ---- 3. Closed loop: log replay (§4.3, Table 5, App. D.3) ----------------------------------------
# Every dt = 0.5 s for T_sim = 10 s: cut a planning sample at the current frame around the SIMULATED
# ego (its simulated 4 s history; the goal and lanes from the logged ego), run the stack, move the
# ego by the first control; the other agents replay their logs. 4 s history + 10 s + the 3 s horizon
# fit in a 20 s scene.


@dataclass
class Rollout:
    """A closed-loop simulation of S scenes over N steps (world frame, float64)."""

    # (S, N+1, 4)     simulated ego states at frames f0 .. f0+N
    ego: torch.Tensor
    # (S, N, 2)       the controls applied (the first of each step's trajectory)
    controls: torch.Tensor
    # (S, N, T+1, 4)  each step's final trajectory (controller output), world frame
    plans: torch.Tensor
    # (S, N)          each step's hindsight cost C_H of its trajectory (eq. 3, GT futures)
    open_loop: torch.Tensor
    # (S, N)          bool: the planner had at least 2 candidates at that step
    plannable: torch.Tensor
    start_frame: int  # f0


def from_frame(states: torch.Tensor, origin: torch.Tensor) -> torch.Tensor:
    """Ego-frame states (S, ..., 4) back to the world, the frame's origin (S, 4) given: the inverse
    of the transform of data_synth.sample_at. [x, y] = [x0, y0] + R(h0) [x', y'],  h = h' + h0."""
    shape = (origin.shape[0],) + (1,) * (states.dim() - 2)
    x0, y0, h0 = (origin[:, i].reshape(shape) for i in range(3))
    c, s = torch.cos(h0), torch.sin(h0)
    x, y = states[..., 0], states[..., 1]
    return torch.stack(
        [x0 + c * x - s * y, y0 + s * x + c * y, wrap_angle(states[..., 2] + h0), states[..., 3]],
        -1,
    )


def stack_policy(model, method: Method, cfg: Config, device=None):
    """The stack as a closed-loop policy, in evaluation mode on `device` (default: the model's, or
    the CPU): batch -> (x (S, T+1, 4) in the sample's frame, u (S, T, 2), C_H (S,) with every agent,
    plannable (S,)), on the batch's device. Planner and controller see the predicted agent only
    (App. D.3), the predictor every neighbour."""
    if model is not None:
        model.eval()
    if device is None:
        device = next(model.parameters()).device if model is not None else "cpu"

    def policy(batch):
        with torch.no_grad():
            out = run_stack(to_device(batch, device), model, method, cfg, plan_others=False)
        home = batch.ego_hist.device
        return out.s.to(home), out.u.to(home), out.hindsight.to(home), out.plannable.to(home)

    return policy


def simulate(
    scenes,
    policy,
    cfg: Config,
    sim_time: float = 10.0,
    start_frame: int | None = None,
    scfg=None,
    dtype=torch.float32,
) -> Rollout:
    """Log replay (§4.3) of every scene at once: N = sim_time / dt steps from start_frame (default:
    the first frame with a full history); policy as stack_policy's. scfg: the data's SynthConfig
    (frame period, history and horizon); dtype: the policy's samples (the simulation is float64)."""
    scfg = scfg or data_synth.SynthConfig()
    H, T = scfg.hist, scfg.fut
    F = scenes.ego.shape[1]
    if abs(cfg.dt - scfg.dt) > 1e-9:
        raise ValueError(
            "dt: the simulation replans at every logged frame, so cfg.dt must be the log's "
            f"{scfg.dt} s, got {cfg.dt}"
        )
    steps = sim_time / cfg.dt
    if not sim_time > 0 or abs(steps - round(steps)) > 1e-9:
        raise ValueError(
            f"sim_time: must be a positive multiple of dt = {cfg.dt} s, got {sim_time}"
        )
    N = round(steps)
    f0 = H if start_frame is None else start_frame
    if f0 < H or f0 + N - 1 + T > F - 1:
        raise ValueError(
            f"start_frame: {f0} + {N} steps + the {T}-step horizon must lie in frames [{H}, "
            f"{F - 1}] (start_frame >= {H}, sim_time <= {(F - 1 - T - H + 1) * cfg.dt} s)"
        )
    # (S, H+1, 4) the simulated ego's history, world frame
    hist = scenes.ego[:, f0 - H : f0 + 1].clone()
    ego = [hist[:, -1]]
    controls, plans, open_loop, plannable = [], [], [], []
    for k in range(N):  # a loop over simulation steps; every scene at once
        batch = data_synth.sample_at(scenes, f0 + k, ego_state=hist, cfg=scfg, dtype=dtype)
        x, u, hindsight, ok = policy(batch)  # (S, T+1, 4), (S, T, 2), (S,), (S,)
        s = hist[:, -1]  # (S, 4)
        u0 = u[:, 0].to(s)  # (S, 2) the simulation's dtype and device
        # s_{k+1} = f(s_k, u_0) in the world frame (u does not depend on it)
        s_next = unicycle_step(s, u0, cfg.dt)
        s_next = torch.cat([s_next[:, :2], wrap_angle(s_next[:, 2:3]), s_next[:, 3:]], -1)  # (S, 4)
        hist = torch.cat([hist[:, 1:], s_next[:, None]], 1)  # (S, H+1, 4)
        ego.append(s_next)
        controls.append(u0)
        plans.append(from_frame(x.to(s), s))
        open_loop.append(hindsight.to(s))
        plannable.append(ok.to(s.device))
    stacked = (torch.stack(xs, 1) for xs in (ego, controls, plans, open_loop, plannable))
    return Rollout(*stacked, f0)


def closed_loop_metrics(scenes, roll: Rollout, cfg: Config) -> dict:
    """The metrics of §4.3 per scene (S,), on the unrolled trajectory s_1..s_N, u_0..u_N-1:
    trajectory cost 1/N sum_t C(s_t, u_t; GT agents, map) without the goal term
    (eq. 3, hand-tuned w); collision 1/N sum_t w1 C_coll (every logged agent present); lane 1/N
    sum_t (w3 C_lat + w4 C_head); control effort 1/N sum_t w5 ||u_t||^2; open-loop cost, the mean
    hindsight cost C_H of the plannable steps; deviation 1/N sum_t ||s_t - s_log,t|| (m)."""
    N = roll.controls.shape[1]
    f0 = roll.start_frame
    x, u = roll.ego[:, 1:], roll.controls  # (S, N, 4), (S, N, 2)
    frames = slice(f0 + 1, f0 + N + 1)
    agents = scenes.agents[:, :, frames, :2]  # (S, M, N, 2)
    present = scenes.agents_mask[:, :, frames]  # (S, M, N)
    # (S, M, N); C_coll = sum_a phi(d2),  phi(d2) = exp(-d2 / 2 sigma^2)
    d2 = ((x[:, None, :, :2] - agents) ** 2).sum(-1)
    coll = (present * torch.exp(-d2 / (2 * cfg.rbf_var))).sum(1)  # (S, N)
    lanes = scenes.lanes.to(x.dtype)
    lat, head, _ = project_to_lanes(x[..., :2], x[..., 2], lanes, scenes.lanes_mask)  # (S, N)
    w = dict(zip(COST_TERMS, cost_weights(cfg, x.dtype, x.device)))
    # (S, N) each
    parts = dict(
        collision=w["coll"] * coll,
        lane=w["lat"] * lat + w["head"] * head**2,
        control=w["ctrl"] * (u**2).sum(-1),
    )
    out = {k: v.mean(-1) for k, v in parts.items()}
    out["trajectory"] = out["collision"] + out["lane"] + out["control"]
    keep = roll.plannable.to(x.dtype)
    out["open_loop"] = (roll.open_loop * keep).sum(-1) / keep.sum(-1).clamp_min(1)
    out["deviation"] = (x[..., :2] - scenes.ego[:, frames, :2]).norm(dim=-1).mean(-1)
    out["plannable"] = keep.mean(-1)
    return out


def closed_loop_scenes(scenes, cfg: Config, sim_time=10.0, scfg=None):
    """The scenes with a predicted agent at every simulated frame (all synthetic ones; real logs may
    lack one). ValueError when there are none (scenes None: the data has no scene logs), saying what
    the closed loop needs."""
    if scenes is None:
        raise ValueError("closed_loop: the data has no validation scene logs")
    scfg = scfg or data_synth.SynthConfig()
    H, T = scfg.hist, scfg.fut
    N = round(sim_time / cfg.dt)
    # (S, <=N) a predicted agent (with its 3 s future) at each frame
    window = scenes.pred_idx[:, H : H + N] >= 0
    ok = (
        (window.all(1) & (window.shape[1] == N))
        if len(scenes)
        else torch.zeros(0, dtype=torch.bool)
    )
    if not ok.any():
        run = window.int().cumprod(1).sum(1).max().item() if window.numel() else 0
        raise ValueError(
            f"closed_loop: a {sim_time:g} s closed loop needs scenes with a predicted agent at "
            f"each of its {N} frames after {H * cfg.dt:g} s of history, i.e. at least {H + N + T} "
            f"frames ({(H + N + T - 1) * cfg.dt:g} s at {1 / cfg.dt:g} Hz, the {T * cfg.dt:g} s "
            f"horizon included); the data has {len(scenes)} validation scene(s) of "
            f"{scenes.ego.shape[1]} frames, the best with a predicted agent for {run} frame(s) "
            f"from frame {H}"
        )
    return scenes[ok]


def closed_loop_experiment(
    data,
    val_scenes,
    cfg: Config,
    seeds=(0,),
    epochs=1.0,
    sim_time=10.0,
    log=print,
    models=None,
    device="cpu",
):
    """Table 5: the methods trained by the open-loop RL procedure, each simulated on every
    validation scene (the simulation on the CPU in float64, the stack on `device`). Returns
    ({method: [per seed: closed_loop_run's metrics, 'rel_*' as closed_loop_relative's]}, {method:
    (Rollout, per-scene metrics) of the first seed}, the scenes)."""
    scenes = closed_loop_scenes(val_scenes, cfg, sim_time)
    results, rollouts = {}, {}
    for m in CLOSED_LOOP_METHODS:
        for seed in seeds if m.predictor == "learned" else seeds[:1]:
            r, roll, per_scene = closed_loop_run(
                m, seed, scenes, data, cfg, epochs, sim_time, log, models, device
            )
            results.setdefault(m.name, []).append(r)
            rollouts.setdefault(m.name, (roll, per_scene))
    return closed_loop_relative(results), rollouts, scenes


def closed_loop_run(
    m: Method,
    seed,
    scenes,
    data,
    cfg: Config,
    epochs=1.0,
    sim_time=10.0,
    log=print,
    models=None,
    device="cpu",
    store=None,
):
    """One method and seed of Table 5 on the closed-loop scenes: (metric means over scenes, Rollout,
    per-scene metrics)."""
    t0 = time.time()
    model = None
    if m.predictor == "learned":
        model = trained_predictor(
            m, data, cfg, "rl", epochs, seed, log, models=models, device=device, store=store
        )
    t1 = time.time()
    roll = simulate(scenes, stack_policy(model, m, cfg, device), cfg, sim_time)
    per_scene = closed_loop_metrics(scenes, roll, cfg)
    r = {k: v.mean().item() for k, v in per_scene.items()}
    r.update(seconds=time.time() - t0, sim_seconds=time.time() - t1, scenes=len(scenes))
    if log:
        log(f"{m.name:14s} seed {seed}: {metrics_line(r)}")
    return r, roll, per_scene


def closed_loop_relative(results: dict) -> dict:
    """add_relative for Table 5: 'rel_<metric>' (x1e-2 vs No prediction's first run), in place."""
    return add_relative(results, "closed_loop")


# ---- 4. Ablations (App. A.1, Table 6), and where a perfect prediction is worth something ---------


def goal_breakdown(val, m: Method, cfg: Config, device="cpu", batch_size=512) -> dict:
    """Method m (No prediction or GT prediction: nothing trained) on the validation set under
    cfg.goal, by behaviour of the predicted vehicle: scenes, hindsight cost, its weighted terms and
    the share of scenes where the final ego trajectory comes within CLOSE of the predicted vehicle's
    GT future."""
    sums, dists = {}, {}
    for i in range(0, len(val), batch_size):
        batch = to_device(val[i : i + batch_size], device)
        out = run_stack(batch, None, m, cfg, "rl")
        w = cost_weights(cfg, out.s.dtype, device)
        s0 = batch.ego_hist[:, -1]
        goal = (
            batch.goal
            if cfg.goal == "logged"
            else route_goal(s0, batch.lanes, batch.lanes_mask, cfg)
        )
        ones = torch.ones(len(batch), device=device)
        _, hctx = cost_contexts(
            batch,
            torch.zeros(len(batch), 1, cfg.horizon, 2, device=device),
            ones[:, None],
            ones,
            goal=goal,
        )
        # terms: (B, 5) weighted, as they add up to the hindsight cost
        terms = cost_terms(out.s, out.u, hctx, cfg.rbf_var) * w
        closest = (out.s[:, 1:, :2] - batch.agent_fut[..., :2]).norm(dim=-1).min(-1).values  # (B,)
        for b in batch.behaviour[out.plannable].unique().tolist():
            rows = out.plannable & (batch.behaviour == b)
            name = data_synth.BEHAVIOURS[b] if b >= 0 else "real"
            acc = sums.setdefault(
                name,
                dict(n=0, hindsight=0.0, terms=torch.zeros(len(COST_TERMS), dtype=torch.float64)),
            )
            acc["n"] += rows.sum().item()
            acc["hindsight"] += out.hindsight[rows].sum().item()
            acc["terms"] += terms[rows].sum(0).double().cpu()
            dists.setdefault(name, []).append(closest[rows].cpu())
    by = {
        name: dict(
            n=a["n"],
            hindsight=a["hindsight"] / a["n"],
            terms=(a["terms"] / a["n"]).tolist(),
            close=(torch.cat(dists[name]) < CLOSE).float().mean().item(),
        )
        for name, a in sums.items()
    }
    n = sum(a["n"] for a in by.values())
    return dict(
        n=n, hindsight=sum(a["hindsight"] * a["n"] for a in by.values()) / n, by_behaviour=by
    )


def validation_spread(draws=5, n=VAL_N, cache_dir="data_cache", log=print) -> str:
    """Why the tables share one validation set of VAL_N samples: GT prediction's hindsight cost
    relative to No prediction (x1e-2, no training) on `draws` draws of validation scenes none of the
    tables uses (data seeds after VAL_SEED), each at the old size (the validation side of an
    n-sample draw: 1,500 of 10,000) and at n. A markdown table: each draw's value, and the mean and
    standard deviation over draws."""
    seeds = range(VAL_SEED + 1, VAL_SEED + 1 + draws)
    pair = (NO_PREDICTION, GT_PREDICTION)  # nothing trained
    cfg, rows = Config(), {}
    for seed in seeds:
        data = lab.data.load_data(None, n, seed, cache_dir, log)
        whole = data_synth.Scenarios.cat([data.train, data.val])
        for size, val in (("old", data.val), ("new", whole)):
            runs = {m.name: [evaluate_stack(None, val, m, cfg, "rl")] for m in pair}
            rel = add_relative(runs, "rl")["GT prediction"][0]["rel_hindsight"]
            rows.setdefault(size, []).append((len(val), rel))
    table = []
    for r in rows.values():
        values = [v for _, v in r]
        spread = f"{statistics.fmean(values):.2f} ± {statistics.stdev(values):.2f}"
        samples = f"{statistics.fmean(n for n, _ in r):,.0f}"
        table.append([samples, *(f"{v:.2f}" for v in values), spread])
    header = ["Validation samples", *(f"data seed {s}" for s in seeds), "mean ± s.d. over draws"]
    return markdown_table(header, table)


def main(argv=None):
    """python experiments.py: the command line, lab/tables.py's (a hand-over: running the tables,
    resuming them, their files and workers is the lab's)."""
    from lab import tables

    return tables.main(argv)


if __name__ == "__main__":
    main()
