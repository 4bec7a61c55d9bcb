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

import argparse
import collections
import contextlib
import dataclasses
import functools
import json
import os
import pathlib
import pickle
import re
import statistics
import sys
import time
from typing import NamedTuple

import torch
import torch.distributed as dist
from tqdm import tqdm

import data_real
import data_synth
import figures
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
    GT_PREDICTION,
    NO_PREDICTION,
    TABLE1_METHODS,
    TrainingDiverged,
    add_relative,
    alphas,
    compare_methods,
    evaluate_stack,
    to_device,
    train_predictor,
    train_stack,
    experiment_data,
    VAL_N,
    VAL_SEED,
    Rollout,
    simulate,
    stack_policy,
    closed_loop_metrics,
    closed_loop_scenes,
)

# hand-over: the command line's argument types and checks, shared with diffstack.py's
from lab.cli import bounded, check_writable, config_with, device_arg, machine

# hand-over: the lab's run machinery (the resume store, files written whole, locks, workers)
from lab.runs import (
    RUNS_DIR,
    OutputRefused,
    RunStore,
    above,
    code_version,
    command_line,
    compute_in_workers,
    die_with_parent,
    default_threads,
    first_non_finite,
    folder_lock,
    ranks,
    git_commit,
    one_line,
    ours_files,
    outputs_manifest,
    planned_outputs,
    progress,
    load_json,
    read_results,
    record_outputs,
    refuse_existing,
    results_json,
    run_key,
    save_atomic,
    write_atomic,
)
from specs import (
    ABLATION_SECTIONS,
    CLOSED_LOOP_METHODS,
    CLOSED_LOOP_METRICS,
    CLOSE,
    COST_WEIGHTS_ROW,
    CURVE_SAMPLES,
    EXPERIMENTS,
    GOALS,
    REAL,
    REAL_OUT,
    SPECS,
    TableSpec,
)
from specs import TABLES as TABLES  # tutorial.py reads them as experiments.TABLES

# hand-over: the tables' text (markdown, the claims' lines, the report) is lab/report.py's; the
# notebook and the course read three of its functions as experiments'
from lab.report import behaviour_markdown as behaviour_markdown
from lab.report import claim_line as claim_line
from lab.report import gap_closed as gap_closed
from lab.report import (
    has_curves,
    results_markdown,
    section_markdown,
    table_file_markdown,
    write_report,
)


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


# ============================================================================================
# 5. Running a spec, the report, the command line
# ============================================================================================


# --------------------------------------------------------------------------------------------
# 5.1 Pieces: each (table, method, seed) result, computed alone; the units of worker processes
# --------------------------------------------------------------------------------------------
# A table's pieces, and its trained predictors, are kept and resumed by runs.RunStore (lab/runs.py:
# where, which key).


class Piece(NamedTuple):
    """One result of a table: a method (Table 3: its one row, both weightings) and a seed; section:
    the ablation section's title, or the goal table's goal (None elsewhere)."""

    method: str
    seed: int
    section: str | None = None

    @property
    def stem(self) -> str:

        def slug(text):
            return re.sub(r"[^A-Za-z0-9]+", "_", text).strip("_")

        return (
            f"{slug(self.section)}--" if self.section is not None else ""
        ) + f"{slug(self.method)}-seed{self.seed}"


def _rows(methods, seeds, section=None) -> list:
    """The pieces of some methods: every seed of a learned one, the first seed only of the others
    (no training)."""
    return [
        Piece(m.name, s, section)
        for m in methods
        for s in (seeds if m.predictor == "learned" else seeds[:1])
    ]


def _ablation_methods(methods) -> tuple:
    return (NO_PREDICTION, *methods, GT_PREDICTION)


def table_seeds(spec: TableSpec, seeds=None) -> tuple:
    """The training seeds of a table: those given, else the spec's own count (Table 1: 10, the
    others 5)."""
    return tuple(range(spec.seeds)) if seeds is None else tuple(seeds)


def table_pieces(spec: TableSpec, seeds) -> list:
    """Every piece of a table, in the order a one-process run makes them."""
    seeds = tuple(seeds)
    if spec.kind == "cost":
        return [Piece(COST_WEIGHTS_ROW.name, s) for s in seeds]
    if spec.kind == "ablation":
        return [
            p
            for title, _, methods in ABLATION_SECTIONS
            for p in _rows(_ablation_methods(methods), seeds, title)
        ]
    if spec.kind == "goal":
        return [p for goal in GOALS for p in _rows(spec.methods, seeds, goal)]
    return _rows(spec.methods, seeds)


