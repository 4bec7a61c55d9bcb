"""The figures of the experiments (lab/tables.py draws them into results/, the notebook some), and
drawing only: the numbers come from experiments.py's results or the stack run on a batch; what they
show: docs/results.md. matplotlib is imported only when drawing."""

from __future__ import annotations

import math

import numpy as np
import torch

import data_synth
from diffstack import COST_TERMS, Config, Prediction, StackOutput, masked_argmin, run_stack
from specs import COST_LABELS
from train import GT_PREDICTION, NO_PREDICTION, Method, evaluate_stack, to_device

# hand-over to the lab: figures written whole (lab/runs.py), mean and s.e. (lab/stats.py)
from lab.runs import write_file_atomic
from lab.stats import mean_se

# one colour per method in every figure
COLORS = {
    "No prediction": "tab:gray",
    "Standard": "tab:red",
    "DiffStack": "tab:green",
    "GT prediction": "tab:blue",
}
# what plot_stack's colours mean, under each figure that draws it
STACK_KEY = (
    "predictions red, alpha by probability; candidates green by p_n; the plan black dashed; the "
    "controller purple; the ego blue (its logged future dashed); the predicted vehicle orange"
)


def save_figure(fig, path) -> None:
    """fig.savefig at 130 dpi, atomically, or shown where path is None (the notebook); closed."""
    import matplotlib.pyplot as plt

    if path is None:
        plt.show()
    else:
        write_file_atomic(path, lambda tmp: fig.savefig(tmp, dpi=130, bbox_inches="tight"))
    plt.close(fig)


def plot_prediction(ax, pred: Prediction, i, color="tab:red", cov=True, label="prediction"):
    """Scenario i's K modes, alpha and width by probability, (cov) the most likely's 1σ ellipses."""
    p = pred.probs[i].detach().cpu()  # (K,)
    start = pred.s0[i, None, None, :2].expand(len(p), 1, 2)
    xy = torch.cat([start, pred.means[i]], 1).detach().cpu()  # (K, 1+T, 2)
    rel = p / p.max()
    best = int(p.argmax())
    for k in torch.argsort(p).tolist():  # the likely modes drawn last, on top
        r, lab = rel[k].item(), label if k == best else None
        ax.plot(*xy[k].T, color=color, alpha=0.1 + 0.9 * r, lw=0.5 + 2.5 * r, label=lab)
    if cov:
        theta = torch.linspace(0, 2 * math.pi, 40, dtype=pred.pos_cov.dtype)
        circle = torch.stack([torch.cos(theta), torch.sin(theta)], -1)  # (40, 2)
        for t in range(pred.pos_cov.shape[2]):
            L = torch.linalg.cholesky(pred.pos_cov[i, best, t].detach().cpu())  # (2, 2)
            ell = xy[best, t + 1] + circle @ L.T  # (40, 2)
            ax.plot(*ell.T, color="k", lw=1.0, zorder=9)  # over the modes


def plot_stack(ax, batch, i, out: StackOutput, cfg: Config, title=None, extent=(-10, 45, -12, 14)):
    """Fig. 3's panel for scenario i: scene, modes, candidates by p_n, plan and controller."""
    import matplotlib.pyplot as plt

    data_synth.plot_scenario(ax, batch, i, title=title, extent=extent)
    if out.pred is not None:
        plot_prediction(ax, out.pred, i, cov=False)
    valid = out.cands.valid[i]  # (N,)
    # p: (N,) eq. (2) relaxed
    p = torch.softmax(torch.where(valid, -cfg.beta * out.cand_cost[i].detach(), -math.inf), -1)
    xs = out.cands.s[i].detach()  # (N, T+1, 4)
    cmap = plt.get_cmap("Greens")
    for n in torch.argsort(p).tolist():  # the likely candidates on top
        if valid[n]:
            shade = cmap(0.25 + 0.75 * p[n].item() / p.max().item())
            ax.plot(xs[n, :, 0], xs[n, :, 1], color=shade, lw=1.0, zorder=6)
    # the controller's trajectory wide and translucent, the plan thin and dashed on top of it: both
    # stay visible where they overlap (the controller moves the plan by centimetres to metres)
    ctrl = out.s[i, :, :2].detach()
    wide = dict(lw=4, alpha=0.55, zorder=8, solid_capstyle="round")
    ax.plot(*ctrl.T, color="tab:purple", label="controller", **wide)
    best = xs[int(p.argmax()), :, :2]
    ax.plot(*best.T, "k--", lw=1.4, marker="o", ms=3, zorder=9, label="plan (argmin)")
    return ax


