"""The paper's experiments on diffstack.py: Tables 1-5, the ablations of App. A.1, the report.

    python experiments.py --experiment rl     # Table 1 (10 seeds) -> results/rl.json, results/rl.md
    python experiments.py --experiment all    # every table, results/report.md (40 epochs a method)
    python experiments.py --experiment all --seeds 5 --epochs 20 --out runs/epochs20
                                              # at the paper's length

Each table of the paper is a declarative TableSpec (specs.py: its methods, setting, loss weights,
metrics and the paper's own numbers), and one function, run_table, runs any of them (run_experiment:
what each result file records).

Map of the module:
    1. Training       trained_predictor: a predictor is trained once per (method, seed, ...) and
                      shared by the tables
    2. Cost learning  Table 3, the learned cost weights (App. A.2, Table 7)
    3. Closed loop    log replay (§4.3, Table 5, App. D.3)
    4. Ablations      App. A.1; the goal table (what a perfect prediction is worth, by behaviour)
    5. Running        a table's pieces, computed and assembled (run_table), the report, the command
                      line; under it, lab/runs.py (resuming, provenance, worker processes, progress)
                      and figures.py
Over it, specs.py: Column, Claim, TableSpec, and the paper's tables: 1, 2, 3, 4, 5 and the ablations
(App. A.1, Table 6).

Shape letters as in diffstack.py; in the closed loop, as in data_synth.py, S counts scenes and N
simulation steps.
"""

from __future__ import annotations

import json
import os
import pickle
import statistics
import sys
import time

import torch

import data_real
import data_synth
from diffstack import (
    COST_TERMS,
    Config,
    Predictor,
    cost_contexts,
    cost_terms,
    cost_weights,
    route_goal,
    run_stack,
)
from lab.stats import markdown_table
from train import (
    CostWeights,
    Method,
    TABLE1_METHODS,
    TrainingDiverged,
    add_relative,
    alphas,
    compare_methods,
    evaluate_stack,
    to_device,
    train_predictor,
    train_stack,
    VAL_N,
    VAL_SEED,
    simulate,
    stack_policy,
    closed_loop_metrics,
    closed_loop_scenes,
)

# hand-over: the command line's argument types and checks, shared with diffstack.py's

# hand-over: the lab's run machinery (the resume store, files written whole, locks, workers)
from lab.runs import (
    first_non_finite,
    load_json,
    save_atomic,
    write_atomic,
)
from specs import (
    CLOSED_LOOP_METHODS,
    CLOSED_LOOP_METRICS,
    CLOSE,
    COST_WEIGHTS_ROW,
    CURVE_SAMPLES,
    GOALS,
    TableSpec,
)
from specs import TABLES as TABLES  # tutorial.py reads them as experiments.TABLES

# hand-over: the tables' text (markdown, the claims' lines, the report) is lab/report.py's; the
# notebook and the course read three of its functions as experiments'
from lab.report import behaviour_markdown as behaviour_markdown
from lab.report import claim_line as claim_line
from lab.report import gap_closed as gap_closed


# ============================================================================================
# 1. Training, shared between tables
# ============================================================================================


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
    kw = dict(stack_kw)
    runs_stack = True
    if a[1:] == (0, 0):
        kw = {}
        runs_stack = False
    elif a[2] == 0:
        kw.pop("controller", None)
    plan_weights = (m.train_plan_weights or cfg.train_plan_weights) if runs_stack else None
    key = (
        a,
        method_key(m)[3],  # the weighting, by name
        seed,
        epochs,
        pred_offset,
        str(device),
        setting if runs_stack else None,
        tuple(sorted(kw.items())),
    )
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


def non_finite(o) -> str | None:
    """The first number in o (nested dicts and lists) that is NaN or infinite, as 'a.1.b, not a
    number' (or 'infinite'); None when every one is finite."""
    found = first_non_finite(o)
    if found is None:
        return None
    keys, v = found
    return f"{'.'.join(map(str, keys)) or 'a value'}, " + ("not a number" if v != v else "infinite")


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
            log(
                f"  [{m.name}] seed {seed}: trained by an earlier piece of this run, loaded from "
                f"{path}"
            )
    else:
        model = train_predictor(
            m,
            data,
            cfg,
            setting,
            epochs,
            seed,
            log,
            pred_offset,
            device=device,
            curve_samples=CURVE_SAMPLES,
            **stack_kw,
        )
        bad = non_finite(getattr(model, "learning_curve", None) or [])
        if bad is not None:  # neither file is written: a result is never written with NaN
            raise TrainingDiverged(f"{m.name}, seed {seed}: its learning curve holds {bad}")
        if path is not None:  # the curve first: a model file on disk always has its curve beside it
            path.parent.mkdir(parents=True, exist_ok=True)
            write_atomic(path.with_suffix(".curve.json"), json.dumps(model.learning_curve))
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
    **stack_kw,
) -> dict:
    """train.compare_methods with predictors shared through `models` (trained_predictor), run on
    `device`."""

    def train(m, *a, **k):
        return trained_predictor(m, *a, models=models, **k)

    return compare_methods(
        data,
        cfg,
        setting,
        methods,
        tuple(seeds),
        epochs,
        pred_offset,
        log,
        train,
        device,
        **stack_kw,
    )