def piece_method(spec: TableSpec, piece: Piece) -> tuple:
    """(method, setting, target offset, run_stack options) of a piece of any table but Table 3."""
    if spec.kind == "ablation":
        _, stack_kw, methods = next(s for s in ABLATION_SECTIONS if s[0] == piece.section)
        return (
            next(m for m in _ablation_methods(methods) if m.name == piece.method),
            "rl",
            0.0,
            stack_kw,
        )
    return (
        next(m for m in spec.methods if m.name == piece.method),
        spec.setting,
        spec.pred_offset,
        {},
    )


# the first item of Table 3's cost-weight training in piece_trainings' keys
COST_WEIGHTS = "cost weights"


def piece_trainings(spec: TableSpec, piece: Piece, cfg: Config, epochs, device="cpu") -> tuple:
    """What a piece trains unless another piece has trained it already (timed_piece's 'trained'):
    its predictor's training_key as compute_piece's, and Table 3's cost weights; () for No
    prediction, GT prediction, the goal table."""
    if spec.kind == "cost":
        return (
            training_key(Method("Standard"), cfg, "il", epochs, piece.seed, 0.0, device),
            (COST_WEIGHTS, piece.seed),
        )
    m, setting, pred_offset, stack_kw = piece_method(spec, piece)
    if spec.kind == "goal" or m.predictor != "learned":
        return ()
    return (training_key(m, cfg, setting, epochs, piece.seed, pred_offset, device, **stack_kw),)


def compute_piece(
    spec: TableSpec,
    piece: Piece,
    data,
    cfg: Config,
    epochs,
    log=print,
    models=None,
    device="cpu",
    store=None,
):
    """Train (or take from models / store) and evaluate one piece: (its result before the values
    relative to No prediction, which assemble adds; a dict of tensors to keep beside it or None). A
    training that diverges is a result too ({'diverged': what}: a resumed run does not retrain it,
    and the table says which seed is left out), and so is one whose evaluation gives a value that is
    not finite (a result is never written with NaN)."""
    try:
        result, extra = piece_result(spec, piece, data, cfg, epochs, log, models, device, store)
        bad = non_finite(result)
        if bad is not None:
            raise TrainingDiverged(f"{piece.stem}: its evaluation gave {bad}")
        return result, extra
    except TrainingDiverged as e:
        if log:
            log(f"  {piece.stem}: {e}")
        return dict(diverged=str(e)), None


def non_finite(o) -> str | None:
    """The first number in o (nested dicts and lists) that is NaN or infinite, as 'a.1.b, not a
    number' (or 'infinite'); None when every one is finite."""
    found = first_non_finite(o)
    if found is None:
        return None
    keys, v = found
    return f"{'.'.join(map(str, keys)) or 'a value'}, " + ("not a number" if v != v else "infinite")


def piece_result(
    spec: TableSpec,
    piece: Piece,
    data,
    cfg: Config,
    epochs,
    log=print,
    models=None,
    device="cpu",
    store=None,
):
    """compute_piece's work: the piece's result, or TrainingDiverged."""
    if spec.kind not in ("open_loop", "real", "ablation", "goal", "closed_loop", "cost"):
        raise ValueError(f"spec.kind: unknown kind {spec.kind!r}")
    if spec.kind == "cost":
        return cost_learning_seed(data, cfg, piece.seed, epochs, log, models, device, store), None
    m, setting, pred_offset, stack_kw = piece_method(spec, piece)
    if spec.kind == "goal":
        return goal_breakdown(
            data.val, m, dataclasses.replace(cfg, goal=piece.section), device
        ), None
    if spec.kind == "closed_loop":
        scenes = closed_loop_scenes(data.val_scenes, cfg)
        r, roll, per_scene = closed_loop_run(
            m,
            piece.seed,
            scenes,
            data,
            cfg,
            epochs,
            log=log,
            models=models,
            device=device,
            store=store,
        )
        return r, dict(rollout=dataclasses.asdict(roll), per_scene=per_scene)

    def train(m, *a, **k):
        return trained_predictor(m, *a, models=models, store=store, **k)

    return compare_methods(
        data,
        cfg,
        setting,
        (m,),
        (piece.seed,),
        epochs,
        pred_offset,
        log,
        train,
        device,
        **stack_kw,
    )[m.name][0], None


def assemble(spec: TableSpec, pieces: dict, seeds) -> dict:
    """A table's results from its pieces {Piece: result}, as its experiment function returns them
    in one run."""
    seeds = tuple(seeds)

    def rows(methods, section=None):
        # a copy: the relative values are added
        return {
            m.name: [
                json.loads(json.dumps(pieces[Piece(m.name, s, section)]))
                for s in (seeds if m.predictor == "learned" else seeds[:1])
            ]
            for m in methods
        }

    if spec.kind in ("open_loop", "real"):
        return add_relative(rows(spec.methods), spec.setting)
    if spec.kind == "ablation":
        return {
            title: add_relative(rows(_ablation_methods(methods), title), "rl")
            for title, _, methods in ABLATION_SECTIONS
        }
    if spec.kind == "cost":
        runs = [pieces[Piece(COST_WEIGHTS_ROW.name, s)] for s in seeds]
        return {
            name: [r[name] if name in r else r for r in runs] for name in ("Hand-tuned", "Learned")
        }
    if spec.kind == "goal":
        return {goal: rows(spec.methods, goal) for goal in GOALS}
    if spec.kind == "closed_loop":
        return closed_loop_relative(rows(spec.methods))
    raise ValueError(f"spec.kind: unknown kind {spec.kind!r}")