def plot_plans(ax, outs: dict, i) -> None:
    """Sample i's plan (dashed) and executed trajectory per stack in outs, y stretched."""
    xy = []
    for name, out in outs.items():
        n = int(masked_argmin(out.cand_cost[i : i + 1], out.cands.valid[i : i + 1]))
        xy.append((out.cands.s[i, n, :, :2], out.s[i, :, :2]))
        color = COLORS.get(name)
        ax.plot(*xy[-1][0].T, "--", color=color, lw=1, label=f"{name}'s plan")
        ax.plot(*xy[-1][1].T, "o-", color=color, lw=2, ms=3, label=f"{name}'s controller")
    ax.set(xlabel="x (m)", ylabel="y (m), stretched")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", fontsize=8)
    (pa, ca), (pb, cb) = xy[:2]
    plans, ends = (pa - pb).norm(dim=-1).max(), (ca[-1] - cb[-1]).norm()
    title = f"zoomed, y stretched: the plans up to {plans:.2f} m apart, the executed trajectories"
    ax.set_title(f"{title} end {ends:.2f} m apart", fontsize=9)


def stack_outputs(batch, models: dict, cfg: Config) -> dict:
    """{name: StackOutput} of each predictor in models on a batch (eval mode, RL), on the CPU."""
    outs = {}
    with torch.no_grad():
        for name, model in models.items():
            model.eval()
            device = next(model.parameters()).device
            out = run_stack(to_device(batch, device), model, Method(name), cfg, "rl")
            outs[name] = to_device(out, "cpu")
    return outs


def figure_stack_example(data, models: dict, cfg: Config, path, n_search=256):
    """Fig. 3 (returns its scenario: the first model's hindsight cost over the second's most): the
    stacks mostly plan the same candidate, the predictions acting through the controller."""
    batch = data.val[:n_search]
    outs = stack_outputs(batch, models, cfg)  # name -> StackOutput on the CPU
    (a, oa), (b, ob) = list(outs.items())[:2]
    both = oa.plannable & ob.plannable  # (B,)
    i = int(torch.where(both, oa.hindsight - ob.hindsight, -math.inf).argmax())
    # planned: (B,) the planned candidate
    planned = {name: masked_argmin(o.cand_cost, o.cands.valid) for name, o in outs.items()}
    same = int((planned[a] == planned[b])[both].sum())
    title = (
        f"Validation scenario {i}, where {a}'s hindsight cost exceeds {b}'s most: the stacks plan "
        f"the same candidate in {same} of {int(both.sum())} scenarios\n({STACK_KEY})"
    )
    figure_stacks(batch, i, outs, cfg, title, path)
    return i


def figure_stacks(batch, i, outs: dict, cfg: Config, title="", path=None) -> None:
    """Sample i through the two stacks in outs (plot_stack), then plot_plans; path None: shown."""
    import matplotlib.pyplot as plt

    kw = dict(figsize=(10, 9.2), layout="constrained", height_ratios=(1, 1, 0.8))
    fig, axes = plt.subplots(3, 1, **kw)
    for ax, (name, out) in zip(axes, outs.items()):
        title_n = f"{name}: hindsight cost {out.hindsight[i].item():.3f}"
        plot_stack(ax, batch, i, out, cfg, title_n, extent=(-12, 48, -10, 10))
        ax.set(xlabel="x (m)", ylabel="y (m)")
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7)
    sm = plt.cm.ScalarMappable(cmap="Greens", norm=plt.Normalize(-1 / 3, 1))  # 0.25 .. 1 used
    ticks = dict(ticks=[0, 0.25, 0.5, 0.75, 1], boundaries=np.linspace(0, 1, 101))
    fig.colorbar(sm, ax=axes[:2], shrink=0.8, label="candidate p_n / max p_n", **ticks)
    plot_plans(axes[2], outs, i)
    fig.suptitle(title, fontsize=10)
    save_figure(fig, path)


