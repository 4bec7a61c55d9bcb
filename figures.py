"""The figures of the paper's experiments (experiments.py draws them into results/, the notebook
some of them).

    plot_prediction, plot_stack  panels: the predicted modes; Fig. 3's kind of panel (scene, modes,
                                 candidates, plan)
    figure_stack_example         Fig. 3: one validation scenario under Standard and DiffStack
    figure_real_scenes           real (Waymo) scenes where the two predictors' plans differ most
    figure_closed_loop           one closed-loop scene: every method's executed trajectory, their
                                 distances
    figure_learning_curves       validation ADE and hindsight cost after every epoch
    figure_cost_weights          learned vs hand-tuned cost weights (Table 3)

Drawing only: the numbers drawn come from experiments.py's results (or, for a few panels, from
running the stack on a batch), and no number written to results/ comes from here. matplotlib is
imported only when drawing.
"""

from __future__ import annotations

import math

import numpy as np
import torch

import data_synth
from lab.runs import write_file_atomic
from diffstack import COST_TERMS, Config, Prediction, StackOutput, masked_argmin, run_stack
from specs import COST_LABELS
from lab.stats import mean_se
from train import GT_PREDICTION, NO_PREDICTION, Method, evaluate_stack, to_device


def save_figure(fig, path) -> None:
    """fig.savefig at 130 dpi through the project's one atomic writer (a full disk is one line, a
    kill leaves the old file); closes the figure."""
    import matplotlib.pyplot as plt

    write_file_atomic(path, lambda tmp: fig.savefig(tmp, dpi=130, bbox_inches="tight"))
    plt.close(fig)


def plot_prediction(
    ax,
    pred: Prediction,
    i: int,
    color: str = "tab:red",
    cov: bool = True,
    label: str | None = "prediction",
):
    """Draw scenario i's K modes from the agent's current position; alpha and line width grow with
    the mode's probability (pred.probs), and (cov) the 1-sigma ellipses of the most likely mode.
    Meant to go over plot_scenario."""
    p = pred.probs[i].detach().cpu()  # (K,)
    # xy: (K, 1+T, 2)
    xy = (
        torch.cat([pred.s0[i, None, None, :2].expand(len(p), 1, 2), pred.means[i]], 1)
        .detach()
        .cpu()
    )
    rel = p / p.max()
    for k in torch.argsort(p).tolist():  # the likely modes drawn last, on top
        ax.plot(
            xy[k, :, 0],
            xy[k, :, 1],
            color=color,
            alpha=0.1 + 0.9 * rel[k].item(),
            lw=0.5 + 2.5 * rel[k].item(),
            label=label if k == int(p.argmax()) else None,
        )
    if cov:
        k = int(p.argmax())
        theta = torch.linspace(0, 2 * math.pi, 40, dtype=pred.pos_cov.dtype)
        circle = torch.stack([torch.cos(theta), torch.sin(theta)], -1)  # (40, 2)
        for t in range(pred.pos_cov.shape[2]):
            L = torch.linalg.cholesky(pred.pos_cov[i, k, t].detach().cpu())  # (2, 2)
            ell = xy[k, t + 1] + circle @ L.T  # (40, 2)
            ax.plot(ell[:, 0], ell[:, 1], color=color, lw=0.6, alpha=0.6)


def plot_stack(
    ax,
    batch,
    i: int,
    out: StackOutput,
    cfg: Config,
    title: str | None = None,
    extent=(-10, 45, -12, 14),
):
    """Fig. 3's kind of panel for scenario i: the scene (data_synth.plot_scenario), the predicted
    modes (alpha by probability), the planner's candidates coloured by p_n = softmax(-beta C_n), the
    plan (argmin) and the controller's trajectory."""
    import matplotlib.pyplot as plt

    data_synth.plot_scenario(ax, batch, i, title=title, extent=extent)
    if out.pred is not None:
        plot_prediction(ax, out.pred, i, cov=False)
    valid = out.cands.valid[i]  # (N,)
    # p: (N,) eq. (2) relaxed
    p = torch.softmax(torch.where(valid, -cfg.beta * out.cand_cost[i].detach(), -math.inf), -1)
    xs = out.cands.x[i].detach()  # (N, T+1, 4)
    cmap = plt.get_cmap("Greens")
    for n in torch.argsort(p).tolist():  # the likely candidates on top
        if valid[n]:
            ax.plot(
                xs[n, :, 0],
                xs[n, :, 1],
                color=cmap(0.25 + 0.75 * p[n].item() / p.max().item()),
                lw=1.0,
                zorder=6,
            )
    best = int(p.argmax())
    # the controller's trajectory wide and translucent, the plan thin and dashed on top of it: both
    # stay visible where they overlap (the controller usually moves the plan by centimetres to
    # a few metres)
    ax.plot(
        out.x[i, :, 0].detach(),
        out.x[i, :, 1].detach(),
        color="tab:purple",
        lw=4,
        alpha=0.55,
        zorder=8,
        solid_capstyle="round",
        label="controller",
    )
    ax.plot(
        xs[best, :, 0],
        xs[best, :, 1],
        "k--",
        lw=1.4,
        marker="o",
        ms=3,
        zorder=9,
        label="plan (argmin)",
    )
    return ax