# ============================================================================================
# 2. Cost learning (§4.2, Table 3; App. A.2, Table 7)
# ============================================================================================


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
    model = trained_predictor(
        Method("Standard"),
        data,
        cfg,
        "il",
        epochs,
        seed,
        log,
        models=models,
        device=device,
        store=store,
    )
    weights = CostWeights(cfg).to(device)
    for name in ("Hand-tuned", "Learned"):
        if name == "Learned":
            train_stack(
                model,
                data.train_for(seed),
                COST_WEIGHTS_ROW,
                cfg,
                "il",
                epochs,
                seed,
                log,
                weights=weights,
            )
        with torch.no_grad():
            w = weights()
            w_norm = weights.normalised()
            alpha = weights.alpha.item()
        res[name] = r = evaluate_stack(
            model, data.val, Method("Standard"), cfg, "il", w=w, device=device
        )
        r.update(w=w_norm.tolist(), alpha=alpha)
        if log:
            log(
                f"{name:10s} seed {seed}: w' "
                + " ".join(f"{v:.3f}" for v in r["w"])
                + f"  alpha {alpha:.3f}  plan_loss {r['plan_loss']:.4f}  mse {r['mse']:.4f}"
            )
    return res


# ============================================================================================
# 3. Closed loop: log replay (§4.3, Table 5, App. D.3)
# ============================================================================================
# The simulation (simulate, stack_policy, closed_loop_metrics, closed_loop_scenes) is closed-loop
# evaluation, in train.py; here, the table's runs.


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
        log(
            f"{m.name:14s} seed {seed}: "
            + "  ".join(f"{k} {v:.4f}" for k, v in r.items() if isinstance(v, float))
        )
    return r, roll, per_scene


def closed_loop_relative(results: dict) -> dict:
    """Add 'rel_<metric>' (x1e-2 vs No prediction's first run) to every run of {method: [per seed]},
    in place."""
    base = results["No prediction"][0]
    for r in (r for runs in results.values() for r in runs):
        for k in CLOSED_LOOP_METRICS:
            if k in r:  # (a diverged seed has no metrics)
                r["rel_" + k] = (r[k] - base[k]) / 1e-2
    return results


# ============================================================================================
# 4. Ablations (App. A.1, Table 6), and where a perfect prediction is worth something
# ============================================================================================


def goal_breakdown(val, m: Method, cfg: Config, device="cpu", batch_size=512) -> dict:
    """Method m (No prediction or GT prediction: nothing trained) on the validation set under
    cfg.goal, by behaviour of the predicted vehicle: scenes, hindsight cost, its weighted terms and
    the share of scenes where the final ego trajectory comes within CLOSE of the predicted vehicle's
    GT future."""
    sums, dists = {}, {}
    for i in range(0, len(val), batch_size):
        batch = to_device(val[i : i + batch_size], device)
        out = run_stack(batch, None, m, cfg, "rl")
        w = cost_weights(cfg, out.x.dtype, device)
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
        terms = cost_terms(out.x, out.u, hctx, cfg.rbf_var) * w
        closest = (out.x[:, 1:, :2] - batch.agent_fut[..., :2]).norm(dim=-1).min(-1).values  # (B,)
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
    gt, no = (
        next(m for m in TABLE1_METHODS if m.name == name)
        for name in ("GT prediction", "No prediction")
    )
    rows = {}
    cfg = Config()
    for seed in range(VAL_SEED + 1, VAL_SEED + 1 + draws):
        data = data_real.load_data(None, n, seed, cache_dir, log)
        for size, val in (
            ("old", data.val),
            ("new", data_synth.Scenarios.cat([data.train, data.val])),
        ):
            res = add_relative(
                {m.name: [evaluate_stack(None, val, m, cfg, "rl")] for m in (no, gt)}, "rl"
            )
            rows.setdefault(size, []).append((len(val), res["GT prediction"][0]["rel_hindsight"]))
    return markdown_table(
        [
            "Validation samples",
            *(f"data seed {s}" for s in range(VAL_SEED + 1, VAL_SEED + 1 + draws)),
            "mean ± s.d. over draws",
        ],
        [
            [
                f"{statistics.fmean(n for n, _ in r):,.0f}",
                *(f"{v:.2f}" for _, v in r),
                f"{statistics.fmean(v for _, v in r):.2f} ± "
                f"{statistics.stdev(v for _, v in r):.2f}",
            ]
            for r in rows.values()
        ],
    )


def main(argv=None):
    """python experiments.py: the command line, lab/tables.py's (a hand-over: running the tables,
    resuming them, their files and workers is the lab's)."""
    from lab import tables

    return tables.main(argv)


if __name__ == "__main__":
    main()
