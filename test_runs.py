"""Runs that survive: every (table, method, seed) piece is kept in <out>/.runs/ as it finishes, a
re-run of the same command resumes (and a changed config is a new run), --jobs N runs the seeds in
worker processes with the numbers of one process, and a progress bar counts the pieces done. Tiny
models and data."""

import dataclasses
import json
import os
import pathlib
import re
import time

import pytest
import torch
from torch.optim.optimizer import register_optimizer_step_post_hook

import data_synth
import diffstack as ds
import experiments as ex
from lab import tables as lt
from lab import runs
import train as tr
from lab import cli
import math
from lab import quick as lq
from conftest import TINY, cli_error, launcher_env, make_batch, small_cfg
from lab import checks
import sys
from lab import data as lab_data
import subprocess
import specs

TINY10 = dict(
    pred_modes=5, pred_dec_hidden=16, pred_enc_hidden=16, pred_latent_hidden=16, batch_size=32
)


@pytest.fixture(scope="module")
def small():
    data = data_synth.make_dataset(
        120, data_synth.SynthConfig(pos_noise=0.0, yaw_noise=0.0), seed=3
    )
    return data_synth.Dataset(data.train[:64], data.val[:16], data.val_scenes[:2])


@pytest.fixture
def trainings(monkeypatch):
    """Count the predictors trained ((method, seed) per call); trainings.fail_at = k: the k-th
    training raises."""
    calls = []
    train = tr.train_stack

    def counting(model, data, m, cfg, setting, epochs, seed, *a, **k):
        if k.get("weights") is None:
            if len(calls) + 1 == counting.fail_at:
                raise RuntimeError("killed")
            calls.append((m.name, seed))
        return train(model, data, m, cfg, setting, epochs, seed, *a, **k)

    counting.fail_at = None
    counting.calls = calls
    monkeypatch.setattr(tr, "train_stack", counting)
    return counting


def numbers(out, name="il") -> dict:
    """A result file's results without the wall-clock times (they differ from run to run)."""
    res = json.loads((out / f"{name}.json").read_text())["results"]
    return {
        m: [{k: v for k, v in r.items() if "seconds" not in k} for r in runs]
        for m, runs in res.items()
    }


def table_of(out, name="il") -> str:
    """The .md file less its provenance line (which has the run's seconds)."""
    return "\n".join(
        ln for ln in (out / f"{name}.md").read_text().splitlines() if not ln.startswith("`")
    )


def test_an_interrupted_run_resumes_and_trains_only_the_rest(small, tmp_path, trainings):
    cfg = ds.Config(**TINY10)
    lt.run_experiment("il", small, cfg, (0, 1), 0.5, tmp_path / "whole", "test", log=None)
    assert sorted(trainings.calls) == [
        ("DiffStack", 0),
        ("DiffStack", 1),
        ("Standard", 0),
        ("Standard", 1),
    ]
    trainings.calls.clear()
    # Standard seeds 0 and 1 train, then the run dies while training DiffStack seed 0
    trainings.fail_at = 3
    with pytest.raises(RuntimeError, match="killed"):
        lt.run_experiment("il", small, cfg, (0, 1), 0.5, tmp_path / "cut", "test", log=None)
    kept = sorted(p.name for p in (tmp_path / "cut" / ".runs" / "il").glob("*/*-seed*.json"))
    assert kept == ["No_prediction-seed0.json", "Standard-seed0.json", "Standard-seed1.json"]
    assert not (tmp_path / "cut" / "il.json").exists()
    trainings.calls.clear()
    trainings.fail_at = None
    lines = []
    lt.run_experiment("il", small, cfg, (0, 1), 0.5, tmp_path / "cut", "test", log=lines.append)
    assert trainings.calls == [("DiffStack", 0), ("DiffStack", 1)]  # only what was missing
    assert any(
        "3 of 6 pieces done by an earlier run" in ln and "Standard-seed1" in ln for ln in lines
    )
    # the table's computing time is its pieces', the interrupted run's three included (its own
    # seconds are not)
    kept = [
        json.loads(f.read_text())["timing"]
        for f in (tmp_path / "cut" / ".runs" / "il").glob("*/*-seed*.json")
    ]
    meta = json.loads((tmp_path / "cut" / "il.json").read_text())["meta"]
    assert len(kept) == meta["pieces"] == 6 and all(
        t["seconds"] > 0 and t["cpu_seconds"] > 0 for t in kept
    )
    assert meta["piece_seconds"] == pytest.approx(sum(t["seconds"] for t in kept))
    assert "s wall in this command" in (tmp_path / "cut" / "il.md").read_text()
    assert "s of computing summed over its 6 pieces" in (tmp_path / "cut" / "il.md").read_text()
    assert numbers(tmp_path / "cut") == numbers(tmp_path / "whole")
    assert table_of(tmp_path / "cut") == table_of(tmp_path / "whole")


def test_a_changed_config_is_a_new_run_and_a_finished_run_reruns_from_its_pieces(
    small, tmp_path, trainings
):
    cfg = ds.Config(**TINY10)
    out = tmp_path / "out"
    lt.run_experiment("il", small, cfg, (0,), 0.5, out, "test", log=None)
    assert len(trainings.calls) == 2
    before = numbers(out)
    # the same command again: its files exist, so only --overwrite replaces them; then nothing is
    # trained and the same numbers come out
    with pytest.raises(ValueError, match="--overwrite"):
        lt.run_experiment("il", small, cfg, (0,), 0.5, out, "test", log=None)
    lt.run_experiment("il", small, cfg, (0,), 0.5, out, "test", log=None, overwrite=True)
    assert len(trainings.calls) == 2 and numbers(out) == before
    # another config is another run, and all is retrained
    other = dataclasses.replace(cfg, beta=2 * cfg.beta)
    lt.run_experiment("il", small, other, (0,), 0.5, out, "test", log=None, overwrite=True)
    assert len(trainings.calls) == 4 and len(list((out / ".runs" / "il").iterdir())) == 2
    assert numbers(out) != before
    # an output edited by hand (or any other file of the same name) is refused, and kept
    (out / "il.md").write_text("edited")
    with pytest.raises(ValueError, match="il.md"):
        lt.run_experiment("il", small, other, (0,), 0.5, out, "test", log=None)
    assert (out / "il.md").read_text() == "edited"


