# ---
# jupyter:
#   jupytext:
#     formats: ipynb,py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
#       format_version: '1.3'
#       jupytext_version: 1.19.6
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # DiffStack, walked through on a CPU
#
# Karkus, Ivanovic, Mannor, Pavone, *DiffStack: A Differentiable and Modular Control Stack for Autonomous
# Vehicles*, CoRL 2022. This notebook follows the paper section by section. Every piece of code here **imports**
# from [`diffstack.py`](diffstack.py) (the method), [`experiments.py`](experiments.py) (the paper's tables) and
# [`data_synth.py`](data_synth.py) (the data); nothing is
# copied into cells, so what you read below is what the module runs.
#
# | § | what | paper |
# |---|---|---|
# | 1 | the problem and the stack: predictor → planner → controller, and the gradient path back | §3, Fig. 1 |
# | 2 | the data: synthetic nuScenes-like scenarios, and the same scenes through the nuScenes writer and loader | §4.1 |
# | 3 | dynamics and cost: the unicycle, the five cost terms over a scenario | eq. (3), App. C |
# | 4 | the planner: spline candidates, the relaxed argmin and its temperature β | eq. (2), §3.1 |
# | 5 | the controller: box-constrained iLQR and its KKT backward, checked live against finite differences | eq. (4), App. C |
# | 6 | the predictor: a Trajectron++-style CVAE trained the standard way, against constant velocity | §3.1 |
# | 7 | end-to-end training: DiffStack against Standard, Table 1, an example where they differ | §4.2 |
# | 8 | a biased predictor (Table 2), imitation learning (Table 4), cost learning (Table 3), closed loop (Table 5), planning and control at 0.1 s | §4.2, §4.3, App. A |
#
# Three **exercises** (the collision term, the relaxed planner's loss, one step of the Riccati recursion) check
# themselves against the module. Their solutions are in the cell right after each exercise (collapsed in
# JupyterLab); replace a solution's body with your own code and run the check below it.
#
# **Running it.** `pip install -r requirements.txt`, then open this file in Jupyter (`jupyter lab tutorial.ipynb`)
# or VS Code and *Run All*. `QUICK = True` runs everything on small data in about 1 minute on 2 CPU cores;
# `QUICK = False` is the run whose outputs are stored in this file (about 9 minutes). Each heavy cell says how
# long it takes. Numbers from this short CPU training are **not** the paper's (4 GPUs, 20 epochs on nuScenes):
# the tables have the paper's shape, and the checkpoint cells say what value to expect on this machine class.

# %% tags=["parameters"]
# Parameters
import os

QUICK = True     # True: small data, short training (about 1 min on 2 CPU cores); False: the stored run (about 9 min)
SEED = 0         # every experiment cell seeds itself from this: re-running one cell reproduces its output
DEVICE = "cpu"   # the module runs on the CPU (float32 training, float64 gradient checks)

QUICK = os.environ.get("DIFFSTACK_QUICK", str(int(QUICK))) == "1"  # the test suite sets this
print(f"QUICK = {QUICK}  ({'quick' if QUICK else 'full'} mode), SEED = {SEED}, DEVICE = {DEVICE!r}")

# %%
import dataclasses
import math
import tempfile
import time
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import torch
from IPython.display import Image, Markdown, display

import data_synth
import diffstack as ds
import experiments as xp

assert DEVICE == "cpu", "diffstack.py is a CPU teaching implementation"
torch.set_num_threads(1)  # one thread: reproducible numbers, and the machine stays usable
plt.rcParams.update({"figure.dpi": 72, "savefig.dpi": 72, "font.size": 9})
T_START, CPU_START = time.time(), time.process_time()


def checkpoint(name, measured, expected, tol, rel=False):
    # Print a measured value, the value expected on this machine class, and whether they agree within tol.
    err = abs(measured - expected) / max(abs(expected), 1e-12) if rel else abs(measured - expected)
    ok = err <= tol
    print(f"CHECKPOINT {name}: measured {measured:.4g}, expected {expected:.4g} "
          f"(tolerance {'%g%%' % (100 * tol) if rel else tol}) -> {'OK' if ok else 'MISMATCH'}")


def rel_err(a, b):
    return ((a - b).norm() / b.norm()).item()


# Sizes: quick mode caps the work; full mode is the stored run.
N_DATA = 800 if QUICK else 4000           # synthetic planning samples (85 % train, 15 % validation, split by scene)
TRAIN_STEPS = 16 if QUICK else 100        # optimiser steps per trained predictor
N_CLOSED_LOOP = 8 if QUICK else 60        # validation scenes simulated in closed loop (Table 5)
cfg = ds.Config(batch_size=64 if QUICK else 256)
print(f"{N_DATA} samples, {TRAIN_STEPS} training steps of batch {cfg.batch_size} per method")

# %% [markdown]
# ## 1. The problem and the stack
#
# An autonomous vehicle (the *ego*) has to drive among other agents whose futures it does not know. DiffStack keeps
# the classic modular stack, and makes every module differentiable:
#
# * the **predictor** (a Trajectron++-style CVAE, learned) turns 4 s of history into $K$ weighted futures
#   $\{\hat s_{k,t}, \pi_k\}$ of a nearby vehicle;
# * the **planner** scores spline candidates $n = 1..N$ with the cost $C(\cdot;\hat s, \pi)$ of eq. (3) and picks
#   $\arg\min_n C_n$ (eq. 2);
# * the **controller** refines the plan with a box-constrained iLQR (eq. 4).
#
# Planner and controller are not learned here, but they are differentiable, so the losses downstream of the
# predictor can train it:
#
# $$\mathcal L \;=\; \alpha_1\,\mathcal L_\text{pred} + \alpha_2\,\mathcal L_\text{plan} + \alpha_3\,\mathcal L_\text{ctr},$$
#
# with $\mathcal L_\text{pred}$ the predictor's own (InfoVAE) loss, $\mathcal L_\text{plan} = -\log p_{n^*}$ the
# cross-entropy of a softmax-relaxed planner with the best candidate in hindsight, and $\mathcal L_\text{ctr}$ the
# hindsight cost of the controller's trajectory (RL setting; $\alpha = (1, 100, 1000)$) or its squared error to
# the expert (IL setting; $\alpha = (1, 10, 1000)$). *Standard* training uses $\mathcal L_\text{pred}$ alone.

# %%
# Figure: the modules (boxes), the forward data flow (black) and the gradient path of DiffStack (red, dashed).
from matplotlib.patches import FancyBboxPatch

fig, ax = plt.subplots(figsize=(10, 4.2))
ax.set_xlim(0, 10); ax.set_ylim(-0.55, 4.45); ax.axis("off")
boxes = {"inputs": (0.1, 1.7, "history of all agents\nlanes, goal"), "pred": (2.45, 1.7, "Predictor\n(CVAE, learned θ)"),
         "plan": (4.8, 1.7, "Planner\nsplines + argmin"), "ctrl": (7.15, 1.7, "Controller\nbox-iLQR")}
for key, (x, y, text) in boxes.items():
    color = "#e8e8e8" if key == "inputs" else ("#ffd9b3" if key == "pred" else "#cfe2f3")
    ax.add_patch(FancyBboxPatch((x, y), 1.9, 1.0, boxstyle="round,pad=0.05", fc=color, ec="k"))
    ax.text(x + 0.95, y + 0.5, text, ha="center", va="center", fontsize=9)
arrow = lambda x0, y0, x1, y1, **kw: ax.annotate("", (x1, y1), (x0, y0), arrowprops=dict(arrowstyle="->", **kw))
for x0, x1, label in ((2.0, 2.45, ""), (4.35, 4.8, r"$\hat s_{k,t},\ \pi_k$"), (6.7, 7.15, r"plan $u^{(0)}$")):
    arrow(x0, 2.2, x1, 2.2, lw=1.5)
    ax.text((x0 + x1) / 2, 1.4, label, ha="center", fontsize=9)