def stack_outputs(batch, models: dict, cfg: Config) -> dict:
    """{name: StackOutput}: the stack of each (name -> predictor) in models on a batch, in
    evaluation mode (RL), run on the predictor's device and brought back to the CPU for plotting."""
    outs = {}
    with torch.no_grad():
        for name, model in models.items():
            model.eval()
            device = next(model.parameters()).device
            outs[name] = to_device(
                run_stack(to_device(batch, device), model, Method(name), cfg, "rl"), "cpu"
            )
    return outs


def figure_stack_example(data, models: dict, cfg: Config, path, n_search=256):
    """Fig. 3: the same validation scenario under two (name -> predictor) models (Standard,
    DiffStack), the one of the first n_search where the first's hindsight cost exceeds the second's
    the most. Its point: the two stacks mostly plan the same candidate; the predictions reach the
    outcome through the controller, whose cost holds them too (the bottom panel stretches the
    lateral scale to show how far apart the executed trajectories end). The stack runs on each
    model's device; the plot, on the CPU."""
    import matplotlib.pyplot as plt

    batch = data.val[:n_search]
    outs = stack_outputs(batch, models, cfg)  # name -> StackOutput on the CPU
    (a, oa), (b, ob) = list(outs.items())[:2]
    both = oa.plannable & ob.plannable  # (B,)
    i = int(torch.where(both, oa.hindsight - ob.hindsight, -math.inf).argmax())
    # planned: (B,) the planned candidate
    planned = {name: masked_argmin(o.cand_cost, o.cands.valid) for name, o in outs.items()}
    plan = {name: int(p[i]) for name, p in planned.items()}
    same = int((planned[a] == planned[b])[both].sum())
    fig, axes = plt.subplots(
        3, 1, figsize=(10, 9.6), layout="constrained", height_ratios=(1, 1, 0.8)
    )
    for ax, (name, out) in zip(axes, outs.items()):
        plot_stack(
            ax,
            batch,
            i,
            out,
            cfg,
            f"{name}: hindsight cost {out.hindsight[i].item():.3f}",
            extent=(-12, 48, -10, 10),
        )
        ax.legend(loc="lower left", fontsize=7)
    # the 0.25 .. 1 colours used
    sm = plt.cm.ScalarMappable(cmap="Greens", norm=plt.Normalize(-1 / 3, 1))
    fig.colorbar(
        sm,
        ax=axes[:2],
        shrink=0.8,
        label="candidate p_n / max p_n",
        boundaries=np.linspace(0, 1, 101),
        ticks=[0, 0.25, 0.5, 0.75, 1],
    )
    ax = axes[2]
    for (name, out), color in zip(outs.items(), ("tab:red", "tab:green")):
        ax.plot(
            out.cands.x[i, plan[name], :, 0],
            out.cands.x[i, plan[name], :, 1],
            "--",
            color=color,
            lw=1,
            label=f"{name}'s plan",
        )
        ax.plot(
            out.x[i, :, 0],
            out.x[i, :, 1],
            "o-",
            color=color,
            lw=2,
            ms=3,
            label=f"{name}'s controller",
        )
    ax.set(xlabel="x (m)", ylabel="y (m), stretched")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", fontsize=8)
    apart = (oa.x[i, -1, :2] - ob.x[i, -1, :2]).norm().item()
    ax.set_title(
        f"the executed trajectories end {apart:.2f} m apart"
        + (" from the same plan" if plan[a] == plan[b] else ""),
        fontsize=9,
    )
    fig.suptitle(
        f"Validation scenario {i}: {a}'s hindsight cost exceeds {b}'s by "
        f"{oa.hindsight[i] - ob.hindsight[i]:.2f} (the stacks plan the same candidate in {same} "
        f"of {int(both.sum())} scenarios)\n(predictions red, alpha by probability; candidates "
        "green by p_n; the plan black; the controller purple)",
        fontsize=10,
    )
    save_figure(fig, path)
    return i


