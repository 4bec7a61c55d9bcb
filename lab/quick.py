"""`python diffstack.py --quick` and `--pretrain` (diffstack.py's __main__ hands over here): the
predictors shipped in pretrained/ evaluated beside No prediction and GT prediction, two trained
live, and the verdicts computed from the numbers; training the shipped predictors; their command
line."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import pathlib
import pickle
import statistics
import sys
import time

import torch

import data_synth
from diffstack import Config, Predictor
from lab.cli import add_shared_options, check_writable, config_with, machine
from lab.runs import (
    command_line,
    default_threads,
    folder_lock,
    git_commit,
    load_json,
    one_line,
    ranks,
    save_atomic,
    in_workers,
    write_atomic,
)
from lab.stats import claim_verdict, p_value, paired_difference, plus_minus
from lab.report import open_loop_table
from specs import FOUR_METHODS
from experiments import (
    VAL_N,
    add_relative,
    compare_methods,
    experiment_data,
)
from train import (
    NO_PREDICTION,
    Method,
    evaluate_stack,
    train_predictor,
)


# the tables' data; the live runs train on a part of it, and everything is evaluated on the first
# 1,500 samples of the tables' common validation set (all 10,000: Table 1)
QUICK = dict(n=10000, live_train=2560, epochs=8.0, val=1500)


QUICK_METHODS = FOUR_METHODS


# predictors trained at the paper's length, shipped with the code (pretrain, load_pretrained)
PRETRAINED = "pretrained"


# = Table 1's five seeds at the tables' length (experiments.py)
PRETRAIN = dict(n=10000, epochs=40.0, seeds=(0, 1, 2, 3, 4))


def load_pretrained(method: Method, cfg: Config, folder=PRETRAINED, device="cpu"):
    """The predictors of `method` that `pretrain` wrote, one per seed, each checked against the
    provenance (the file's sha256, the Config it was trained with) and loaded with
    weights_only=True. Returns ({seed: model}, provenance) or (None, why not)."""
    folder = pathlib.Path(folder)
    prov_path = folder / "provenance.json"
    if not prov_path.exists():
        return None, f"no {prov_path} (python diffstack.py --pretrain makes it)"
    prov, entries, trained_with = _shipped_entries(prov_path, method)
    if not entries:
        return None, f"{prov_path} lists no {method.name} predictor"
    if trained_with != dataclasses.asdict(cfg):
        changed = sorted(k for k, v in dataclasses.asdict(cfg).items() if trained_with.get(k) != v)
        return (
            None,
            f"{folder}/ was trained with the default Config, not with {', '.join(changed)} as set "
            "here",
        )
    models = {
        seed: _load_shipped(folder / name, entry["sha256"], prov_path, cfg).to(device)
        for seed, name, entry in entries
    }
    missing = [
        f for f in ("command", "date", "commit", "epochs", "seeds", "threads") if f not in prov
    ]
    if missing or not all(isinstance(e.get("cpu_seconds"), (int, float)) for _, _, e in entries):
        raise ValueError(
            f"{prov_path}: not a provenance file of python diffstack.py --pretrain (no "
            f"{', '.join(missing) or 'cpu_seconds of a file'})"
        )
    return models, prov


def _shipped_entries(prov_path, method: Method):
    """(provenance, [(seed, file name, entry)] of the method's files by seed, the Config they were
    trained with), every field read here checked before any is used: ValueError naming the file."""
    try:
        prov = load_json(prov_path, "a provenance file of python diffstack.py --pretrain")
        entries = sorted(
            (e["seed"], name, e) for name, e in prov["files"].items() if e["method"] == method.name
        )
        for _, name, e in entries:
            if not isinstance(e.get("sha256"), str) or not isinstance(e["seed"], int):
                raise ValueError(f"files.{name}: no sha256 or seed")
        trained_with = {
            k: tuple(v) if isinstance(v, list) else v for k, v in prov["config"].items()
        }
    except (ValueError, KeyError, TypeError) as e:
        raise ValueError(
            f"{prov_path}: not a provenance file of python diffstack.py --pretrain ({e})"
        ) from None
    return prov, entries, trained_with


def _load_shipped(path, sha256: str, prov_path, cfg: Config) -> Predictor:
    """The predictor in path, on the CPU, once its sha256 is the provenance's; ValueError naming
    the file otherwise, or when it does not load as a predictor of this version."""
    if not path.exists() or hashlib.sha256(path.read_bytes()).hexdigest() != sha256:
        raise ValueError(
            f"{path}: missing, or not the file {prov_path} describes (sha256 differs); "
            f"re-make it with python diffstack.py --pretrain --overwrite"
        )
    model = Predictor(cfg)
    try:
        model.load_state_dict(torch.load(path, map_location="cpu", weights_only=True))
    except (RuntimeError, ValueError, OSError, EOFError, pickle.UnpicklingError) as e:
        raise ValueError(
            f"{path}: not a predictor of this version ({' '.join(str(e).split())[:200]}); "
            "re-make it with python diffstack.py --pretrain --overwrite"
        ) from None
    return model


def _slug(name: str) -> str:
    return name.lower().replace(" ", "-")


def _pretrain_one(
    method: Method, seed: int, n: int, epochs, cfg: Config, cache_dir, threads: int, val: int
):
    """One predictor of `pretrain` (a worker process when --jobs > 1): trained as the tables train
    it, on `threads` threads, and evaluated on the validation set. Returns (state_dict, metrics, CPU
    seconds): CPU time, not the wall clock, so that what it records does not depend on what else the
    machine was doing."""

    torch.set_num_threads(threads)
    t0 = time.process_time()
    # its draw: as the tables train it
    data = experiment_data(n, range(seed + 1), val, cache_dir, log=None)
    model = train_predictor(method, data, cfg, "rl", epochs, seed, log=None)
    metrics = evaluate_stack(model, data.val, method, cfg, "rl")
    return (
        model.state_dict(),
        {k: metrics[k] for k in ("ade", "nll", "hindsight")},
        time.process_time() - t0,
    )


def pretrain(
    out=PRETRAINED,
    threads=1,
    n=PRETRAIN["n"],
    epochs=PRETRAIN["epochs"],
    seeds=PRETRAIN["seeds"],
    jobs=1,
    cfg=None,
    cache_dir="data_cache",
    overwrite=False,
    log=print,
    command="python diffstack.py --pretrain",
    val=None,
):
    """`--pretrain`: train Standard and DiffStack (RL) on the tables' synthetic data for the tables'
    40 epochs (the paper trains 20; on this data Standard's ADE was still falling at 20, README
    "Results"), one predictor per seed, and write their weights to out/<name>-seed<seed>.pt with
    out/provenance.json (the command, date, commit, data, config, each file's sha256 and validation
    metrics). On one thread each, these are Table 1's predictors of the same seeds to the bit (the
    tables train each seed on one thread). `jobs` worker processes train them side by side. --quick
    evaluates them (load_pretrained). About 8 minutes a predictor on one core."""
    out, log = pathlib.Path(out), log or (lambda *_: None)
    cfg = cfg or Config()
    seeds = tuple(seeds)
    val = val or VAL_N
    learned = [m for m in QUICK_METHODS if m.predictor == "learned"]
    work = [(m, seed, out / f"{_slug(m.name)}-seed{seed}.pt") for seed in seeds for m in learned]
    if not overwrite and any(f.exists() for f in [w[2] for w in work] + [out / "provenance.json"]):
        raise ValueError(
            f"--pretrain: {out}/ holds pre-trained predictors already; pass --overwrite to replace "
            "them"
        )
    check_writable(out, f"the pre-trained predictors' folder ({out})")
    with folder_lock(out, command):  # one --pretrain into a folder at a time
        # made (or checked) once, here, before the workers read it
        experiment_data(n, seeds, val, cache_dir)
        about = dict(
            command=command,
            date=time.strftime("%Y-%m-%d"),
            n=n,
            val=val,
            epochs=epochs,
            seeds=list(seeds),
            setting="rl",
            threads=threads,
            torch=torch.__version__,
            machine=machine(),
            commit=git_commit(),
            config=dataclasses.asdict(cfg),
            files={},
        )
        paths = {(m.name, seed): path for m, seed, path in work}

        def finished(unit, result):  # one predictor trained: its file and its provenance entry
            (m, seed, *_), (state, metrics, seconds) = unit, result
            path = paths[m.name, seed]
            save_atomic(state, path)
            about["files"][path.name] = dict(
                method=m.name,
                seed=seed,
                sha256=hashlib.sha256(path.read_bytes()).hexdigest(),
                cpu_seconds=round(seconds),
                **metrics,
            )
            log(f"{path}: {m.name}, seed {seed}: ADE {metrics['ade']:.3f} m ({seconds:.0f} CPU s)")

        units = [(m, seed, n, epochs, cfg, cache_dir, threads, val) for m, seed, _ in work]
        if jobs > 1:
            in_workers(_pretrain_one, units, jobs, finished, out)
        for unit in units if jobs == 1 else ():
            finished(unit, _pretrain_one(*unit))
        write_atomic(out / "provenance.json", json.dumps(about, indent=1))
        return about


def _seed_list(seeds) -> str:
    seeds = list(seeds)
    return (
        f"seeds {seeds[0]}-{seeds[-1]}"
        if len(seeds) > 1 and seeds == list(range(seeds[0], seeds[-1] + 1))
        else f"seed{'s' * (len(seeds) > 1)} {', '.join(map(str, seeds))}"
    )


def shipped_rows(val, cfg: Config, pretrained, device, log) -> tuple:
    """--quick's first table: No prediction, the shipped predictors (one run per seed) and GT
    prediction evaluated on `val`, with the planning metrics relative to No prediction; and the
    shipped predictors' provenance (None when none could be loaded: their rows are left out)."""
    res = {}
    prov = None
    for m in QUICK_METHODS:
        if m.predictor != "learned":
            res[m.name] = [evaluate_stack(None, val, m, cfg, "rl", device=device)]
            continue
        models, about = load_pretrained(m, cfg, pretrained, device)
        if models is None:
            log(f"{m.name}: no pre-trained predictor ({about}): its row is left out")
            continue
        prov = about
        # one run per seed
        res[f"{m.name} ({prov['epochs']:g} epochs)"] = [
            evaluate_stack(model, val, m, cfg, "rl", device=device) for model in models.values()
        ]
    return add_relative(res, "rl"), prov


