"""tutorial.ipynb's harness (section clock, checks that stop the notebook, helpers, the larger
figures) and its exercises' checks (lab/grader.py runs them): each runs the student's function on
its own seeded float64 problems against an independent answer; a wrong one raises AssertionError
saying what differs, a stub (NotImplementedError) is not done, so *Run All* goes on past it."""

import contextlib
import dataclasses
import functools
import inspect
import json
import math
import time
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import torch
from IPython.display import Markdown, display
from matplotlib.colors import ListedColormap, LogNorm
from matplotlib.lines import Line2D
from matplotlib.patches import FancyBboxPatch

import data_synth
import diffstack as ds
import experiments as xp
import figures
import specs

F64 = torch.float64
P_NORM = LogNorm(1e-4, 1)  # the colour scale of the candidates' p_n
FUTURE = dict(color="tab:orange", mec="k", ms=4, lw=2, zorder=10)  # a true future, on top
G_NORM, G_MAP = LogNorm(1e-3, 10), ListedColormap(plt.cm.Reds(np.linspace(0.3, 1, 256)))  # |dL/dŝ|
SECTION_TIMES = {}
_CLOCK = {}


def start():
    """One torch thread (reproducible numbers), the figures' style, the section clock."""
    torch.set_num_threads(1)
    plt.rcParams.update({"figure.dpi": 100, "savefig.dpi": 100})
    plt.rcParams.update({"font.size": 9, "legend.fontsize": 8})
    SECTION_TIMES.clear()
    _CLOCK.update(wall=time.time(), cpu=time.process_time(), section=time.time())


def section_done(name):
    """Print and record the wall time since the previous section ended."""
    SECTION_TIMES[name] = time.time() - _CLOCK["section"]
    _CLOCK["section"] = time.time()
    print(f"{name}: {SECTION_TIMES[name]:.0f} s")


def report_times(quick):
    """Wall clock per section and in all, and the kernel's CPU time."""
    print("  ".join(f"{k} {v:.0f} s" for k, v in SECTION_TIMES.items()))
    wall, cpu = time.time() - _CLOCK["wall"], time.process_time() - _CLOCK["cpu"]
    mode = "quick" if quick else "full"
    print(f"notebook run time: {wall:.0f}s wall, {cpu:.0f}s CPU ({mode} mode)")


class CheckpointError(AssertionError):
    """A failed check: the notebook stops at the cell (and CI fails)."""


def checkpoint(name, measured, expected, tol, rel=False):
    """For what is deterministic (no training): measured within tol of expected, or a stop."""
    err = abs(measured - expected) / max(abs(expected), 1e-12) if rel else abs(measured - expected)
    within = "%g%%" % (100 * tol) if rel else tol
    said = f"measured {measured:.4g}, expected {expected:.4g}"
    print(f"CHECKPOINT {name}: {said} (tolerance {within}) -> {'OK' if err <= tol else 'FAILED'}")
    if err > tol:
        rerun = "re-run the section's cells in order from a fresh kernel"
        raise CheckpointError(f"{name}: {said} within {within}; {rerun}")


def check_order(name, values, order, margin=0.0):
    """For what training makes (its last digits differ between machines): only an ordering that
    holds on any machine, lowest first, each value at least `margin` below the next, or a stop."""
    print(f"CHECK {name}: " + " < ".join(f"{k} {values[k]:.4g}" for k in order), end=" -> ")
    bad = [(a, b) for a, b in zip(order, order[1:]) if not values[a] + margin <= values[b]]
    print("OK" if not bad else "FAILED")
    if bad:
        raise CheckpointError(
            f"{name}: expected {' < '.join(order)} (margin {margin:g}); "
            + ", ".join(f"{a} {values[a]:.4g} is not below {b} {values[b]:.4g}" for a, b in bad)
        )


def check_claim(table, method, baseline, column, expect):
    """A finding the notebook states: the verdict on results/<table>.json of its paired t-test
    over seeds (p < 0.05 in the paper's direction: reproduced) must be the text's, or a stop."""
    saved = json.loads((Path("results") / f"{table}.json").read_text())["results"]
    line = xp.claim_line(specs.Claim(method, baseline, column), specs.TABLES[table], saved)
    verdict = line.rsplit("): ", 1)[-1]
    print(f"CLAIM {line} -> {'OK' if verdict.startswith(expect) else 'FAILED'}")
    if not verdict.startswith(expect):
        raise CheckpointError(
            f"results/{table}.json says {verdict!r}, the text says {expect!r}: update the text"
        )


def results_table(name):
    """Display the committed table of results/<name>.md (mean ± standard error over its seeds)."""
    text = (Path("results") / f"{name}.md").read_text()
    seeds = len(json.loads((Path("results") / f"{name}.json").read_text())["meta"]["seeds"])
    body = text.split("\n", 1)[1].split("![")[0].strip()  # without the title and figure links
    display(Markdown(f"**{seeds} seeds, from `results/{name}.md`:** " + body))


def gt_context(batch):
    """The cost's view of a batch with the GT future as a one-mode prediction (GT prediction)."""
    one = torch.ones(len(batch), dtype=batch.ego_hist.dtype)
    others, mask = batch.others_fut[..., :2], batch.others_mask.to(one.dtype)
    scene = (batch.goal[:, :2], batch.lanes, batch.lanes_mask)
    return ds.CostContext(batch.agent_fut[:, None, :, :2], one[:, None], one, others, mask, *scene)


def first_of(batch, behaviour, where=None):
    """The index of the first sample of `batch` doing `behaviour` (and where `where` holds)."""
    sel = batch.behaviour == data_synth.BEHAVIOURS.index(behaviour)
    return int((sel if where is None else sel & where).nonzero()[0])


def behaviour_rows(behaviour, mask, row):
    """A table row [name, count, *row(sel)] per behaviour with samples under `mask` (sel)."""
    sels = [(name, mask & (behaviour == b)) for b, name in enumerate(data_synth.BEHAVIOURS)]
    return [[name, str(int(sel.sum())), *row(sel)] for name, sel in sels if sel.any()]


# --- the notebook's figures (drawing only: each cell computes what it shows) ----------------------


def _scene(ax, batch, i, title=None, extent=(-30, 60, -25, 25)):
    """Sample i drawn in the ego frame (data_synth.plot_scenario), on axes in metres."""
    data_synth.plot_scenario(ax, batch, i, title=title, extent=extent)
    ax.set(xlabel="x (m)", ylabel="y (m)")


def _colorbar(fig, axes, cmap, norm, label, shrink, **kw):
    """A colour bar for lines coloured by cmap under norm (no image to take it from)."""
    bar = plt.cm.ScalarMappable(cmap=cmap, norm=norm)
    fig.colorbar(bar, ax=axes, shrink=shrink, label=label, **kw)


def _show(fig, title):
    fig.suptitle(title, fontsize=10)
    plt.show()