def figure_real_scenes(batch, models: dict, cfg: Config, path, rows: int = 3, apart: int = 3):
    """A few real scenes under each (name -> predictor) in models, one row per scene, one column per
    model: plot_stack's panel (lanes, agents, the predicted modes, the candidates, the plan and the
    controller's output). The rows are the plannable samples where the first model's hindsight cost
    exceeds the second's the most (as Fig. 3 picks), at least `apart` samples from each other
    (neighbours are the same moment 0.5 s later): the point is that the more accurate predictor by
    ADE can make the costlier plan. The caption gives both models' mean ADE and hindsight cost over
    the whole batch. Returns the indices drawn."""
    import matplotlib.pyplot as plt

    outs = stack_outputs(batch, models, cfg)  # name -> StackOutput on the CPU
    (a, oa), (b, ob) = list(outs.items())[:2]
    plannable = oa.plannable & ob.plannable  # (B,)
    # score: (B,) lowest: the first model's worst
    score = torch.where(plannable, ob.hindsight - oa.hindsight, math.inf)
    ade = {name: _ade(out.pred, batch) for name, out in outs.items()}  # (B,) each
    picks = []
    # a few rows: the worst gap, then the worst away from it, ...
    for _ in range(min(rows, int(plannable.sum()))):
        i = int(score.argmin())
        picks.append(i)
        score[max(0, i - apart + 1) : i + apart] = math.inf
    fig, axes = plt.subplots(
        len(picks),
        len(outs),
        figsize=(6.2 * len(outs), 3.5 * len(picks)),
        squeeze=False,
        layout="constrained",
    )
    for row, i in enumerate(picks):
        for ax, (name, out) in zip(axes[row], outs.items()):
            plot_stack(
                ax,
                batch,
                i,
                out,
                cfg,
                f"{name}, sample {i}: hindsight cost {out.hindsight[i].item():.3f}, "
                f"ADE {ade[name][i].item():.2f} m",
                extent=(-15, 50, -15, 15),
            )
    axes[0, 0].legend(loc="lower left", fontsize=7)

    def mean(name, v):
        return v[plannable].mean().item()

    fig.suptitle(
        "Real scenes (Waymo), predictors trained on synthetic data. Where their plans' "
        f"hindsight costs differ most, {a} predicts one confident manoeuvre that did not happen "
        f"and its plan pays for it; {b}'s wider\nmodes leave the plan near the logged one. Over "
        f"all {int(plannable.sum())} samples {b} is the worse predictor by ADE "
        f"({mean(b, ade[b]):.2f} m vs {mean(a, ade[a]):.2f} m) and the better one to plan with "
        f"(hindsight cost {mean(b, ob.hindsight):.3f} vs {mean(a, oa.hindsight):.3f}).\nRed: "
        "predicted modes (alpha by probability); green: candidates by p_n; black dashed: plan; "
        "purple: controller output; blue dashed: the logged ego; orange: the predicted "
        "vehicle's log",
        fontsize=9,
    )
    save_figure(fig, path)
    return picks


def _ade(pred: Prediction, batch) -> torch.Tensor:
    """ADE of the most likely mode (B,), as diffstack.prediction_metrics computes it."""
    best = pred.probs.argmax(-1)  # (B,)
    means = pred.means[torch.arange(len(best)), best]  # (B, T, 2)
    return (means - batch.agent_fut[..., :2]).norm(dim=-1).mean(-1)


def widest_pair(rollouts):
    """(S, N+1) m: per closed-loop scene and step, the largest distance between two methods'
    executed egos."""
    xy = torch.stack([r.ego[..., :2] for r, _ in rollouts.values()])  # (M, S, N+1, 2)
    return (xy[:, None] - xy[None]).norm(dim=-1).amax((0, 1))