def timed_piece(
    spec: TableSpec, piece: Piece, data, cfg: Config, epochs, log, models, device, store
):
    """compute_piece, how long it took, where, and whether it trained: (result, extra, {'seconds':
    wall, 'cpu_seconds': this process's CPU, 'machine': lab.cli.machine() (the same seed gives other
    numbers on another kind of processor), 'trained': it trained something no piece had trained
    before it (piece_trainings)})."""

    # by an earlier piece: in this process's models, or in the store on disk
    def trained_before(key) -> bool:
        path = store.model_path(key) if store is not None and key[0] != COST_WEIGHTS else None
        return key in (models or {}) or (path is not None and path.exists())

    trains = not all(
        trained_before(key) for key in piece_trainings(spec, piece, cfg, epochs, device)
    )
    t0, c0 = time.time(), time.process_time()
    result, extra = compute_piece(spec, piece, data, cfg, epochs, log, models, device, store)
    return (
        result,
        extra,
        dict(
            seconds=time.time() - t0,
            cpu_seconds=time.process_time() - c0,
            machine=machine(),
            trained=trains,
        ),
    )


def run_about(spec: TableSpec, store: RunStore, cfg: Config, epochs, device, data) -> dict:
    """What a table's run key stands for (run.json in its folder of pieces)."""
    return dict(
        table=spec.name,
        run_key=store.key,
        config=dataclasses.asdict(cfg),
        epochs=epochs,
        code=code_version() if store.root is not None else None,
        device=str(device),
        train=len(data.train),
        val=len(data.val),
    )


def _compute(
    table: str, piece: Piece, log, models, store, data=None, cfg=None, epochs=1.0, device="cpu"
):
    """timed_piece of the table named `table`: what a worker process computes (in_workers)."""
    return timed_piece(SPECS[table], piece, data, cfg, epochs, log, models, device, store)


def in_workers(
    units: list, data, cfg: Config, epochs, device, store: RunStore, jobs: int, verbose=True
):
    """runs.compute_in_workers of units (table name, pieces of one seed), computed by
    timed_piece."""
    compute = functools.partial(_compute, data=data, cfg=cfg, epochs=epochs, device=device)
    abouts = {name: run_about(SPECS[name], store, cfg, epochs, device, data) for name, _ in units}
    compute_in_workers(compute, units, store, jobs, abouts, verbose)


def work_units(names, seeds: dict, store: RunStore) -> list:
    """The missing pieces of several tables as units for in_workers, one per (table, ablation
    section, seed): the longest (the ablation's) first, so that the short ones fill the workers at
    the end; within a table the seeds alternate, so that two workers never train the same predictor
    (the later units load it from the store)."""
    units = []
    for name in sorted(names, key=lambda n: SPECS[n].kind != "ablation"):
        pieces = [p for p in table_pieces(SPECS[name], seeds[name]) if not store.has(name, p)]
        units += [
            (name, unit)
            for section in dict.fromkeys(p.section for p in pieces)
            for seed in seeds[name]
            if (unit := [p for p in pieces if p.section == section and p.seed == seed])
        ]
    return units