def figure_stack():
    """§1: the modules, the forward data flow (black), DiffStack's gradient path (red)."""
    _, ax = plt.subplots(figsize=(10, 4.2))
    ax.set(xlim=(0, 10), ylim=(-0.55, 4.45))
    ax.axis("off")
    boxes = (
        (0.1, "#e8e8e8", "history of all agents\nlanes, goal"),
        (2.45, "#ffd9b3", "Predictor\n(CVAE, learned θ)"),
        (4.8, "#cfe2f3", "Planner\nsplines + argmin"),
        (7.15, "#cfe2f3", "Controller\nbox-iLQR"),
    )
    for x, color, text in boxes:
        ax.add_patch(FancyBboxPatch((x, 1.7), 1.9, 1, boxstyle="round,pad=0.05", fc=color, ec="k"))
        ax.text(x + 0.95, 1.7 + 0.5, text, ha="center", va="center", fontsize=9)

    def arrow(x0, y0, x1, y1, **kw):
        return ax.annotate("", (x1, y1), (x0, y0), arrowprops=dict(arrowstyle="->", **kw))

    flow = ((2.0, 2.45, ""), (4.35, 4.8, r"$\hat s_{k,t},\ \pi_k$"), (6.7, 7.15, r"plan $u^{(0)}$"))
    for x0, x1, label in (*flow, (9.05, 9.6, "")):
        arrow(x0, 2.2, x1, 2.2, lw=1.5)
        ax.text((x0 + x1) / 2, 1.4, label, ha="center", fontsize=9)
    ax.text(9.65, 2.2, "$s_{ctr}, u_{ctr}$", va="center", fontsize=9)
    # the losses, the arrows into them (black) and the gradient paths back to the predictor (red)
    losses = (
        (3.4, r"$\mathcal{L}_{pred}$" "\n(GT future)"),
        (5.75, r"$\mathcal{L}_{plan} = -\log p_{n^*}$" "\n" r"$p_n \propto e^{-\beta C_n}$"),
        (8.1, r"$\mathcal{L}_{ctr}$" "\n(hindsight cost / MSE)"),
    )
    frame = dict(fc="white", ec="tab:red")
    for x, text in losses:
        ax.text(x, 0.45, text, ha="center", va="center", fontsize=9, bbox=frame)
        arrow(x, 1.65, x, 0.9, lw=1)
    gradients = (
        (5.75, 3.55, 0.45, 4.65, 2.93, r"$\partial\mathcal{L}_{plan} / \partial \hat s$"),
        (8.1, 3.25, 0.35, 6.9, 3.85, r"$\partial\mathcal{L}_{ctr} / \partial \hat s$ (KKT)"),
    )
    for x0, x1, rad, x, y, text in gradients:
        arrow(x0, 2.8, x1, 2.8, connectionstyle=f"arc3,rad={rad}", color="tab:red", lw=1.8, ls="--")
        ax.text(x, y, text, color="tab:red", ha="center", fontsize=9)
    ax.text(5.0, 4.3, "forward (black): predict → plan → control", ha="center", fontsize=10)
    backward = "backward (red): through the softmax over the candidates and iLQR's KKT (§5) to θ"
    ax.text(5.0, -0.4, backward, ha="center", fontsize=8.5, color="tab:red")
    plt.show()


def scene_legend(fig, extra=(), ncol=4):
    """A legend for data_synth.plot_scenario's drawing, and `extra` handles, below the panels."""
    box = dict(marker="s", ms=7)
    handles = [
        Line2D([], [], color="tab:blue", ls="--", label="ego (GT future dashed)", **box),
        Line2D([], [], color="tab:blue", ls="", marker="*", ms=12, mec="k", label="goal g"),
        Line2D([], [], color="tab:orange", label="predicted vehicle (GT future)", **box),
        Line2D([], [], color="0.6", label="other vehicles", **box),
        Line2D([], [], color="tab:green", marker="o", ms=5, label="pedestrians"),
        Line2D([], [], color="k", ls=":", label="history (4 s)"),
        Line2D([], [], color="k", marker=".", label="GT future (3 s, dots every 0.5 s)"),
        Line2D([], [], color="0.75", label="lanes (arrow: direction)"),
    ]
    fig.legend(handles=handles + list(extra), loc="outside lower center", ncol=ncol, fontsize=8)


def figure_scenarios(val, extent=(-20, 50, -20, 20)):
    """§2: the first validation sample of each of four pairs of behaviours, a pair a column."""
    acts = ("cut_in", "lead_brake", "turn_across", "cross_go")
    twins = ("keep_lane", "lead_cruise", "go_straight", "cross_yield")
    kw = dict(figsize=(15, 5.8), layout="constrained", sharex=True, sharey=True)
    fig, axes = plt.subplots(2, len(acts), **kw)
    for col, pair in enumerate(zip(acts, twins)):
        for row, name in enumerate(pair):
            i = first_of(val, name)
            data_synth.plot_scenario(axes[row, col], val, i, f"{name} (val sample {i})", extent)
            axes[row, col].set(xlabel="x (m)" if row else "", ylabel="y (m)" if col == 0 else "")
    scene_legend(fig)
    title = (
        "The four pairs of behaviours (columns): the same set-up, then the predicted vehicle acts "
        "(top: cuts in, brakes, turns across, crosses) or does not (bottom)"
    )
    _show(fig, title)


def figure_cost_map(ex, gx, gy, c_coll, c_goal, c_lat, c_sum, w_coll, ctx_t, t=1.5):
    """§3: one step t of the cost over the ego's position, term by term and weighted."""
    coll = w_coll * c_coll
    terms = {
        f"$C_{{coll}}$ at t = {t:g} s (GT future as prediction)": (c_coll, None),
        r"$C_{goal}$ (its own scale)": (c_goal, None),
        r"$C_{lat}$: distance² to the nearest lane going the ego's way (clipped)": (c_lat, None),
        r"weighted sum $w_1C_{coll} + w_2C_{goal} + w_3C_{lat} + w_4C_{head}$ (log scale); "
        r"contours: $w_1C_{coll}$": (c_sum, LogNorm(max(c_sum.min().item(), 0.1), c_sum.max())),
    }
    fig, axes = plt.subplots(2, 2, figsize=(12, 6.6), layout="constrained")
    at_t = dict(marker="X", ms=11, mec="k", ls="", zorder=9)
    for ax, (name, (val, norm)) in zip(axes.flat, terms.items()):
        vmax = val.quantile(0.95).item() if "lat" in name else None
        kw = dict(norm=norm) if norm else dict(vmax=vmax)
        im = ax.pcolormesh(gx, gy, val.reshape(gx.shape), shading="auto", cmap="magma_r", **kw)
        _scene(ax, ex, 0, name, (-10, 45, -12, 12))
        fig.colorbar(im, ax=ax, shrink=0.9, label="cost")
        ax.plot(*ctx_t.preds[0, 0, 0].tolist(), color="tab:orange", **at_t)
        for ped, color in ((False, "0.6"), (True, "tab:green")):
            sel = (ctx_t.others_mask[0] > 0) & (ex.others_is_ped[0] == ped)
            ax.plot(*ctx_t.others[0, sel, 0].T, color=color, **at_t)  # the agents at t
    levels = [v for v in (0.5, 1.0, 2.0, 4.0) if v < coll.max()]
    cs = axes[1, 1].contour(gx, gy, coll.reshape(gx.shape), levels, colors="tab:cyan", zorder=8)
    axes[1, 1].clabel(cs, fontsize=7)
    who = {"tab:orange": "predicted vehicle", "0.6": "other vehicles", "tab:green": "pedestrians"}
    extra = [Line2D([], [], color=c, label=f"{w} at t = {t:g} s", **at_t) for c, w in who.items()]
    extra.append(Line2D([], [], color="tab:cyan", label=r"contours of $w_1 C_{coll}$"))
    scene_legend(fig, extra, ncol=6)
    title = (
        f"One step of the cost (t = {t:g} s) over the ego's position, a cut-in: the collision "
        f"term adds at most {coll.max():.1f} (bumps at the vehicles' positions at {t:g} s, "
        f"crosses) to a sum of {c_sum.min():.1f} .. {c_sum.max():.0f},\nmostly the goal's bowl: it "
        "decides only between positions that the goal and the lanes rate alike"
    )
    _show(fig, title)


