"""Training on many processes (lab/ddp.py): DistributedDataParallel on 2 CPU processes
over loopback (gloo) gives the parameters of one process training on the same global batches, in
float64 within 1e-10.

Every training path is checked: Standard (L_pred's batch statistics: the KL free-bits test and the
mutual information's mean p(z|x), taken over the global batch), Distance weighted
(the weights' normaliser), DiffStack (L_plan and L_ctr, means over the *plannable* scenarios: one
scenario is made unplannable, so the two ranks hold different numbers of them) and the learned cost
weights (DDP around CostWeights). Two steps each, so that Adam's state and the lr schedule are
exercised too, and the second step draws from the permutation's next batch. At every step the
loss, the gradient DDP hands the optimiser (before clipping) and the parameters after the step are
compared; two broken ranks (the wrong rows of the decoder's noise, a mean over the rank's own count
of plannable scenarios) fail that comparison (`test_a_broken_rank_fails_the_comparison`).

Only float64 is compared number for number: in float32 the two runs sum in other orders, and a
table passes through discrete choices (the planner's argmin, iLQR's convergence test, the most
likely mode) that such rounding can flip, scenario by scenario, on another CPU's kernels
(`test_experiments_cli_on_two_processes` bounds those columns by one flipped scenario).
"""

import contextlib
import dataclasses
import datetime
import json
import math
import os
import socket
import sys

import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp
from torch.optim.optimizer import register_optimizer_step_post_hook

import data_synth
import diffstack as ds
import experiments
import specs
import train as tr

WORLD = 2
GLOBAL_BATCH = 8  # 4 scenarios per rank
STEPS = 2
# the whole 2-process run; it takes about 10 s (a hung collective fails the test, never the suite)
TIMEOUT_S = 120


def cases():
    """The same problems in every process:
    (name, method, setting, float64 data, cfg, learn the cost weights?)."""
    cfg = dataclasses.replace(ds.Config(), batch_size=GLOBAL_BATCH)
    # (16, ...)
    train = data_synth.make_dataset(40, seed=3).train[: GLOBAL_BATCH * STEPS].to(torch.float64)
    lanes_mask = train.lanes_mask.clone()
    lanes_mask[5] = False  # no lanes: fewer than 2 candidates, so scenario 5 is not plannable
    train = dataclasses.replace(train, lanes_mask=lanes_mask)
    methods = {m.name: m for m in specs.TABLE1_METHODS}
    return [
        ("Standard", methods["Standard"], "rl", train, cfg, False),
        ("Distance weighted", methods["Distance weighted"], "rl", train, cfg, False),
        ("DiffStack", methods["DiffStack"], "rl", train, cfg, False),
        ("cost weights", tr.Method("Cost weights", losses=(0, 0, 1)), "il", train, cfg, True),
    ]


@contextlib.contextmanager
def recording_steps():
    """Yield a list that gets, at every optimiser step of train_stack, (the gradients it is handed
    before clipping, the parameters after the step): clip_grad_value_ wrapped, and a global
    post-step hook of torch.optim."""
    steps, clip = [], torch.nn.utils.clip_grad_value_

    def record_then_clip(params, clip_value):
        params = list(params)
        steps.append(([p.grad.detach().clone() for p in params], None))
        return clip(params, clip_value)

    def record_params(opt, args, kwargs):
        params = [p.detach().clone() for g in opt.param_groups for p in g["params"]]
        steps[-1] = (steps[-1][0], params)

    torch.nn.utils.clip_grad_value_ = record_then_clip
    handle = register_optimizer_step_post_hook(record_params)
    try:
        yield steps
    finally:
        torch.nn.utils.clip_grad_value_ = clip
        handle.remove()


def train_all(names=None) -> dict:
    """Run every case (or those named) from the same initial predictor (seed 0):
    {name: (trained parameters, per-step log, per-step (gradients, parameters))}."""
    out = {}
    for name, method, setting, data, cfg, learn_cost in cases():
        if names is not None and name not in names:
            continue
        torch.manual_seed(0)
        model = ds.Predictor(cfg).double()
        weights = tr.CostWeights(cfg).double() if learn_cost else None
        with recording_steps() as steps:
            history = tr.train_stack(
                model,
                data,
                method,
                cfg,
                setting,
                epochs=STEPS * GLOBAL_BATCH / len(data),
                seed=7,
                log=None,
                weights=weights,
            )
        trained = weights if learn_cost else model
        params = {k: v.detach().clone() for k, v in trained.state_dict().items()}
        out[name] = (params, history, steps)
    return out


