"""The paper's tables as declarative specs (TableSpec): rows (methods), setting, columns (metrics),
the paper's claims and numbers; experiments.py computes them, lab/tables.py runs them."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

from diffstack import COST_TERMS
from train import GT_PREDICTION, NO_PREDICTION, Method


@dataclass(frozen=True)
class Column:
    """One column of a results table: a metric of a run (a key of its dict, or a function of it)."""

    header: str
    key: str | Callable
    fmt: str = "{:.2f}"

    def values(self, runs) -> list:
        """The column's value in every run (seed) that has it."""
        if callable(self.key):
            return [self.key(r) for r in runs]
        return [r[self.key] for r in runs if self.key in r]


@dataclass(frozen=True)
class Claim:
    """A finding of the paper on a column: `method` lower than `baseline` (direction -1: each metric
    claimed on is a cost), or higher (+1); section: the ablation's section (or None)."""

    method: str
    baseline: str
    column: str  # a header of the table's columns
    section: str | None = None
    direction: int = -1


@dataclass(frozen=True)
class TableSpec:
    """A table of the paper, as run here. kind: 'open_loop' (Tables 1, 2, 4), 'cost' (Table 3),
    'closed_loop' (Table 5), 'ablation' (App. A.1, Table 6), 'goal' or 'real'; methods: the rows;
    paper: {row: {column header: value}} in the columns' units (absent: not reported)."""

    name: str
    title: str
    kind: str
    setting: str
    methods: tuple
    columns: tuple = ()
    paper: dict = field(default_factory=dict)
    pred_offset: float = 0.0
    # (Standard row, DiffStack row): the share of the Standard -> GT prediction gap closed
    gap: tuple | None = None
    figures: tuple = ()
    sections: tuple = ()  # ablations: (title, run_stack options, methods) per section
    # the paper's "method beats baseline" findings, each tested by its paired difference over seeds
    claims: tuple = ()
    seeds: int = 5  # training seeds when the command names none (--seeds)


CLOSED_LOOP_METRICS = {
    "trajectory": "Trajectory cost",
    "open_loop": "Open-loop cost",
    "collision": "Collision cost",
    "lane": "Lane keep cost",
    "control": "Control effort",
    "deviation": "Deviation (m)",
}
# The planning metrics of Tables 1, 2, 4 and 5 are differences to No prediction on the same
# scenarios, in the units of the paper's columns (x1e-2 or x1e-3).
RELATIVE_SCALE = {
    "rl": {"plan_loss": 1e-2, "hindsight": 1e-2},
    "il": {"plan_loss": 1e-3, "mse": 1e-2},
    "closed_loop": dict.fromkeys(CLOSED_LOOP_METRICS, 1e-2),
}

# Tables 1, 2 and 4: ADE, NLL, the planning metrics relative to No prediction, iLQR's convergence
RL_COLUMNS = (
    Column("ADE (m)", "ade"),
    Column("NLL (nats)", "nll"),
    Column("Planning loss (x1e-2)", "rel_plan_loss"),
    Column("Hindsight cost (x1e-2)", "rel_hindsight"),
    Column("iLQR converged", "converged", "{:.3f}"),
)
IL_COLUMNS = (
    *RL_COLUMNS[:2],
    Column("Planning loss (x1e-3)", "rel_plan_loss"),
    Column("MSE (x1e-2)", "rel_mse"),
    RL_COLUMNS[4],
)


def open_loop_columns(setting: str) -> tuple:
    return RL_COLUMNS if setting == "rl" else IL_COLUMNS


# Table 1's rows; No prediction, GT prediction, Standard and DiffStack are named wherever meant
STANDARD, DIFFSTACK = Method("Standard"), Method("DiffStack", losses=(1, 1, 1))
TABLE1_METHODS = (
    NO_PREDICTION,
    STANDARD,
    Method("Distance weighted", weighting="distance"),
    Method("Grad-cost weighted", weighting="grad_cost"),
    Method("DiffStack (no L_pred)", losses=(0, 1, 1)),
    DIFFSTACK,
    GT_PREDICTION,
)
FOUR_METHODS = CLOSED_LOOP_METHODS = (NO_PREDICTION, STANDARD, DIFFSTACK, GT_PREDICTION)