def figure_beta_signal(betas, extra, beta_paper, n):
    """§4: the mean L_plan that ignoring the vehicle adds (`extra`, nats) per β, and its title."""
    e = np.asarray(extra)
    up = next(i for i in range(len(e)) if (np.diff(e[i:]) > 0).all())  # monotone from betas[up]
    at = float(np.interp(np.log(beta_paper), np.log(betas), e))
    k = int(e[: up + 1].argmax())  # (a bump below betas[up]: k < up)
    bump = f"; below, a bump at β = {betas[k]:.2g} ({e[k]:.3f})" if k < up else ""
    _, ax = plt.subplots(figsize=(8, 3.8), layout="constrained")
    ax.plot(betas, e, "o-", ms=3, color="tab:red", label="mean over the samples")
    ax.set(xscale="log", yscale="log", xlabel="β (1/cost)")
    ax.set_ylabel("L_plan(no prediction) −\nL_plan(GT) (nats)")
    ax.axvline(beta_paper, color="0.6", ls=":", label=f"β = {beta_paper:g} (the paper's): {at:.3f}")
    ax.legend(loc="upper left")
    ax.grid(alpha=0.3, which="both")
    ax.set_title(
        f"What ignoring the vehicle adds to L_plan ({n} samples): it grows with β from "
        f"β = {betas[up]:.2g} on,\nto {e[-1]:.2f} nats at β = {betas[-1]:g}{bump}",
        fontsize=10,
    )
    plt.show()


def figure_plan_gradient(bg, show, preds, gmax, cfg):
    """§4: -dL_plan/d(preds (B, 1, T, 2)) on the samples `show` of bg, the longest arrow 6 m."""
    kw = dict(beta=cfg.beta, what="constant velocity")
    panels = [dict(ex=bg[j : j + 1], preds=preds[j : j + 1], **kw) for j in show]
    title = (
        "Which prediction errors the planner cares about: -dL_plan/d(prediction) on a constant-"
        "velocity prediction\n(orange: the vehicle's true future; red arrows, at one scale: where "
        "a gradient step moves each predicted position)"
    )
    planner_panels(panels, cfg, title, scale=6.0 / gmax[show].max().item())


def figure_ilqr(batch, i, rel, plan_x, plan_u, ctrl_x, ctrl_u, cfg):
    """§5: iLQR's cost / the plan's per iteration (rel); sample i's controller - plan, controls."""
    mosaic = [["cost", "map", "map"], ["cost", "w", "a"]]
    _, axd = plt.subplot_mosaic(mosaic, figsize=(13, 6), layout="constrained")
    ax = axd["cost"]
    ax.plot(rel.T, color="tab:blue", alpha=0.15, lw=0.8)
    ax.plot(rel.mean(0), color="k", lw=2, label="mean")
    title = "iLQR: the true cost never rises\n(line search), mean in black"
    ax.set(xlabel="iteration", ylabel="cost / cost of the plan", title=title)
    ax.legend(loc="lower left")
    ax = axd["map"]
    tt = cfg.dt * torch.arange(len(plan_x))  # (T+1,) s
    diff = ctrl_x[:, :2] - plan_x[:, :2]  # (T+1, 2) m
    for j, (name, color) in enumerate((("x (ahead)", "tab:blue"), ("y (left)", "tab:orange"))):
        ax.plot(tt, diff[:, j], "o-", color=color, lw=2, ms=4, label=f"Δ{name}")
    ax.plot(tt, diff.norm(dim=-1), "k:", lw=1.5, label="distance")
    ax.axhline(0, color="0.5", lw=0.8)
    ax.set(xlabel="time (s)", ylabel="controller − plan (m)")
    top = diff.abs().max(0).values  # (2,) m the largest change along x, along y
    big = int(top.argmax())
    ax.set_title(
        f"sample {i} ({data_synth.BEHAVIOURS[int(batch.behaviour[i])]}): the controller's position "
        f"minus the plan's;\nthe change is along {'xy'[big]}, up to {top[big]:.2f} m (along "
        f"{'yx'[big]}: at most {top[1 - big]:.2f} m)",
        fontsize=9,
    )
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0))
    tt_u = cfg.dt * torch.arange(len(plan_u))
    for key, j, label in (("w", 0, "yaw rate ω (rad/s)"), ("a", 1, "acceleration a (m/s²)")):
        ax = axd[key]
        ax.axhspan(cfg.u_lower[j], cfg.u_upper[j], color="0.93", zorder=0)
        ax.step(tt_u, plan_u[:, j], "--", where="post", color="tab:green", lw=2, label="plan")
        ax.step(tt_u, ctrl_u[:, j], "-", where="post", color="purple", lw=2, label="controller")
        lim = max(plan_u[:, j].abs().max().item(), ctrl_u[:, j].abs().max().item()) * 1.3 + 0.05
        ax.set(ylim=(-lim, lim), xlabel="time (s)", ylabel=label)
    for ax in axd.values():
        ax.grid(alpha=0.3)
    axd["w"].legend(loc="best")
    plt.show()


def _modes_panel(ax, z, sub, pred, j, norm_p):
    """figure_modes' panels of sample j: ax on its vehicle, z on the most likely mode's end (1σ)."""
    K = pred.probs.shape[1]
    P = torch.cat([pred.s0[j, None, None, :2].expand(K, 1, 2), pred.means[j]], 1)  # (K, 1+T, 2)
    pts = torch.cat([P.reshape(-1, 2), sub.agent_fut[j, :, :2], sub.agent_hist[j, -3:, :2]])
    c = ((pts.max(0).values + pts.min(0).values) / 2).tolist()
    half = ((pts.max(0).values - pts.min(0).values) / 2 + 1.5).tolist()
    hx, hy = max(half[0], 1.3 * half[1]), max(half[1], half[0] / 1.3)  # the panels' shape
    top3 = ", ".join(f"{q:.2f}" for q in pred.probs[j].sort(descending=True).values[:3].tolist())
    title = f"{data_synth.BEHAVIOURS[int(sub.behaviour[j])]}: largest p = {top3}"
    _scene(ax, sub, j, title, (c[0] - hx, c[0] + hx, c[1] - hy, c[1] + hy))
    for k in torch.argsort(pred.probs[j]).tolist():  # the likely modes drawn last, on top
        pk = pred.probs[j, k].item()
        colour = plt.cm.viridis_r(norm_p(pk))
        ax.plot(*P[k].T, color=colour, lw=0.6 + 3 * pk / norm_p.vmax, zorder=8)
    ax.plot(*torch.cat([sub.agent_hist[j, -1:, :2], sub.agent_fut[j, :, :2]]).T, "o-", **FUTURE)
    figures.plot_prediction(z, pred, j, color="tab:red", label=None)
    z.plot(*sub.agent_fut[j, :, :2].T, "o-", **dict(FUTURE, zorder=8, lw=1.2))
    k = int(pred.probs[j].argmax())
    sd = torch.linalg.eigvalsh(pred.pos_cov[j, k, -1]).sqrt().tolist()  # (2,) m at T
    (x, y), h = pred.means[j, k, -1].tolist(), max(2.0, 1.5 * sd[1])
    z.set(xlim=(x - 1.5 * h, x + 1.5 * h), ylim=(y - h, y + h), aspect="equal", xlabel="x (m)")
    title = f"the box above: most likely mode (p = {pred.probs[j, k]:.2f}), 1σ at 3 s"
    z.set_title(f"{title} {sd[1]:.2f} × {sd[0]:.2f} m", fontsize=8)
    ax.indicate_inset([x - 1.5 * h, y - h, 3 * h, 2 * h], edgecolor="0.3")