def figure_real_scenes(batch, models: dict, cfg: Config, path, rows: int = 3, apart: int = 3):
    """Real scenes (rows) under each model (columns), returned: the plannable samples where the
    first's hindsight cost exceeds the second's most, `apart` apart (neighbours: 0.5 s later)."""
    import matplotlib.pyplot as plt

    outs = stack_outputs(batch, models, cfg)  # name -> StackOutput on the CPU
    (a, oa), (b, ob) = list(outs.items())[:2]
    plannable = oa.plannable & ob.plannable  # (B,)
    score = torch.where(plannable, ob.hindsight - oa.hindsight, math.inf)  # lowest: first's worst
    ade = {name: _ade(out.pred, batch) for name, out in outs.items()}  # (B,) each
    picks = []
    for _ in range(min(rows, int(plannable.sum()))):  # the worst gap, then the worst away from it
        i = int(score.argmin())
        picks.append(i)
        score[max(0, i - apart + 1) : i + apart] = math.inf
    size = (6.2 * len(outs), 3.5 * len(picks))
    fig, axes = plt.subplots(
        len(picks), len(outs), figsize=size, squeeze=False, layout="constrained"
    )
    for row, i in enumerate(picks):
        for ax, (name, out) in zip(axes[row], outs.items()):
            h, e = out.hindsight[i].item(), ade[name][i].item()
            title = f"{name}, sample {i}: hindsight cost {h:.3f}, ADE {e:.2f} m"
            plot_stack(ax, batch, i, out, cfg, title, extent=(-15, 50, -15, 15))
    axes[0, 0].legend(loc="lower left", fontsize=7)
    means = ", ".join(
        f"{name} ADE {ade[name][plannable].mean():.2f} m, hindsight cost "
        f"{out.hindsight[plannable].mean():.3f}"
        for name, out in outs.items()
    )
    fig.suptitle(
        f"Real scenes (Waymo), predictors trained on synthetic data: the samples where {a}'s "
        f"hindsight cost exceeds {b}'s the most\nmean over {int(plannable.sum())} samples: "
        f"{means}\n({STACK_KEY})",
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
    """(S, N+1) m: per scene and step, the largest distance between two methods' executed egos."""
    xy = torch.stack([r.ego[..., :2] for r, _ in rollouts.values()])  # (M, S, N+1, 2)
    return (xy[:, None] - xy[None]).norm(dim=-1).amax((0, 1))


def figure_closed_loop(scenes, rollouts: dict, path=None, dt=0.5, scene=None):
    """One closed-loop scene (default: Standard's trajectory cost over DiffStack's most): replanning
    keeps the executed trajectories centimetres apart. rollouts: {method: (Rollout, per-scene)}."""
    import matplotlib.pyplot as plt

    if scene is None:
        cost = {m: per["trajectory"] for m, (_, per) in rollouts.items()}
        scene = int((cost["Standard"] - cost["DiffStack"]).argmax())
    first, _ = next(iter(rollouts.values()))
    f0, N = first.start_frame, first.controls.shape[1]
    frames = slice(f0, f0 + N + 1)
    tt = dt * torch.arange(N + 1)  # (N+1,) seconds
    apart = widest_pair(rollouts)[scene]  # (N+1,)
    mosaic = [["map", "dist"], ["zoom", "speed"]]
    fig, axd = plt.subplot_mosaic(
        mosaic, figsize=(13, 7), layout="constrained", width_ratios=(1.6, 1)
    )
    _closed_loop_map(axd["map"], scenes, scene, frames, rollouts)
    _closed_loop_zoom(axd["zoom"], axd["map"], rollouts, scene, apart, tt)
    _closed_loop_series(axd["dist"], axd["speed"], rollouts, scene, apart, tt)
    axd["speed"].plot(tt, scenes.ego[scene, frames, 3], "k--", lw=1, label="logged ego")
    for ax in axd.values():
        ax.grid(alpha=0.3)
    handles = axd["map"].get_legend_handles_labels()
    fig.legend(*handles, loc="outside lower center", ncol=3, fontsize=9)
    fig.suptitle(
        f"Closed loop, scene {scenes.names[scene]}: replanning every {dt:g} s, the methods' "
        f"executed trajectories stay within {100 * apart.max():.1f} cm of each other"
    )
    save_figure(fig, path)
    return scene


def _closed_loop_map(ax, scenes, sc, frames, rollouts) -> None:
    """The map: lanes, logs, each method's executed ego, framed on the egos and the near vehicle."""
    logged = scenes.ego[sc, frames, :2]  # (N+1, 2)
    agent = scenes.agents[sc, int(scenes.pred_idx[sc, frames.start]), frames, :2]  # (N+1, 2)
    egos = torch.cat([r.ego[sc, :, :2] for r, _ in rollouts.values()] + [logged])
    near = agent[torch.cdist(agent, egos).min(-1).values < 12]
    pts = torch.cat([egos, near])
    lo, hi = pts.min(0).values - 3, pts.max(0).values + 3
    for lane, m in zip(scenes.lanes[sc], scenes.lanes_mask[sc]):
        ax.plot(lane[m, 0], lane[m, 1], color="0.85", lw=0.8)
    ax.plot(*logged.T, "k--", lw=1.2, label="logged ego")
    ax.plot(*agent.T, "s-", color="tab:orange", ms=3, lw=0.8, label="predicted vehicle (log)")
    for name, (roll, per) in rollouts.items():
        label = f"{name} (cost {per['trajectory'][sc]:.3f})"
        ax.plot(*roll.ego[sc, :, :2].T, "o-", color=COLORS.get(name), ms=2.5, lw=1.2, label=label)
    ax.set(xlim=(lo[0], hi[0]), ylim=(lo[1], hi[1]), xlabel="x (m)", ylabel="y (m)")


def _closed_loop_zoom(zoom, ax, rollouts, sc, apart, tt) -> None:
    """A zoom on where the executed egos are furthest apart, marked on the map ax."""
    t = int(apart.argmax())
    half = max(2 * apart.max().item(), 0.02)
    xy = torch.stack([r.ego[sc, :, :2] for r, _ in rollouts.values()])  # (M, N+1, 2)
    cx, cy = xy[:, t].mean(0).tolist()
    zoom.set(xlim=(cx - 3 * half, cx + 3 * half), ylim=(cy - half, cy + half))
    for name, xy_m in zip(rollouts, xy):
        zoom.plot(*xy_m.T, "o-", color=COLORS.get(name), ms=4, lw=1.5)
    zoom.set(xlabel="x (m)", ylabel="y (m)")
    title = f"zoomed in where they are furthest apart (t = {tt[t]:.1f} s, the box on the map)"
    zoom.set_title(title, fontsize=9)
    ax.indicate_inset_zoom(zoom, edgecolor="0.3")


def _closed_loop_series(ax_d, ax_v, rollouts, sc, apart, tt) -> None:
    """Over time: each method's distance from No prediction's ego (cm) and speed."""
    first, _ = next(iter(rollouts.values()))
    base = rollouts.get("No prediction", (first, None))[0].ego[sc, :, :2]
    for name, (roll, _) in rollouts.items():
        color = COLORS.get(name)
        ax_d.plot(tt, 100 * (roll.ego[sc, :, :2] - base).norm(dim=-1), color=color, label=name)
        ax_v.plot(tt, roll.ego[sc, :, 3], color=color, label=name)
    ax_d.plot(tt, 100 * apart, "k:", lw=1.2, label="widest pair")
    ax_d.set(ylabel="distance (cm)", title="from No prediction's ego, and the widest pair")
    ax_d.legend(fontsize=8)
    ax_v.set(xlabel="time (s)", ylabel="ego speed (m/s)")


def _mean_curve(runs, key):
    """(epochs (E,), values (seeds, E)) of some runs' learning curves, on their common epochs."""
    curves = [r["curve"] for r in runs if r.get("curve")]
    n = min(len(c) for c in curves)
    epoch = np.array([c["epoch"] for c in curves[0][:n]])
    return epoch, np.array([[c[i][key] for i in range(n)] for c in curves])


def figure_learning_curves(results: dict, path, reference=None, methods=("Standard", "DiffStack")):
    """Validation ADE and hindsight cost per epoch, mean ± s.e.; reference {name: cost}: lines."""
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.6), dpi=110, layout="constrained")
    for m in [m for m in methods if any(r.get("curve") for r in results.get(m, []))]:
        for ax, key in zip(axes, ("ade", "hindsight")):
            epoch, v = _mean_curve(results[m], key)  # v: (seeds, epochs)
            mean, se = v.mean(0), (v.std(0, ddof=1) / np.sqrt(len(v)) if len(v) > 1 else 0 * v[0])
            ax.plot(epoch, mean, color=COLORS.get(m), label=f"{m} ({len(v)} seeds)")
            ax.fill_between(epoch, mean - se, mean + se, color=COLORS.get(m), alpha=0.25, lw=0)
    for name, value in (reference or {}).items():
        ls = "--" if name == "No prediction" else ":"
        axes[1].axhline(value, color="0.3", ls=ls, lw=1, label=name)
    axes[0].set(xlabel="epoch", ylabel="ADE (m)", title="Prediction: ADE")
    axes[1].set(xlabel="epoch", ylabel="hindsight cost", title="Planning: hindsight cost")
    for ax in axes:
        ax.grid(alpha=0.3)
    axes[1].legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.02, 1.0))
    title = "Learning curves on fixed validation scenes, mean ± s.e. over seeds (lower is better)"
    fig.suptitle(title, fontsize=10)
    save_figure(fig, path)