# Two ways a rank can break DDP's equality (lab/ddp.py), each swapped in on every rank
def _wrong_noise_rows(self, model, b, cfg, like):
    """The decoder's noise: the next rank's rows of the global draw instead of this rank's."""
    other = dataclasses.replace(self, rank=(self.rank + 1) % self.world)
    return BROKEN_FROM[0](other, model, b, cfg, like)


def _own_count(self, x):
    """A sum over this rank's rows only: L_plan and L_ctr divided by the rank's own number of
    plannable scenarios, not the global one."""
    return x.detach().sum(0)


BREAKS = {"noise rows": ("decoder_noise", _wrong_noise_rows), "own count": ("total", _own_count)}
BROKEN_FROM = []  # the unbroken method, in a worker that breaks one


def _worker(rank: int, port: int, path: str, names=None, broken=None) -> None:
    """One rank: join the process group on 127.0.0.1:port, train every case (or those named, with
    BREAKS[broken] swapped into train.Shard); rank 0 saves the results to path."""
    torch.set_num_threads(1)
    if broken is not None:
        attr, replacement = BREAKS[broken]
        BROKEN_FROM.append(getattr(tr.Shard, attr))
        setattr(tr.Shard, attr, replacement)
    dist.init_process_group(
        "gloo",
        init_method=f"tcp://127.0.0.1:{port}",
        rank=rank,
        world_size=WORLD,
        timeout=datetime.timedelta(seconds=60),
    )
    try:
        result = train_all(names)
        if rank == 0:
            torch.save(result, path)
    finally:
        dist.destroy_process_group()


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _cli_worker(rank: int, port: int, argv: list, log_dir: str) -> None:
    """One rank of `torchrun --nproc_per_node WORLD experiments.py ARGV`: torchrun's environment,
    then main(argv), its output (stdout and stderr) to log_dir/rank<rank>.log."""
    os.environ.update(
        RANK=str(rank),
        LOCAL_RANK=str(rank),
        WORLD_SIZE=str(WORLD),
        MASTER_ADDR="127.0.0.1",
        MASTER_PORT=str(port),
    )
    with (
        open(os.path.join(log_dir, f"rank{rank}.log"), "w") as f,
        contextlib.redirect_stdout(f),
        contextlib.redirect_stderr(f),
    ):
        experiments.main(argv)


def spawn(worker, *args) -> None:
    """worker(rank, free port, *args) on WORLD processes; every one is ended (killed if need be)
    before this returns or raises."""
    env = {"GLOO_SOCKET_IFNAME": "lo"} if sys.platform.startswith("linux") else {}
    old = {k: os.environ.get(k) for k in env}
    os.environ.update(env)  # spawned workers inherit it: gloo on the loopback interface
    try:
        ctx = mp.start_processes(
            worker, args=(free_port(), *args), nprocs=WORLD, join=False, start_method="spawn"
        )
    finally:
        for k, v in old.items():
            os.environ.pop(k) if v is None else os.environ.__setitem__(k, v)
    deadline = datetime.datetime.now() + datetime.timedelta(seconds=TIMEOUT_S)
    try:
        while not ctx.join(
            timeout=1
        ):  # True once all exited cleanly; raises if one failed (and ends the others)
            if datetime.datetime.now() > deadline:
                raise TimeoutError(f"the {WORLD} DDP workers did not finish within {TIMEOUT_S} s")
    finally:
        for p in ctx.processes:
            if p.is_alive():
                p.kill()
            p.join(5)


def run_ddp(path, names=None, broken=None) -> dict:
    """train_all on WORLD processes."""
    spawn(_worker, str(path), names, broken)
    return torch.load(path, weights_only=False)


@pytest.fixture(scope="module")
def both(tmp_path_factory):
    """(single-process results, DDP results)."""
    ddp = run_ddp(tmp_path_factory.mktemp("ddp") / "ranks.pt")
    return train_all(), ddp