def quick(
    threads=2,
    n=None,
    epochs=None,
    cfg=None,
    cache_dir="data_cache",
    log=print,
    device="cpu",
    pretrained=PRETRAINED,
):
    """`--quick`, about a minute on 2 cores: Table 1's story on the tables' synthetic validation
    data. Standard and DiffStack trained for the tables' 40 epochs (shipped in pretrained/:
    Table 1's five seeds, so the rows are that table's, mean ± s.e.) beside No prediction and GT
    prediction; then both trained live for a few epochs so that the losses are seen to fall; then
    the verdicts computed from the numbers (quick_verdicts)."""

    torch.set_num_threads(threads)
    cfg = cfg or Config()
    n = n or QUICK["n"]
    epochs = epochs or QUICK["epochs"]
    learned = [m for m in QUICK_METHODS if m.predictor == "learned"]
    log(
        f"DiffStack --quick: the shipped {PRETRAIN['epochs']:g}-epoch predictors ({pretrained}/) "
        f"beside No prediction and GT prediction, then Standard and DiffStack trained"
        f" for {epochs:g} epochs."
    )
    t0 = time.time()
    data = experiment_data(n, (0,), cache_dir=cache_dir, log=log)
    data = data._replace(val=data.val[: QUICK["val"]])
    log(
        f"data: {len(data.train)} training scenarios (seed 0's draw), the first {len(data.val)} of "
        f"the tables' {VAL_N:,} validation scenarios ({time.time() - t0:.0f}s)"
    )
    res, prov = shipped_rows(data.val, cfg, pretrained, device, log)
    if prov is not None:
        log(
            f"\nThe shipped predictors: `{prov['command']}` ({prov['date']}, commit "
            f"{prov['commit']}, {prov['epochs']:g} epochs, {_seed_list(prov['seeds'])}, "
            f"{prov['threads']} thread each), on the {len(data.val)} validation scenarios; mean ± "
            "s.e. over the seeds:"
        )
    log("\n" + open_loop_table(res, "rl"))
    # live: a few epochs on part of the training data, to watch the three losses fall
    part = data_synth.Dataset(data.train[: QUICK["live_train"]], data.val, None)
    took = (
        " (the shipped rows above took "
        f"{sum(f['cpu_seconds'] for f in prov['files'].values()) / 60:.0f} minutes of CPU to "
        f"train, {prov['threads']} thread each)"
        if prov is not None
        else ""
    )
    log(f"\nTrained now, {epochs:g} epochs on {len(part.train)} scenarios{took}:")
    live = compare_methods(
        part,
        cfg,
        "rl",
        (NO_PREDICTION, *learned),
        seeds=(0,),
        epochs=epochs,
        log=log,
        device=device,
    )
    log(
        "\n"
        + open_loop_table(
            {f"{k} ({epochs:g} epochs)" if k != "No prediction" else k: v for k, v in live.items()},
            "rl",
        )
    )
    log("\n" + "\n".join(quick_verdicts(res)))
    log(f"\ntotal {time.time() - t0:.0f}s")
    return res, live