def test_a_run_resumed_on_another_machine_says_where_its_pieces_ran(small, tmp_path, trainings):
    cfg = ds.Config(**TINY10)
    out = tmp_path / "out"
    lt.run_experiment("il", small, cfg, (0,), 0.5, out, "test", log=None)
    kept = sorted((out / ".runs" / "il").glob("*/*-seed*.json"))
    assert [json.loads(f.read_text())["timing"]["machine"] for f in kept] == [cli.machine()] * 4
    # one machine: nothing to say
    assert "computed_on" not in json.loads((out / "il.json").read_text())["meta"]
    assert "pieces ran on" not in (out / "il.md").read_text()
    # as if Standard had been trained on another host before the run was resumed here
    piece = json.loads(kept[-1].read_text())
    piece["timing"]["machine"] = "x86_64, another processor, AVX2, 2 cores"
    kept[-1].write_text(json.dumps(piece))
    lt.run_experiment("il", small, cfg, (0,), 0.5, out, "test", log=None, overwrite=True)
    assert len(trainings.calls) == 2  # resumed: nothing trained again
    meta = json.loads((out / "il.json").read_text())["meta"]
    assert meta["computed_on"] == {cli.machine(): 3, "x86_64, another processor, AVX2, 2 cores": 1}
    assert (
        "its pieces ran on 2 machines, and the same seed gives other numbers on another kind of "
        "processor: " in (out / "il.md").read_text()
    )


def test_a_resumed_closed_loop_draws_its_figure_from_the_kept_rollouts(
    small, tmp_path, trainings, monkeypatch
):
    cfg = ds.Config(**TINY10)
    out = tmp_path / "out"
    lt.run_experiment("closed_loop", small, cfg, (0,), 0.5, out, "test", log=None)
    before = numbers(out, "closed_loop")
    (out / "closed_loop.png").unlink()
    monkeypatch.setattr(
        ex, "simulate", lambda *a, **k: pytest.fail("every piece is kept: nothing is simulated")
    )
    lt.run_experiment("closed_loop", small, cfg, (0,), 0.5, out, "test", log=None, overwrite=True)
    # Standard and DiffStack, once; the figure's predictors are loaded
    assert len(trainings.calls) == 2
    assert (
        numbers(out, "closed_loop") == before and (out / "closed_loop.png").stat().st_size > 10_000
    )


@pytest.mark.slow
def test_jobs_2_gives_the_numbers_of_one_process(small, tmp_path):
    cfg = ds.Config(**TINY10)
    t0 = time.time()
    lt.run_experiment("il", small, cfg, (0, 1), 0.5, tmp_path / "one", "test", log=None, jobs=1)
    t1 = time.time()
    lt.run_experiment("il", small, cfg, (0, 1), 0.5, tmp_path / "two", "test", log=None, jobs=2)
    print(f"--jobs 1: {t1 - t0:.1f} s, --jobs 2: {time.time() - t1:.1f} s")
    assert numbers(tmp_path / "two") == numbers(tmp_path / "one")
    machine = json.loads((tmp_path / "two" / "il.json").read_text())["meta"]["machine"]
    assert "2 worker processes (--jobs)" in machine
    # the kind of processor, on which the numbers depend (cli.machine: oneDNN's kernels follow its
    # instruction set)
    assert f", {torch.backends.cpu.get_cpu_capability()}, {os.cpu_count()} cores, torch " in machine


@pytest.mark.parametrize("jobs", ["0", "-1", "x", "2.5"])
def test_bad_jobs_is_a_one_line_error_naming_it(jobs, capsys, tmp_path):
    with pytest.raises(SystemExit) as e:
        ex.main(["--experiment", "rl", "--jobs", jobs, "--out", str(tmp_path)])
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and "--jobs" in err[-1] and err[-1].startswith("usage") is False


def test_the_progress_bar_starts_at_the_reused_pieces_and_counts_up_to_the_total(
    small, tmp_path, monkeypatch
):
    """The bar (tqdm) counts the pieces of the run: those an earlier run finished from the start,
    then each one as it is kept."""
    bars = []

    class Bar(lt.tqdm):
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            if not self.disable:  # (the bar of a run that logs)
                bars.append(self)

    monkeypatch.setattr(lt, "tqdm", Bar)
    cfg = ds.Config(**TINY10)
    lines = []  # (a run that logs has a bar)
    lt.run_experiment("il", small, cfg, (0,), 0.5, tmp_path, "test", log=lines.append)
    (piece,) = (tmp_path / ".runs" / "il").glob("*/Standard-seed0.json")
    piece.unlink()
    lt.run_experiment("il", small, cfg, (0,), 0.5, tmp_path, "t", log=lines.append, overwrite=True)
    assert [(b.initial, b.n, b.total) for b in bars] == [(0, 4, 4), (3, 4, 4)]


def test_a_refused_out_is_a_one_line_error_on_the_command_line(tmp_path, capsys):
    """Found only once the data (and so the run's key) is known, the refusal is still argparse's
    one-line error."""
    args = [
        "--experiment",
        "il",
        "--seeds",
        "1",
        "--epochs",
        "0.05",
        "--n",
        "120",
        "--val",
        "120",
        "--threads",
        "1",
        "--jobs",
        "1",
        "--out",
        str(tmp_path),
        "--set",
        "pred_modes=5",
        "--set",
        "pred_dec_hidden=16",
    ]
    ex.main(args)
    capsys.readouterr()
    with pytest.raises(SystemExit) as e:
        ex.main(args + ["--set", "beta=2"])  # another config: the files of the first run are kept
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and "error: --out:" in err[-1] and "--overwrite" in err[-1]
    assert not any("Traceback" in line for line in err)


def test_a_diverged_training_is_kept_as_a_result_and_named_in_the_table(
    small, tmp_path, monkeypatch
):
    """A training whose loss turns NaN stops with TrainingDiverged (method, seed, step); the run
    keeps going, keeps that piece as 'diverged' (a resumed run does not retrain it), and the table
    leaves the seed out and says so."""
    cfg = ds.Config(**TINY10)
    train = tr.train_stack
    calls = []

    def diverging(model, data, m, cfg_, setting, epochs, seed, *a, **k):
        calls.append((m.name, seed))
        if (m.name, seed) == ("DiffStack", 1):
            raise tr.TrainingDiverged(
                f"{m.name}, seed {seed}: training diverged at step 3 of 4: L_pred is not finite"
            )
        return train(model, data, m, cfg_, setting, epochs, seed, *a, **k)

    monkeypatch.setattr(tr, "train_stack", diverging)
    lt.run_experiment("il", small, cfg, (0, 1), 0.5, tmp_path, "test", log=None)
    res = json.loads((tmp_path / "il.json").read_text())["results"]
    assert res["DiffStack"][1] == {
        "diverged": "DiffStack, seed 1: training diverged at step 3 of 4: L_pred is not finite"
    }
    md = (tmp_path / "il.md").read_text()
    assert "Diverged, left out of the means: DiffStack, seed 1: training diverged at step 3" in md
    assert "1 of 1 seeds better" in md or "0 of 1 seeds better" in md
    assert "1 diverged, left out" in md
    calls.clear()
    lt.run_experiment("il", small, cfg, (0, 1), 0.5, tmp_path, "test", log=None, overwrite=True)
    assert calls == []  # every piece kept, the diverged one too