def run_table(
    spec: TableSpec,
    data,
    cfg: Config,
    seeds=(0,),
    epochs=1.0,
    out_dir="results",
    log=print,
    models=None,
    device="cpu",
    write=True,
    store=None,
    jobs=1,
):
    """Train and evaluate what a table's spec declares on `device`, its figures into out_dir if
    `write`. models: the predictors the tables of one run share; store: a RunStore keeping every
    piece (None: in memory); jobs > 1 (a store on disk): the seeds' pieces in that many one-thread
    worker processes. Returns (results, markdown table)."""
    seeds = tuple(seeds)
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    models = {} if models is None else models
    store = RunStore(None, "") if store is None else store
    if spec.kind == "closed_loop":
        closed_loop_scenes(data.val_scenes, cfg)
    about = run_about(spec, store, cfg, epochs, device, data)
    pieces = table_pieces(spec, seeds)
    missing = [p for p in pieces if not store.has(spec.name, p)]
    if log and len(missing) < len(pieces):
        reused = [p.stem for p in pieces if p not in missing]
        log(
            f"{spec.name}: {len(reused)} of {len(pieces)} pieces done by an earlier run of the "
            "same key, reused from "
            f"{store.table_dir(spec.name) if store.root is not None else 'memory'}: "
            f"{', '.join(reused)}"
        )
    by_seed = {
        s: [p for p in missing if p.seed == s] for s in dict.fromkeys(p.seed for p in missing)
    }
    if jobs > 1 and store.root is not None and len(by_seed) > 1:
        if log:
            log(
                f"{spec.name}: {len(missing)} pieces of {len(by_seed)} seeds in "
                f"{min(jobs, len(by_seed))} worker processes, one thread each"
            )
        in_workers(
            [(spec.name, ps) for ps in by_seed.values()],
            data,
            cfg,
            epochs,
            device,
            store,
            jobs,
            log is not None,
        )
    else:
        for p in missing:
            result, extra, timing = timed_piece(
                spec, p, data, cfg, epochs, log, models, device, store
            )
            store.save(spec.name, p, result, extra, about, timing)
    loaded = {p: store.load(spec.name, p) for p in pieces}
    res = assemble(spec, {p: r for p, (r, _) in loaded.items()}, seeds)

    def first_pair():  # the first seed's Standard and DiffStack, the predictors the figures compare
        return {
            m.name: trained_predictor(
                m, data, cfg, "rl", epochs, seeds[0], log, models=models, device=device, store=store
            )
            for m in spec.methods[1:3]
        }

    if write and spec.kind == "cost":
        figures.figure_cost_weights(res, out / "cost_weights.png")
    elif write and "learning_curves.png" in spec.figures and has_curves(res):
        figures.figure_learning_curves(
            res,
            out / "learning_curves.png",
            figures.learning_curve_reference(data, cfg, CURVE_SAMPLES),
        )
    elif write and spec.kind == "closed_loop":
        # the first seed's rollouts (a diverged training has none)
        rollouts = {
            p.method: (Rollout(**extra["rollout"]), extra["per_scene"])
            for p, (_, extra) in loaded.items()
            if p.seed == seeds[0] and extra is not None
        }
        figures.figure_closed_loop(
            closed_loop_scenes(data.val_scenes, cfg), rollouts, out / "closed_loop.png", cfg.dt
        )
        try:
            figures.figure_stack_example(data, first_pair(), cfg, out / "stack_example.png")
        except TrainingDiverged as e:  # the figure needs seed 0's two predictors
            if log:
                log(f"stack_example.png not drawn: {e}")
    elif write and spec.kind == "real":
        figures.figure_real_scenes(data.val, first_pair(), cfg, out / "real_scenes.png")
    return res, results_markdown(spec, res)


def check_outputs(names, out_dir, overwrite: bool, ours=()) -> None:
    """Before any work: out_dir must be writable, and no file a run of these tables would write may
    exist already unless overwrite or it is in ours (runs.refuse_existing). OutputRefused naming the
    folder or the files."""
    here = pathlib.Path(__file__).resolve().parent
    out = pathlib.Path(out_dir).resolve()

    def inside(folder):
        return folder == out or folder in out.parents

    # before check_writable makes the folder
    if REAL.name in names and inside(here) and not inside(here / "runs"):
        raise OutputRefused(
            f"--out {out_dir}: the real-scene results derive from the Waymo Open Dataset, whose "
            "licence forbids committing them; inside this repository they go under runs/ "
            f"(git-ignored; default {REAL_OUT}/), or write them outside it"
        )
    try:
        check_writable(out_dir, "--out")
    except ValueError as e:
        raise OutputRefused(str(e)) from None
    refuse_existing(planned_outputs(out_dir, {n: SPECS[n].figures for n in names}), overwrite, ours)


def render_markdown(name: str, out_dir="results") -> pathlib.Path:
    """Re-write out_dir/<name>.md from out_dir/<name>.json, running nothing: for when the way a
    table is written changes (e.g. the claim lines) but its numbers do not. Returns the
    path written."""
    src, _, section, _ = rendered(name, out_dir)
    write_atomic(src.with_suffix(".md"), table_file_markdown(SPECS[name], section))
    return src.with_suffix(".md")


def rendered(name: str, out_dir) -> tuple:
    """(out_dir/<name>.json, its contents, its section's markdown, the Config of its learning
    curves or None), every field render reads checked: ValueError naming the file and the field,
    before anything is written."""
    if name not in SPECS:
        raise ValueError(f"name: {name!r} is not an experiment ({', '.join(SPECS)})")
    src = pathlib.Path(out_dir) / f"{name}.json"
    if not src.exists():
        raise ValueError(f"out_dir: no {src} to render {name} from")
    saved = read_results(src)
    spec = SPECS[name]
    try:
        section = section_markdown(spec, saved["meta"], results_markdown(spec, saved["results"]))
        config = saved["meta"].get("config")
        cfg = None
        if "learning_curves.png" in spec.figures and has_curves(saved["results"]):
            cfg = Config(**{k: tuple(v) if isinstance(v, list) else v for k, v in config.items()})
    except KeyError as e:
        raise ValueError(f"{src}: not a {name} table's results (field {e} missing)") from None
    except (TypeError, ValueError, IndexError, AttributeError, ZeroDivisionError) as e:
        why = " ".join(str(e).split())[:200]
        raise ValueError(f"{src}: not a {name} table's results ({why})") from None
    return src, saved, section, cfg


