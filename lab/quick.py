"""`python diffstack.py --quick` and `--pretrain` (diffstack.py's __main__ hands over here): the
shipped predictors beside the baselines, two trained live, the verdicts; and training them."""

from __future__ import annotations

import argparse
import dataclasses
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
from lab.cli import add_shared_options, check_writable, config_with, machine, torch_threads
from lab.runs import command_line, git_commit, in_workers, load_json, one_line, ranks
from lab.runs import ROOT, save_atomic, sha256_of, write_atomic, write_folder
from lab.report import claim_line, open_loop_table
from specs import FOUR_METHODS, TABLE1
from experiments import VAL_N, add_relative, compare_methods, experiment_data
from train import NO_PREDICTION, Method, evaluate_stack, train_predictor

# --quick: the tables' data; the live runs on part of it; evaluated on 1,500 validation samples
QUICK = dict(n=10000, live_train=2560, epochs=8.0, val=1500)
# beside the module, wherever it runs from: --pretrain's predictors (Table 1's), the data cache
PRETRAINED, CACHE = ROOT / "pretrained", ROOT / "data_cache"
PRETRAIN = dict(n=10000, epochs=40.0, seeds=(0, 1, 2, 3, 4))
LEARNED = [m for m in FOUR_METHODS if m.predictor == "learned"]  # Standard, DiffStack
AGAIN = "re-make it with python diffstack.py --pretrain --overwrite"


def load_pretrained(method: Method, cfg: Config, folder=PRETRAINED, device="cpu"):
    """({seed: model}, provenance) of `method` from `pretrain`'s folder, every field and sha256
    checked; (None, why) where they do not fit cfg."""
    folder = pathlib.Path(folder)
    prov_path = folder / "provenance.json"
    if not prov_path.exists():
        return None, f"no {prov_path} (python diffstack.py --pretrain makes it)"
    what = "a provenance file of python diffstack.py --pretrain"
    prov = load_json(prov_path, what)
    try:
        files = {n: e for n, e in prov["files"].items() if e["method"] == method.name}
        shas = {n: (e["seed"], e["sha256"]) for n, e in files.items()}
        trained_with = {
            k: tuple(v) if isinstance(v, list) else v for k, v in prov["config"].items()
        }
        about = {f: prov[f] for f in ("command", "date", "commit", "epochs", "seeds", "threads")}
        about["cpu_minutes"] = sum(e["cpu_seconds"] for e in prov["files"].values()) / 60
    except (KeyError, TypeError, AttributeError) as e:
        raise ValueError(f"{prov_path}: not {what} ({type(e).__name__}: {e})") from None
    if not files:
        return None, f"{prov_path} lists no {method.name} predictor"
    changed = sorted(k for k, v in dataclasses.asdict(cfg).items() if trained_with.get(k) != v)
    if changed:
        return None, f"{folder}/ was trained with the default Config, not with {', '.join(changed)}"
    models = {}
    for name, (seed, sha256) in sorted(shas.items(), key=lambda item: item[1][0]):
        path = folder / name
        if not path.exists() or sha256_of(path) != sha256:
            why = f"missing, or not the file {prov_path} describes (sha256 differs)"
            raise ValueError(f"{path}: {why}; {AGAIN}")
        models[seed] = Predictor(cfg)
        try:
            models[seed].load_state_dict(torch.load(path, map_location="cpu", weights_only=True))
        except (RuntimeError, ValueError, OSError, EOFError, pickle.UnpicklingError) as e:
            why = " ".join(str(e).split())[:200]
            raise ValueError(f"{path}: not a predictor of this version ({why}); {AGAIN}") from None
        models[seed].to(device)
    return models, about