def test_train_stack_stops_before_a_nan_reaches_the_parameters(small, monkeypatch):
    cfg = ds.Config(**TINY10)
    data = small.train[:64]
    orig = ds.pred_loss
    seen = []

    def nan_at_step_2(pred, batch, step, cfg_, shard=None):
        loss, parts = orig(pred, batch, step, cfg_, shard)
        seen.append(step)
        return (loss * float("nan") if step == 2 else loss), parts

    monkeypatch.setattr(ds, "pred_loss", nan_at_step_2)
    torch.manual_seed(0)
    model = ds.Predictor(cfg)
    with pytest.raises(
        tr.TrainingDiverged,
        match=r"DiffStack, seed 7: training diverged at step 3 of 4: L_pred is not finite",
    ):
        tr.train_stack(
            model, data, tr.Method("DiffStack", losses=(1, 1, 1)), cfg, "rl", 2.0, 7, None
        )
    assert seen == [0, 1, 2] and all(torch.isfinite(p).all() for p in model.parameters())


def test_a_recorded_command_names_paths_relative_to_the_repository(tmp_path):
    """Results record their command with the repository's own paths relative (the same on every
    machine); a path outside the repository is kept as given."""
    root = runs.ROOT
    cmd = runs.command_line(
        "python experiments.py",
        [
            "--experiment",
            "rl",
            "--out",
            str(root / "results" / "x"),
            f"--data={root / 'data'}",
            "--cache",
            str(tmp_path),
        ],
    )
    assert (
        cmd
        == f"python experiments.py --experiment rl --out results/x --data=data --cache {tmp_path}"
    )


def test_a_nan_gradient_stops_training_before_it_reaches_the_parameters(small, monkeypatch):
    """A finite loss with a NaN gradient (what a NaN inside the stack's backward gives) stops the
    training too."""
    cfg = ds.Config(**TINY10)
    torch.manual_seed(0)
    model = ds.Predictor(cfg)
    model.dec_out.weight.register_hook(lambda g: g * float("nan"))
    with pytest.raises(
        tr.TrainingDiverged,
        match=r"Standard, seed 7: training diverged at step 1 of 2: a gradient is NaN",
    ):
        tr.train_stack(model, small.train[:64], tr.Method("Standard"), cfg, "rl", 1.0, 7, None)
    assert all(torch.isfinite(p).all() for p in model.parameters())


def test_a_parameter_that_overflows_stops_training(small):
    """A step that makes a parameter infinite under a finite loss and gradient (an overflowing
    update) stops the training at that step; the loss would only show it at the next one, and after
    the last step never."""
    cfg = ds.Config(**TINY10)
    torch.manual_seed(0)
    model = ds.Predictor(cfg)

    def overflow(opt, args, kwargs):
        with torch.no_grad():
            opt.param_groups[0]["params"][0].view(-1)[0] = float("inf")

    hook = register_optimizer_step_post_hook(overflow)
    try:
        with pytest.raises(
            tr.TrainingDiverged,
            match=r"Standard, seed 7: training diverged at step 1 of 2: a parameter "
            r"is not finite",
        ):
            tr.train_stack(model, small.train[:64], tr.Method("Standard"), cfg, "rl", 1.0, 7, None)
    finally:
        hook.remove()


def test_a_predictor_whose_evaluation_is_not_finite_is_a_diverged_training(small, monkeypatch):
    evaluate = tr.evaluate_stack
    monkeypatch.setattr(
        ex,  # compare_methods evaluates through experiments' name
        "evaluate_stack",
        lambda model, *a, **k: {**evaluate(model, *a, **k), "ade": float("nan")},
    )
    cfg = ds.Config(**TINY10)
    with pytest.raises(
        tr.TrainingDiverged, match=r"Standard, seed 0: its evaluation is not finite \(ade\)"
    ):
        ex.compare_methods(small, cfg, "rl", (tr.Method("Standard"),), (0,), 0.5, log=None)


def test_a_result_with_nan_or_infinity_is_never_written(tmp_path):
    runs.write_json(tmp_path / "x.json", {"a": [1.0, {"b": 2.0}]})
    assert json.loads((tmp_path / "x.json").read_text()) == {"a": [1.0, {"b": 2.0}]}
    for bad in ({"a": [1.0, {"b": float("nan")}]}, {"c": float("-inf")}):
        with pytest.raises(ValueError, match=re.escape(f"{tmp_path / 'rl.json'}: Out of range")):
            runs.write_json(tmp_path / "rl.json", bad)
        assert not (tmp_path / "rl.json").exists()


def _children(pid: int) -> set:
    """The processes whose parent is `pid` (Linux /proc)."""
    found = set()
    for stat in pathlib.Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            found.add(int(stat.parent.name))
    return found