def quick_verdicts(res: dict) -> list:
    """The verdicts --quick prints under its table, each computed from its numbers: the order of
    the hindsight costs against the paper's, and DiffStack against Standard by the paired t-test
    over the shipped seeds. What they mean is in docs/results.md."""

    def shipped(name):  # a shipped predictor's rel_hindsight per seed (its rows start so)
        return next(
            ([r["rel_hindsight"] for r in runs] for k, runs in res.items() if k.startswith(name)),
            None,
        )

    std, dif = shipped("Standard ("), shipped("DiffStack (")
    if std is None or dif is None:
        return []
    h = {
        "GT": res["GT prediction"][0]["rel_hindsight"],
        "DiffStack": statistics.fmean(dif),
        "Standard": statistics.fmean(std),
        "No prediction": res["No prediction"][0]["rel_hindsight"],
    }
    order = " < ".join(sorted(h, key=h.get))
    paper = "GT < DiffStack < Standard < No prediction"
    same = "the paper's order" if order == paper else f"NOT the paper's order ({paper})"
    p = paired_difference(std, dif)
    return [
        f"Hindsight cost: {order}: {same} (its Table 1).",
        f"DiffStack vs Standard, hindsight cost (x1e-2), paired over the {p.n} shipped seeds: "
        f"{plus_minus('{:.2f}', p.mean, p.se)} ({p_value(p.p)}, {p.better} of {p.n} seeds better): "
        f"{claim_verdict(p)}; over Table 1's 10 seeds: results/rl.md.",
    ]