def figure_modes(sub, pred, label):
    """§6: a predictor's (`label`) K modes on the samples of `sub`, coloured by p(z = k | x)."""
    norm_p = plt.Normalize(0, pred.probs.max().item())
    kw = dict(figsize=(14, 7.4), layout="constrained", height_ratios=(1, 1))
    fig, (axes, zoom) = plt.subplots(2, len(sub), **kw)
    for j, (ax, z) in enumerate(zip(axes, zoom)):
        _modes_panel(ax, z, sub, pred, j, norm_p)
    _colorbar(fig, axes, "viridis_r", norm_p, "mode probability p(z = k | x)", 0.8)
    mode = Line2D([], [], color="tab:blue", ls="-", label="a mode (colour, width: p)")
    future = Line2D([], [], color="tab:orange", marker="o", mec="k", label="true future (0.5 s)")
    axes[0].legend(handles=[mode, future], loc="lower left", fontsize=7)
    ends = pred.means[:, :, -1, :2]  # (B, K, 2) the modes' positions at T
    likely = pred.probs >= 0.05  # (B, K) the modes drawn thick enough to see
    spread = max(torch.cdist(e[m], e[m]).max().item() for e, m in zip(ends, likely))
    closest = (ends - sub.agent_fut[:, None, -1, :2]).norm(dim=-1).min(-1).values  # (B,)
    top = pred.probs.max(-1).values
    title = (
        f"Standard predictor, {label}: its {pred.probs.shape[1]} modes (orange: the true future; "
        "below, each box zoomed: the most likely mode's 1σ ellipses).\nThe most likely mode has "
        f"p = {top.min():.2f} .. {top.max():.2f}; the modes with p ≥ 0.05 end up to {spread:.1f} m "
        f"apart, and the closest mode ends {closest.min():.1f} .. "
        f"{closest.max():.1f} m from the true position at T = 3 s"
    )
    _show(fig, title)