@pytest.mark.slow
@pytest.mark.skipif(not pathlib.Path("/proc").is_dir(), reason="reads the process table from /proc")
@pytest.mark.parametrize("how", ["kill -9", "Ctrl-C", "kill -INT"])
def test_a_killed_runs_workers_do_not_outlive_it(tmp_path, how):
    """kill -9 of a --jobs 2 run, Ctrl-C in its terminal (SIGINT to its process group), or SIGINT to
    the run alone (kill -INT PID): its worker processes end too (they watch their parent) instead of
    training on under PID 1, and the run ends at once, not when its workers' pieces are done."""
    import signal
    import subprocess
    import sys

    script = runs.ROOT / "experiments.py"
    # (start_new_session: a process group of its own, as a terminal gives a command; SIGINT at its
    # default, which Python turns into KeyboardInterrupt, also where the tests run in the
    # background, whose jobs ignore SIGINT)
    run = subprocess.Popen(
        [
            sys.executable,
            str(script),
            "--experiment",
            "rl",
            "--seeds",
            "2",
            "--jobs",
            "2",
            "--n",
            "200",
            "--val",
            "200",
            "--epochs",
            "300",
            "--out",
            "out",
        ],
        cwd=tmp_path,
        stdout=subprocess.DEVNULL,
        stderr=open(tmp_path / "stderr", "wb"),
        start_new_session=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    workers = set()
    t0 = time.time()
    while len(workers) < 2 and time.time() - t0 < 120 and run.poll() is None:
        workers = {
            p
            for p in _children(run.pid)
            if b"spawn_main" in pathlib.Path(f"/proc/{p}/cmdline").read_bytes().replace(b"\0", b" ")
        }
        time.sleep(0.2)
    assert len(workers) == 2, "the run's two worker processes never started"
    time.sleep(10)  # into their training (a piece here takes minutes)
    assert all(pathlib.Path(f"/proc/{p}").exists() for p in workers)
    if how == "kill -9":
        run.send_signal(signal.SIGKILL)
    elif how == "Ctrl-C":
        os.killpg(run.pid, signal.SIGINT)
    else:
        os.kill(run.pid, signal.SIGINT)
    try:
        run.wait(30)
    finally:
        run.kill()
    said = (tmp_path / "stderr").read_text()
    assert run.returncode == (-signal.SIGKILL if how == "kill -9" else 130)
    assert how == "kill -9" or (
        "interrupted (Ctrl-C); the pieces finished so far are kept" in said
        and "Traceback" not in said
    )
    t0 = time.time()
    while any(pathlib.Path(f"/proc/{p}").exists() for p in workers) and time.time() - t0 < 5:
        time.sleep(0.2)
    alive = [p for p in workers if pathlib.Path(f"/proc/{p}").exists()]
    for p in alive:  # (so that a failing run leaves nothing behind)
        os.kill(p, signal.SIGKILL)
    assert not alive, f"workers {alive} outlived their killed parent"


def _dies(code):
    """A unit of work whose worker process dies (as one killed by the OOM killer would)."""
    os._exit(code)


def test_a_worker_that_dies_stops_the_run_saying_so(tmp_path):
    with pytest.raises(
        runs.WorkerDied, match=r"a worker process died .*the same command resumes it"
    ):
        runs.in_workers(_dies, [(3,), (3,)], 2, print, tmp_path)


@pytest.mark.slow
@pytest.mark.skipif(not pathlib.Path("/proc").is_dir(), reason="reads the process table from /proc")
def test_the_ranks_of_a_killed_torchrun_do_not_outlive_it(tmp_path):
    """kill -9 of torchrun (its agent) mid-training: the ranks it started end too."""
    import signal
    import subprocess
    import sys

    script = runs.ROOT / "experiments.py"
    agent = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "torch.distributed.run",
            "--nproc_per_node",
            "2",
            str(script),
            "--experiment",
            "rl",
            "--samples",
            "200",
            "--val",
            "200",
            "--epochs",
            "300",
            "--threads",
            "1",
            "--out",
            "out",
        ],
        cwd=tmp_path,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    ranks = set()
    t0 = time.time()
    while len(ranks) < 2 and time.time() - t0 < 120 and agent.poll() is None:
        ranks = {
            p
            for p in _children(agent.pid)
            if b"experiments.py" in pathlib.Path(f"/proc/{p}/cmdline").read_bytes()
        }
        time.sleep(0.2)
    assert len(ranks) == 2, "torchrun's two ranks never started"
    time.sleep(12)  # into their training
    assert all(pathlib.Path(f"/proc/{p}").exists() for p in ranks)
    agent.send_signal(signal.SIGKILL)
    agent.wait()
    t0 = time.time()
    while any(pathlib.Path(f"/proc/{p}").exists() for p in ranks) and time.time() - t0 < 5:
        time.sleep(0.2)
    alive = [p for p in ranks if pathlib.Path(f"/proc/{p}").exists()]
    for p in alive:
        os.kill(p, signal.SIGKILL)
    assert not alive, f"ranks {alive} outlived their killed torchrun"


def test_a_learning_curve_that_is_not_finite_is_a_diverged_training(small, tmp_path, monkeypatch):
    # neither the model nor its curve is written; the piece is kept as diverged, with its reason
    train = tr.train_predictor

    def nan_curve(*a, **k):
        model = train(*a, **k)
        model.learning_curve[-1]["nll"] = float("nan")
        return model

    monkeypatch.setattr(ex, "train_predictor", nan_curve)
    store = runs.RunStore(tmp_path / ".runs", "k")
    cfg = ds.Config(**TINY10)
    with pytest.raises(tr.TrainingDiverged, match=r"Standard, seed 0: its learning curve holds "):
        ex.trained_predictor(tr.Method("Standard"), small, cfg, "rl", 0.5, 0, log=None, store=store)
    assert not list((tmp_path / ".runs").rglob("*.curve.json"))
    assert not list((tmp_path / ".runs").rglob("*.pt"))


# ---------------------------------------------------------------------------------------------
# A full disk: one line naming the file and the space, nothing half-written, the old file kept
# ---------------------------------------------------------------------------------------------


@pytest.fixture
def full_disk(tmp_path):
    """A 256 kB tmpfs (mounting needs root, as in CI): a disk that a few hundred kB fill."""
    import subprocess

    mnt = tmp_path / "small"
    mnt.mkdir()
    done = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(mnt)], capture_output=True
    )
    if done.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here (root only): {done.stderr.decode().strip()}")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "--lazy", str(mnt)], check=True)


def test_every_writer_survives_a_full_disk(full_disk):
    path = full_disk / "rl.json"
    path.write_text("the previous version")
    writers = {
        "write_atomic": lambda p: runs.write_atomic(p, "x" * 2**20),
        "save_atomic": lambda p: runs.save_atomic({"w": torch.zeros(2**18)}, p),
        "write_file_atomic": lambda p: runs.write_file_atomic(
            p, lambda tmp: pathlib.Path(tmp).write_bytes(b"x" * 2**20)
        ),
    }
    for name, write in writers.items():
        with pytest.raises(runs.DiskFull) as e:
            write(path)
        msg = str(e.value)
        assert (
            msg.startswith(f"{path}: cannot write it, No space left on device") and "\n" not in msg
        )
        assert "MB are free" in msg and "an earlier version of it, if any, is kept" in msg
        if name != "write_file_atomic":  # (a figure's size is not known before it is drawn)
            assert "it needs about 1.0 MB" in msg, msg
        assert sorted(p.name for p in full_disk.iterdir()) == ["rl.json"], name
        assert path.read_text() == "the previous version"