arrow(9.05, 2.2, 9.6, 2.2, lw=1.5); ax.text(9.65, 2.2, "$s_{ctr}, u_{ctr}$", va="center", fontsize=9)
# the losses, the arrows into them (black) and the gradient paths back to the predictor (red)
for x, text in ((3.4, r"$\mathcal{L}_{pred}$" "\n(GT future)"), (5.75, r"$\mathcal{L}_{plan} = -\log p_{n^*}$" "\n" r"$p_n \propto e^{-\beta C_n}$"),
                (8.1, r"$\mathcal{L}_{ctr}$" "\n(hindsight cost / MSE)")):
    ax.text(x, 0.45, text, ha="center", va="center", fontsize=9, bbox=dict(fc="white", ec="tab:red"))
    arrow(x, 1.65, x, 0.9, lw=1)
red = dict(color="tab:red", lw=1.8, ls="--")
ax.annotate("", (3.55, 2.8), (5.75, 2.8), arrowprops=dict(arrowstyle="->", connectionstyle="arc3,rad=0.45", **red))
ax.annotate("", (3.25, 2.8), (8.1, 2.8), arrowprops=dict(arrowstyle="->", connectionstyle="arc3,rad=0.35", **red))
ax.text(4.65, 2.93, r"$\partial\mathcal{L}_{plan} / \partial \hat s$", color="tab:red", ha="center", fontsize=9)
ax.text(6.9, 3.85, r"$\partial\mathcal{L}_{ctr} / \partial \hat s$ (KKT)", color="tab:red", ha="center", fontsize=9)
ax.text(5.0, 4.3, "forward (black): predict → plan → control", ha="center", fontsize=10)
ax.text(5.0, -0.4, "backward (red): ∂L_plan through the softmax over candidate costs;  ∂L_ctr through the iLQR "
        "solution (KKT, §5); both reach θ through the predictions", ha="center", fontsize=8.5, color="tab:red")
plt.show()

# %% [markdown]
# ## 2. The data: synthetic scenarios, and the nuScenes format
#
# The paper trains on nuScenes *planning samples*: at a time $t_0$, 4 s of history (9 states at 2 Hz) and 3 s of
# future (6 steps) of the ego, of one **predicted vehicle** (the moving vehicle that comes closest to the ego) and
# of the other agents, plus the lanes near the ego and a **goal** $g$ = the ego's ground-truth (GT) state at
# $T$. Everything is in the ego frame at $t_0$ (ego at the origin, heading $+x$).
#
# nuScenes itself needs a licence and a download, so `data_synth.py` generates nuScenes-like scenes: roads and
# intersections built from the map's own primitive (arcline paths), one predicted vehicle whose manoeuvre comes in
# *pairs* that share a set-up (cut in / keep lane, brake / cruise, turn across / go straight, ...), so that its
# history only partly tells which will happen, and an expert ego that reacts to the true future.
# `load_or_generate` caches them in `data_cache/`.