def figure_closed_loop(
    scenes, rollouts: dict, path=None, dt: float = 0.5, scene: int | None = None
):
    """One closed-loop scene, its point: replanning every dt keeps the methods' executed
    trajectories within centimetres of each other. Left, every method's executed ego over the logged
    ego and the predicted vehicle where it comes near, with a zoom where they are furthest apart;
    right, each one's distance from No prediction's ego and the widest pair's (cm), and the ego's
    speed over time. rollouts: {method: (Rollout, per-scene
    metrics)}; default scene: the one where Standard's trajectory cost exceeds DiffStack's the most.
    path None: shown (the notebook), else saved."""
    import matplotlib.pyplot as plt

    if scene is None:
        scene = int(
            (
                rollouts["Standard"][1]["trajectory"] - rollouts["DiffStack"][1]["trajectory"]
            ).argmax()
        )
    sc = scene
    first, _ = next(iter(rollouts.values()))
    f0, N = first.start_frame, first.controls.shape[1]
    frames = slice(f0, f0 + N + 1)
    # agent: (N+1, 4) the predicted vehicle's log
    agent = scenes.agents[sc, int(scenes.pred_idx[sc, f0]), frames]
    fig, axd = plt.subplot_mosaic(
        [["map", "dist"], ["zoom", "speed"]],
        figsize=(13, 7),
        layout="constrained",
        width_ratios=(1.6, 1),
    )
    ax, ax_d, ax_v = axd["map"], axd["dist"], axd["speed"]
    # egos: (M, 2)
    egos = torch.cat(
        [r.ego[sc, :, :2] for r, _ in rollouts.values()] + [scenes.ego[sc, frames, :2]]
    )
    # the vehicle where it comes within 12 m
    near = agent[(torch.cdist(agent[:, :2], egos).min(-1).values < 12), :2]
    pts = torch.cat([egos, near])
    lo, hi = pts.min(0).values - 3, pts.max(0).values + 3
    for lane, m in zip(scenes.lanes[sc], scenes.lanes_mask[sc]):
        ax.plot(lane[m, 0], lane[m, 1], color="0.85", lw=0.8)
    ax.plot(scenes.ego[sc, frames, 0], scenes.ego[sc, frames, 1], "k--", lw=1.2, label="logged ego")
    ax.plot(
        agent[:, 0],
        agent[:, 1],
        "s-",
        color="tab:orange",
        ms=3,
        lw=0.8,
        label="predicted vehicle (log)",
    )
    tt = dt * torch.arange(N + 1)  # (N+1,) seconds
    base = rollouts.get("No prediction", (first, None))[0].ego[sc, :, :2]
    xy = torch.stack([r.ego[sc, :, :2] for r, _ in rollouts.values()])  # (M, N+1, 2)
    apart = widest_pair(rollouts)[sc]  # (N+1,)
    spread, t_max = apart.max().item(), int(apart.argmax())
    # a zoom on where they are furthest apart, a square of side 4 x spread (at least 4 cm)
    half = max(2 * spread, 0.02)
    zoom = axd["zoom"]
    c0 = xy[:, t_max].mean(0).tolist()
    zoom.set(xlim=(c0[0] - 3 * half, c0[0] + 3 * half), ylim=(c0[1] - half, c0[1] + half))
    zoom.set(xlabel="x (m)", ylabel="y (m)")
    zoom.set_title(
        f"zoomed in where they are furthest apart (t = {tt[t_max]:.1f} s, the box on the map)",
        fontsize=9,
    )
    ax.indicate_inset_zoom(zoom, edgecolor="0.3")
    colors = dict(
        zip(
            ("No prediction", "Standard", "DiffStack", "GT prediction"),
            ("tab:gray", "tab:red", "tab:green", "tab:blue"),
        )
    )
    for name, (roll, per) in rollouts.items():
        c = colors.get(name)
        ax.plot(
            roll.ego[sc, :, 0],
            roll.ego[sc, :, 1],
            "o-",
            color=c,
            ms=2.5,
            lw=1.2,
            label=f"{name} (cost {per['trajectory'][sc]:.3f})",
        )
        zoom.plot(roll.ego[sc, :, 0], roll.ego[sc, :, 1], "o-", color=c, ms=4, lw=1.5)
        ax_d.plot(tt, 100 * (roll.ego[sc, :, :2] - base).norm(dim=-1), color=c, label=name)
        ax_v.plot(tt, roll.ego[sc, :, 3], color=c, label=name)
    ax_v.plot(tt, scenes.ego[sc, frames, 3], "k--", lw=1, label="logged ego")
    ax.set(xlim=(lo[0], hi[0]), ylim=(lo[1], hi[1]), xlabel="x (m)", ylabel="y (m)")
    fig.legend(*ax.get_legend_handles_labels(), loc="outside lower center", ncol=3, fontsize=9)
    fig.suptitle(
        f"Closed loop, scene {scenes.names[sc]} ({N * dt:.0f} s): the methods' executed "
        f"trajectories lie within {100 * spread:.1f} cm of each other (at most, at "
        f"t = {tt[t_max]:.1f} s)"
    )
    ax_d.plot(tt, 100 * apart, "k:", lw=1.2, label="widest pair")
    ax_d.set(ylabel="distance (cm)", title="from No prediction's ego, and the widest pair")
    ax_v.set(xlabel="time (s)", ylabel="ego speed (m/s)")
    for a in (ax, ax_d, ax_v, zoom):
        a.grid(alpha=0.3)
    ax_d.legend(fontsize=8)
    if path is None:
        plt.show()
    else:
        save_figure(fig, path)
    return sc


