"""Training on many processes (train.py section 3): DistributedDataParallel on 2 CPU processes
over loopback (gloo) gives the parameters of one process training on the same global batches, in
float64 within 1e-10.

Every training path is checked: Standard (L_pred's batch statistics: the KL free-bits test and the
mutual information's mean p(z|x), taken over the global batch), Distance weighted
(the weights' normaliser), DiffStack (L_plan and L_ctr, means over the *plannable* scenarios: one
scenario is made unplannable, so the two ranks hold different numbers of them) and the learned cost
weights (DDP around CostWeights). Two steps each, so that Adam's state and the lr schedule are
exercised too, and the second step draws from the permutation's next batch.
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

import data_synth
import diffstack as ds
import experiments
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
    methods = {m.name: m for m in tr.TABLE1_METHODS}
    return [
        ("Standard", methods["Standard"], "rl", train, cfg, False),
        ("Distance weighted", methods["Distance weighted"], "rl", train, cfg, False),
        ("DiffStack", methods["DiffStack"], "rl", train, cfg, False),
        ("cost weights", tr.Method("Cost weights", losses=(0, 0, 1)), "il", train, cfg, True),
    ]


def train_all() -> dict:
    """Run every case from the same initial predictor (seed 0):
    {name: (trained parameters, per-step log)}."""
    out = {}
    for name, method, setting, data, cfg, learn_cost in cases():
        torch.manual_seed(0)
        model = ds.Predictor(cfg).double()
        weights = tr.CostWeights(cfg).double() if learn_cost else None
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
        out[name] = ({k: v.detach().clone() for k, v in trained.state_dict().items()}, history)
    return out


def _worker(rank: int, port: int, path: str) -> None:
    """One rank: join the process group on 127.0.0.1:port, train every case; rank 0 saves the
    results to path."""
    torch.set_num_threads(1)
    dist.init_process_group(
        "gloo",
        init_method=f"tcp://127.0.0.1:{port}",
        rank=rank,
        world_size=WORLD,
        timeout=datetime.timedelta(seconds=60),
    )
    try:
        result = train_all()
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


def run_ddp(path) -> dict:
    """train_all on WORLD processes."""
    spawn(_worker, str(path))
    return torch.load(path, weights_only=False)


@pytest.fixture(scope="module")
def both(tmp_path_factory):
    """(single-process results, DDP results)."""
    ddp = run_ddp(tmp_path_factory.mktemp("ddp") / "ranks.pt")
    return train_all(), ddp


@pytest.mark.parametrize("name", [c[0] for c in cases()])
def test_ddp_step_equals_single_process_step(both, name):
    single, ddp = both
    (p1, h1), (p2, h2) = single[name], ddp[name]
    assert len(h1) == len(h2) == STEPS
    for k in p1:
        err = (p1[k] - p2[k]).abs().max().item()
        assert err <= 1e-10, (
            f"{name}: parameter {k} differs by {err:.3g} between 1 process and {WORLD} DDP ranks"
        )
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


def test_experiments_cli_on_two_processes(tmp_path):
    """experiments.py as torchrun starts it, on 2 processes: one training step per method (float32)
    gives the single-process table to float32 rounding; only rank 0 writes files and prints, and the
    command is recorded. The rel_ columns are differences of two metrics of size 1 to 5: their
    rounding is absolute (7.6e-6 measured; a rank that takes the wrong rows of the decoder's noise
    moves them by 2e-3 to 0.8)."""
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
    for method, runs in one["results"].items():
        for key, value in runs[0].items():
            if key != "seconds" and isinstance(value, float):
                tol = 1e-5 if key.startswith("rel_") else 1e-6
                assert two["results"][method][0][key] == pytest.approx(value, rel=1e-4, abs=tol), (
                    method,
                    key,
                )
    assert "Table 1" in (tmp_path / "rank0.log").read_text()
    assert (tmp_path / "rank1.log").read_text() == "", "rank 1 printed"
    assert sorted(p.name for p in (tmp_path / "two").iterdir()) == [
        ".lock",
        "learning_curves.png",
        "rl.json",
        "rl.md",
    ]