def learning_curve_reference(data, cfg: Config, samples: int) -> dict:
    """No and GT prediction's hindsight cost on the first `samples` of data.val (the curves')."""
    subset = data.val[:samples]
    return {
        m.name: evaluate_stack(None, subset, m, cfg, "rl")["hindsight"]
        for m in (NO_PREDICTION, GT_PREDICTION)
    }


def figure_cost_weights(results: dict, path, source: str = ""):
    """Learned vs hand-tuned weights w' and alpha, with s.e. over seeds; a mean that is not positive
    has no bar on the log scale: it is written in its place (and returned), never dropped."""
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
        at = x + (j - 0.5) * 0.38
        ax.bar(at, [m for m, _ in ms], 0.38, yerr=[s for _, s in ms], label=label, capsize=2)
        for i, (m, _) in enumerate(ms):
            if m <= 0:  # a log axis cannot draw it: say it where the bar would be
                notes.append(f"{label} {names[i]} = {m:.3f}")
                text = f"{m:.3f}\n(not > 0)"
                ax.text(at[i], 0.22, text, color="tab:red", ha="center", va="bottom", fontsize=8)
    ax.set_xticks(x, names, fontsize=8)
    ax.set_yscale("log")
    # down to the smallest bar
    ticks = [t for t in (0.01, 0.02, 0.05, 0.1, 0.2, 0.3, 0.5, 1, 2, 5) if t >= lowest / 2]
    ax.set_yticks(ticks, [f"{t:g}" for t in ticks])
    ax.minorticks_off()
    ax.set_ylabel("weight (log scale)")
    ax.legend(fontsize=8)
    seeds = len(next(iter(results.values())))
    title = f"Cost weights: hand-tuned vs learned (IL, L_ctr = MSE), {seeds} seed"
    title += "s" if seeds > 1 else ""
    title += f", {source}" if source else ""
    if notes:
        title += "\nnot positive, written not drawn: " + ", ".join(notes)
    ax.set_title(title, fontsize=9)
    save_figure(fig, path)
    return notes