def test_the_data_cache_on_a_full_disk_is_one_line_and_leaves_nothing(full_disk):
    with pytest.raises(
        runs.DiskFull, match=r"cannot write it, No space left on device \(it needs about"
    ):
        data_synth.load_or_generate(600, seed=0, cache_dir=full_disk)
    assert list(full_disk.iterdir()) == []


def test_bench_json_on_a_full_disk_is_one_line(full_disk, monkeypatch, capsys):
    from lab import bench

    big = [dict(key=f"k{i}", note="x" * 1000) for i in range(1000)]
    monkeypatch.setattr(bench, "run", lambda *a, **k: dict(meta={}, figures=big))
    with pytest.raises(SystemExit) as e:
        bench.main(["--quick", "--json", str(full_disk / "b.json")])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "Traceback" not in err
    assert f"{full_disk / 'b.json'}: cannot write it, No space" in err.strip().splitlines()[-1]
    assert list(full_disk.iterdir()) == []


def test_set_overrides_config_fields_with_their_types():
    cfg = cli.config_with(
        ds.Config(), ["beta=2", "ilqr_iters=7", "u_upper=0.5,3", "plan_offsets=(-1, 0, 1, 2)"]
    )
    assert cfg.beta == 2.0 and isinstance(cfg.beta, float)
    assert cfg.ilqr_iters == 7 and isinstance(cfg.ilqr_iters, int)
    assert cfg.u_upper == (0.5, 3.0) and cfg.plan_offsets == (-1.0, 0.0, 1.0, 2.0)
    assert cli.config_with(ds.Config(), []) == ds.Config()
    for bad, culprit in (
        (["nope=1"], "nope"),
        (["beta"], "beta"),
        (["ilqr_iters=2.5"], "ilqr_iters"),
        (["beta=nan"], "beta"),
        (["u_upper=a,b"], "u_upper"),
    ):
        with pytest.raises(ValueError, match=culprit):
            cli.config_with(ds.Config(), bad)


def test_batches_with_inf_or_no_scenarios_are_refused(batch):
    cfg = ds.Config(**TINY)
    model = (
        ds.Predictor(cfg).double() if batch.agent_hist.dtype == torch.float64 else ds.Predictor(cfg)
    )
    import dataclasses

    method = tr.Method("DiffStack", losses=(1, 1, 1))
    for field in ("agent_hist", "others_hist", "ego_fut", "others_fut", "goal", "lanes"):
        bad = getattr(batch, field).clone()
        bad.view(-1)[0] = math.inf
        with pytest.raises(ValueError, match=field):
            tr.evaluate_stack(model, dataclasses.replace(batch, **{field: bad}), method, cfg)
        with pytest.raises(ValueError, match=field):
            tr.train_stack(
                model, dataclasses.replace(batch, **{field: bad}), method, cfg, epochs=0.1
            )
    with pytest.raises(ValueError, match="batch"):
        checks.check_batch(batch[:0], cfg, need_future=False)
    with pytest.raises(ValueError, match="batch"):
        checks.check_batch(batch[:0], cfg, need_future=True, stack=True)
    # the valid batch runs
    ds.run_stack(batch, model, method, cfg, train=True, step=0)


def test_bad_input_names_the_argument():
    """The data check where data enters a run (checks.check_batch, before training and
    evaluation)."""
    cfg = small_cfg()
    b = make_batch(4)
    checks.check_batch(b, cfg, need_future=True)  # the valid batch passes
    with pytest.raises(ValueError, match="agent_hist"):
        checks.check_batch(
            b.replace(agent_hist=b.agent_hist[:, 1:], agent_hist_mask=b.agent_hist_mask[:, 1:]),
            cfg,
            False,
        )
    with pytest.raises(ValueError, match="others_hist"):
        checks.check_batch(b.replace(others_hist=b.others_hist[:, :, :5]), cfg, False)
    with pytest.raises(ValueError, match="agent_fut"):
        checks.check_batch(b.replace(agent_fut=b.agent_fut[:, :4]), cfg, True)
    for name in ("agent_hist", "ego_hist", "others_hist", "agent_fut"):
        x = getattr(b, name).clone()
        x.view(-1)[5] = float("nan")
        with pytest.raises(ValueError, match=f"{name} contains NaN"):
            checks.check_batch(b.replace(**{name: x}), cfg, True)
    bad = b.agent_hist_mask.clone()
    bad[0, 4] = False  # a gap in the middle
    with pytest.raises(ValueError, match="agent_hist_mask"):
        checks.check_batch(b.replace(agent_hist_mask=bad), cfg, False)


@pytest.mark.parametrize("name", ["gpu", "cuda", "cuda:0", "meta", ""])
@pytest.mark.parametrize("cli", ["diffstack", "experiments"])
def test_a_device_this_machine_lacks_is_a_one_line_error(cli, name, capsys, monkeypatch, tmp_path):
    # the same on a machine with a GPU
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    work = []
    monkeypatch.setattr(lq, "quick", lambda *a, **k: work.append(1))
    monkeypatch.setattr(lab_data, "load_data", lambda *a, **k: work.append(1))
    monkeypatch.setattr(lt, "experiment_data", lambda *a, **k: work.append(1))
    if cli == "diffstack":
        err = cli_error(lq.main, ["--quick", "--device", name], capsys)
    else:
        err = cli_error(
            ex.main, ["--experiment", "rl", "--out", str(tmp_path), "--device", name], capsys
        )
    last = err.strip().splitlines()[-1]
    assert "argument --device" in last and (name in last if name else "torch device" in last), err
    assert "cuda" in last and not work  # it says what would do, and refused before any work


def test_device_reaches_the_work(capsys, monkeypatch, tmp_path):
    seen = {}
    monkeypatch.setattr(lq, "quick", lambda *a, **k: seen.update(quick=k["device"]))
    lq.main(["--quick"])
    lq.main(["--quick", "--device", "cpu"])
    monkeypatch.setattr(lt, "experiment_data", lambda *a, **k: "data")
    monkeypatch.setattr(lt, "run_experiment", lambda *a, **k: seen.update(experiment=k["device"]))
    ex.main(["--experiment", "rl", "--out", str(tmp_path), "--device", "cpu"])
    assert seen == {"quick": torch.device("cpu"), "experiment": torch.device("cpu")}