def _mean_curve(runs, key):
    """(epochs, mean over seeds) of the learning curves of some runs, on their common epochs."""
    curves = [r["curve"] for r in runs if r.get("curve")]
    n = min(len(c) for c in curves)
    return np.array([c["epoch"] for c in curves[0][:n]]), np.array(
        [[c[i][key] for i in range(n)] for c in curves]
    )


def learning_curves_caption(results: dict) -> str:
    """The point the learning curves make, read off them: from which epoch on DiffStack's mean
    hindsight cost stays below Standard's, and where each ADE curve ends relative to the other."""
    if not all(any(r.get("curve") for r in results.get(m, [])) for m in ("Standard", "DiffStack")):
        return "Learning curves (validation)"
    epoch, std = _mean_curve(results["Standard"], "hindsight")
    _, dif = _mean_curve(results["DiffStack"], "hindsight")
    n = min(std.shape[1], dif.shape[1])
    below = dif.mean(0)[:n] < std.mean(0)[:n]
    first = next((i for i in range(n) if below[i:].all()), None)
    ade_std, ade_dif = (
        _mean_curve(results["Standard"], "ade")[1].mean(0)[-1],
        _mean_curve(results["DiffStack"], "ade")[1].mean(0)[-1],
    )
    plans = (
        f"DiffStack plans better than Standard from epoch {epoch[first]:g} on"
        if first is not None
        else "DiffStack does not stay below Standard in hindsight cost"
    )
    return (
        f"{plans} (right), with a {'higher' if ade_dif > ade_std else 'lower'} ADE at the "
        "end (left)"
    )


def figure_learning_curves(
    results: dict,
    path,
    reference: dict | None = None,
    methods=("Standard", "DiffStack"),
    title=None,
):
    """Validation ADE and hindsight cost after every epoch (experiments.CURVE_SAMPLES scenes), mean
    and s.e. band over seeds, of the methods whose runs have a learning curve. reference: {name:
    hindsight cost on the same scenes}, drawn as horizontal lines (No prediction, GT prediction).
    title: default learning_curves_caption's."""
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.6), dpi=110, layout="constrained")
    colors = dict(Standard="tab:blue", DiffStack="tab:red")
    for m in methods:
        curves = [r["curve"] for r in results.get(m, []) if r.get("curve")]
        if not curves:
            continue
        n = min(len(c) for c in curves)
        epoch = np.array([c["epoch"] for c in curves[0][:n]])
        for ax, key in zip(axes, ("ade", "hindsight")):
            v = np.array([[c[i][key] for i in range(n)] for c in curves])  # (seeds, epochs)
            mean, se = v.mean(0), (v.std(0, ddof=1) / np.sqrt(len(v)) if len(v) > 1 else 0 * v[0])
            ax.plot(epoch, mean, color=colors.get(m), label=f"{m} ({len(v)} seeds)")
            ax.fill_between(epoch, mean - se, mean + se, color=colors.get(m), alpha=0.25, lw=0)
    for name, value in (reference or {}).items():
        axes[1].axhline(
            value, color="0.3", ls="--" if name == "No prediction" else ":", lw=1, label=name
        )
    axes[0].set(xlabel="epoch", ylabel="ADE (m)", title="Prediction: ADE")
    axes[1].set(
        xlabel="epoch", ylabel="hindsight cost", title="Planning: hindsight cost (lower is better)"
    )
    for ax in axes:
        ax.grid(alpha=0.3)
    axes[1].legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.02, 1.0))
    fig.suptitle(title or learning_curves_caption(results), fontsize=10)
    save_figure(fig, path)