def _paper(columns, rows: dict) -> dict:
    """{row: values in column order (None: not reported)} -> {row: {header: value}}."""
    return {
        name: {c.header: v for c, v in zip(columns, vals) if v is not None}
        for name, vals in rows.items()
    }


def _spec(name, title, kind, setting, methods, columns, paper, **kw) -> TableSpec:
    """A TableSpec, the paper's numbers given as _paper takes them."""
    return TableSpec(name, title, kind, setting, methods, columns, _paper(columns, paper), **kw)


# ADE, NLL, planning loss, hindsight cost (paper §4.2, Table 1); Tables 2 and 6 repeat some rows
RL_PAPER = {
    "No prediction": (None, None, 0.00, 0.00),
    "Standard": (1.32, 0.42, -3.76, -1.61),
    "Distance weighted": (1.34, 1.19, -4.04, -1.68),
    "Grad-cost weighted": (1.43, -1.06, -4.29, -1.77),
    "DiffStack (no L_pred)": (1.37, 8.01, -5.13, -1.87),
    "DiffStack": (1.27, 0.38, -5.13, -1.86),
    "GT prediction": (None, None, -7.56, -2.25),
}
TABLE1 = _spec(
    "rl",
    "Table 1: reinforcement learning (hindsight cost)",
    "open_loop",
    "rl",
    TABLE1_METHODS,
    RL_COLUMNS,
    RL_PAPER,
    gap=("Standard", "DiffStack"),
    figures=("learning_curves.png",),
    claims=(
        Claim("DiffStack", "Standard", "Hindsight cost (x1e-2)"),
        Claim("DiffStack", "Standard", "Planning loss (x1e-2)"),
        # "outperforms all baselines"
        Claim("DiffStack", "Distance weighted", "Hindsight cost (x1e-2)"),
        Claim("DiffStack", "Grad-cost weighted", "Hindsight cost (x1e-2)"),
    ),
    seeds=10,  # the paper's headline claim: 10 seeds
)

TABLE2 = _spec(
    "biased",
    "Table 2: a 1 m offset on the prediction targets",
    "open_loop",
    "rl",
    (
        NO_PREDICTION,
        Method("Standard-biased"),
        Method("DiffStack-biased", losses=(1, 1, 1)),
        GT_PREDICTION,
    ),
    RL_COLUMNS,
    {
        "No prediction": RL_PAPER["No prediction"],
        "Standard-biased": (3.64, 8.43, 16.22, 3.13),
        "DiffStack-biased": (2.01, 4.20, -3.58, -1.61),
        "GT prediction": RL_PAPER["GT prediction"],
    },
    pred_offset=1.0,
    gap=("Standard-biased", "DiffStack-biased"),
    claims=(
        Claim("DiffStack-biased", "Standard-biased", "Hindsight cost (x1e-2)"),
        Claim("DiffStack-biased", "Standard-biased", "Planning loss (x1e-2)"),
    ),
)

# Table 3's header for each term of eq. (3) (diffstack.COST_TERMS; a term without one: its name)
COST_LABELS = {"coll": "coll", "goal": "goal", "lat": "lane", "head": "heading", "ctrl": "control"}
COST_COLUMNS = tuple(
    Column(f"w'{i + 1} ({COST_LABELS.get(t, t)})", lambda r, i=i: r["w"][i], "{:.3f}")
    for i, t in enumerate(COST_TERMS)
) + (
    Column("alpha", "alpha", "{:.3f}"),
    Column("Planning loss", "plan_loss", "{:.3f}"),
    Column("MSE (m^2)", "mse", "{:.3f}"),
)