def _pretrain_one(m: Method, seed: int, n: int, epochs, cfg: Config, cache_dir, threads, val):
    """One predictor of `pretrain`, trained as the tables train it: (state_dict, validation metrics,
    CPU seconds: the wall clock depends on the load)."""
    torch.set_num_threads(threads)
    t0 = time.process_time()
    data = experiment_data(n, range(seed + 1), val, cache_dir, log=None)  # its draw, as the tables'
    model = train_predictor(m, data, cfg, "rl", epochs, seed, log=None)
    metrics = evaluate_stack(model, data.val, m, cfg, "rl")
    metrics = {k: metrics[k] for k in ("ade", "nll", "hindsight")}
    return model.state_dict(), metrics, time.process_time() - t0


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
    """`--pretrain`: Standard and DiffStack (RL) trained as Table 1's seeds, bit for bit on one
    thread (40 epochs: after the paper's 20 Standard's ADE still falls), into out/."""
    out, log, cfg, val = pathlib.Path(out), log or (lambda *_: None), cfg or Config(), val or VAL_N
    names = {(m.name, s): f"{m.name.lower()}-seed{s}.pt" for s in seeds for m in LEARNED}
    about = dict(command=command, date=time.strftime("%Y-%m-%d"), n=n, val=val, epochs=epochs)
    about.update(seeds=list(seeds), setting="rl", threads=threads, torch=torch.__version__)
    about.update(machine=machine(), commit=git_commit(), config=dataclasses.asdict(cfg), files={})

    def write(tmp):  # every predictor and the provenance into tmp, renamed onto out when done
        experiment_data(n, seeds, val, cache_dir)  # made here, before the workers read it

        def finished(unit, result):  # one predictor trained: its file and its provenance entry
            (m, seed, *_), (state, metrics, seconds) = unit, result
            path = tmp / names[m.name, seed]
            save_atomic(state, path)
            entry = dict(method=m.name, seed=seed, sha256=sha256_of(path))
            about["files"][path.name] = dict(entry, cpu_seconds=round(seconds), **metrics)
            ade = f"ADE {metrics['ade']:.3f} m ({seconds:.0f} CPU s)"
            log(f"{out}/{path.name}: {m.name}, seed {seed}: {ade}")

        units = [(m, s, n, epochs, cfg, cache_dir, threads, val) for s in seeds for m in LEARNED]
        if jobs > 1:
            in_workers(_pretrain_one, units, jobs, finished, out)
        for unit in units if jobs == 1 else ():
            finished(unit, _pretrain_one(*unit))
        write_atomic(tmp / "provenance.json", json.dumps(about, indent=1))

    files = [out / f for f in [*names.values(), "provenance.json"]]
    write_folder(out, write, "--pretrain", files, overwrite)  # whole, or not at all
    return about


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
    """`--quick`, a minute on 2 cores: the shipped Standard and DiffStack beside No and GT
    prediction, both trained live for a few epochs, the verdicts: (results, live results)."""
    torch.set_num_threads(threads)
    cfg, n, epochs = cfg or Config(), n or QUICK["n"], epochs or QUICK["epochs"]
    log(
        f"DiffStack --quick: the shipped {PRETRAIN['epochs']:g}-epoch predictors ({pretrained}/) "
        f"beside No prediction and GT prediction, then two trained for {epochs:g} epochs."
    )
    t0 = time.time()
    data = experiment_data(n, (0,), cache_dir=cache_dir, log=log)
    data = data._replace(val=data.val[: QUICK["val"]])
    log(f"data: {len(data.train)} training scenarios (seed 0's draw), {len(data.val)} validation")
    res, prov = {}, None
    for m in FOUR_METHODS:  # the shipped ones one run per seed, the baselines one run
        if m.predictor != "learned":
            res[m.name] = [evaluate_stack(None, data.val, m, cfg, "rl", device=device)]
            continue
        models, prov_or_why = load_pretrained(m, cfg, pretrained, device)
        if models is None:
            log(f"{m.name}: no pre-trained predictor ({prov_or_why}): its row is left out")
            continue
        prov = prov_or_why
        res[f"{m.name} ({prov['epochs']:g} epochs)"] = [
            evaluate_stack(model, data.val, m, cfg, "rl", device=device)
            for model in models.values()
        ]
    res = add_relative(res, "rl")
    took = ""
    if prov is not None:
        log(
            f"\nThe shipped predictors: `{prov['command']}` ({prov['date']}, commit "
            f"{prov['commit']}, {prov['epochs']:g} epochs, seeds {prov['seeds']}, "
            f"{prov['threads']} thread each); mean ± s.e. over the seeds:"
        )
        took = f" (the shipped rows took {prov['cpu_minutes']:.0f} minutes of CPU)"
    log("\n" + open_loop_table(res, "rl"))
    part = data_synth.Dataset(data.train[: QUICK["live_train"]], data.val, None)
    log(f"\nTrained now, {epochs:g} epochs on {len(part.train)} scenarios{took}:")
    methods = (NO_PREDICTION, *LEARNED)
    live = compare_methods(part, cfg, "rl", methods, (0,), epochs, log=log, device=device)
    rows = {f"{k} ({epochs:g} epochs)" if k != "No prediction" else k: v for k, v in live.items()}
    log("\n" + open_loop_table(rows, "rl"))
    log("\n" + "\n".join(quick_verdicts(res)))
    log(f"\ntotal {time.time() - t0:.0f}s")
    return res, live