def test_device_arg_takes_the_devices_that_are_there(monkeypatch):
    import argparse

    assert cli.device_arg("cpu") == torch.device("cpu")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    assert cli.device_arg("cuda") == torch.device("cuda") and cli.device_arg(
        "cuda:1"
    ) == torch.device("cuda", 1)
    with pytest.raises(argparse.ArgumentTypeError, match="2 CUDA device"):
        cli.device_arg("cuda:2")


def test_existing_results_are_never_replaced_without_overwrite(tmp_path, capsys):
    (tmp_path / "rl.json").write_text('{"mine": 1}')
    err = cli_error(ex.main, ["--experiment", "rl", "--out", str(tmp_path), "--n", "10"], capsys)
    assert "rl.json" in err and "--overwrite" in err
    assert (tmp_path / "rl.json").read_text() == '{"mine": 1}'
    # 'all' also protects the report and the figures
    (tmp_path / "rl.json").unlink()
    (tmp_path / "closed_loop.png").write_bytes(b"png")
    with pytest.raises(ValueError, match="closed_loop.png"):
        lt.check_outputs(specs.EXPERIMENTS, tmp_path, overwrite=False)
    lt.check_outputs(specs.EXPERIMENTS, tmp_path, overwrite=True)  # --overwrite lets the run start
    # an unrelated file does not block another table
    lt.check_outputs(("rl",), tmp_path, overwrite=False)


def test_run_experiment_refuses_before_training(tmp_path, monkeypatch):
    (tmp_path / "il.md").write_text("# mine")
    monkeypatch.setattr(lt, "run_table", lambda *a, **k: pytest.fail("no work may start"))
    with pytest.raises(ValueError, match="il.md"):
        lt.run_experiment("il", None, ds.Config(), (0,), 1.0, tmp_path)


def test_unwritable_out_and_cache_are_refused_before_any_work(tmp_path, monkeypatch, capsys):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    monkeypatch.setattr(lab_data, "load_data", lambda *a, **k: pytest.fail("no data may be made"))
    err = cli_error(ex.main, ["--experiment", "rl", "--out", str(blocker / "out")], capsys)
    assert "--out" in err and "a_file" in err
    monkeypatch.chdir(tmp_path)
    (tmp_path / "data_cache").write_text("a file where the cache folder should be")
    err = cli_error(ex.main, ["--experiment", "rl", "--out", str(tmp_path / "out")], capsys)
    assert "data cache" in err
    monkeypatch.setattr(lq, "CACHE", tmp_path / "data_cache")  # (beside the module otherwise)
    err = cli_error(lq.main, ["--quick"], capsys)
    assert "data cache" in err


def test_one_run_per_output_folder_and_a_killed_runs_lock_is_taken_over(
    tmp_path, monkeypatch, capsys, lock_held_elsewhere
):
    """A second run on a folder another run holds is refused before any work, naming the holder
    (PID, command); when the holder is killed (SIGKILL), the next run takes the folder over."""
    out = tmp_path / "out"
    with lock_held_elsewhere(out, "the other run") as holder:
        monkeypatch.setattr(
            lab_data, "load_data", lambda *a, **k: pytest.fail("no data may be made")
        )
        for argv in (
            ["--experiment", "rl", "--out", str(out), "--n", "100"],
            ["--experiment", "rl", "--out", str(out)],
        ):
            err = cli_error(ex.main, argv, capsys)
            assert f"PID {holder.pid}" in err and "the other run" in err and str(out) in err
        (out / "rl.json").write_text("{}")
        # --render writes too
        err = cli_error(ex.main, ["--experiment", "rl", "--render", "--out", str(out)], capsys)
        assert f"PID {holder.pid}" in err
    with runs.folder_lock(out, "this run"):  # the killed run's lock, taken over
        assert json.loads((out / ".lock").read_text())["pid"] == os.getpid()


def test_a_run_holding_a_folder_may_hold_it_again_inside(tmp_path):
    # --out data_cache: the run holds its output folder, and making the data cache holds the same
    # folder again (spelled another way); another process is still refused while the run holds it
    out = tmp_path / "data_cache"
    with runs.folder_lock(out, "the run"):
        with runs.folder_lock(tmp_path / "x" / ".." / "data_cache", "the data cache"):
            assert json.loads((out / ".lock").read_text())["command"] == "the run"
        other = subprocess.run(
            [
                sys.executable,
                "-c",
                "import sys\nfrom lab import runs\n"
                "with runs.folder_lock(sys.argv[1], 'other'): pass",
                str(out),
            ],
            cwd=runs.ROOT,
            capture_output=True,
            text=True,
        )
        assert other.returncode != 0 and "another run is writing here" in other.stderr
    with runs.folder_lock(out, "the next run"):  # released when the outer block ended
        pass


def test_a_kill_mid_write_leaves_the_old_result(tmp_path, monkeypatch):
    path = tmp_path / "rl.json"
    path.write_text("old")

    def killed(src, dst):
        # the process dies between writing the temporary file and the rename
        raise KeyboardInterrupt

    monkeypatch.setattr(os, "replace", killed)
    with pytest.raises(KeyboardInterrupt):
        runs.write_atomic(path, json.dumps({"new": 1}))
    assert path.read_text() == "old"
    # and no half-written temporary file is left
    assert [p.name for p in tmp_path.iterdir()] == ["rl.json"]


def test_atomic_writes_give_results_the_usual_permissions(tmp_path, monkeypatch):
    """A result written through a temporary file (mkstemp: 0600) ends up readable as open() would
    have made it (0666 less the umask), so that others in a shared lab folder can read it; a plain
    file is the reference."""
    # the umask lab/runs.py read at import, here the common one
    monkeypatch.setattr(runs, "_UMASK", 0o022)
    old = os.umask(0o022)
    try:
        (tmp_path / "plain.txt").write_text("x")
        runs.write_atomic(tmp_path / "rl.json", "{}")
        runs.save_atomic({"w": 1}, tmp_path / "model.pt")
    finally:
        os.umask(old)

    def mode(name):
        return (tmp_path / name).stat().st_mode & 0o777

    assert mode("plain.txt") == 0o644
    assert mode("rl.json") == mode("model.pt") == mode("plain.txt")