def largest_differences(one, other) -> dict:
    """The largest difference, relative to max(1, |value|), of a case's runs in one process and
    in DDP: {'loss' (every logged loss), 'gradient', 'parameters' (after each step): value}."""
    (_, h1, s1), (_, h2, s2) = one, other
    assert len(h1) == len(h2) == len(s1) == len(s2) == STEPS

    def rel(a, b):
        return ((a - b).abs().max() / max(1.0, b.abs().max().item())).item()

    losses = [(a[k], b[k]) for a, b in zip(h1, h2) for k in ("loss", "l_pred", "l_plan", "l_ctr")]
    return {
        "loss": max(abs(x - y) / max(1.0, abs(x)) for x, y in losses),
        "gradient": max(rel(a, b) for (g1, _), (g2, _) in zip(s1, s2) for a, b in zip(g1, g2)),
        "parameters": max(rel(a, b) for (_, p1), (_, p2) in zip(s1, s2) for a, b in zip(p1, p2)),
    }


# float64 rounding of sums taken in another order (measured: at most 4e-15)
EXACT = 1e-10


@pytest.mark.slow
@pytest.mark.parametrize("name", [c[0] for c in cases()])
def test_ddp_step_equals_single_process_step(both, name):
    single, ddp = both
    (p1, h1, _), (p2, h2, _) = single[name], ddp[name]
    assert len(h1) == len(h2) == STEPS
    for k in p1:
        err = (p1[k] - p2[k]).abs().max().item()
        assert err <= EXACT, (
            f"{name}: parameter {k} differs by {err:.3g} between 1 process and {WORLD} DDP ranks"
        )
    # every step: the same loss, the same gradient before clipping, the same parameters after it
    for what, err in largest_differences(single[name], ddp[name]).items():
        assert err <= EXACT, f"{name}: the {what} differs by {err:.3g} (relative) under DDP"
    # the parameters moved (the comparison is not of two untouched initialisations) ...
    torch.manual_seed(0)
    init = (
        tr.CostWeights(ds.Config()).double()
        if name == "cost weights"
        else ds.Predictor(ds.Config()).double()
    ).state_dict()
    assert any((p1[k] - init[k]).abs().max() > 1e-6 for k in p1 if p1[k].is_floating_point())
    # ... and the logged losses of the global batch are the same too
    for a, b in zip(h1, h2):
        for key in ("loss", "l_pred", "l_plan", "l_ctr", "converged"):
            x, y = a[key], b[key]
            assert (math.isnan(x) and math.isnan(y)) or abs(x - y) <= 1e-10 * max(1.0, abs(x)), (
                name,
                key,
                x,
                y,
            )


@pytest.mark.slow
@pytest.mark.parametrize("broken, name", [("noise rows", "Standard"), ("own count", "DiffStack")])
def test_a_broken_rank_fails_the_comparison(both, tmp_path, broken, name):
    """The comparison above can fail: a rank that takes the wrong rows of the decoder's noise
    (Standard), or divides L_plan and L_ctr by its own count of plannable scenarios instead of the
    global one (DiffStack, whose ranks hold 4 and 3 plannable scenarios), moves the loss, the
    gradient and the parameters far beyond float64 rounding."""
    single, _ = both
    ddp = run_ddp(tmp_path / "broken.pt", names=[name], broken=broken)
    errors = largest_differences(single[name], ddp[name])
    assert errors["gradient"] > 1e-4 and errors["parameters"] > 1e-6, errors


def test_the_ranks_hold_different_numbers_of_plannable_scenarios():
    """What makes DiffStack's case a test of the global count: the unplannable scenario sits in one
    rank's shard (a mean of per-rank means would then differ from the global mean)."""
    _, _, _, data, cfg, _ = cases()[2]
    # train_stack's order, seed 7
    perm = torch.randperm(len(data), generator=torch.Generator().manual_seed(7))
    step = next(i for i in range(STEPS) if 5 in perm[i * GLOBAL_BATCH : (i + 1) * GLOBAL_BATCH])
    batch = perm[step * GLOBAL_BATCH : (step + 1) * GLOBAL_BATCH]
    counts = [
        int((batch[tr.Shard(r, WORLD).positions(GLOBAL_BATCH)] == 5).sum()) for r in range(WORLD)
    ]
    assert sorted(counts) == [0, 1]