# %%
# Data: generated once (a few seconds), then read from data_cache/.
t0 = time.time()
data = data_synth.load_or_generate(N_DATA, seed=SEED, cache_dir="data_cache")
EPOCHS = TRAIN_STEPS / max(1, len(data.train) // cfg.batch_size)  # train_stack counts in epochs
print(f"{len(data.train)} training and {len(data.val)} validation samples from {len(data.val_scenes)} validation "
      f"scenes ({time.time() - t0:.1f}s); {TRAIN_STEPS} steps = {EPOCHS:.2f} epochs")
b = data.val
print("shapes: ego_hist", tuple(b.ego_hist.shape), " agent_fut", tuple(b.agent_fut.shape), " others_fut",
      tuple(b.others_fut.shape), " lanes", tuple(b.lanes.shape), " goal", tuple(b.goal.shape))
print(data_synth.format_statistics(data_synth.statistics(data.val)))

# %%
# One validation sample of each pair of behaviours: ego blue (GT future dashed, goal = star), predicted vehicle
# orange, other vehicles grey, pedestrians green; dotted = history, solid = GT future.
show = ["cut_in", "keep_lane", "lead_brake", "turn_across", "cross_go", "cross_yield"]
fig, axes = plt.subplots(2, 3, figsize=(12, 5.2))
for ax, name in zip(axes.flat, show):
    i = int((data.val.behaviour == data_synth.BEHAVIOURS.index(name)).nonzero()[0])
    data_synth.plot_scenario(ax, data.val, i, title=f"{name} (val sample {i})")
fig.tight_layout()
plt.show()

# %% [markdown]
# **The same scenes through the nuScenes format.** `write_nuscenes` writes scenes as a nuScenes v1.0 folder (the 13
# JSON tables, the ego as `ego_pose` of key-frame `sample_data`, the map expansion with lanes as arcline paths, the
# prediction split); `load_nuscenes` reads any v1.0 folder — this one or the real v1.0-mini — back into world-frame
# `Scenes`, from which `sample_at` / `cut_samples` cut planning samples. The round trip is exact.

# %%
scenes = data.val_scenes[:4]
with tempfile.TemporaryDirectory() as tmp:
    data_synth.write_nuscenes(scenes, tmp, "v1.0-mini")
    files = sorted(str(p.relative_to(tmp)) for p in Path(tmp).rglob("*.json"))
    print(f"{len(files)} JSON files, e.g.", files[:3], "...", files[-3:])
    loaded, report = data_synth.load_nuscenes(tmp, "v1.0-mini")
print("loader report:", report)
frame = (scenes.event_frame - 2).clamp(8, 34)  # a frame per scene, just before the manoeuvre
a = data_synth.sample_at(scenes, frame, dtype=torch.float64)
b = data_synth.sample_at(loaded, frame, dtype=torch.float64)
diff = max((getattr(a, k) - getattr(b, k)).abs().max().item() for k in ("ego_hist", "ego_fut", "agent_hist", "agent_fut", "goal"))
checkpoint("max |written-and-read - original| over ego/agent states and goals (m)", diff, 0.0, 1e-9)
fig, axes = plt.subplots(1, 2, figsize=(10, 3.2))
data_synth.plot_scenario(axes[0], a.to(torch.float32), 0, title=f"generated: {scenes.names[0]}")
data_synth.plot_scenario(axes[1], b.to(torch.float32), 0, title=f"written to nuScenes v1.0 and read back: {loaded.names[0]}")
fig.tight_layout()
plt.show()

# %% [markdown]
# ## 3. Dynamics and cost
#
# **Dynamics.** Every vehicle — the ego in the planner and controller, the predicted vehicle in the predictor —
# is a dynamically-extended unicycle, state $s = (x, y, h, v)$, control $u = (\omega, a)$, integrated exactly for
# constant controls over $\Delta t = 0.5$ s:
#
# $$h' = h + \omega\Delta t,\quad v' = v + a\Delta t,\quad
# x' = x + \frac{v'\sin h' - v\sin h}{\omega} + \frac{a(\cos h' - \cos h)}{\omega^2},\quad
# y' = y - \frac{v'\cos h' - v\cos h}{\omega} + \frac{a(\sin h' - \sin h)}{\omega^2}.$$
#
# `unicycle_step` evaluates this with a series near $\omega = 0$ (dividing by a tiny $\omega$ inside `torch.where`
# would still put NaN into the gradient), and `unicycle_jacobians` gives $\partial f/\partial s$,
# $\partial f/\partial u$ in closed form for the controller.

# %%
# Constant controls from (0, 0, 0, 8 m/s): a fan of yaw rates, three accelerations; and the closed-form Jacobians
# against autograd.
w = torch.linspace(-0.7, 0.7, 9, dtype=torch.float64)
fig, ax = plt.subplots(figsize=(6, 3))
for a_, style in ((-3.0, ":"), (0.0, "-"), (2.0, "--")):
    u = torch.stack([w, torch.full_like(w, a_)], -1)[:, None].expand(9, 6, 2)  # (9, T, 2)
    x = ds.unicycle_rollout(torch.tensor([0.0, 0.0, 0.0, 8.0], dtype=torch.float64).expand(9, 4), u, 0.5)  # (9, T+1, 4)
    for k in range(9):
        ax.plot(x[k, :, 0], x[k, :, 1], style, color=plt.cm.coolwarm(k / 8), lw=1, label=f"a = {a_} m/s²" if k == 0 else None)
ax.set_aspect("equal"); ax.legend(fontsize=8); ax.set_title("unicycle rollouts, 3 s, ω from -0.7 to 0.7 rad/s")
plt.show()
s, u = torch.randn(5, 4, dtype=torch.float64), torch.randn(5, 2, dtype=torch.float64) * 0.3
A, B = ds.unicycle_jacobians(s, u, 0.5)
J = torch.func.vmap(torch.func.jacrev(lambda s, u: ds.unicycle_step(s, u, 0.5), argnums=(0, 1)))(s, u)
checkpoint("max |closed-form Jacobians - autograd|", max((A - J[0]).abs().max().item(), (B - J[1]).abs().max().item()), 0.0, 1e-12)


# %% [markdown]
# **Cost, eq. (3).** The planner and the controller minimise the same cost, a weighted sum of five terms over the
# steps $t = 1..T$:
#
# $$C = w_1 C_\text{coll} + w_2 C_\text{goal} + w_3 C_\text{lat} + w_4 C_\text{head} + w_5 C_u,\qquad w = (5, 0.5, 0.3, 0.3, 1),$$
#
# $$C_\text{coll} = \sum_t \phi\Big(\sum_k \pi_k \lVert s_t - \hat s_{k,t}\rVert^2\Big) + \sum_{a}\sum_t \phi\big(\lVert s_t - s_{a,t}\rVert^2\big),
# \qquad \phi(d^2) = e^{-d^2 / 2\sigma^2},\ \sigma^2 = 2\,\text{m}^2,$$
#
# $$C_\text{goal} = \lVert s_T - g\rVert^2,\quad C_\text{lat} = \sum_t \lVert s_t - s_{\ell,\perp}\rVert^2,\quad
# C_\text{head} = \sum_t \operatorname{wrap}(h_t - h_\ell)^2,\quad C_u = \sum_t \omega_t^2 + a_t^2 .$$
#
# The predicted vehicle enters through its $K$ modes $\hat s_{k,t}$ and weights $\pi_k$, the other agents through
# their GT futures ($a$), the lanes through the closest lane point $s_{\ell,\perp}$ and its heading $h_\ell$. Below,
# each term as a function of the ego's position over a scenario (a single step; $C_\text{coll}$ at $t = 3$, i.e.
# 1.5 s ahead, with the GT future as the prediction; $C_\text{head}$ for heading $0$). $C_u$ depends on the
# controls only.

# %%
def gt_context(batch):
    # The cost's view of a batch with the GT future as a one-mode prediction (the oracle, "GT prediction").
    B = len(batch)
    one = torch.ones(B, dtype=batch.ego_hist.dtype)
    return ds.CostContext(batch.agent_fut[:, None, :, :2], one[:, None], one, batch.others_fut[..., :2],
                          batch.others_mask.to(one.dtype), batch.goal[:, :2], batch.lanes, batch.lanes_mask)


i_ex = int((data.val.behaviour == data_synth.BEHAVIOURS.index("cut_in")).nonzero()[0])  # a cut-in
ex = data.val[torch.tensor([i_ex])]
ctx = gt_context(ex)
gx, gy = torch.meshgrid(torch.linspace(-10, 45, 111), torch.linspace(-12, 12, 49), indexing="xy")  # (49, 111)
pos = torch.stack([gx, gy], -1).reshape(1, -1, 1, 2)  # (B=1, G, T=1, 2): one step at every grid point
t = 2                                                   # the step t = 3 (index 2 of t1..T)
ctx_t = dataclasses.replace(ctx, preds=ctx.preds[:, :, t:t + 1], others=ctx.others[:, :, t:t + 1])
terms = {
    r"$C_{coll}$ at t = 1.5 s": ds.collision_term(pos, ctx_t, cfg.rbf_var)[0],
    r"$C_{goal}$": ((pos[0, :, 0] - ctx.goal) ** 2).sum(-1),
}
d2, herr, _ = ds.project_to_lanes(pos[:, :, 0], torch.zeros(1, pos.shape[1]), ex.lanes, ex.lanes_mask)
terms[r"$C_{lat}$ (one step)"], terms[r"$C_{head}$ (one step, heading 0)"] = d2[0], herr[0] ** 2
fig, axes = plt.subplots(2, 2, figsize=(11, 5.4))
for ax, (name, val) in zip(axes.flat, terms.items()):
    im = ax.pcolormesh(gx, gy, val.reshape(gx.shape), shading="auto", cmap="magma_r", zorder=0,
                       vmax=val.quantile(0.95).item() if "goal" in name or "lat" in name else None)
    data_synth.plot_scenario(ax, ex, 0, title=name, extent=(-10, 45, -12, 12))
    fig.colorbar(im, ax=ax, shrink=0.8)
fig.tight_layout()
plt.show()


# %% [markdown]
# ### Exercise 1: the collision term
#
# Write `my_collision(pos, ctx, rbf_var)`: for ego positions `pos` (B, N, T, 2) (steps $t_1..t_T$, $N$ trajectories
# per scenario), return (B, N) with
#
# $$C_\text{coll} = \sum_t \phi\Big(\sum_k \pi_k \lVert s_t - \hat s_{k,t}\rVert^2\Big) \cdot m_\text{pred}
# + \sum_a m_a \sum_t \phi\big(\lVert s_t - s_{a,t}\rVert^2\big),\qquad \phi(d^2) = e^{-d^2/(2\,\text{rbf\_var})},$$
#
# where `ctx.preds` (B, K, T, 2), `ctx.probs` (B, K), `ctx.pred_mask` (B,), `ctx.others` (B, A, T, 2),
# `ctx.others_mask` (B, A). Compute the expectation over modes directly (the module uses an equivalent
# mean + spread form: can you see why it is equal?). The check below compares with `ds.collision_term`.

# %% jupyter={"source_hidden": true} tags=["solution"]
# Solution (replace the body with your own code to try the exercise)
def my_collision(pos, ctx, rbf_var):
    phi = lambda d2: torch.exp(-d2 / (2 * rbf_var))
    # expected squared distance to the predicted vehicle, over its modes: (B, N, T)
    d2 = ((pos[:, :, None] - ctx.preds[:, None]) ** 2).sum(-1)                # (B, N, K, T)
    expected = (ctx.probs[:, None, :, None] * d2).sum(2)                      # (B, N, T)
    pred_term = ctx.pred_mask[:, None] * phi(expected).sum(-1)                # (B, N)
    d2_others = ((pos[:, :, None] - ctx.others[:, None]) ** 2).sum(-1)        # (B, N, A, T)
    others_term = (ctx.others_mask[:, None] * phi(d2_others).sum(-1)).sum(-1)  # (B, N)
    return pred_term + others_term


# %%
# Check exercise 1 against the module on random positions and a learned-like multi-mode prediction.
g = torch.Generator().manual_seed(SEED)
batch = data.val[:8]
c = gt_context(batch)
K = 5
c = dataclasses.replace(c, preds=c.preds + 2 * torch.randn(8, K, 6, 2, generator=g),
                        probs=torch.softmax(torch.randn(8, K, generator=g), -1))
pos = batch.ego_fut[:, None, :, :2] + 3 * torch.randn(8, 7, 6, 2, generator=g)  # (B, N, T, 2)
mine, theirs = my_collision(pos, c, cfg.rbf_var), ds.collision_term(pos, c, cfg.rbf_var)
assert mine.shape == theirs.shape == (8, 7), mine.shape
checkpoint("exercise 1: max |my_collision - ds.collision_term|", (mine - theirs).abs().max().item(), 0.0, 1e-5)

# %% [markdown]
# ## 4. The planner: candidates, argmin and its relaxation
#
# For each of up to two *goal lanes* (lanes passing within 4.5 m of the goal, heading within 90°), 8 terminal
# accelerations × 3 lateral offsets give 24 terminal states; a cubic spline joins the current state to each, and
# the controls follow from the spline. Infeasible candidates (outside the control box, too much lateral
# acceleration) are dropped. The plan is the cheapest candidate, eq. (2):
#
# $$n_\text{plan} = \arg\min_n C(s^{(n)}, u^{(n)};\ \hat s, \pi).$$
#
# An argmin has no useful gradient, so for training the planner is relaxed into a softmax over candidates, and
# the loss is the cross-entropy with the target candidate $n^*$ (RL: lowest *hindsight* cost, i.e. the cost with
# the GT future in place of the prediction; IL: closest to the expert):
#
# $$p_n = \frac{\exp(-\beta C_n)}{\sum_{n'} \exp(-\beta C_{n'})},\qquad \mathcal L_\text{plan} = -\log p_{n^*}.$$
#
# $\beta$ (1 in the paper) sets how sharp the relaxation is: as $\beta \to \infty$ it becomes the argmin (and
# $\mathcal L_\text{plan}$ either 0 or huge); as $\beta \to 0$ it is uniform and carries no signal.

# %%
# Candidates of one scenario coloured by p_n, for three temperatures. Prediction: the GT future (oracle).
w_hand = ds.cost_weights(cfg)
cands, cost, best, plannable, _ = ds.plan(ex.ego_hist[:, -1], ctx, ex.goal, w_hand, cfg)
print(f"N = {cands.x.shape[1]} candidates, {int(cands.valid.sum())} valid; plan = candidate {int(best)}, "
      f"cost {cost[0, best].item():.2f} (costs of valid ones: {cost[cands.valid].min():.2f} .. {cost[cands.valid].max():.2f})")
fig, axes = plt.subplots(1, 3, figsize=(14, 3.4), layout="constrained")
for ax, beta in zip(axes, (0.1, 1.0, 10.0)):
    p = torch.softmax(torch.where(cands.valid, -beta * cost, -math.inf), -1)[0]  # (N,)
    data_synth.plot_scenario(ax, ex, 0, extent=(-5, 40, -10, 10))
    for n in torch.argsort(p).tolist():
        if cands.valid[0, n]:
            ax.plot(cands.x[0, n, :, 0], cands.x[0, n, :, 1], color=plt.cm.viridis(p[n].item() / p.max().item()),
                    lw=0.7 + 2.5 * (p[n] / p.max()).item(), zorder=7)
    ax.set_title(f"β = {beta}\nmax p_n = {p.max():.2f}, entropy {-(p[p > 0] * p[p > 0].log()).sum():.2f} nats")
fig.colorbar(plt.cm.ScalarMappable(cmap="viridis"), ax=axes, shrink=0.9, label="p_n / max p_n")
plt.show()

# %%
# How beta shapes L_plan over the validation set: planner with the GT prediction (target = its own argmin)
# and with no prediction at all (the predicted vehicle ignored, so the target is often not the argmin).
val = data.val
ctx_gt = gt_context(val)
ctx_none = dataclasses.replace(ctx_gt, pred_mask=torch.zeros(len(val)))
cands, cost_gt, _, plannable, _ = ds.plan(val.ego_hist[:, -1], ctx_gt, val.goal, w_hand, cfg)
cost_none = ds.total_cost(cands.x, cands.u, ctx_none, w_hand, cfg.rbf_var)
target = ds.masked_argmin(cost_gt, cands.valid)  # n* = lowest hindsight cost
betas = torch.logspace(-2, 2, 17)
fig, ax = plt.subplots(figsize=(6, 3))
for c_, name in ((cost_gt, "GT prediction"), (cost_none, "No prediction")):
    ax.plot(betas, [ds.plan_loss(c_, cands.valid, target, b.item())[plannable].mean().item() for b in betas], "o-", ms=3, label=name)
ax.set_xscale("log"); ax.set_xlabel("β"); ax.set_ylabel("mean L_plan"); ax.axvline(cfg.beta, color="0.6", ls=":")
ax.legend(); ax.set_title(f"L_plan over {int(plannable.sum())} plannable validation samples")
plt.show()


# %% [markdown]
# ### Exercise 2: the relaxed planner's loss
#
# Write `my_plan_loss(cost, valid, target, beta)`: `cost` (B, N) candidate costs, `valid` (B, N) bool, `target`
# (B,) the index $n^*$; return (B,) $-\log p_{n^*}$ with $p$ the softmax of $-\beta C$ over the **valid**
# candidates only. Mind numerical stability (costs can be in the thousands). The check compares with
# `ds.plan_loss`, values and gradients.

# %% jupyter={"source_hidden": true} tags=["solution"]
# Solution (replace the body with your own code to try the exercise)
def my_plan_loss(cost, valid, target, beta):
    logits = torch.where(valid, -beta * cost, torch.tensor(-math.inf))         # invalid candidates get p = 0
    logp = logits - torch.logsumexp(logits, -1, keepdim=True)                 # (B, N), stable log-softmax
    return -logp.gather(-1, target[:, None])[:, 0]


# %%
# Check exercise 2: values and gradients wrt the costs, on the validation set's candidates.
c1 = cost_none.detach().clone().requires_grad_()
c2 = cost_none.detach().clone().requires_grad_()
keep = plannable  # at least 2 valid candidates
mine, theirs = my_plan_loss(c1, cands.valid, target, 1.0)[keep], ds.plan_loss(c2, cands.valid, target, 1.0)[keep]
mine.sum().backward(); theirs.sum().backward()
checkpoint("exercise 2: max |my_plan_loss - ds.plan_loss|", (mine - theirs).abs().max().item(), 0.0, 1e-4)
checkpoint("exercise 2: max |gradient difference|", (c1.grad - c2.grad).abs().max().item(), 0.0, 1e-5)

# %% [markdown]
# ## 5. The controller: box-constrained iLQR, and its gradient
#
# The plan is a spline; the controller finds the trajectory that actually minimises the cost under the dynamics
# and the control limits, eq. (4):
#
# $$\min_{s_{1:T},\,u_{0:T-1}} C(s, u)\quad\text{s.t.}\quad s_{t+1} = f(s_t, u_t),\quad
# \underline u \le u_t \le \overline u\ \ (\omega \in [-0.7, 0.7],\ a \in [-5, 4]).$$
#
# **iLQR.** Around the current trajectory, expand the cost to second order ($H_t$, $g_t$) and the dynamics to
# first ($A_t$, $B_t$), and solve the resulting LQR by the Riccati recursion, backwards from
# $V_T(\delta s) = \tfrac12\delta s^\top P\delta s + p^\top\delta s$ with $P = H_{T,ss}$, $p = g_{T,s}$:
#
# $$Q = H_t + F^\top P F,\quad q = g_t + F^\top p,\quad F = [A_t\ B_t];\qquad
# k_t = -Q_{uu}^{-1} q_u,\quad K_t = -Q_{uu}^{-1} Q_{us};$$
# $$P \leftarrow Q_{ss} + K_t^\top Q_{uu} K_t + K_t^\top Q_{us} + Q_{su} K_t,\qquad
# p \leftarrow q_s + K_t^\top Q_{uu} k_t + K_t^\top q_u + Q_{su} k_t .$$
#
# With the box, $k_t$ solves a small box QP and the gain rows of clamped controls are zero. The new controls
# $u_t + \alpha k_t + K_t(s'_t - s_t)$ are rolled out for the step sizes $\alpha = 1, 1/5, 1/25, \dots$ and the
# largest one that does not raise the true cost is kept; at most 5 iterations, converged when the full step is
# below 0.05. The controller starts from the planner's candidate.

# %%
# iLQR on 128 validation samples from the plan, with the GT prediction: the cost after each iteration.
# (under a second)
batch = data.val[:128]
ctx_b = gt_context(batch)
cands, cost_b, best_b, ok_b, _ = ds.plan(batch.ego_hist[:, -1], ctx_b, batch.goal, w_hand, cfg)
u_plan = cands.u[torch.arange(len(batch)), best_b]  # (B, T, 2) the plan's controls
cost_fn = lambda x, u, w: ds.total_cost(x, u, ctx_b, w, cfg.rbf_var)  # the solver's interface: cost(x, u, *params)
t0 = time.time()
x, u, info = ds.ilqr(cost_fn, ds.Unicycle(cfg.dt), batch.ego_hist[:, -1], u_plan, (w_hand,),
                     torch.tensor(cfg.u_lower), torch.tensor(cfg.u_upper), iters=10, tol=cfg.ilqr_tol)
print(f"{time.time() - t0:.2f}s; converged {info.converged[ok_b].float().mean():.3f} of {int(ok_b.sum())} plannable "
      f"samples; iterations used: {torch.bincount(info.iters[ok_b]).tolist()} (count per number of iterations)")
rel = (info.costs / info.costs[:, :1])[ok_b]  # (B, I+1) cost relative to the plan's
fig, axes = plt.subplots(1, 2, figsize=(11, 3))
axes[0].plot(rel.T, color="tab:blue", alpha=0.15, lw=0.8)
axes[0].plot(rel.mean(0), color="k", lw=2, label="mean")
axes[0].set_xlabel("iteration"); axes[0].set_ylabel("cost / cost of the plan"); axes[0].legend()
axes[0].set_title("iLQR: the true cost never rises (line search)")
i = int((info.costs[:, 0] - info.costs[:, -1]).argmax())  # the sample iLQR improves most
data_synth.plot_scenario(axes[1], batch, i, title=f"sample {i}: plan (green) → iLQR (purple)", extent=(-10, 50, -15, 15))
axes[1].plot(cands.x[i, best_b[i], :, 0], cands.x[i, best_b[i], :, 1], "g-", lw=2, zorder=8)
axes[1].plot(x[i, :, 0], x[i, :, 1], "-", color="purple", lw=2, zorder=9)
fig.tight_layout()
plt.show()
checkpoint("mean cost after iLQR / cost of the plan", rel[:, -1].mean().item(), 0.70 if QUICK else 0.62, 0.05)

# %% [markdown]
# **The backward pass** (Amos et al. 2018). At the solution the KKT conditions hold; differentiating them
# (implicit function theorem) gives the sensitivity of the solution $d = \partial z^\star / \partial\theta$ as the
# solution of **one more LQR**, with the incoming gradient $\partial\mathcal L/\partial z$ as its linear term and the
# active control bounds held fixed:
#
# $$\min_d\ \tfrac12 d^\top \mathcal H d + (\partial\mathcal L/\partial z)^\top d\quad\text{s.t.}\quad
# \delta s_0 = 0,\ \delta s_{t+1} = A_t\delta s_t + B_t\delta u_t,\ \delta u_\text{active} = 0,$$
#
# $$\mathcal H_t = \nabla^2 \ell_t + \sum_i \lambda_{t+1,i}\,\nabla^2 f_i(s_t, u_t),\qquad
# \frac{\partial\mathcal L}{\partial\theta} = \frac{\partial}{\partial\theta}\Big[\sum_t \nabla_{z_t}\ell_t(\theta)\cdot d_t\Big].$$
#
# $\mathcal H$ is the Hessian of the Lagrangian: the cost's Hessian **plus the dynamics' curvature** weighted by the
# costates $\lambda$. mpc.pytorch and the authors' code leave the curvature out (`kkt_backward(..., exact=False)`
# here), which is exact for linear dynamics only. Below, a live check on three scenarios in float64: the gradient of
# a random linear function of the solution with respect to the initial state, the cost weights and the predicted
# trajectory, against central finite differences of the re-solved problem.

# %%
# Gradient check (about 10 s): KKT backward (exact and curvature-free) vs central finite differences.
torch.manual_seed(SEED)
d_min = (data.val.ego_fut[..., :2] - data.val.agent_fut[..., :2]).norm(dim=-1).min(-1).values
pick = torch.nonzero(d_min < 6).flatten()[:3]  # three samples where the predicted vehicle comes within 6 m
b64 = data.val[pick].to(torch.float64)
ctx64 = gt_context(b64)
w64 = ds.cost_weights(cfg, torch.float64)
lo, hi = torch.tensor(cfg.u_lower, dtype=torch.float64), torch.tensor(cfg.u_upper, dtype=torch.float64)
fn = lambda x, u, w, preds: ds.total_cost(x, u, dataclasses.replace(ctx64, preds=preds), w, cfg.rbf_var)
s0 = b64.ego_hist[:, -1]
_, u_star, info = ds.ilqr(fn, ds.Unicycle(cfg.dt), s0, torch.zeros(3, 6, 2, dtype=torch.float64), (w64, ctx64.preds),
                          lo, hi, iters=50, tol=1e-11)
assert info.converged.all()
g = torch.Generator().manual_seed(SEED)
wx, wu = torch.randn(3, 7, 4, generator=g, dtype=torch.float64), torch.randn(3, 6, 2, generator=g, dtype=torch.float64)
leaves = (s0, w64, ctx64.preds)


def kkt_grads(exact):
    ls = [v.clone().requires_grad_() for v in leaves]
    x, u, _ = ds.ilqr_solve(fn, ds.Unicycle(cfg.dt), ls[0], u_star, tuple(ls[1:]), lo, hi, iters=30, tol=1e-11, exact=exact)
    return torch.autograd.grad((x * wx).sum() + (u * wu).sum(), ls)


def loss(i, v):  # the same loss, re-solved with leaf i replaced by v
    ls = list(leaves); ls[i] = v
    x, u, inf = ds.ilqr(fn, ds.Unicycle(cfg.dt), ls[0], u_star, tuple(ls[1:]), lo, hi, iters=50, tol=1e-11)
    return (x * wx).sum() + (u * wu).sum()


def central_fd(i, idx, h=1e-4):
    e = torch.zeros_like(leaves[i]); e[idx] = h
    return (loss(i, leaves[i] + e) - loss(i, leaves[i] - e)) / (2 * h)


t0 = time.time()
exact, gn = kkt_grads(True), kkt_grads(False)
coords = {"initial state s0": (0, [(b, j) for b in range(3) for j in range(4)]),
          "cost weights w": (1, [(j,) for j in range(5)]),
          "predicted trajectory": (2, [(b, 0, t, j) for b in range(3) for t in (1, 3, 5) for j in range(2)])}
errs = {}
for name, (i, idx) in coords.items():
    fd = torch.stack([central_fd(i, j) for j in idx])
    e_exact, e_gn = rel_err(torch.stack([exact[i][j] for j in idx]), fd), rel_err(torch.stack([gn[i][j] for j in idx]), fd)
    errs[name] = (e_exact, e_gn)
    print(f"  {name:22s} relative error vs finite differences: exact KKT {e_exact:.1e}   curvature-free {e_gn:.1e}")
print(f"({time.time() - t0:.1f}s)")
checkpoint("largest relative error of the exact KKT gradient", max(e for e, _ in errs.values()), 0.0, 1e-4)
checkpoint("log10 of the largest relative error of the curvature-free gradient (mpc.pytorch's: 0.4-4 % expected)",
           math.log10(max(e for _, e in errs.values())), -2.0, 1.0)


# %% [markdown]
# ### Exercise 3: one step of the Riccati recursion
#
# Write `my_riccati_step(P, p, H_t, g_t, A_t, B_t, n)` for an **unconstrained** LQR: given the value function
# $V_{t+1} = \tfrac12\delta s^\top P\delta s + p^\top\delta s$ (P (B, n, n), p (B, n)), the stage's cost Hessian
# `H_t` (B, n+m, n+m) and gradient `g_t` (B, n+m), and the dynamics Jacobians `A_t` (B, n, n), `B_t` (B, n, m),
# return `(k, K, P_new, p_new)`: the feedforward (B, m), the gain (B, m, n) and the value function at $t$
# (formulas above the iLQR cell). The check runs it on a one-step problem and compares $k$, $K$ and $p_0$ with
# `ds.lqr_backward_fixed` (all controls free).

# %% jupyter={"source_hidden": true} tags=["solution"]
# Solution (replace the body with your own code to try the exercise)
def my_riccati_step(P, p, H_t, g_t, A_t, B_t, n):
    F = torch.cat([A_t, B_t], -1)                                  # (B, n, n+m)
    Q = H_t + F.transpose(-1, -2) @ P @ F                         # (B, n+m, n+m)
    q = g_t + (F.transpose(-1, -2) @ p[..., None])[..., 0]        # (B, n+m)
    Qss, Qsu, Qus, Quu = Q[:, :n, :n], Q[:, :n, n:], Q[:, n:, :n], Q[:, n:, n:]
    qs, qu = q[:, :n], q[:, n:]
    k = -torch.linalg.solve(Quu, qu)                               # (B, m)
    K = -torch.linalg.solve(Quu, Qus)                              # (B, m, n)
    KT = K.transpose(-1, -2)
    P_new = Qss + KT @ Quu @ K + KT @ Qus + Qsu @ K
    p_new = qs + (KT @ Quu @ k[..., None])[..., 0] + (KT @ qu[..., None])[..., 0] + (Qsu @ k[..., None])[..., 0]
    return k, K, P_new, p_new


# %%
# Check exercise 3 on random one-step problems (n = 4, m = 2), float64.
g = torch.Generator().manual_seed(SEED)
Bn, n, m = 6, 4, 2
R = torch.randn(Bn, 2, n + m, n + m, generator=g, dtype=torch.float64)
H = R @ R.transpose(-1, -2) + 0.5 * torch.eye(n + m, dtype=torch.float64)  # (B, T+1, n+m, n+m) positive definite
gv = torch.randn(Bn, 2, n + m, generator=g, dtype=torch.float64)
A_ = torch.randn(Bn, 1, n, n, generator=g, dtype=torch.float64)
B_ = torch.randn(Bn, 1, n, m, generator=g, dtype=torch.float64)
k_ref, K_ref, _, p0_ref = ds.lqr_backward_fixed(A_, B_, H, gv, n, torch.ones(Bn, 1, m, dtype=torch.bool))
k, K, P0, p0 = my_riccati_step(H[:, 1, :n, :n], gv[:, 1, :n], H[:, 0], gv[:, 0], A_[:, 0], B_[:, 0], n)
err = max((k - k_ref[:, 0]).abs().max(), (K - K_ref[:, 0]).abs().max(), (p0 - p0_ref).abs().max()).item()
checkpoint("exercise 3: max |k, K, p_0 - ds.lqr_backward_fixed's|", err, 0.0, 1e-8)

# %% [markdown]
# ## 6. The predictor
#
# A Trajectron++-style conditional VAE. It encodes the predicted vehicle's 4 s history (an LSTM over position,
# velocity, acceleration, heading and heading rate, by *backward* differences) and its neighbours (attention), and
# has a discrete latent $z \in \{1..K\}$, $K = 25$:
#
# $$p(y\mid x) = \sum_{k=1}^{K} p(z = k\mid x)\; p(y\mid x, z = k).$$
#
# For each $k$ a GRU emits per step a Gaussian over the controls $(\omega, a)$; the mean controls are integrated by
# the same unicycle as the planner (the $K$ **modes** $\hat s_{k,t}$), and the control covariances are pushed through
# its Jacobians (EKF) to a Gaussian over positions. *Standard* training maximises Trajectron++'s InfoVAE objective,
#
# $$\mathcal L_\text{pred} = -\Big(\sum_t \log \sum_k q(k\mid x, y)\,\mathcal N(y_t;\hat s_{k,t}, \Sigma_{k,t})
# \;-\; \beta\,\mathrm{KL}\big(q(z\mid x,y)\,\Vert\,p(z\mid x)\big) \;+\; I_p(x; z)\Big),$$
#
# with all $K$ values of $z$ enumerated. Metrics: ADE/FDE of the most likely mode, min-ADE over modes, and the
# NLL of the GT under the position mixture, against **constant velocity**.

# %%
# Train the Standard predictor (L_pred only). Expected run time: ~2 s quick, ~20 s full.
t0 = time.time()
torch.manual_seed(SEED)                       # the initialisation (as open_loop_experiment does)
model_std = ds.Predictor(cfg)
hist = ds.train_stack(model_std, data.train, ds.Method("Standard"), cfg, "rl", epochs=EPOCHS, seed=SEED,
                      log=print if not QUICK else None)
m_std = ds.evaluate_predictor(model_std, data.val, cfg)
print(f"trained {len(hist)} steps in {time.time() - t0:.0f}s")
print("          ADE    FDE    min-ADE  NLL")
print(f"Standard  {m_std['ade']:.2f}   {m_std['fde']:.2f}   {m_std['min_ade']:.2f}     {m_std['nll']:.2f}")
print(f"const vel {m_std['cv_ade']:.2f}   {m_std['cv_fde']:.2f}   --       {m_std['cv_nll']:.2f}  (cv NLL: variance fit to this set)")
fig, ax = plt.subplots(figsize=(5, 2.6))
ax.plot([h["l_pred"] for h in hist]); ax.set_xlabel("step"); ax.set_ylabel("L_pred"); ax.set_title("Standard training")
plt.show()
checkpoint("Standard min-ADE / constant-velocity ADE", m_std["min_ade"] / m_std["cv_ade"], 1.09 if QUICK else 0.70, 0.1)

# %%
# The K = 25 modes over three validation samples: line width and opacity grow with p(z|x); ellipses: 1 sigma of
# the most likely mode. The GT future of the predicted vehicle is the orange solid line.
model_std.eval()
idx = torch.tensor([int((data.val.behaviour == data_synth.BEHAVIOURS.index(n)).nonzero()[0]) for n in ("cut_in", "lead_brake", "turn_across")])
sub = data.val[idx]
with torch.no_grad():
    pred = model_std(sub, use_posterior=False)
fig, axes = plt.subplots(1, 3, figsize=(14, 3.2))
for j, ax in enumerate(axes):
    data_synth.plot_scenario(ax, sub, j, extent=(-20, 55, -15, 15))
    xp.plot_prediction(ax, pred, j, color="tab:red")
    ax.legend(loc="lower left", fontsize=7)
fig.tight_layout()
plt.show()

# %% [markdown]
# ## 7. End-to-end training: DiffStack against Standard (Table 1)
#
# **DiffStack** trains the predictor with all three losses, $\alpha = (1, 100, 1000)$ in the RL setting; the
# gradient of $\mathcal L_\text{plan}$ reaches the predictions through the candidate costs $C_n$ (the collision
# term), and that of $\mathcal L_\text{ctr}$ (the hindsight cost of the controller's trajectory) through the KKT
# backward of section 5 above. The baselines of Table 1: *No prediction* (the predicted vehicle ignored), *Standard*,
# *Distance weighted* and *∇Cost weighted* (L_pred reweighted per sample by closeness to the ego / by how much the
# cost reacts to that agent), *DiffStack (no L_pred)*, and the oracle *GT prediction*. The planning loss and the
# hindsight cost are reported **relative to No prediction** (negative = better), as in the paper.
#
# `open_loop_experiment` trains each learned method (same data, same seed, same number of steps) and evaluates all
# of them on the validation set; `ds.open_loop_table` prints the table (± standard errors over seeds; one seed here).

# %%
# Table 1 (RL). Expected run time: ~10 s quick (4 methods), ~3 min full (all 7 methods).
t0 = time.time()
methods1 = ds.TABLE1_METHODS if not QUICK else [m for m in ds.TABLE1_METHODS
                                              if m.name in ("No prediction", "Standard", "DiffStack", "GT prediction")]
res1 = xp.open_loop_experiment(data, cfg, "rl", methods1, seeds=(SEED,), epochs=EPOCHS, log=None)
print(f"({time.time() - t0:.0f}s)")
display(Markdown(ds.open_loop_table(res1, "rl")))
gap, _ = xp.gap_closed(res1)
print(f"DiffStack closes {100 * gap:.0f} % of the Standard -> GT prediction gap in hindsight cost (paper: 39 %)")
rel = {n: r[0]["rel_hindsight"] for n, r in res1.items()}
checkpoint("Table 1: DiffStack's minus Standard's relative hindsight cost (x1e-2)", rel["DiffStack"] - rel["Standard"],
           -0.95 if QUICK else -1.99, 0.5)


# %%
def plot_table(results, setting, title):
    # Bars of the two relative columns (mean ± s.e. over seeds) and of the ADE, one bar per method.
    cols = xp.open_loop_columns(setting)[2:4]  # the two planning columns, relative to No prediction
    names = list(results)
    fig, axes = plt.subplots(1, 3, figsize=(13, 2.8))
    for ax, (key, header) in zip(axes, [*((c.key.removeprefix("rel_"), c.header) for c in cols), ("ade", "ADE (m)")]):
        k = key if key == "ade" else "rel_" + key
        stats = [ds.mean_se([r[k] for r in results[n]]) if k in results[n][0] else (np.nan, 0) for n in names]
        ax.barh(names, [s[0] for s in stats], xerr=[s[1] for s in stats], color=plt.cm.tab10(np.arange(len(names))))
        ax.axvline(0, color="k", lw=0.8); ax.set_title(header if key == "ade" else f"{header}, rel. to No prediction")
        ax.invert_yaxis()
        if ax is not axes[0]:
            ax.set_yticklabels([])
    fig.suptitle(title, y=1.02); fig.tight_layout()
    plt.show()


plot_table(res1, "rl", "Table 1 (RL setting): lower is better")

# %% [markdown]
# **An example where they differ.** `open_loop_experiment` returns metrics, not models, so we train DiffStack once
# more with the same seed, and run both stacks on the validation set (`train_stack` is deterministic: the
# checkpoints confirm that these models reproduce Table 1's rows; section 6's predictor *is* Table 1's Standard). Below, the sample where DiffStack's hindsight
# cost is lowest relative to Standard's (the paper's Fig. 3): predictions, candidates coloured by $p_n$, plan and
# control (`xp.plot_stack`).

# %%
# DiffStack trained again (same seed as in Table 1), both stacks run on the validation set.
# Expected run time: ~5 s quick, ~1 min full.
t0 = time.time()
torch.manual_seed(SEED)
model_ds = ds.Predictor(cfg)
ds.train_stack(model_ds, data.train, ds.Method("DiffStack", losses=(1, 1, 1)), cfg, "rl", epochs=EPOCHS, seed=SEED, log=None)
outs = {}
for name, model, method in (("Standard", model_std, ds.Method("Standard")), ("DiffStack", model_ds, ds.Method("DiffStack", losses=(1, 1, 1)))):
    model.eval()
    with torch.no_grad():
        outs[name] = ds.run_stack(data.val, model, method, cfg, "rl")
print(f"({time.time() - t0:.0f}s)")
ok = outs["Standard"].plannable
for name in outs:  # section 6's Standard and this DiffStack are the very models behind Table 1's rows
    checkpoint(f"{name}: mean hindsight cost here vs in Table 1", outs[name].hindsight[ok].mean().item(),
               res1[name][0]["hindsight"], 1e-3, rel=True)
delta = torch.where(ok, outs["Standard"].hindsight - outs["DiffStack"].hindsight, -math.inf)
i = int(delta.argmax())
print(f"sample {i} ({data_synth.BEHAVIOURS[int(data.val.behaviour[i])]}): hindsight cost Standard "
      f"{outs['Standard'].hindsight[i]:.2f}, DiffStack {outs['DiffStack'].hindsight[i]:.2f}; "
      f"DiffStack lower on {(delta[ok] > 0).float().mean():.0%} of the samples, higher on {(delta[ok] < 0).float().mean():.0%}")
fig, axes = plt.subplots(1, 2, figsize=(13, 3.6), layout="constrained")
for ax, name in zip(axes, outs):
    xp.plot_stack(ax, data.val, i, outs[name], cfg, f"{name}: hindsight cost {outs[name].hindsight[i]:.2f}", extent=(-15, 50, -14, 14))
    ax.legend(loc="lower left", fontsize=7)
fig.suptitle("predictions (red, opacity by probability), candidates (green by p_n), plan (dashed), controller (purple)")
plt.show()

# %% [markdown]
# ## 8. More experiments
#
# **A biased predictor (Table 2).** The paper adds a 1 m offset to every GT prediction target (to the predicted
# vehicle's left), a stand-in for an interface error between modules. Trained the standard way, the predictor
# learns the bias and the planner pays for it; with DiffStack, the planning and control losses push the
# predictions to where they matter for planning. `open_loop_experiment(..., pred_offset=1.0)` shifts the targets
# of $\mathcal L_\text{pred}$ (the hindsight cost and the ADE are still measured against the true future).

# %%
# Table 2 (biased targets, RL). Expected run time: ~5 s quick, ~75 s full.
t0 = time.time()
methods2 = (ds.Method("No prediction", "none"), ds.Method("Standard-biased"), ds.Method("DiffStack-biased", losses=(1, 1, 1)),
            ds.Method("GT prediction", "gt"))
res2 = xp.open_loop_experiment(data, cfg, "rl", methods2, seeds=(SEED,), epochs=EPOCHS, pred_offset=1.0, log=None)
print(f"({time.time() - t0:.0f}s)")
display(Markdown(ds.open_loop_table(res2, "rl")))
rel = {n: r[0]["rel_hindsight"] for n, r in res2.items()}
checkpoint("Table 2: DiffStack-biased's minus Standard-biased's relative hindsight cost (x1e-2)",
           rel["DiffStack-biased"] - rel["Standard-biased"], -10.19 if QUICK else -1.96, 2.0 if QUICK else 0.5)
plot_table(res2, "rl", "Table 2: a 1 m bias in the prediction targets")

# %% [markdown]
# **Why the full run's Table 2 checkpoint may print MISMATCH.** One seed of this biased training is chaotic: the
# same code on the same data gives −1.66 in a plain script at 2 threads, −1.96 and −4.03 in two full runs of this
# notebook (2026-11-21 and 2026-11-23; the refactoring between them was checked to give bit-identical numbers in
# the script). Only the sign (DiffStack-biased below Standard-biased) is robust here; for the size of the effect
# read the 5-seed table in `results/biased.md`.
#
# **Imitation learning (Table 4).** With a driving log but no cost to trust, the planner's target $n^*$ is the
# candidate closest to the expert's trajectory and $\mathcal L_\text{ctr} = \sum_t \lVert s_{\text{ctr},t} -
# s_{\text{gt},t}\rVert^2$, with $\alpha = (1, 10, 1000)$. The table reports the planning loss (×10⁻³) and the
# controller's squared error to the expert (×10⁻²), both relative to No prediction.

# %%
# Table 4 (IL). Expected run time: ~5 s quick, ~75 s full.
t0 = time.time()
methods_il = [m for m in ds.TABLE1_METHODS if m.name in ("No prediction", "Standard", "DiffStack", "GT prediction")]
res_il = xp.open_loop_experiment(data, cfg, "il", methods_il, seeds=(SEED,), epochs=EPOCHS, log=None)
print(f"({time.time() - t0:.0f}s)")
display(Markdown(ds.open_loop_table(res_il, "il")))
rel = {n: r[0]["rel_mse"] for n, r in res_il.items()}
checkpoint("Table 4: DiffStack's minus Standard's relative MSE (x1e-2)", rel["DiffStack"] - rel["Standard"],
           7.61 if QUICK else -13.68, 1.5 if QUICK else 3.0)
plot_table(res_il, "il", "Table 4 (IL setting): lower is better")

# %% [markdown]
# **Cost learning (Table 3).** The cost weights themselves can be learned through the controller: in the IL
# setting, $w_i = \alpha\,c\,e^{\psi_i} / \sum_j e^{\psi_j}$ (App. A.2), $\psi_1$ (collision) fixed, initialised to
# the hand-tuned weights; $\mathcal L = \alpha_3\,\mathcal L_\text{ctr}$, and $\partial\mathcal L/\partial w$ comes
# from the KKT backward of section 5 above (the weights are parameters of the iLQR problem). The predictor is a frozen Standard
# one. The table lists the normalised weights $w'$, the scale $\alpha$, and the absolute IL planning loss and MSE.

# %%
# Table 3 (cost learning). Expected run time: ~5 s quick, ~65 s full.
t0 = time.time()
res_cost = xp.cost_learning_experiment(data, cfg, seeds=(SEED,), epochs=EPOCHS, log=None)
print(f"({time.time() - t0:.0f}s)")
display(Markdown(xp.results_markdown(xp.TABLES["cost"], res_cost)))
with tempfile.TemporaryDirectory() as tmp:
    xp.figure_cost_weights(res_cost, Path(tmp) / "w.png")
    display(Image(filename=str(Path(tmp) / "w.png"), width=560))
mse = {n: r[0]["mse"] for n, r in res_cost.items()}
checkpoint("Table 3: MSE with learned / with hand-tuned weights", mse["Learned"] / mse["Hand-tuned"],
           0.90 if QUICK else 0.54, 0.1)

# %% [markdown]
# **Closed loop (Table 5).** Open-loop metrics score one plan against a log; in closed loop the plan is executed.
# Log replay (§4.3): every 0.5 s for 10 s the stack replans from the *simulated* ego state, the ego moves by the
# first control through the unicycle, and the other agents replay their logs (they do not react). Metrics over the
# executed trajectory: trajectory cost (eq. 3 without the goal term), open-loop cost of each step's plan, its
# collision, lane and control parts, and the deviation from the logged ego; differences to No prediction
# (×10⁻²). `closed_loop_experiment` trains Standard and DiffStack as in Table 1 and simulates every scene at once.

# %%
# Table 5 (closed loop). Expected run time: ~15 s quick, ~80 s full.
t0 = time.time()
res5, rollouts, cl_scenes = xp.closed_loop_experiment(data, data.val_scenes[:N_CLOSED_LOOP], cfg, seeds=(SEED,),
                                                      epochs=EPOCHS, log=None)
print(f"{len(cl_scenes)} scenes x 10 s ({time.time() - t0:.0f}s)")
display(Markdown(xp.results_markdown(xp.TABLES["closed_loop"], res5)))
# One scene, every method's executed trajectory (the scene where Standard's trajectory cost exceeds DiffStack's most).
sc = int((rollouts["Standard"][1]["trajectory"] - rollouts["DiffStack"][1]["trajectory"]).argmax())
f0, N = rollouts["Standard"][0].start_frame, rollouts["Standard"][0].controls.shape[1]
frames = slice(f0, f0 + N + 1)
agent = cl_scenes.agents[sc, int(cl_scenes.pred_idx[sc, f0]), frames]  # (N+1, 4) the predicted agent's log
fig, axd = plt.subplot_mosaic([["map", "map"], ["dist", "speed"]], figsize=(13, 6.2), layout="constrained")
ax, ax_d, ax_v = axd["map"], axd["dist"], axd["speed"]
for lane, m in zip(cl_scenes.lanes[sc], cl_scenes.lanes_mask[sc]):
    ax.plot(lane[m, 0], lane[m, 1], color="0.85", lw=0.8)
ax.plot(cl_scenes.ego[sc, frames, 0], cl_scenes.ego[sc, frames, 1], "k--", lw=1.2, label="logged ego")
ax.plot(agent[:, 0], agent[:, 1], "s-", color="tab:orange", ms=3, lw=0.8, label="predicted agent (log)")
tt = 0.5 * torch.arange(N + 1)
for (name, (roll, per)), color in zip(rollouts.items(), ("tab:gray", "tab:red", "tab:green", "tab:blue")):
    ax.plot(roll.ego[sc, :, 0], roll.ego[sc, :, 1], "o-", color=color, ms=2.5, lw=1, label=f"{name} ({per['trajectory'][sc]:.3f})")
    ax_d.plot(tt, (roll.ego[sc, :, :2] - agent[:, :2]).norm(dim=-1), color=color, label=name)
    ax_v.plot(tt, roll.ego[sc, :, 3], color=color, label=name)
ax_v.plot(tt, cl_scenes.ego[sc, frames, 3], "k--", lw=1, label="logged ego")
ax.set_aspect("equal", adjustable="datalim"); ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5))
ax.set_title(f"closed loop, scene {cl_scenes.names[sc]}: executed ego trajectories (trajectory cost)")
ax_d.set_xlabel("time (s)"); ax_d.set_ylabel("distance to the predicted agent (m)"); ax_d.legend(fontsize=7)
ax_v.set_xlabel("time (s)"); ax_v.set_ylabel("ego speed (m/s)"); ax_v.legend(fontsize=7)
plt.show()
rel = {n: r[0]["rel_trajectory"] for n, r in res5.items()}
checkpoint("Table 5: DiffStack's minus Standard's relative trajectory cost (x1e-2)", rel["DiffStack"] - rel["Standard"],
           0.075 if QUICK else -0.064, 0.3)