def figure_learning_curves(histories):
    """§7: per-batch training losses of {name: (history, colour)} and their 10-step mean."""
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.7), layout="constrained")
    moved, steps = [], 0
    ylab = {"l_pred": "L_pred (nats)", "l_plan": "L_plan (nats)", "l_ctr": "L_ctr = hindsight cost"}
    for ax, (key, label) in zip(axes, ylab.items()):
        title = []
        for name, (h, color) in histories.items():
            if key != "l_pred" and name == "Standard":
                continue
            v = np.asarray([r[key] for r in h], dtype=float)
            steps = len(v)
            ax.plot(range(1, len(v) + 1), v, color=color, alpha=0.25, lw=0.8)
            # the 10-step mean (the whole series when it is shorter)
            sm = np.convolve(v, np.ones(10) / 10, mode="valid") if len(v) >= 10 else v
            ax.plot(np.arange(len(v) - len(sm) + 1, len(v) + 1), sm, color=color, lw=2, label=name)
            # first and last quarter's means; real: they differ by over 2 s.e. (batch-to-batch)
            q = max(2, len(v) // 4)
            first, last = v[:q].mean(), v[-q:].mean()
            real = abs(last - first) > 2 * np.sqrt(v[:q].var(ddof=1) / q + v[-q:].var(ddof=1) / q)
            fmt = "{:.3f}" if abs(first) < 10 else "{:.1f}"
            change = f"{fmt.format(first)} → {fmt.format(last)}" + ("" if real else " (noise)")
            title.append(f"{name} {change}")
            moved += [f"{name}'s {label.split()[0]}"] if real else []
        ax.set(xlabel="training step", ylabel=label)
        ax.set_title("\n".join(title), fontsize=9)
        ax.grid(alpha=0.3)
        ax.legend(loc="upper right")
    title = (
        f"Training losses per batch over {steps} steps (faint; solid: 10-step mean), first quarter "
        "→ last quarter of the steps; beyond the batch-to-batch noise (2 s.e.): "
    )
    _show(fig, title + (", ".join(moved) or "none"))


def kkt_gradient_check(val, cfg, seed, out=print):
    """§5: the gradient of a random linear function of iLQR's solution (float64) wrt s0, w, the
    prediction, by the KKT backward (exact, curvature-free) vs finite differences: their errors."""
    torch.manual_seed(seed)
    d_min = (val.ego_fut[..., :2] - val.agent_fut[..., :2]).norm(dim=-1).min(-1).values
    pick = torch.nonzero(d_min < 6).flatten()[:3]  # three samples where the vehicle comes near
    b64 = val[pick].to(F64)
    ctx64 = gt_context(b64)
    leaves = (b64.ego_hist[:, -1], ds.cost_weights(cfg, F64), ctx64.preds)  # s0, w, prediction
    lo, hi = (torch.tensor(v, dtype=F64) for v in (cfg.u_lower, cfg.u_upper))
    uni = ds.Unicycle(cfg.dt)

    def fn(x, u, w, preds):
        return ds.total_cost(x, u, dataclasses.replace(ctx64, preds=preds), w, cfg.rbf_var)

    u0 = torch.zeros(3, 6, 2, dtype=F64)
    _, u_star, info = ds.ilqr(fn, uni, leaves[0], u0, leaves[1:], lo, hi, iters=50, tol=1e-11)
    assert info.converged.all()
    g = torch.Generator().manual_seed(seed)
    wx = torch.randn(3, 7, 4, generator=g, dtype=F64)  # the loss's weights on x, u
    wu = torch.randn(3, 6, 2, generator=g, dtype=F64)

    def loss(ls, exact=None):  # the loss of the problem with these leaves, re-solved
        if exact is None:  # iLQR alone, for finite differences
            x, u, _ = ds.ilqr(fn, uni, ls[0], u_star, tuple(ls[1:]), lo, hi, iters=50, tol=1e-11)
        else:  # and its KKT backward, exact or curvature-free
            solve = dict(iters=30, tol=1e-11, exact=exact)
            x, u, _ = ds.ilqr_solve(fn, uni, ls[0], u_star, tuple(ls[1:]), lo, hi, **solve)
        return (x * wx).sum() + (u * wu).sum()

    grads = []
    for exact in (True, False):
        ls = [v.clone().requires_grad_() for v in leaves]
        grads.append(torch.autograd.grad(loss(ls, exact), ls))
    errs = {}
    for i, name in enumerate(("initial state s0", "cost weights w", "predicted trajectory")):
        fd = eval_numerical_gradient(
            lambda v: loss([*leaves[:i], v, *leaves[i + 1 :]]), leaves[i], 1e-4
        )
        errs[name] = [((g[i] - fd).norm() / fd.norm()).item() for g in grads]
        said = f"exact KKT {errs[name][0]:.1e}   curvature-free {errs[name][1]:.1e}"
        out(f"  {name:22s} relative error vs finite differences: {said}")
    return errs


def show_source(fn):
    """Display a function's source as the module has it, naming its file and line."""
    lines, first = inspect.getsourcelines(fn)
    where = f"`{fn.__module__}.{fn.__qualname__}`, {Path(inspect.getfile(fn)).name} line {first}"
    display(Markdown(f"{where}:\n\n```python\n{''.join(lines).rstrip()}\n```"))


def planner_view(ex, cfg, shift=(0.0, 0.0), beta=1.0, preds=None, **_):
    """The relaxed planner of eq. (2) on `ex` (a batch of 1), its prediction `preds` (None: the GT
    future) moved by `shift` (m): C, p_n, the plan, n*, L_plan, dL_plan/dŝ (T, 2), their extent."""
    ctx = gt_context(ex)
    preds = ctx.preds if preds is None else preds.detach()
    preds = (preds + torch.tensor(shift, dtype=preds.dtype)).requires_grad_()
    w = ds.cost_weights(cfg, ctx.preds.dtype)
    start = ex.ego_hist[:, -1]
    cands, cost, plan, _, _ = ds.plan(start, dataclasses.replace(ctx, preds=preds), ex.goal, w, cfg)
    target = ds.masked_argmin(ds.total_cost(cands.s, cands.u, ctx, w, cfg.rbf_var), cands.valid)
    l_plan = ds.plan_loss(cost, cands.valid, target, beta)
    (grad,) = torch.autograd.grad(l_plan.sum(), preds)  # (1, K=1, T, 2)
    p = torch.softmax(torch.where(cands.valid, -beta * cost.detach(), -math.inf), -1)[0]
    view = dict(cost=cost.detach()[0], p=p, plan=int(plan[0]), target=int(target[0]))
    pts = torch.cat([cands.s[0, cands.valid[0], :, :2].flatten(0, 1), preds[0, 0]])
    pts = torch.cat([pts.detach(), ex.agent_hist[0, -1:, :2], ex.agent_fut[0, :, :2]])
    (x0, y0), (x1, y1) = pts.min(0).values.tolist(), pts.max(0).values.tolist()
    view.update(extent=(x0 - 3, x1 + 3, y0 - 2, y1 + 2), l_plan=l_plan.item(), cands=cands)
    return dict(view, grad=grad[0, 0], pred=preds.detach()[0, 0])


def draw_planner_view(ax, v, ex, beta, shift=(0.0, 0.0), what="GT", scale=None, **_):
    """planner_view v drawn (`what`: the prediction): candidates by p_n, the plan, n*, the
    prediction, -dL_plan/dŝ as arrows coloured by size (scale: m per 1/m, None: the longest 3 m)."""
    p, valid, x = v["p"], v["cands"].valid[0], v["cands"].s[0, :, :, :2].detach()  # x (N, T+1, 2)
    hit = "plan = n*" if v["plan"] == v["target"] else f"plan {v['plan']} ≠ n*"
    moved = f" moved ({shift[0]:+.1f}, {shift[1]:+.1f}) m" if any(shift) else ""
    entropy = -(p[p > 0] * p[p > 0].log()).sum()
    title = (
        f"{data_synth.BEHAVIOURS[int(ex.behaviour[0])]}, β = {beta:g}, {what}{moved}: L_plan "
        f"{v['l_plan']:.2f}, {hit}, largest |dL/dŝ_t| {v['grad'].norm(dim=-1).max():.1e} 1/m\n"
        f"max p_n = {p.max():.2f}, entropy {entropy:.2f} nats (uniform: {valid.sum().log():.2f})"
    )
    _scene(ax, ex, 0, title, v["extent"])
    for n in torch.argsort(p).tolist():  # the likely candidates drawn last, on top
        if valid[n]:
            colour = plt.cm.viridis(P_NORM(max(p[n].item(), 1e-4)))
            ax.plot(*x[n].T, color=colour, lw=1.0 + 2 * p[n].item() ** 0.5, zorder=2)
    ax.plot(*x[v["target"]].T, color="magenta", lw=6, alpha=0.45, label="target n* (hindsight)")
    ax.plot(*x[v["plan"]].T, "k--", marker="o", ms=3, lw=1.5, label="plan (argmin C)")
    ax.plot(*v["pred"].T, "o-", color="tab:red", ms=3, label="prediction ŝ", zorder=7)
    g = v["grad"].norm(dim=-1)  # (T,) 1/m
    arrows = -v["grad"] * (scale or 3 / max(g.max().item(), 1e-12))
    q = dict(angles="xy", scale_units="xy", scale=1, width=0.004, zorder=8, label="-dL_plan/dŝ")
    ax.quiver(*v["pred"].T, *arrows.T, color=G_MAP(G_NORM(g.numpy())), **q)


def planner_panels(panels, cfg, title, scale=None):
    """A draw_planner_view panel per dict of its arguments (ex, shift, beta, preds, what) in
    panels, stacked, under colour bars of p_n and |dL_plan/dŝ_t|; scale: draw_planner_view's."""
    views = [planner_view(cfg=cfg, **panel) for panel in panels]
    # each panel's height from its data's aspect (equal axes), so no panel is left mostly empty
    heights = [1.0 + 7 * (e[3] - e[2]) / (e[1] - e[0]) for e in [v["extent"] for v in views]]
    kw = dict(figsize=(10, sum(heights) + 0.6), height_ratios=heights, layout="constrained")
    fig, axes = plt.subplots(len(panels), 1, squeeze=False, **kw)
    for ax, v, panel in zip(axes[:, 0], views, panels):
        draw_planner_view(ax, v, scale=scale, **panel)
    fig.legend(*axes[0, 0].get_legend_handles_labels(), loc="outside lower center", ncol=4)
    _colorbar(fig, axes, "viridis", P_NORM, "p_n (log scale)", 0.9)
    _colorbar(fig, axes, G_MAP, G_NORM, "|dL_plan/dŝ_t| (1/m), arrows", 0.9)
    lengths = f"{scale:.2g} m per 1/m in all" if scale else "the longest 3 m in each panel"
    _show(fig, f"{title}\n(arrows -dL_plan/dŝ: {lengths}; colour: size, one scale in all)".strip())


def interactive_planner(ex, cfg, settings):
    """planner_panels of settings (shift, beta), then ipywidgets' sliders, shown (None without)."""
    title = "Move the prediction or change β: C, p_n, the plan and -dL_plan/dŝ (arrows) follow"
    panels = [dict(ex=ex, shift=shift, beta=beta) for shift, beta in settings]
    planner_panels(panels, cfg, title)
    try:
        import ipywidgets as widgets
    except ImportError:
        return None

    def redraw(dx=0.0, dy=0.0, beta=1.0):
        planner_panels([dict(ex=ex, shift=(dx, dy), beta=beta)], cfg, "")

    return widgets.interact(  # shown at once, as the cell ends with another call
        redraw,
        dx=widgets.FloatSlider(value=0.0, min=-8, max=8, step=0.5, description="move x (m)"),
        dy=widgets.FloatSlider(value=0.0, min=-4, max=4, step=0.25, description="move y (m)"),
        beta=widgets.FloatLogSlider(value=1.0, base=10, min=-2, max=1, description="β"),
    ).widget


# --- the exercises' checks: the common part -------------------------------------------------------


class Forbidden(AssertionError):
    """An answer that used what its exercise rules out (autograd where the closed form is asked)."""


# the relations between an answer and the reference that one number explains (mine = c * ref)
FACTORS = {-1.0: "the sign is flipped", 2.0: "a factor 2 too many", 0.5: "a factor 2 missing"}


def _relation(mine, ref, factors):
    """How mine relates to ref when one number c explains the whole difference, mine = c ref (a
    sign, a factor 2, a mean for a sum): a sentence naming c and, from factors, why; or ''."""
    m, r = mine.detach().double().flatten(), ref.detach().double().flatten()
    if not torch.isfinite(m).all() or (r @ r).item() == 0:
        return ""
    if m.abs().max() == 0:
        return " Yours is zero everywhere."
    c = (m @ r).item() / (r @ r).item()
    if abs(c - 1) < 1e-6 or (m - c * r).norm() > 1e-4 * r.norm():  # the reference, or no multiple
        return ""
    why = next((w for v, w in factors.items() if abs(c - v) <= 1e-4 * abs(v)), None)
    return f" Yours is {c:.4g} times the reference" + (f": {why}." if why else ".")


def _close(name, mine, ref, hint, tol=1e-9, cond=1.0, dtype=None, factors=None, diagnose=None):
    """Assert mine ~ ref: same shape, finite, max error <= max(tol, 16 eps cond) max(1, |ref|),
    so a right float32 answer passes (cond: how much the problem magnifies rounding). A failure says
    what differs: a ratio to the reference (factors: {c: why}), diagnose(mine) (the term, stage)."""
    try:
        mine = torch.as_tensor(mine)
    except (TypeError, ValueError, RuntimeError):
        raise AssertionError(
            f"{name}: expected a tensor of shape {tuple(ref.shape)}, got "
            f"{type(mine).__name__}. {hint}"
        ) from None
    assert mine.shape == ref.shape, (
        f"{name}: shape {tuple(mine.shape)}, expected {tuple(ref.shape)}. {hint}"
    )
    assert mine.is_floating_point(), (
        f"{name}: dtype {mine.dtype}, expected a floating-point tensor. {hint}"
    )
    bad = (~torch.isfinite(mine)).nonzero()
    if len(bad):
        raise AssertionError(
            f"{name}: inf or NaN in {len(bad)} of {mine.numel()} entries (the first at index "
            f"{tuple(bad[0].tolist())}).{diagnose(mine) if diagnose else ''} {hint}"
        )
    err = (mine.to(ref.dtype) - ref).abs().max().item()
    scale = max(1.0, ref.abs().max().item())
    allowed = max(tol, 16 * torch.finfo(dtype or mine.dtype).eps * cond) * scale
    if err > allowed:
        ratio = _relation(mine, ref, {**FACTORS, **(factors or {})})
        raise AssertionError(
            f"{name}: max |yours - reference| = {err:.3g} (allowed {allowed:.1g}).{ratio}"
            f"{diagnose(mine) if diagnose else ''} {hint}"
        )
    return err


def _call(name, fn, *args, returns=""):
    """fn(*args); its error (but a stub's, or Forbidden) is a failure naming the inputs' shapes."""
    try:
        return fn(*args)
    except (NotImplementedError, Forbidden):
        raise
    except Exception as e:  # whatever the student's code raises is the answer's failure
        shapes = [str(tuple(a.shape)) if torch.is_tensor(a) else type(a).__name__ for a in args]
        raise AssertionError(
            f"{name} raised {type(e).__name__}: {e} (its inputs: {', '.join(shapes)}; it should "
            f"return {returns})"
        ) from None


def _parts(name, out, count, parts, hint):
    """An answer that returns several tensors: assert it returned `count` of them (parts: what)."""
    many = isinstance(out, (tuple, list))
    got = f"{type(out).__name__}{f' of {len(out)}' if many else ''}"
    assert many and len(out) == count, f"{name}: returned {got}, expected the {parts}. {hint}"
    return out


@contextlib.contextmanager
def no_autograd(name):
    """Within it, autograd's entry points raise Forbidden naming the one called, and an answer
    that records a graph anyway (enable_grad, a name imported) is caught by a saved-tensors hook."""
    entries = [(torch.autograd, "grad"), (torch.autograd, "backward"), (torch.Tensor, "backward")]
    entries += [
        (torch.func, f) for f in ("grad", "grad_and_value", "vjp", "jvp", "jacrev", "jacfwd")
    ]
    entries += [(torch.autograd.functional, f) for f in ("jacobian", "vjp", "jvp", "hessian")]
    saved = {(owner, attr): getattr(owner, attr) for owner, attr in entries}
    recorded = []  # autograd saves a tensor for a backward pass: a graph is being recorded
    pack = torch.autograd.graph.saved_tensors_hooks(lambda t: recorded.append(1) or t, lambda t: t)
    try:
        for owner, attr in saved:
            refused = f"{name} used autograd ({owner.__name__}.{attr})"
            setattr(owner, attr, functools.partial(_refuse, refused))
        with pack, torch.no_grad():
            yield
    finally:
        for (owner, attr), value in saved.items():
            setattr(owner, attr, value)
    if recorded:
        _refuse(f"{name} recorded a graph for autograd")


def _refuse(what, *args, **kwargs):
    """no_autograd's stand-in for autograd's entry points: Forbidden, saying what was used."""
    raise Forbidden(f"{what}: this exercise asks for the closed form")


def exercise(number, check, fn, reveal=None):
    """A check from a notebook cell, printed: PASS (True), not done (a stub) or FAIL and what is
    wrong (False: Run All goes on); once it passes, reveal's source (the module's answer)."""
    try:
        detail = check(fn)
    except NotImplementedError:
        print(
            f"EXERCISE {number}: not done yet: fill in `{fn.__name__}` in the cell above, run "
            "it, then this cell. (The rest of the notebook does not need it.)"
        )
        return False
    except Exception as e:  # a wrong answer: said, and the notebook goes on (the grader decides)
        print(f"EXERCISE {number}: FAIL ✗ {type(e).__name__}: {e}\n(the notebook goes on)")
        return False
    print(f"EXERCISE {number}: PASS ({detail})")
    if reveal is not None:
        print("Now that yours passes, the module's own version, to compare:")
        show_source(reveal)
    return True


def show_failure(check, fn):
    """Print what a check says of a wrong answer, without stopping the notebook."""
    try:
        check(fn)
        print("the check passes")
    except AssertionError as e:
        print(f"the check says: {e}")


def eval_numerical_gradient(f, x, h=1e-6):
    """The gradient of a scalar f at x (float64) by central differences, entry by entry."""
    x = x.detach().to(F64)
    grad = torch.zeros_like(x)
    for i in range(x.numel()):
        e = torch.zeros_like(x)
        e.view(-1)[i] = h
        grad.view(-1)[i] = (float(f(x + e)) - float(f(x - e))) / (2 * h)
    return grad


def grad_check(f, x, analytic, h=1e-6, out=print):
    """Your gradient `analytic` against eval_numerical_gradient(f, x): the largest relative error
    |a - n| / (|a| + |n|), printed; 1e-7 or below: right, 1e-2 or above: almost surely wrong."""
    numeric = eval_numerical_gradient(f, x, h)
    a = torch.as_tensor(analytic).detach().to(F64)
    assert a.shape == numeric.shape, f"the gradient's shape {tuple(a.shape)}, x's {tuple(x.shape)}"
    rel = ((a - numeric).abs() / (a.abs() + numeric.abs()).clamp_min(1e-12)).max().item()
    out(f"gradient check: largest relative error {rel:.1e} over {x.numel()} entries")
    return rel


def collision_problem(seed=0, B=6, N=7, K=5, T=6, A=3):
    """Ego positions (B, N, T, 2) near a multi-mode prediction, and a CostContext in which some
    scenarios have no predicted agent (pred_mask 0) and some other agents are masked out."""
    g = torch.Generator().manual_seed(seed)
    preds = 3 * torch.randn(B, K, T, 2, generator=g, dtype=F64)
    probs = torch.softmax(2 * torch.randn(B, K, generator=g, dtype=F64), -1)  # far from uniform
    pred_mask = (torch.arange(B) % 3 != 1).to(F64)  # scenarios 1, 4: no predicted agent
    others = 3 * torch.randn(B, A, T, 2, generator=g, dtype=F64)
    others_mask = torch.ones(B, A, dtype=F64)
    others_mask[::2, 0] = 0  # some other agents absent
    lanes = torch.zeros(B, 1, 5, 3, dtype=F64)
    lanes[..., 0] = torch.linspace(-10, 30, 5, dtype=F64)
    goal, lanes_mask = torch.zeros(B, 2, dtype=F64), torch.ones(B, 1, 5, dtype=torch.bool)
    ctx = ds.CostContext(preds, probs, pred_mask, others, others_mask, goal, lanes, lanes_mask)
    pos = 3 * torch.randn(B, N, T, 2, generator=g, dtype=F64)
    return pos, ctx


def collision_terms_at_fault(_, fn, pos, ctx, rbf_var):
    """Which part of C_coll the answer fn gets wrong, run again: a mask it ignores (it equals C_coll
    with that mask all 1), or one of the two terms, each scored alone. A sentence, or ''."""

    def agrees(answer_ctx, reference_ctx):  # the answer on one context, the module on another
        try:
            mine = torch.as_tensor(fn(pos, answer_ctx, rbf_var)).double()
            ref = ds.collision_term(pos, reference_ctx, rbf_var)
            return torch.allclose(mine, ref, rtol=1e-5, atol=1e-9)
        except Exception:  # (the answer's own error is reported by the check)
            return False

    for mask in ("pred_mask", "others_mask"):
        all_ones = dataclasses.replace(ctx, **{mask: torch.ones_like(getattr(ctx, mask))})
        if agrees(ctx, all_ones):
            return f" Yours equals C_coll with every {mask} entry 1: it ignores {mask}."
    no_others = dataclasses.replace(ctx, others_mask=torch.zeros_like(ctx.others_mask))
    no_vehicle = dataclasses.replace(ctx, pred_mask=torch.zeros_like(ctx.pred_mask))
    alone = {
        "the predicted vehicle's term (preds, probs, pred_mask)": no_others,
        "the other agents' term (others, others_mask)": no_vehicle,
    }
    wrong = [term for term, c in alone.items() if not agrees(c, c)]
    if len(wrong) != 1:
        return ""
    right_one = next(t for t in alone if t not in wrong)
    return f" Scored alone, {wrong[0]} is wrong and {right_one} right."


def check_collision(fn):
    hint = (
        "C_coll = pred_mask * sum_t phi(sum_k pi_k ||s_t - s^_kt||^2) + sum_a mask_a sum_t "
        "phi(||s_t - s_at||^2), phi(d2) = exp(-d2 / (2 rbf_var)); the expectation is over "
        "squared distances, not of positions."
    )
    worst = 0.0
    for seed, rbf_var in ((0, 2.0), (1, 3.5)):
        pos, ctx = collision_problem(seed)
        mine = _call("my_collision", fn, pos, ctx, rbf_var, returns="C_coll of shape (B, N)")
        T, ref = pos.shape[2], ds.collision_term(pos, ctx, rbf_var)
        mean = {1 / T: f"a mean over the T = {T} steps, where eq. (3) sums them"}
        why = functools.partial(collision_terms_at_fault, fn=fn, pos=pos, ctx=ctx, rbf_var=rbf_var)
        err = _close("my_collision", mine, ref, hint, cond=10, factors=mean, diagnose=why)
        worst = max(worst, err)
    return f"max error {worst:.1e}, 2 problems, masks and rbf_var varied"


def plan_problem(seed=0, B=8, N=12):
    """Candidate costs near 2000 (B, N), invalid candidates cheaper than every valid one (a
    softmax that ignores the mask picks them), and targets n* among the valid ones."""
    g = torch.Generator().manual_seed(seed)
    cost = 2000 + 3 * torch.randn(B, N, generator=g, dtype=F64)
    valid = torch.rand(B, N, generator=g) > 0.3
    valid[:, :2] = True  # at least two valid candidates
    cost = torch.where(valid, cost, cost - 20)
    pick = [torch.randint(int(v.sum()), (1,), generator=g) for v in valid]
    target = torch.stack([torch.nonzero(v).flatten()[k][0] for v, k in zip(valid, pick)])
    return cost, valid, target


def target_off_by_one(mine, cost, valid, target, beta):
    """A sentence if the answer is the loss of the candidate next to n* (off by one), or ''."""
    m = mine.detach().double()
    for shift in (1, -1):
        other = (target + shift).clamp(0, cost.shape[-1] - 1)
        alt = ds.plan_loss(cost.detach().double(), valid, other, beta)  # inf where it is invalid
        finite = torch.isfinite(alt)
        if (finite == torch.isfinite(m)).all() and torch.allclose(m[finite], alt[finite], 1e-5):
            return (
                f" Yours is the loss of candidate n* {shift:+d} (an off-by-one in the target index;"
                " where that candidate is invalid, its loss is inf)."
            )
    return ""


def check_plan_loss(fn, name="my_plan_loss"):
    hint = (
        "L_plan = -log p_{n*}, p_n = exp(-beta C_n) / sum over the *valid* n' of exp(-beta "
        "C_n'); use a stable log-softmax (logsumexp): exp(-2000) underflows."
    )
    returns, worst = "L_plan of shape (B,)", 0.0
    for seed, beta in ((0, 1.0), (1, 0.3), (2, 2.5)):
        cost, valid, target = plan_problem(seed)
        c1, c2 = cost.clone().requires_grad_(), cost.clone().requires_grad_()
        mine = _call(name, fn, c1, valid, target, beta, returns=returns)
        ref = ds.plan_loss(c2, valid, target, beta)
        cond = beta * cost.abs().max().item()  # the costs' rounding, magnified by beta
        factors = {beta: "beta applied twice?", 1 / beta: "beta left out"}
        off = functools.partial(target_off_by_one, cost=cost, valid=valid, target=target, beta=beta)
        at = f"(beta = {beta})"
        err = _close(f"{name} {at}", mine, ref, hint, cond=cond, factors=factors, diagnose=off)
        worst = max(worst, err)
        ref.sum().backward()
        assert mine.requires_grad, f"{name}: the result carries no gradient. {hint}"
        mine.sum().backward()
        _close(
            f"gradient of {name} wrt the costs {at}", c1.grad, c2.grad, hint, 1e-9, cond, mine.dtype
        )
    # the fragile cases: float32 costs near 500, an invalid candidate 200, then 1000, cheaper than
    # every valid one; next to it exp(-beta C) of every valid candidate underflows (exp(-200) in
    # float32, exp(-1000) in float64 too), so a softmax over all candidates renormalised over the
    # valid ones is 0/0, in whatever float type it is computed
    g = torch.Generator().manual_seed(3)
    cost = 500 + 5 * torch.rand(4, 6, generator=g)
    valid = torch.ones(4, 6, dtype=torch.bool)
    valid[:, 0] = False
    target = torch.randint(1, 6, (4,), generator=g)
    wrong = "Every target here is valid, so its loss is finite; yours is not."
    for gap in (200, 1000):
        cost[:, 0] = cost[:, 1:].min(-1).values - gap
        mine = _call(name, fn, cost, valid, target, 1.0, returns=returns)
        case = f"{name} in float32, an invalid candidate {gap} cheaper than every valid one"
        _close(case, mine, ds.plan_loss(cost.double(), valid, target, 1.0), wrong, cond=500)
    return (
        f"values and gradients, max error {worst:.1e}, beta in (0.3, 1, 2.5), masked candidates, "
        "float32 with a far cheaper invalid candidate"
    )


# exercise 4 (find the bug): the fixed loss passes exercise 2's check
check_plan_loss_fixed = functools.partial(check_plan_loss, name="my_plan_loss_fixed")


def check_plan_grad(fn):
    hint = (
        "differentiate -log p_{n*} = beta C_{n*} + log sum_{n' valid} exp(-beta C_n') with "
        "respect to C_n; invalid candidates get 0."
    )
    worst = 0.0
    for seed, beta in ((0, 1.0), (1, 0.3), (2, 2.5)):
        cost, valid, target = plan_problem(seed)
        c = cost.clone().requires_grad_()
        (ref,) = torch.autograd.grad(ds.plan_loss(c, valid, target, beta).sum(), c)  # autograd's
        returns = "dL_plan/dC of shape (B, N)"
        with no_autograd("my_plan_loss_grad"):
            mine = _call("my_plan_loss_grad", fn, cost, valid, target, beta, returns=returns)
        B, cond = len(cost), beta * cost.abs().max().item()
        factors = {
            1 / B: f"divided by B = {B} (the gradient of the batch's mean; the check asks for each "
            "sample's own)",
            1 / beta: "beta left out",
            beta: "beta applied twice",
        }
        name = f"my_plan_loss_grad (beta = {beta})"
        worst = max(worst, _close(name, mine, ref, hint, cond=cond, factors=factors))
    return f"against autograd, max error {worst:.1e}, beta in (0.3, 1, 2.5), masked candidates"


def check_riccati(fn):
    hint = "see the formulas above the iLQR cell: Q = H_t + F'PF, q = g_t + F'p with F = [A_t B_t]."
    n, m, worst = 4, 2, 0.0
    for seed in (0, 1):
        # a random one-step LQR (positive definite cost), as ds.lqr_backward takes it
        g = torch.Generator().manual_seed(seed)
        randn = functools.partial(torch.randn, generator=g, dtype=F64)
        R = randn(6, 2, n + m, n + m)
        H = R @ R.transpose(-1, -2) + 0.5 * torch.eye(n + m, dtype=F64)  # (B, 2, n+m, n+m)
        gv, A, Bm = randn(6, 2, n + m), randn(6, 1, n, n), randn(6, 1, n, m)
        free = torch.ones(len(H), 1, m, dtype=torch.bool)
        k_ref, K_ref, _, p0_ref = ds.lqr_backward(A, Bm, H, gv, free=free)
        # P_new independently: the Schur complement of Q's control block, Q_ss - Q_su Q_uu^-1 Q_us
        F = torch.cat([A[:, 0], Bm[:, 0]], -1)
        Q = H[:, 0] + F.transpose(-1, -2) @ H[:, 1, :n, :n] @ F
        P_ref = Q[:, :n, :n] - Q[:, :n, n:] @ torch.linalg.solve(Q[:, n:, n:], Q[:, n:, :n])
        args = (H[:, 1, :n, :n], gv[:, 1, :n], H[:, 0], gv[:, 0], A[:, 0], Bm[:, 0], n)
        returns = f"(k (B, {m}), K (B, {m}, {n}), P_new (B, {n}, {n}), p_new (B, {n}))"
        out = _call("my_riccati_step", fn, *args, returns=returns)
        out = _parts("my_riccati_step", out, 4, "four (k, K, P_new, p_new)", hint)
        cond = torch.linalg.cond(Q[:, n:, n:]).max().item()  # the solves with Q_uu
        names = ("k (feed-forward)", "K (feedback gain)", "P_new", "p_new")
        for name, mine, ref in zip(names, out, (k_ref[:, 0], K_ref[:, 0], P_ref, p0_ref)):
            worst = max(worst, _close(f"my_riccati_step: {name}", mine, ref, hint, 1e-8, cond))
    return f"k, K, P_new, p_new, max error {worst:.1e}"


def kkt_problem(seed=0, B=4, T=5, n=3, m=2):
    """An LQR as the KKT backward sees one: x_{t+1} = A_t x_t + B_t u_t, cost sum_t z_t'H_t z_t / 2
    + g_t'z_t (z_t = [x_t; u_t], t = 0..T), some controls held (free False), grad_x and grad_u."""
    gen = torch.Generator().manual_seed(seed)
    randn = functools.partial(torch.randn, generator=gen, dtype=F64)
    A = torch.eye(n, dtype=F64) + 0.3 * randn(B, T, n, n)
    Bm = randn(B, T, n, m)
    R = randn(B, T + 1, n + m, n + m)
    H = R @ R.transpose(-1, -2) / (n + m) + torch.eye(n + m, dtype=F64)
    free = torch.rand(B, T, m, generator=gen) > 0.3
    return A, Bm, H, randn(B, T + 1, n + m), randn(B, n), free, randn(B, T + 1, n), randn(B, T, m)


def lqr_solve(A, Bm, H, g, x_init, free):
    """The problem's solution (x*, u*): the module's Riccati policy rolled out from x_init."""
    k, K, _, _ = ds.lqr_backward(A, Bm, H, g, free=free)
    x, u = [x_init], []
    for t in range(A.shape[1]):
        u.append(k[:, t] + (K[:, t] @ x[-1][..., None])[..., 0])
        x.append((A[:, t] @ x[-1][..., None] + Bm[:, t] @ u[-1][..., None])[..., 0])
    return torch.stack(x, 1), torch.stack(u, 1)


def kkt_stage_at_fault(mine, ref, free, n, allowed):
    """Where a wrong dL/dg first differs: the stage, and its states, free or held controls."""
    T = free.shape[1]
    bad = (mine.detach().double() - ref).abs() > allowed  # (B, T+1, n+m)
    held, free_u, states = (torch.zeros_like(bad) for _ in range(3))
    held[:, :T, n:], free_u[:, :T, n:], states[..., :n] = ~free, free, True
    t = int(bad.any(0).any(-1).nonzero()[0])
    parts = {
        "state entries": states,
        "free controls": free_u,
        "controls held at a bound (free False; there d holds du = 0, so dL/dg is 0)": held,
    }
    where = [p for p, sel in parts.items() if (bad[:, t] & sel[:, t]).any()]
    if bad[:, T, n:].any():
        where.append("the last stage's control block (it has no control: 0)")
    found = f" It differs first at stage t = {t} (of 0..{T}), in its {' and in its '.join(where)}."
    if (mine.detach().double()[:, :T, n:][~free].abs() > allowed).any():
        found += " At the held controls yours is not 0: the backward pass keeps the active set."
    return found


def check_kkt(fn):
    hint = (
        "the backward pass is the same LQR (A, B, H, the active set) with the incoming gradient "
        "[grad_x; grad_u] as its linear term and dx_0 = 0 (see the derivation above)."
    )
    worst = 0.0
    for seed in (0, 1):
        A, Bm, H, g, x_init, free, grad_x, grad_u = kkt_problem(seed)
        (_, T1, nm), n = g.shape, x_init.shape[-1]
        # the reference: autograd through lqr_solve of L = <grad_x, x*> + <grad_u, u*> ...
        xi, gg = x_init.clone().requires_grad_(), g.clone().requires_grad_()

        def loss(xi, gg):
            x, u = lqr_solve(A, Bm, H, gg, xi, free)
            return (grad_x * x).sum() + (grad_u * u).sum()

        ref_x, ref_g = torch.autograd.grad(loss(xi, gg), (xi, gg))
        fd = eval_numerical_gradient(lambda v: loss(v, g), x_init)  # ... itself against FD
        assert (fd - ref_x).abs().max() < 1e-6
        returns = f"(dL/dx_init (B, {n}), dL/dg (B, {T1}, {nm}))"
        out = _call("my_kkt_backward", fn, A, Bm, H, grad_x, grad_u, free, n, returns=returns)
        out = _parts("my_kkt_backward", out, 2, "two (dL/dx_init, dL/dg)", hint)
        cond = torch.linalg.cond(H).max().item()
        allowed = max(1e-9, 16 * torch.finfo(torch.as_tensor(out[1]).dtype).eps * cond)
        allowed *= max(1.0, ref_g.abs().max().item())
        stage = functools.partial(kkt_stage_at_fault, ref=ref_g, free=free, n=n, allowed=allowed)
        err_g = _close("my_kkt_backward: dL/dg", out[1], ref_g, hint, cond=cond, diagnose=stage)
        costate = {-1.0: "p_0 with the wrong sign"}
        err = _close("my_kkt_backward: dL/dx_init", out[0], ref_x, hint, cond=cond, factors=costate)
        worst = max(worst, err, err_g)
    return (
        "dL/dx_init and dL/dg against autograd through the solver (itself against finite "
        f"differences), max error {worst:.1e}, held controls"
    )


# the exercises: the function each asks for, what it is, its check (lab/grader.py grades them)
EXERCISES = {
    1: ("my_collision", "the collision term", check_collision),
    2: ("my_plan_loss", "the relaxed planner's loss", check_plan_loss),
    3: ("my_plan_loss_grad", "the gradient through the relaxed argmin", check_plan_grad),
    4: ("my_plan_loss_fixed", "find the bug: the planner's loss in float32", check_plan_loss_fixed),
    5: ("my_riccati_step", "one step of the Riccati recursion", check_riccati),
    6: ("my_kkt_backward", "the controller's gradient, the KKT backward", check_kkt),
}
CHECKS = {number: check for number, (_, _, check) in EXERCISES.items()}