def quick_verdicts(res: dict) -> list:
    """The order of the hindsight costs against the paper's, and Table 1's claim (DiffStack vs
    Standard) on the shipped seeds; what they mean: docs/results.md."""
    rows = {k.split(" (")[0].replace("GT prediction", "GT"): v for k, v in res.items()}
    if not {"Standard", "DiffStack"} <= rows.keys():
        return []
    h = {k: statistics.fmean(r["rel_hindsight"] for r in v) for k, v in rows.items()}
    order = " < ".join(sorted(h, key=h.get))
    paper = "GT < DiffStack < Standard < No prediction"
    same = "the paper's order" if order == paper else f"NOT the paper's order ({paper})"
    claim = TABLE1.claims[0]  # DiffStack vs Standard, hindsight cost
    return [
        f"Hindsight cost: {order}: {same} (its Table 1).",
        f"{claim_line(claim, TABLE1, rows)} (the shipped seeds; Table 1's 10: results/rl.md)",
    ]


def parser():
    """diffstack.py's command line: --quick, --pretrain."""
    ap = argparse.ArgumentParser(
        description="DiffStack (CoRL 2022), the readable reference: the method, and a quick run.",
        epilog="The paper's tables: python experiments.py. Benchmarks: python -m lab.bench.",
    )
    ap.add_argument("--quick", action="store_true", help="Table 1's story in about a minute")
    pretrain_help = f"train the predictors --quick ships into {PRETRAINED}/ (~40 min on 2 cores)"
    ap.add_argument("--pretrain", action="store_true", help=pretrain_help)
    add_shared_options(
        ap,
        jobs="--pretrain: worker processes of one thread (default: the machine's cores)",
        overwrite=f"--pretrain: replace the predictors in {PRETRAINED}/",
        threads="torch threads (default: 2 for --quick, 1 for --pretrain)",
        device="cpu (default), cuda, cuda:N or mps",
        set="override a Config field, e.g. --set beta=2 --set u_upper=0.7,4 (repeatable)",
    )
    return ap


def main(argv=None):
    ap = parser()
    argv = sys.argv[1:] if argv is None else list(argv)
    rank, world, misuse = ranks()
    if misuse:
        ap.error(misuse)
    if world > 1:  # one line from rank 0; the others exit alike
        if rank != 0:
            sys.exit(2)
        ap.error(f"--quick and --pretrain are not under torchrun (it would run them {world} times)")
    args = ap.parse_args(argv)
    if args.quick == args.pretrain:
        ap.error("choose --quick or --pretrain (the paper's tables: python experiments.py)")
    if args.jobs is not None and not args.pretrain:
        ap.error("--jobs is an option of --pretrain")
    kept = f"{PRETRAINED} is as it was" if args.pretrain else "nothing half-written is left"
    with one_line(ap, kept):
        cfg = config_with(Config(), args.set)
        check_writable(CACHE, f"the data cache ({CACHE})")
        if args.pretrain:
            jobs, threads = args.jobs or os.cpu_count() or 1, args.threads or 1
            kw = dict(jobs=jobs, overwrite=args.overwrite, cache_dir=CACHE)
            command = command_line("python diffstack.py", argv)
            return pretrain(PRETRAINED, threads, cfg=cfg, command=command, **kw)
        kw = dict(cfg=cfg, device=args.device, cache_dir=CACHE, pretrained=PRETRAINED)
        return quick(torch_threads(args.threads), **kw)