def learning_curve_reference(data, cfg: Config, samples: int) -> dict:
    """No prediction's and GT prediction's hindsight cost on the learning curves' scenes, the first
    `samples` of data.val (figure_learning_curves' reference lines)."""
    subset = data.val[:samples]
    return {
        m.name: evaluate_stack(None, subset, m, cfg, "rl")["hindsight"]
        for m in (NO_PREDICTION, GT_PREDICTION)
    }


def figure_cost_weights(results: dict, path, source: str = ""):
    """Learned vs hand-tuned normalised weights w' and alpha, bars with standard errors over seeds;
    the title says which weights learning raised or lowered by more than 10 % (`source`: where the
    results come from, added to it). A mean that is not positive has no bar on the log scale: it is
    written in its place instead (returned too), never dropped."""
    import matplotlib.pyplot as plt

    names = [f"w'{i + 1} {COST_LABELS.get(t, t)}" for i, t in enumerate(COST_TERMS)] + ["alpha"]
    fig, ax = plt.subplots(figsize=(7, 3.2))
    x = np.arange(len(names))
    notes = []
    lowest = 0.2
    for j, (label, runs) in enumerate(results.items()):
        vals = [[*r["w"], r["alpha"]] for r in runs]
        ms = [mean_se([v[i] for v in vals]) for i in range(len(names))]
        lowest = min([lowest] + [m for m, _ in ms if m > 0])
        ax.bar(
            x + (j - 0.5) * 0.38,
            [m for m, _ in ms],
            0.38,
            yerr=[s for _, s in ms],
            label=label,
            capsize=2,
        )
        for i, (m, _) in enumerate(ms):
            if m <= 0:  # a log axis cannot draw it: say it where the bar would be
                notes.append(f"{label} {names[i]} = {m:.3f}")
                ax.text(
                    x[i] + (j - 0.5) * 0.38,
                    0.22,
                    f"{m:.3f}\n(not > 0)",
                    color="tab:red",
                    ha="center",
                    va="bottom",
                    fontsize=8,
                )
    ax.set_xticks(x, names, fontsize=8)
    ax.set_yscale("log")
    # down to the smallest bar
    ticks = [t for t in (0.01, 0.02, 0.05, 0.1, 0.2, 0.3, 0.5, 1, 2, 5) if t >= lowest / 2]
    ax.set_yticks(ticks, [f"{t:g}" for t in ticks])
    ax.minorticks_off()
    ax.set_ylabel("weight (log scale)")
    ax.legend(fontsize=8)
    means = {
        label: np.mean([[*r["w"], r["alpha"]] for r in runs], 0) for label, runs in results.items()
    }
    moved = ""
    if {"Hand-tuned", "Learned"} <= set(means):
        ratio = means["Learned"] / means["Hand-tuned"]
        words = [f"{names[i].split()[-1]} x{ratio[i]:.2g}" for i in range(len(names))]
        up = ", ".join(w for w, r in zip(words[1:], ratio[1:]) if r > 1.1)
        down = ", ".join(w for w, r in zip(words[1:], ratio[1:]) if r < 1 / 1.1)
        moved = f"\nlearning raises {up or 'none'}; lowers {down or 'none'} (more than 10 %)"
    seeds = len(next(iter(results.values())))
    ax.set_title(
        f"Cost weights: hand-tuned vs learned (IL, L_ctr = MSE), {seeds} seed"
        + "s" * (seeds > 1)
        + (f", {source}" if source else "")
        + moved
        + ("; not positive, written not drawn: " + ", ".join(notes) if notes else ""),
        fontsize=9 if not notes else 8,
    )
    save_figure(fig, path)
    return notes