def render_outputs(
    name: str, out_dir="results", data=None, cfg: Config | None = None, log=print
) -> list:
    """Re-write the .md files and learning curves (their reference lines when `data` is given) of an
    earlier run of `name` ('all': every table and report.md) from its JSON files in out_dir,
    training nothing; every file is read and checked before the first is written. Returns the
    paths."""
    names = EXPERIMENTS if name == "all" else (name,)
    out = pathlib.Path(out_dir)
    done = {one: rendered(one, out) for one in names}
    written = []
    sections = []
    for one, (src, saved, section, cfg_run) in done.items():
        spec = SPECS[one]
        write_atomic(src.with_suffix(".md"), table_file_markdown(spec, section))
        written.append(src.with_suffix(".md"))
        if cfg_run is not None:  # (no learning curves in older runs)
            ref = (
                figures.learning_curve_reference(data, cfg_run, CURVE_SAMPLES)
                if data is not None
                else None
            )
            figures.figure_learning_curves(saved["results"], out / "learning_curves.png", ref)
            written.append(out / "learning_curves.png")
        sections.append((spec.title, section, [f for f in spec.figures if (out / f).exists()]))
    if name == "all":
        metas = [saved["meta"] for _, saved, _, _ in done.values()]
        tables = {one: saved["results"] for one, (_, saved, _, _) in done.items()}
        written.append(write_report(out, sections, metas, rendered=True, tables=tables))
    if log:
        log("rendered: " + ", ".join(str(p) for p in written))
    return written


def run_experiment(
    name,
    data,
    cfg: Config,
    seeds,
    epochs,
    out_dir="results",
    command="",
    log=print,
    overwrite=False,
    device="cpu",
    write=True,
    jobs=1,
    progress_every=2.0,
):
    """Run one table (or 'all', each predictor trained once for every table) on `device`, writing
    out_dir/<name>.json (results, the full Config, the device, the git commit), .md and the figures
    (for 'all', report.md too) unless write=False (torchrun's other ranks). Every piece is kept in
    out_dir/.runs/: re-running the command resumes it. A progress bar while log and write.
    OutputRefused when a file it would write exists, unless overwrite or this same run wrote
    it as is."""
    names = EXPERIMENTS if name == "all" else (name,)
    out = pathlib.Path(out_dir)
    per_table = {one: table_seeds(SPECS[one], seeds) for one in names}
    seeds = tuple(seeds) if seeds is not None else None
    processes = dist.get_world_size() if dist.is_available() and dist.is_initialized() else 1
    # under torchrun every rank must train the same pieces together: nothing is kept or
    # resumed there
    root = out / RUNS_DIR if write and processes == 1 else None
    # no run wrote outputs here: check before hashing the data
    if root is None or not (root / "outputs").is_dir():
        check_outputs(names, out_dir, overwrite)
    store = RunStore(
        root, run_key(data, cfg, epochs, device), {n: spec_key(SPECS[n]) for n in names}
    )
    manifest = outputs_manifest(out, name, seeds or (), store.key)
    check_outputs(
        names, out_dir, overwrite, ours=ours_files(out, [manifest]) if root is not None else ()
    )
    sections = []
    metas = []
    models = {}
    tables = {}
    all_pieces = [(one, p) for one in names for p in table_pieces(SPECS[one], per_table[one])]
    # worker processes only where there are seeds to share out (the goal table has one run per row)
    jobs = (
        max(1, min(jobs, len({p.seed for _, p in all_pieces}))) if write and processes == 1 else 1
    )
    if store.root is not None and log:
        log(
            f"run key {store.key[:16]}: {len(all_pieces)} pieces (table, method, seed), kept in "
            f"{out / RUNS_DIR} as they finish"
            + (f"; {jobs} worker processes of one thread" if jobs > 1 else "")
        )
    with progress(store, all_pieces, progress_every, disable=not (log and write)) as bar:
        log = above(bar, log) if log else log
        units = (
            work_units(names, per_table, store)
            if jobs > 1 and store.root is not None and len(names) > 1
            else []
        )
        # every table's pieces in one pool of workers (then each table below finds its pieces done)
        if units:
            if log:
                log(
                    f"{sum(len(u) for _, u in units)} pieces in {len(units)} units (table, seed) "
                    f"over {jobs} worker processes, one thread each"
                )
            in_workers(units, data, cfg, epochs, device, store, jobs, log is not None)
        for one in names:
            spec = SPECS[one]
            t0 = time.time()
            seeds_one = per_table[one]
            res, table = run_table(
                spec, data, cfg, seeds_one, epochs, out, log, models, device, write, store, jobs
            )
            tables[one] = res
            threads = (
                f"{torch.get_num_threads()} threads"
                if jobs == 1
                else f"1 thread per process, {jobs} worker processes (--jobs)"
            )
            timings = [store.timing(one, p) for p in table_pieces(spec, seeds_one)]
            piece_time = {}
            # the table's computing time, summed over its pieces, whenever they ran
            if timings and all(timings):
                piece_time = dict(
                    piece_seconds=sum(t["seconds"] for t in timings),
                    piece_cpu_seconds=sum(t["cpu_seconds"] for t in timings),
                    pieces=len(timings),
                )
            computed_on = collections.Counter(t["machine"] for t in timings if t and "machine" in t)
            if len(computed_on) > 1:  # not all on one machine (a run resumed on another host, say)
                piece_time["computed_on"] = dict(computed_on)
            meta = dict(
                experiment=one,
                command=command,
                seeds=list(seeds_one),
                epochs=epochs,
                seconds=time.time() - t0,
                **piece_time,
                date=time.strftime("%Y-%m-%d"),
                train=len(data.train),
                val=len(data.val),
                data_seeds=list(seeds_one) if data.train_draws is not None else None,
                machine=f"{machine()}, torch {torch.__version__}, {threads}"
                + (f" per process, {processes} processes (DDP)" if processes > 1 else ""),
                device=str(device),
                git_commit=git_commit(),
                config=dataclasses.asdict(cfg),
            )
            md = section_markdown(spec, meta, table) if write else table
            if write:
                write_atomic(
                    out / f"{one}.json",
                    results_json(dict(meta=meta, results=res), str(out / f"{one}.json")),
                )
                write_atomic(out / f"{one}.md", table_file_markdown(spec, md))
                if store.root is not None:
                    record_outputs(
                        manifest,
                        [out / f"{one}.json", out / f"{one}.md"] + [out / f for f in spec.figures],
                    )
                metas.append(meta)
                if log:
                    log(f"\n{spec.title}\n{table}")
            sections.append((spec.title, md, list(spec.figures)))
    timings = [store.timing(one, p) for one, p in all_pieces] if store.root is not None else []
    if log and timings and all(timings):
        total = sum(t["seconds"] for t in timings)
        log(
            f"computing time summed over the {len(timings)} pieces (whenever they ran): "
            f"{tqdm.format_interval(total)}"
            + (
                f", {tqdm.format_interval(total / jobs)} of wall time on {jobs} workers sharing "
                "it evenly"
                if jobs > 1
                else ""
            )
        )
    if name == "all" and write:
        report = write_report(out, sections, metas, tables=tables)
        if store.root is not None:
            record_outputs(manifest, [report])
        if log:
            log(f"report: {report}")
    return sections