# %% [markdown]
# **A finer clock (the dt = 0.1 s ablation, App. A.1).** The predictor works on the data's 0.5 s steps; the planner
# and the controller can plan the same 3 s in 30 steps of 0.1 s: `run_stack(..., plan_dt=0.1)` interpolates the
# predicted modes and the GT futures linearly to that clock (`ds.upsample`, differentiable) and scales the per-step
# cost terms by 1/5, so that eq. (3) adds up the same cost per second and only the resolution changes. Here the
# predictors trained above at 0.5 s are *evaluated* at 0.1 s; the ablation proper (`python diffstack.py
# --experiment ablation`) also *trains* DiffStack through the 0.1 s planner and controller (README: results).

# %%
# Standard and DiffStack (trained at 0.5 s) planned and controlled at 0.1 s. Expected run time: ~5 s quick, ~30 s full.
t0 = time.time()
stacks = {"No prediction": (None, ds.Method("No prediction", "none")), "Standard": (model_std, ds.Method("Standard")),
          "DiffStack": (model_ds, ds.Method("DiffStack", losses=(1, 1, 1))), "GT prediction": (None, ds.Method("GT prediction", "gt"))}
fine = {name: [ds.evaluate_stack(model, data.val, method, cfg, "rl", plan_dt=0.1)] for name, (model, method) in stacks.items()}
with torch.no_grad():  # the two stacks drawn below (evaluate_stack has put the models in eval mode)
    outs01 = {name: ds.run_stack(data.val, *stacks[name], cfg, "rl", plan_dt=0.1) for name in ("Standard", "DiffStack")}