# Table 3's one row: the cost weights learned on L_ctr (App. A.2), the predictor frozen
COST_WEIGHTS_ROW = Method("Cost weights", losses=(0, 0, 1))
TABLE3 = _spec(
    "cost",
    "Table 3: learned cost weights (IL; the weights as in App. A.2, Table 7)",
    "cost",
    "il",
    (COST_WEIGHTS_ROW,),
    COST_COLUMNS,
    {
        "Hand-tuned": (5.00, 0.50, 0.30, 0.30, 1.00, 1.00, 2.67, 0.38),
        "Learned": (5.00, 0.68, 0.36, 0.43, 0.63, 1.10, 2.41, 0.32),
    },
    figures=("cost_weights.png",),
    # the weights are learned on L_ctr, the MSE to the expert (IL); the paper reports the planning
    # loss falling too
    claims=(
        Claim("Learned", "Hand-tuned", "MSE (m^2)"),
        Claim("Learned", "Hand-tuned", "Planning loss"),
    ),
)

TABLE4 = _spec(
    "il",
    "Table 4: imitation learning",
    "open_loop",
    "il",
    FOUR_METHODS,
    IL_COLUMNS,
    {
        "No prediction": (None, None, 0.00, 0.00),
        "Standard": (1.25, 0.53, -0.50, 0.60),
        "DiffStack": (1.43, 0.30, -0.80, -1.80),
        "GT prediction": (None, None, -1.10, -2.80),
    },
    claims=(Claim("DiffStack", "Standard", "MSE (x1e-2)"),),
)

CLOSED_LOOP_COLUMNS = tuple(
    Column(f"{h} (x1e-2)", "rel_" + k) for k, h in CLOSED_LOOP_METRICS.items()
) + (Column("Plannable steps", "plannable", "{:.3f}"),)

TABLE5 = _spec(
    "closed_loop",
    "Table 5: closed-loop log replay",
    "closed_loop",
    "rl",
    CLOSED_LOOP_METHODS,
    CLOSED_LOOP_COLUMNS,
    {
        "No prediction": (0.00,) * 6,
        "Standard": (0.87, 0.33, -8.21, 8.91, 0.18, 1.05),
        "DiffStack": (-4.37, -2.40, -8.20, 4.84, -0.99, 0.98),
        "GT prediction": (-6.30, -2.58, -8.54, 3.34, -1.08, 0.70),
    },
    figures=("closed_loop.png", "stack_example.png"),
    claims=(
        Claim("DiffStack", "Standard", "Trajectory cost (x1e-2)"),
        Claim("DiffStack", "Standard", "Open-loop cost (x1e-2)"),
        # "substantially better than no prediction"
        Claim("DiffStack", "No prediction", "Trajectory cost (x1e-2)"),
        # "the standard stack performs worse"
        Claim("Standard", "No prediction", "Trajectory cost (x1e-2)", direction=1),
    ),
)

# Each section: methods under one configuration of the stack, with its own No prediction and GT
# prediction rows (metrics are not comparable across sections); Method.losses multiplies the RL
# alphas (1, 100, 1000). dt = 0.1 s: the predictor stays at 0.5 s; planner and controller run at
# 0.1 s over the same 3 s (T = 30) on interpolated predictions and GT futures (run_stack's plan_dt).
# The paper's table shows "--" for L_ctr there; its text says planning AND control change.

ABLATION_SECTIONS = (
    (
        "Loss weights",
        {},
        (
            STANDARD,
            DIFFSTACK,
            Method("DiffStack (no L_plan)", losses=(1, 0, 1)),
            Method("DiffStack (no L_ctr)", losses=(1, 1, 0)),
            Method("DiffStack (1, 5, 5)", losses=(1, 5, 5)),
            Method("DiffStack (1, 0.2, 0.2)", losses=(1, 0.2, 0.2)),
            # the planner weighs the modes by p(z|x) in training too (Config.train_plan_weights):
            # L_plan and L_ctr then reach the prior that evaluation uses, which the default q(z|x,y)
            # never trains (without L_pred: nothing does)
            Method("DiffStack (prior weights)", losses=(1, 1, 1), train_plan_weights="prior"),
            Method("DiffStack (no L_pred)", losses=(0, 1, 1)),
            Method(
                "DiffStack (no L_pred, prior weights)", losses=(0, 1, 1), train_plan_weights="prior"
            ),
        ),
    ),
    (
        "No planner (iLQR from zero controls)",
        dict(planner=False),
        (STANDARD, Method("DiffStack", losses=(1, 0, 1))),
    ),
    (
        "No controller (the plan is final)",
        dict(controller=False),
        (STANDARD, Method("DiffStack", losses=(1, 1, 0))),
    ),
    ("dt = 0.1 s for planning and control", dict(plan_dt=0.1), (STANDARD, DIFFSTACK)),
)