class RealData(NamedTuple):
    """Training samples (synthetic), and the real samples as the validation side, grouped
    by scene."""

    train: data_synth.Scenarios
    val: data_synth.Scenarios
    val_scenes: None = None  # no closed loop on the real logs
    val_groups: dict = {}  # {scene name: number of its samples}, in the order of val
    # the synthetic training draws, one per seed (Dataset.train_for)
    train_draws: tuple | None = None

    train_for = data_synth.Dataset.train_for


def real_data(data, phases=(0,), cache_dir="data_cache", log=print) -> RealData:
    """data's (synthetic) training side, and the Waymo samples (fetched on the first call) as the
    validation side."""
    real, report = data_real.load_waymo_scenarios(cache_dir, tuple(phases), log=log)
    log(
        f"real: {report['samples']} samples from {report['files']} Waymo logs "
        f"({len(tuple(phases))} 2 Hz phase(s) each), training on {len(data.train)} synthetic "
        f"samples. {data_real.WAYMO_LICENCE}"
    )
    return RealData(data.train, real, None, report["samples_per_scene"], data.train_draws)


def start_distributed(device: torch.device) -> torch.device:
    """Join torchrun's process group (named by its environment): gloo on CPUs, nccl on GPUs, each
    rank on its own, cuda:LOCAL_RANK. Returns this rank's device; train_stack then trains with
    DistributedDataParallel."""
    if device.type == "cuda":
        local = int(os.environ.get("LOCAL_RANK", 0))
        if local >= torch.cuda.device_count():
            raise ValueError(
                f"--device {device}: rank {local} of this machine needs cuda:{local}, but there "
                f"are {torch.cuda.device_count()} CUDA devices; start at most that many "
                "processes per machine"
            )
        device = torch.device("cuda", local)
        torch.cuda.set_device(device)
        dist.init_process_group("nccl", device_id=device)
    elif device.type == "cpu":
        dist.init_process_group("gloo")
    else:
        raise ValueError(
            f"--device {device}: torchrun trains on cpu (gloo) or cuda (nccl), not {device.type}"
        )
    return device