@pytest.mark.parametrize(
    "argv, culprit",
    [
        (["--epochs", "nan"], "--epochs"),
        (["--epochs", "inf"], "--epochs"),
        (["--epochs", "0"], "--epochs"),
        (["--epochs", "1e9"], "--epochs"),
        (["--threads", "0"], "--threads"),
        (["--seeds", "0"], "--seeds"),
        (["--seeds", "1000"], "--seeds"),
        (["--n", "5"], "--n"),
        (["--n", "100000000"], "--n"),
        (["--n", "1e8"], "--n"),
        (["--set", "dt=0"], "dt"),
        (["--set", "horizon=-1"], "horizon"),
        (["--set", "dt=10"], "dt is the data's (0.5)"),
        (["--set", "dt=0.001"], "dt is the data's (0.5)"),
        (["--set", "horizon=7"], "horizon is the data's (6)"),
        (["--set", "hist_len=4"], "hist_len is the data's (8)"),
        (["--set", "nope=1"], "nope"),
    ],
)
def test_experiments_cli_numbers(argv, culprit, capsys, tmp_path):
    err = cli_error(ex.main, ["--experiment", "rl", "--out", str(tmp_path), *argv], capsys)
    assert culprit in err.splitlines()[-1]


@pytest.mark.slow
def test_the_command_lines_answer_a_broken_file_in_one_line(tmp_path, monkeypatch, capsys, batch):
    """--render of a truncated results file, and --quick over a broken shipped predictor: one line
    naming the file, exit code 2, no traceback."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "rl.json").write_text('{"meta": {"command"')  # cut off mid-write
    err = cli_error(ex.main, ["--experiment", "rl", "--render", "--out", str(out)], capsys)
    assert (
        f"{out / 'rl.json'}: not a results file" in err.splitlines()[-1] and "Traceback" not in err
    )
    monkeypatch.setattr(lq, "PRETRAINED", tmp_path / "pretrained")
    monkeypatch.setattr(lq, "CACHE", tmp_path / "data_cache")
    (tmp_path / "pretrained").mkdir()
    entry = {"method": "Standard", "seed": 0, "sha256": "0", "cpu_seconds": 1}
    prov = {
        "files": {"standard-seed0.pt": entry},
        "config": dataclasses.asdict(ds.Config()),  # the defaults: the file listed, but missing
        **dict(command="c", date="d", commit="x", epochs=1, seeds=[0], threads=1),
    }
    (tmp_path / "pretrained" / "provenance.json").write_text(json.dumps(prov))
    monkeypatch.setattr(lab_data, "load_data", lambda *a, **k: data_synth.make_dataset(120, seed=5))
    # (the rows before the shipped ones)
    monkeypatch.setattr(lq, "evaluate_stack", lambda *a, **k: {})
    monkeypatch.setattr(lq, "add_relative", lambda res, setting: res)
    monkeypatch.setattr(lq, "open_loop_table", lambda *a, **k: "")
    err = cli_error(lq.main, ["--quick"], capsys)
    assert "standard-seed0.pt: missing" in err.splitlines()[-1] and "Traceback" not in err


def test_a_corrupt_piece_of_the_resume_store_is_named_and_computed_again(tmp_path, capsys):
    store = runs.RunStore(tmp_path, "k")
    piece = lt.Piece("Standard", 0, None)
    store.save("rl", piece, {"ade": 1.0})
    assert store.has("rl", piece)
    store.path("rl", piece).write_text('{"table": "rl", "res')  # a disk error cut it
    assert not store.has("rl", piece)  # computed again
    assert f"{store.path('rl', piece)}: not a finished piece" in capsys.readouterr().err
    assert store.path("rl", piece).with_suffix(".corrupt").exists()


@pytest.mark.parametrize("rank", ["0", "1"])
def test_rank_variables_without_a_launcher_are_refused_in_one_line(rank, monkeypatch, capsys):
    launcher_env(monkeypatch, RANK=rank, WORLD_SIZE="2")
    monkeypatch.setattr(lab_data, "load_data", lambda *a, **k: pytest.fail("work started"))
    for main in (ex.main, lq.main):
        err = cli_error(main, ["--experiment", "rl"] if main is ex.main else ["--quick"], capsys)
        lines = err.strip().splitlines()
        assert (
            f"RANK={rank} WORLD_SIZE=2 are set, but no launcher started this process" in (lines[-1])
        )
        assert "Traceback" not in err


META = dict(command="python experiments.py --experiment rl", date="d", machine="m", seconds=1.0)


@pytest.mark.parametrize(
    "text, why",
    [
        ('{"meta": {}, "results": {}}', "meta.command is missing or not text"),
        (
            json.dumps(dict(meta=META, results={"Standard": [{"ade": None}]})),
            "results.Standard[0].ade is null",
        ),
        ('{"meta": {"command": "c"}, "results": {"Standard": [{"ade": NaN}]}}', "it holds NaN"),
        ("[" * 5000 + "]" * 5000, "nested too deeply"),
        ("\xff\xfe not text", "not a results file"),
        (
            json.dumps(dict(meta=dict(META, config={"no_such_field": 1}), results={})),
            "no_such_field",
        ),
    ],
)
def test_render_of_a_file_of_the_wrong_schema_is_one_line(text, why, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "rl.json").write_text(text, errors="surrogateescape")
    (out / "rl.md").write_text("kept")
    if "no_such_field" in text:  # the committed Table 1, its Config from a later version
        saved = json.loads(pathlib.Path("results/rl.json").read_text())
        saved["meta"]["config"]["no_such_field"] = 1
        (out / "rl.json").write_text(json.dumps(saved))
    err = cli_error(ex.main, ["--experiment", "rl", "--render", "--out", str(out)], capsys)
    last = err.strip().splitlines()[-1]
    assert str(out / "rl.json") in last and why in last, err
    assert "Traceback" not in err and (out / "rl.md").read_text() == "kept"


def test_render_all_checks_every_file_before_writing_any(tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    for name in specs.EXPERIMENTS:  # the committed results, the last one damaged
        (out / f"{name}.json").write_text((pathlib.Path("results") / f"{name}.json").read_text())
        (out / f"{name}.md").write_text("kept")
    (out / f"{specs.EXPERIMENTS[-1]}.json").write_text('{"meta": {}, "results": {}}')
    err = cli_error(ex.main, ["--experiment", "all", "--render", "--out", str(out)], capsys)
    assert f"{specs.EXPERIMENTS[-1]}.json: meta.command" in err.strip().splitlines()[-1]
    assert all((out / f"{n}.md").read_text() == "kept" for n in specs.EXPERIMENTS)


def test_damaged_pieces_models_and_provenance_are_named_and_set_aside(tmp_path, capsys):
    store = runs.RunStore(tmp_path, "k")
    piece = lt.Piece("Standard", 0)
    path = store.path("rl", piece)
    path.parent.mkdir(parents=True)
    path.write_text("[" * 100 + "]" * 100)
    assert not store.has("rl", piece) and path.with_suffix(".corrupt").exists()
    assert f"{path}: not a finished piece" in capsys.readouterr().err
    # a model file of the run store that is not a model: set aside, trained again
    model = tmp_path / "m.pt"
    model.write_bytes(b"not a model")
    assert ex.stored_predictor(model, ds.Config(**TINY), "cpu") is None
    assert (tmp_path / "m.pt.corrupt").exists() and not model.exists()
    assert "m.pt: not a stored predictor" in capsys.readouterr().err
    # a provenance entry without its sha256
    folder = tmp_path / "pretrained"
    folder.mkdir()
    prov = dict(
        files={"s0.pt": dict(method="Standard", seed=0)},
        config={},
        command="c",
        date="d",
        commit="x",
        epochs=1,
        seeds=[0],
        threads=1,
    )
    (folder / "provenance.json").write_text(json.dumps(prov))
    with pytest.raises(ValueError, match=r"provenance.json: not a provenance file .*sha256"):
        lq.load_pretrained(tr.Method("Standard"), ds.Config(), folder)


@pytest.mark.parametrize("damage", ["truncated", "missing", "edited"])
def test_a_pieces_tensors_and_fields_are_checked_before_they_are_trusted(damage, tmp_path, capsys):
    store = runs.RunStore(tmp_path, "k")
    piece = lt.Piece("Standard", 0, None)
    store.save("rl", piece, {"ade": 1.0, "hindsight": 2.0}, extra={"x": torch.ones(3)})
    path, pt = store.path("rl", piece), store.path("rl", piece).with_suffix(".pt")
    assert store.has("rl", piece) and store.load("rl", piece)[0]["hindsight"] == 2.0
    if damage == "truncated":
        pt.write_bytes(pt.read_bytes()[:40])
    elif damage == "missing":
        pt.unlink()
    else:  # the JSON edited to another shape
        path.write_text(path.read_text().replace('"hindsight"', '"other"'))
    assert not store.has("rl", piece)  # set aside, computed again
    assert f"{path}: not a finished piece" in capsys.readouterr().err
    assert path.with_suffix(".corrupt").exists() and not path.exists() and not pt.exists()


def test_a_run_stopped_among_its_tables_files_is_resumed_by_the_same_command(
    small, tmp_path, monkeypatch
):
    cfg, write = ds.Config(**TINY10), runs.write_atomic

    def ctrl_c_after_the_json(path, text):
        if str(path).endswith("il.md"):
            raise KeyboardInterrupt
        write(path, text)

    monkeypatch.setattr(runs, "write_atomic", ctrl_c_after_the_json)
    with pytest.raises(KeyboardInterrupt):
        lt.run_experiment("il", small, cfg, (0,), 0.5, tmp_path, "test", log=None)
    assert (tmp_path / "il.json").exists() and not (tmp_path / "il.md").exists()
    monkeypatch.setattr(runs, "write_atomic", write)
    lt.run_experiment("il", small, cfg, (0,), 0.5, tmp_path, "test", log=None)  # not refused
    assert (tmp_path / "il.md").exists() and not (tmp_path / ".writing.json").exists()
    with pytest.raises(runs.OutputRefused, match="exist and are kept"):  # now a finished run's
        lt.run_experiment("il", small, cfg, (0,), 0.5, tmp_path, "test", log=None)


def test_paths_that_are_not_utf8_and_lock_files_that_are_symlinks_are_refused(tmp_path):
    bad = tmp_path / os.fsdecode(b"out-\xff")
    with pytest.raises(runs.OutputRefused, match=r"not a UTF-8 name") as e:
        lt.check_outputs(("il",), bad, False)
    assert len(str(e.value).splitlines()) == 1 and not bad.exists()
    (tmp_path / "victim").write_text("precious")
    (tmp_path / "held").mkdir()
    (tmp_path / "held" / ".lock").symlink_to(tmp_path / "victim")
    with pytest.raises(runs.OutputRefused, match="cannot hold it"):
        with runs.folder_lock(tmp_path / "held", "test"):
            pass
    assert (tmp_path / "victim").read_text() == "precious"


def test_a_tuple_set_is_bounded_in_length():
    with pytest.raises(ValueError, match="at most 64 values") as e:
        cli.config_with(ds.Config(), ["plan_accels=" + ",".join(["1"] * 20000)])
    assert len(str(e.value)) < 300


def test_a_tampered_data_cache_is_refused_in_one_line_without_torchs_advice(tmp_path):
    class Payload:
        def __reduce__(self):
            return (os.getcwd, ())

    path = data_synth._cache_path(200, 0, data_synth.SynthConfig(), tmp_path)[0]
    path.write_bytes(__import__("pickle").dumps(Payload()))
    with pytest.raises(ValueError) as e:
        lab_data.load_data(None, 200, 0, tmp_path)
    assert str(path) in str(e.value) and "\n" not in str(e.value)
    assert "weights_only" not in str(e.value) and "objects other than tensors" in str(e.value)


def test_a_killed_writers_temporary_is_removed_by_the_next_writer_but_a_live_ones_kept(tmp_path):
    """kill -9 inside write_file_atomic leaves its temporary beside the target; the next atomic
    write into that folder (of any file) removes it, but never the temporary of a writer still
    writing, which then finishes."""
    code = (
        "import sys\nfrom lab import runs\n"
        "def write(tmp):\n    open(tmp, 'w').write('whole')\n"
        "    print('writing', flush=True)\n    sys.stdin.readline()\n"
        "runs.write_file_atomic(sys.argv[1], write)\n"
    )

    def writer(name):
        run = subprocess.Popen(
            [sys.executable, "-c", code, str(tmp_path / name)],
            cwd=runs.ROOT,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        assert run.stdout.readline() == "writing\n"
        return run

    killed, live = writer("a.json"), writer("b.json")
    (live_tmp,) = set(tmp_path.glob(".b.json.*")) & set(tmp_path.glob(".*.tmp"))
    killed.kill()
    killed.wait()
    assert len(list(tmp_path.glob(".*.tmp"))) == 2
    runs.write_atomic(tmp_path / "c.json", "{}")  # another file of that folder
    assert list(tmp_path.glob(".*.tmp")) == [live_tmp] and not (tmp_path / "a.json").exists()
    live.communicate("\n", timeout=60)
    assert live.returncode == 0 and (tmp_path / "b.json").read_text() == "whole"
    assert not list(tmp_path.glob(".*.tmp"))