def test_batch_size_must_split_over_the_ranks():
    """An uneven split is refused by name (a Shard standing in for a 3-process world; nothing is
    launched)."""
    cfg = dataclasses.replace(ds.Config(), batch_size=GLOBAL_BATCH)
    data = cases()[0][3]
    original = tr.Shard.of_process_group
    tr.Shard.of_process_group = staticmethod(lambda: tr.Shard(0, 3))
    try:
        with pytest.raises(
            ValueError, match="cfg.batch_size: 8 scenarios per step do not split evenly over 3"
        ):
            tr.train_stack(ds.Predictor(cfg).double(), data, tr.Method("Standard"), cfg, log=None)
    finally:
        tr.Shard.of_process_group = original


# How far one scenario's value can move when rounding flips one of its discrete choices (another
# of the 48 candidates, another iLQR iterate, another most likely mode). Measured on this test's
# 200 validation scenarios: switching every scenario from No prediction's plan to GT prediction's
# moves one scenario's hindsight cost by at most 0.18, its planning loss by 0.34 and its MSE to the
# expert by 0.35 m^2; the bounds are those, rounded up, a converged flag flips by 1, and the most
# likely mode's ADE and FDE by the distance between two modes (a few metres).
ONE_FLIP = {
    "hindsight": 0.5,
    "plan_loss": 0.5,
    "mse": 1.0,
    "converged": 1.0,
    "ade": 5.0,
    "fde": 10.0,
}


@pytest.mark.slow
def test_experiments_cli_on_two_processes(tmp_path):
    """experiments.py as torchrun starts it, on 2 processes: only rank 0 writes files and prints,
    the command and the machine are recorded, and the table has the single-process table's rows,
    columns and scenario counts. Its numbers come from one float32 training step per method: a
    column that passes through a discrete choice is held within what one flipped scenario can move
    a mean over n scenarios, ONE_FLIP / n (in a rel_ column also divided by its scale); the others
    (NLL, min-ADE, constant velocity) to float32 rounding. DDP's own equality is tested in float64
    above (a wrong rank moves the loss by 2e-4 to 0.5 there)."""
    argv = [
        "--experiment",
        "rl",
        "--seeds",
        "1",
        "--epochs",
        "0.02",
        "--n",
        "600",
        "--val",
        "200",
        "--threads",
        "1",
    ]
    experiments.main(argv + ["--out", str(tmp_path / "one")])
    spawn(_cli_worker, argv + ["--out", str(tmp_path / "two")], str(tmp_path))
    one, two = (json.loads((tmp_path / d / "rl.json").read_text()) for d in ("one", "two"))
    assert two["meta"]["command"].startswith(f"torchrun --nproc_per_node {WORLD} experiments.py")
    assert f"{WORLD} processes (DDP)" in two["meta"]["machine"]
    assert list(two["results"]) == list(one["results"]) == [m.name for m in specs.TABLE1_METHODS]
    for method, runs in one["results"].items():
        (run,) = runs
        other = two["results"][method][0]
        assert sorted(other) == sorted(run), method
        assert (other["n"], other["skipped"]) == (run["n"], run["skipped"]), method
        for key, value in run.items():
            if key == "seconds" or not isinstance(value, float):
                continue
            metric = key.removeprefix("rel_")
            if metric in ONE_FLIP:
                scale = specs.RELATIVE_SCALE["rl"][metric] if key.startswith("rel_") else 1.0
                tol = ONE_FLIP[metric] / run["n"] / scale
                assert abs(other[key] - value) <= tol, (method, key, value, other[key], tol)
            else:
                assert other[key] == pytest.approx(value, rel=1e-4, abs=1e-6), (method, key)
    assert "Table 1" in (tmp_path / "rank0.log").read_text()
    assert (tmp_path / "rank1.log").read_text() == "", "rank 1 printed"
    assert sorted(p.name for p in (tmp_path / "two").iterdir()) == [
        ".lock",
        "learning_curves.png",
        "rl.json",
        "rl.md",
    ]