def main(argv=None):
    # Under torchrun every process runs main: all ranks train together (DDP) and evaluate alike;
    # rank 0 prints, writes
    rank, world, misuse = ranks()
    if misuse:  # every process says it: none of them can reach the others
        print(f"experiments.py: error: {misuse}", file=sys.stderr)
        sys.exit(2)
    if world > 1:  # a rank ends with the torchrun that started it, as a --jobs worker with its run
        die_with_parent(os.getppid())
    ap = argparse.ArgumentParser(
        description="DiffStack (CoRL 2022): the paper's tables, run on this machine. "
        "Under torchrun, on N processes: training with DistributedDataParallel."
    )
    # the same errors come up on every rank: rank 0 says what they are, the others exit alike
    if rank != 0:
        ap.error = lambda message: sys.exit(2)
    ap.add_argument(
        "--experiment",
        choices=EXPERIMENTS + (REAL.name, "all"),  # (required, but by --validation-spread)
        help="a table of the paper (results/<name>.json, .md, figures); all: every one, and "
        "results/report.md; real: the synthetic-trained stack on three real Waymo scenes "
        f"(downloaded once into data_cache/waymo; outputs to {REAL_OUT}/, never results/)",
    )
    ap.add_argument(
        "--phases",
        type=bounded(int, 1, data_real.WAYMO_PHASES, "--phases"),
        default=1,
        help="real: how many of the five 2 Hz clocks of each 10 Hz log give samples (default 1: "
        "78 samples)",
    )
    ap.add_argument(
        "--seeds",
        type=bounded(int, 1, 100, "--seeds"),
        default=None,
        help="training seeds per method, at most 100 (default: each table's own, 10 for Table 1 "
        "and 5 for the others)",
    )
    ap.add_argument(
        "--epochs",
        type=bounded(float, 0, 1000, "--epochs"),
        default=40.0,
        help="training epochs per method (default 40, the committed tables': the paper's 20 "
        "left Standard short of its plateau on this data, results/epochs20/; fractions allowed; "
        "at most 1000)",
    )
    ap.add_argument(
        "--n",
        "--samples",
        type=bounded(int, 10, data_synth.MAX_SAMPLES, "--n"),
        default=10000,
        help="synthetic scenarios per training draw (each seed trains on the training scenes, "
        f"85 %%, of its own draw; default 10000, at most {data_synth.MAX_SAMPLES:,}); under "
        "torchrun write --samples (torchrun's own parser takes --n for an abbreviation of its "
        "options)",
    )
    ap.add_argument(
        "--val",
        type=bounded(int, 10, data_synth.MAX_SAMPLES, "--val"),
        default=VAL_N,
        help=f"samples of the common validation set every method and seed is evaluated on (default "
        f"{VAL_N:,}; scenes of data seed {VAL_SEED}, which no training draw holds)",
    )
    ap.add_argument(
        "--data",
        help="a nuScenes folder (real, or written by data_synth.py) instead of synthetic data",
    )
    ap.add_argument(
        "--threads",
        type=bounded(int, 1, 256, "--threads"),
        default=None,
        help="torch threads (default 2, or 1 when other work keeps a core busy)",
    )
    ap.add_argument(
        "--jobs",
        type=bounded(int, 1, 256, "--jobs"),
        default=None,
        help="worker processes, one thread each, running a table's seeds in parallel (default: "
        f"the machine's cores, here {os.cpu_count()}; 1: one process with --threads threads; 1 "
        "under torchrun)",
    )
    ap.add_argument(
        "--device",
        type=device_arg,
        default="cpu",
        help="where training, evaluation and the stack run: cpu (default), cuda, cuda:N or mps; "
        "the data is made and cached on the CPU",
    )
    ap.add_argument("--out", help=f"where the results go (default results/; for real, {REAL_OUT}/)")
    ap.add_argument(
        "--overwrite",
        action="store_true",
        help="replace result files that exist already in --out (without it, the run refuses to "
        "start)",
    )
    ap.add_argument(
        "--render",
        action="store_true",
        help="train nothing: re-write the .md files, the report and the learning curves of an "
        "earlier run from its JSON files in --out (after a change to how results are written)",
    )
    ap.add_argument(
        "--validation-spread",
        action="store_true",
        help="train nothing: print GT prediction's relative hindsight cost on 5 unseen "
        "validation draws at about 1,500 samples and at --val's default (validation_spread); "
        "about 2 minutes",
    )
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a Config field, e.g. --set beta=2 (repeatable)",
    )
    args = ap.parse_args(argv)
    if args.validation_spread:
        return print(validation_spread())
    if args.experiment is None:
        ap.error("the following arguments are required: --experiment")
    names = EXPERIMENTS if args.experiment == "all" else (args.experiment,)
    args.out = args.out or (REAL_OUT if args.experiment == REAL.name else "results")
    launcher = (
        f"torchrun --nproc_per_node {world} experiments.py"
        if world > 1
        else "python experiments.py"
    )
    command = command_line(launcher, argv if argv is not None else sys.argv[1:])
    held = contextlib.ExitStack()
    # rank 0 holds --out from the checks to the end: one run per folder (runs.folder_lock); the
    # project's errors and a file's (a NaN result, a bad JSON) are one line
    with (
        held,
        one_line(ap, "the pieces finished so far are kept, and the same command resumes the run"),
    ):
        return _main(ap, args, names, world, rank, command, held)