for runs in fine.values():  # relative to No prediction, as open_loop_experiment reports
    for key, scale in ds.RELATIVE_SCALE["rl"].items():
        runs[0]["rel_" + key] = (runs[0][key] - fine["No prediction"][0][key]) / scale
print(f"({time.time() - t0:.0f}s)")
display(Markdown(ds.open_loop_table(fine, "rl")))
# sample i of the figure above: the controller's trajectory at 0.5 s (7 states) and at 0.1 s (31 states)
fig, axes = plt.subplots(1, 2, figsize=(13, 3.6), layout="constrained")
for ax, name in zip(axes, ("Standard", "DiffStack")):
    xp.plot_stack(ax, data.val, i, outs01[name], cfg, f"{name} at 0.1 s: hindsight cost {outs01[name].hindsight[i]:.2f}",
                  extent=(-15, 50, -14, 14))
    ax.plot(outs[name].x[i, :, 0], outs[name].x[i, :, 1], "o", color="tab:purple", ms=4, mfc="none", zorder=9, label="controller at 0.5 s")
    ax.legend(loc="lower left", fontsize=7)
plt.show()
rel01 = {n: r[0]["rel_hindsight"] for n, r in fine.items()}
checkpoint("dt = 0.1 s: DiffStack's minus Standard's relative hindsight cost (x1e-2)", rel01["DiffStack"] - rel01["Standard"],
           1.27 if QUICK else -1.48, 0.5)

# %% [markdown]
# ## Where to go from here
#
# * `python experiments.py --experiment rl --seeds 5 --out runs` runs Table 1 with several seeds (`biased`, `cost`, `il`,
#   `closed_loop`: Tables 2-5) and writes `runs/<name>.md`; more steps and more data move the numbers towards the paper's shape.
#   `--experiment ablation` runs the ablations of App. A.1, `--experiment all` every table and one report.
# * Change `cfg` (e.g. `ds.Config(beta=10.0)`, other cost weights, `ilqr_iters`) and re-run a section: every
#   experiment cell seeds itself.
# * The tests (`python -m pytest -q test_diffstack.py`) check each module against an independent computation:
#   the dynamics against RK4, the KKT gradients against finite differences, the predictor's loss by hand.

# %%
# Wall clock, and the kernel's CPU time (one thread: about what the wall clock would be on an idle machine).
print(f"notebook run time: {time.time() - T_START:.0f}s wall, {time.process_time() - CPU_START:.0f}s CPU "
      f"({'quick' if QUICK else 'full'} mode)")