def parser():
    """diffstack.py's command line: --quick, --pretrain."""
    import argparse

    ap = argparse.ArgumentParser(
        description="DiffStack (CoRL 2022), the readable reference: the method, and a quick run "
        "of it.",
        epilog="The paper's tables: python experiments.py --experiment NAME. Benchmarks: python "
        "-m lab.bench.",
    )
    ap.add_argument(
        "--quick",
        action="store_true",
        help=f"Table 1's story in about a minute: the shipped {PRETRAIN['epochs']:g}-epoch "
        "Standard and DiffStack beside No prediction and GT prediction, then both trained live "
        "for a few epochs",
    )
    ap.add_argument(
        "--pretrain",
        action="store_true",
        help=f"train the predictors --quick ships (Standard and DiffStack, {PRETRAIN['epochs']:g} "
        f"epochs, {_seed_list(PRETRAIN['seeds'])}, one thread each: Table 1's) into {PRETRAINED}/, "
        "~40 min on 2 cores",
    )
    add_shared_options(
        ap,
        jobs="--pretrain: worker processes training side by side, one thread each (default: the "
        "machine's cores)",
        overwrite=f"--pretrain: replace the predictors in {PRETRAINED}/",
        threads="torch threads (default: 1 for --pretrain, as the tables train; for --quick 2, or "
        "1 when other work keeps a core busy; at most 256)",
        device="where training and evaluation run: cpu (default), cuda, cuda:N or mps; the data "
        "is made on the CPU",
        set="override a Config field, e.g. --set beta=2 --set u_upper=0.7,4 (repeatable)",
    )
    return ap


def main(argv=None):
    ap = parser()
    argv = sys.argv[1:] if argv is None else list(argv)
    for moved, now in (
        ("--experiment", "python experiments.py --experiment NAME"),
        ("--bench", "python -m lab.bench"),
    ):
        if any(a == moved or a.startswith(moved + "=") for a in argv):
            ap.error(f"{moved} moved: {now}")
    rank, world, misuse = ranks()
    if misuse:
        ap.error(misuse)
    if world > 1:  # one line from rank 0; the others exit alike
        if rank != 0:
            sys.exit(2)
        ap.error(
            "--quick and --pretrain run in one process, not under torchrun (it would run them "
            f"{world} times); the tables train with DistributedDataParallel: torchrun "
            "--nproc_per_node N experiments.py --experiment NAME"
        )
    args = ap.parse_args(argv)
    if args.quick == args.pretrain:
        ap.error(
            "choose --quick or --pretrain (the paper's tables: python experiments.py --experiment "
            "NAME)"
        )
    if args.jobs is not None and not args.pretrain:
        ap.error("--jobs is an option of --pretrain (the tables': python experiments.py --jobs N)")
    # every refusal, of the arguments or of a file (the shipped predictors, a cache), is one line
    with one_line(
        ap,
        "the predictors written so far stay in pretrained/; --pretrain --overwrite trains them "
        "all again"
        if args.pretrain
        else "nothing half-written is left",
    ):
        cfg = config_with(Config(), args.set)
        check_writable("data_cache", "the data cache (./data_cache)")
        if args.pretrain:
            return pretrain(
                threads=args.threads or 1,
                jobs=args.jobs or os.cpu_count() or 1,
                cfg=cfg,
                overwrite=args.overwrite,
                command=command_line("python diffstack.py", argv),
            )
        threads, why = (args.threads, "--threads") if args.threads else default_threads()
        print(f"torch threads: {threads} ({why}; --threads N to choose)")
        return quick(threads, cfg=cfg, device=args.device)