def _main(ap, args, names, world, rank, command, held):
    seeds = range(args.seeds) if args.seeds is not None else None  # (None: each table's own count)
    # derived files only, from the JSON an earlier run wrote: nothing it made is lost
    if args.render:
        missing = [
            f"{args.out}/{n}.json"
            for n in names
            if not pathlib.Path(args.out, f"{n}.json").exists()
        ]
        if missing:
            ap.error(f"--render: no results to render from: {', '.join(missing)} missing")
        try:
            # (its validation scenes draw the learning curves' reference lines)
            if args.data is not None:
                data_real.nuscenes_version(args.data)
            held.enter_context(folder_lock(args.out, command))
        except ValueError as e:
            ap.error(str(e))
        data = (
            experiment_data(args.n, (0,), args.val, log=print)
            if args.data is None
            else data_real.load_data(args.data, args.n, log=print)
        )
        return render_outputs(args.experiment, args.out, data)
    try:  # everything that can be checked before the data is made and the first model trained
        cfg = config_with(Config(), args.set)
        if cfg.batch_size % world:
            raise ValueError(
                f"--set batch_size={cfg.batch_size}: a training batch must split evenly over the "
                f"{world} processes torchrun started; choose a multiple of {world}"
            )
        if args.jobs is not None and args.jobs > 1 and world > 1:
            raise ValueError(
                f"--jobs {args.jobs}: under torchrun the processes train together (DDP); run "
                "without --jobs"
            )
        if args.data is not None:  # before --out is made: a folder that holds a nuScenes version
            data_real.nuscenes_version(args.data)
        check_outputs(
            names,
            args.out,
            args.overwrite,  # an earlier run's files may be ours: run_experiment decides
            ours=ours_files(args.out, pathlib.Path(args.out, RUNS_DIR, "outputs").glob("*.json")),
        )
        # synthetic data, a folder's parse, Waymo
        check_writable("data_cache", "the data cache (./data_cache)")
        if rank == 0:
            held.enter_context(folder_lock(args.out, command))
        device = start_distributed(args.device) if world > 1 else args.device
    except ValueError as e:
        ap.error(str(e))
    threads, why = (args.threads, "--threads") if args.threads else default_threads()
    torch.set_num_threads(threads)
    if rank == 0:
        print(f"torch threads: {threads} ({why}; --threads N to choose)", flush=True)
    # flushed line by line: a run's log is often a file (a long run in the background), read
    # while it runs
    log = functools.partial(print, flush=True) if rank == 0 else (lambda *a, **k: None)

    def load():  # (the data, None), or (None, why it cannot be made)
        try:
            most = max(len(table_seeds(SPECS[one], seeds)) for one in names)
            data = (
                experiment_data(args.n, range(most), args.val, log=log)
                if args.data is None
                else data_real.load_data(args.data, args.n, log=log)
            )
            if args.experiment == REAL.name:
                data = real_data(data, range(args.phases), log=log)
            if "closed_loop" in names:
                closed_loop_scenes(data.val_scenes, cfg)
            return data, None
        except (ValueError, OSError) as e:  # (OSError: a file, or the Waymo download offline)
            return None, str(e)

    # Rank 0 makes (or reads) the data caches first, the others then read them: one process
    # generates or parses, and if it fails the others hear of it (a broadcast) instead of waiting
    # for it at the first training step.
    data, error = load() if rank == 0 else (None, None)
    if world > 1:
        verdict = [error]
        dist.broadcast_object_list(verdict, src=0)
        error = verdict[0]
        if rank != 0 and error is None:
            data, error = load()
    if error is not None:
        if world > 1:
            dist.destroy_process_group()
        ap.error(error)
    try:
        return run_experiment(
            args.experiment,
            data,
            cfg,
            seeds,
            args.epochs,
            args.out,
            command,
            log=log,
            overwrite=args.overwrite,
            device=device,
            write=rank == 0,
            jobs=args.jobs or (1 if world > 1 else os.cpu_count() or 1),
        )
    finally:
        if world > 1:
            dist.destroy_process_group()


if __name__ == "__main__":
    main()