ABLATION_COLUMNS = RL_COLUMNS[:4]  # ADE, NLL, planning loss, hindsight cost

TABLE6 = TableSpec(
    "ablation",
    "Ablations (App. A.1, Table 6)",
    "ablation",
    "rl",
    (),
    ABLATION_COLUMNS,
    {  # per section, the rows in ABLATION_SECTIONS' names: ADE, NLL, planning loss, hindsight cost
        title: _paper(ABLATION_COLUMNS, rows)
        for (title, _, _), rows in zip(
            ABLATION_SECTIONS,
            (
                {
                    "Standard": RL_PAPER["Standard"],
                    "DiffStack": RL_PAPER["DiffStack"],
                    "DiffStack (no L_plan)": (1.33, 0.48, -4.98, -1.86),
                    "DiffStack (no L_ctr)": (1.48, 0.55, -5.24, -1.85),
                    "DiffStack (1, 5, 5)": (1.64, 0.85, -5.53, -1.89),
                    "DiffStack (1, 0.2, 0.2)": (1.28, 0.66, -4.79, -1.81),
                    "GT prediction": RL_PAPER["GT prediction"],
                },
                {
                    "Standard": (1.27, 0.31, None, -1.8),
                    "DiffStack": (1.40, 0.19, None, -2.0),
                    "GT prediction": (None, None, None, -2.6),
                },
                {
                    "Standard": (1.23, 0.56, -4.08, -1.1),
                    "DiffStack": (1.46, 0.53, -5.29, -1.2),
                    "GT prediction": (None, None, -7.56, -1.5),
                },
                {
                    "Standard": (1.23, 0.56, -5.65, -2.1),
                    "DiffStack": (1.49, 0.88, -14.01, -2.4),
                    "GT prediction": (None, None, -25.11, -2.9),
                },
            ),
        )
    },
    sections=ABLATION_SECTIONS,
    claims=tuple(
        Claim("DiffStack", "Standard", "Hindsight cost (x1e-2)", title)
        for title, _, _ in ABLATION_SECTIONS
    ),
)

# Not a table of the paper: why a prediction is worth little to the planner in most scenes. No and
# GT prediction (the best any predictor can do) by behaviour, under the paper's goal (the GT ego
# state at T, which already holds the driver's reaction) and a route goal (Config.goal = 'route').
GOALS = ("logged", "route")
GOAL_TABLE = TableSpec(
    "goal",
    "Where a perfect prediction is worth something: hindsight cost by behaviour, the paper's "
    "goal vs a route goal",
    "goal",
    "rl",
    (NO_PREDICTION, GT_PREDICTION),
)

# every trained predictor's learning curve: the stack on this many validation scenarios per epoch
CURVE_SAMPLES = 512
CLOSE = 5.0  # m, centre to centre: a car's length (the goal table's "close" share)

TABLES = {t.name: t for t in (TABLE1, TABLE2, TABLE4, TABLE3, TABLE5, TABLE6, GOAL_TABLE)}
EXPERIMENTS = tuple(TABLES)  # the order `all` runs them in

# Real driving scenes: the three Waymo logs of lab/waymo.py, evaluated with predictors trained on
# synthetic data. Not a table of the paper, so not in `all`; its outputs derive from data whose
# licence forbids committing them: they go to REAL_OUT (git-ignored), never to results/.
REAL_COLUMNS = (
    RL_COLUMNS[0],
    Column("CV ADE (m)", "cv_ade"),
    *RL_COLUMNS[1:],
    Column("Plannable samples", "n", "{:.0f}"),
)
REAL = TableSpec(
    "real",
    "Real driving scenes (Waymo Open Motion Dataset, 3 logs): synthetic-trained predictors",
    "real",
    "rl",
    FOUR_METHODS,
    REAL_COLUMNS,
    figures=("real_scenes.png",),
)
SPECS = {**TABLES, REAL.name: REAL}  # every experiment the command line runs
REAL_OUT = "runs/real"
