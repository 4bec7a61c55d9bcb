"""Running the paper's tables (experiments.py's command line hands over here): each table cut into
pieces, one (method, seed) result each, computed alone (in worker processes with --jobs), kept as
they finish and resumed by a re-run (lab/runs.py), assembled into the table, its files written and
rendered; real Waymo scenes; torchrun's ranks."""

from __future__ import annotations

import argparse
import collections
import contextlib
import dataclasses
import functools
import json
import os
import pathlib
import re
import sys
import time
from typing import NamedTuple

import torch
import torch.distributed as dist
from tqdm import tqdm

from lab import data as lab_data
from lab import waymo
import data_synth
import figures
from diffstack import Config
from train import (
    Method,
    GT_PREDICTION,
    NO_PREDICTION,
    TrainingDiverged,
)
from experiments import (
    VAL_N,
    VAL_SEED,
    add_relative,
    closed_loop_relative,
    closed_loop_run,
    closed_loop_scenes,
    compare_methods,
    cost_learning_seed,
    experiment_data,
    goal_breakdown,
    non_finite,
    Rollout,
    spec_key,
    trained_predictor,
    training_key,
    validation_spread,
)

from lab.cli import add_shared_options, bounded, check_writable, config_with, machine

from lab.runs import (
    ROOT,
    RUNS_DIR,
    OutputRefused,
    RunStore,
    above,
    code_version,
    command_line,
    compute_in_workers,
    die_with_parent,
    default_threads,
    folder_lock,
    ranks,
    git_commit,
    one_line,
    ours_files,
    outputs_manifest,
    planned_outputs,
    progress,
    read_results,
    record_outputs,
    refuse_existing,
    results_json,
    run_key,
    write_atomic,
)
from specs import (
    ABLATION_SECTIONS,
    COST_WEIGHTS_ROW,
    CURVE_SAMPLES,
    EXPERIMENTS,
    GOALS,
    REAL,
    REAL_OUT,
    SPECS,
    TableSpec,
)
from lab.report import (
    has_curves,
    results_markdown,
    section_markdown,
    table_file_markdown,
    write_report,
)


class Piece(NamedTuple):
    """One result of a table: a method (Table 3: its one row, both weightings) and a seed; section:
    the ablation section's title, or the goal table's goal (None elsewhere)."""

    method: str
    seed: int
    section: str | None = None

    @property
    def stem(self) -> str:

        def slug(text):
            return re.sub(r"[^A-Za-z0-9]+", "_", text).strip("_")

        return (
            f"{slug(self.section)}--" if self.section is not None else ""
        ) + f"{slug(self.method)}-seed{self.seed}"


def _rows(methods, seeds, section=None) -> list:
    """The pieces of some methods: every seed of a learned one, the first seed only of the others
    (no training)."""
    return [
        Piece(m.name, s, section)
        for m in methods
        for s in (seeds if m.predictor == "learned" else seeds[:1])
    ]


def _ablation_methods(methods) -> tuple:
    return (NO_PREDICTION, *methods, GT_PREDICTION)


def table_seeds(spec: TableSpec, seeds=None) -> tuple:
    """The training seeds of a table: those given, else the spec's own count (Table 1: 10, the
    others 5)."""
    return tuple(range(spec.seeds)) if seeds is None else tuple(seeds)


def table_pieces(spec: TableSpec, seeds) -> list:
    """Every piece of a table, in the order a one-process run makes them."""
    seeds = tuple(seeds)
    if spec.kind == "cost":
        return [Piece(COST_WEIGHTS_ROW.name, s) for s in seeds]
    if spec.kind == "ablation":
        return [
            p
            for title, _, methods in ABLATION_SECTIONS
            for p in _rows(_ablation_methods(methods), seeds, title)
        ]
    if spec.kind == "goal":
        return [p for goal in GOALS for p in _rows(spec.methods, seeds, goal)]
    return _rows(spec.methods, seeds)


def piece_method(spec: TableSpec, piece: Piece) -> tuple:
    """(method, setting, target offset, run_stack options) of a piece of any table but Table 3."""
    if spec.kind == "ablation":
        _, stack_kw, methods = next(s for s in ABLATION_SECTIONS if s[0] == piece.section)
        return (
            next(m for m in _ablation_methods(methods) if m.name == piece.method),
            "rl",
            0.0,
            stack_kw,
        )
    return (
        next(m for m in spec.methods if m.name == piece.method),
        spec.setting,
        spec.pred_offset,
        {},
    )


# the first item of Table 3's cost-weight training in piece_trainings' keys
COST_WEIGHTS = "cost weights"


def piece_trainings(spec: TableSpec, piece: Piece, cfg: Config, epochs, device="cpu") -> tuple:
    """What a piece trains unless another piece has trained it already (timed_piece's 'trained'):
    its predictor's training_key as compute_piece's, and Table 3's cost weights; () for No
    prediction, GT prediction, the goal table."""
    if spec.kind == "cost":
        return (
            training_key(Method("Standard"), cfg, "il", epochs, piece.seed, 0.0, device),
            (COST_WEIGHTS, piece.seed),
        )
    m, setting, pred_offset, stack_kw = piece_method(spec, piece)
    if spec.kind == "goal" or m.predictor != "learned":
        return ()
    return (training_key(m, cfg, setting, epochs, piece.seed, pred_offset, device, **stack_kw),)


def compute_piece(
    spec: TableSpec,
    piece: Piece,
    data,
    cfg: Config,
    epochs,
    log=print,
    models=None,
    device="cpu",
    store=None,
):
    """Train (or take from models / store) and evaluate one piece: (its result before the values
    relative to No prediction, which assemble adds; a dict of tensors to keep beside it or None). A
    training that diverges is a result too ({'diverged': what}: a resumed run does not retrain it,
    and the table says which seed is left out), and so is one whose evaluation gives a value that is
    not finite (a result is never written with NaN)."""
    try:
        result, extra = piece_result(spec, piece, data, cfg, epochs, log, models, device, store)
        bad = non_finite(result)
        if bad is not None:
            raise TrainingDiverged(f"{piece.stem}: its evaluation gave {bad}")
        return result, extra
    except TrainingDiverged as e:
        if log:
            log(f"  {piece.stem}: {e}")
        return dict(diverged=str(e)), None


def piece_result(
    spec: TableSpec,
    piece: Piece,
    data,
    cfg: Config,
    epochs,
    log=print,
    models=None,
    device="cpu",
    store=None,
):
    """compute_piece's work: the piece's result, or TrainingDiverged."""
    if spec.kind not in ("open_loop", "real", "ablation", "goal", "closed_loop", "cost"):
        raise ValueError(f"spec.kind: unknown kind {spec.kind!r}")
    if spec.kind == "cost":
        return cost_learning_seed(data, cfg, piece.seed, epochs, log, models, device, store), None
    m, setting, pred_offset, stack_kw = piece_method(spec, piece)
    if spec.kind == "goal":
        return goal_breakdown(
            data.val, m, dataclasses.replace(cfg, goal=piece.section), device
        ), None
    if spec.kind == "closed_loop":
        scenes = closed_loop_scenes(data.val_scenes, cfg)
        r, roll, per_scene = closed_loop_run(
            m,
            piece.seed,
            scenes,
            data,
            cfg,
            epochs,
            log=log,
            models=models,
            device=device,
            store=store,
        )
        return r, dict(rollout=dataclasses.asdict(roll), per_scene=per_scene)

    def train(m, *a, **k):
        return trained_predictor(m, *a, models=models, store=store, **k)

    return compare_methods(
        data,
        cfg,
        setting,
        (m,),
        (piece.seed,),
        epochs,
        pred_offset,
        log,
        train,
        device,
        **stack_kw,
    )[m.name][0], None


def assemble(spec: TableSpec, pieces: dict, seeds) -> dict:
    """A table's results from its pieces {Piece: result}, as its experiment function returns them
    in one run."""
    seeds = tuple(seeds)

    def rows(methods, section=None):
        # a copy: the relative values are added
        return {
            m.name: [
                json.loads(json.dumps(pieces[Piece(m.name, s, section)]))
                for s in (seeds if m.predictor == "learned" else seeds[:1])
            ]
            for m in methods
        }

    if spec.kind in ("open_loop", "real"):
        return add_relative(rows(spec.methods), spec.setting)
    if spec.kind == "ablation":
        return {
            title: add_relative(rows(_ablation_methods(methods), title), "rl")
            for title, _, methods in ABLATION_SECTIONS
        }
    if spec.kind == "cost":
        runs = [pieces[Piece(COST_WEIGHTS_ROW.name, s)] for s in seeds]
        return {
            name: [r[name] if name in r else r for r in runs] for name in ("Hand-tuned", "Learned")
        }
    if spec.kind == "goal":
        return {goal: rows(spec.methods, goal) for goal in GOALS}
    if spec.kind == "closed_loop":
        return closed_loop_relative(rows(spec.methods))
    raise ValueError(f"spec.kind: unknown kind {spec.kind!r}")


def timed_piece(
    spec: TableSpec, piece: Piece, data, cfg: Config, epochs, log, models, device, store
):
    """compute_piece, how long it took, where, and whether it trained: (result, extra, {'seconds':
    wall, 'cpu_seconds': this process's CPU, 'machine': lab.cli.machine() (the same seed gives other
    numbers on another kind of processor), 'trained': it trained something no piece had trained
    before it (piece_trainings)})."""

    # by an earlier piece: in this process's models, or in the store on disk
    def trained_before(key) -> bool:
        path = store.model_path(key) if store is not None and key[0] != COST_WEIGHTS else None
        return key in (models or {}) or (path is not None and path.exists())

    trains = not all(
        trained_before(key) for key in piece_trainings(spec, piece, cfg, epochs, device)
    )
    t0, c0 = time.time(), time.process_time()
    result, extra = compute_piece(spec, piece, data, cfg, epochs, log, models, device, store)
    return (
        result,
        extra,
        dict(
            seconds=time.time() - t0,
            cpu_seconds=time.process_time() - c0,
            machine=machine(),
            trained=trains,
        ),
    )


def run_about(spec: TableSpec, store: RunStore, cfg: Config, epochs, device, data) -> dict:
    """What a table's run key stands for (run.json in its folder of pieces)."""
    return dict(
        table=spec.name,
        run_key=store.key,
        config=dataclasses.asdict(cfg),
        epochs=epochs,
        code=code_version() if store.root is not None else None,
        device=str(device),
        train=len(data.train),
        val=len(data.val),
    )


def _compute(
    table: str, piece: Piece, log, models, store, data=None, cfg=None, epochs=1.0, device="cpu"
):
    """timed_piece of the table named `table`: what a worker process computes (in_workers)."""
    return timed_piece(SPECS[table], piece, data, cfg, epochs, log, models, device, store)


def in_workers(
    units: list, data, cfg: Config, epochs, device, store: RunStore, jobs: int, verbose=True
):
    """runs.compute_in_workers of units (table name, pieces of one seed), computed by
    timed_piece."""
    compute = functools.partial(_compute, data=data, cfg=cfg, epochs=epochs, device=device)
    abouts = {name: run_about(SPECS[name], store, cfg, epochs, device, data) for name, _ in units}
    compute_in_workers(compute, units, store, jobs, abouts, verbose)


def work_units(names, seeds: dict, store: RunStore) -> list:
    """The missing pieces of several tables as units for in_workers, one per (table, ablation
    section, seed): the longest (the ablation's) first, so that the short ones fill the workers at
    the end; within a table the seeds alternate, so that two workers never train the same predictor
    (the later units load it from the store)."""
    units = []
    for name in sorted(names, key=lambda n: SPECS[n].kind != "ablation"):
        pieces = [p for p in table_pieces(SPECS[name], seeds[name]) if not store.has(name, p)]
        units += [
            (name, unit)
            for section in dict.fromkeys(p.section for p in pieces)
            for seed in seeds[name]
            if (unit := [p for p in pieces if p.section == section and p.seed == seed])
        ]
    return units


def run_table(
    spec: TableSpec,
    data,
    cfg: Config,
    seeds=(0,),
    epochs=1.0,
    out_dir="results",
    log=print,
    models=None,
    device="cpu",
    write=True,
    store=None,
    jobs=1,
):
    """Train and evaluate what a table's spec declares on `device`, its figures into out_dir if
    `write`. models: the predictors the tables of one run share; store: a RunStore keeping every
    piece (None: in memory); jobs > 1 (a store on disk): the seeds' pieces in that many one-thread
    worker processes. Returns (results, markdown table)."""
    seeds = tuple(seeds)
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    models = {} if models is None else models
    store = RunStore(None, "") if store is None else store
    if spec.kind == "closed_loop":
        closed_loop_scenes(data.val_scenes, cfg)
    about = run_about(spec, store, cfg, epochs, device, data)
    pieces = table_pieces(spec, seeds)
    missing = [p for p in pieces if not store.has(spec.name, p)]
    if log and len(missing) < len(pieces):
        reused = [p.stem for p in pieces if p not in missing]
        log(
            f"{spec.name}: {len(reused)} of {len(pieces)} pieces done by an earlier run of the "
            "same key, reused from "
            f"{store.table_dir(spec.name) if store.root is not None else 'memory'}: "
            f"{', '.join(reused)}"
        )
    by_seed = {
        s: [p for p in missing if p.seed == s] for s in dict.fromkeys(p.seed for p in missing)
    }
    if jobs > 1 and store.root is not None and len(by_seed) > 1:
        if log:
            log(
                f"{spec.name}: {len(missing)} pieces of {len(by_seed)} seeds in "
                f"{min(jobs, len(by_seed))} worker processes, one thread each"
            )
        in_workers(
            [(spec.name, ps) for ps in by_seed.values()],
            data,
            cfg,
            epochs,
            device,
            store,
            jobs,
            log is not None,
        )
    else:
        for p in missing:
            result, extra, timing = timed_piece(
                spec, p, data, cfg, epochs, log, models, device, store
            )
            store.save(spec.name, p, result, extra, about, timing)
    loaded = {p: store.load(spec.name, p) for p in pieces}
    res = assemble(spec, {p: r for p, (r, _) in loaded.items()}, seeds)

    def first_pair():  # the first seed's Standard and DiffStack, the predictors the figures compare
        return {
            m.name: trained_predictor(
                m, data, cfg, "rl", epochs, seeds[0], log, models=models, device=device, store=store
            )
            for m in spec.methods[1:3]
        }

    if write and spec.kind == "cost":
        figures.figure_cost_weights(res, out / "cost_weights.png")
    elif write and "learning_curves.png" in spec.figures and has_curves(res):
        figures.figure_learning_curves(
            res,
            out / "learning_curves.png",
            figures.learning_curve_reference(data, cfg, CURVE_SAMPLES),
        )
    elif write and spec.kind == "closed_loop":
        # the first seed's rollouts (a diverged training has none)
        rollouts = {
            p.method: (Rollout(**extra["rollout"]), extra["per_scene"])
            for p, (_, extra) in loaded.items()
            if p.seed == seeds[0] and extra is not None
        }
        figures.figure_closed_loop(
            closed_loop_scenes(data.val_scenes, cfg), rollouts, out / "closed_loop.png", cfg.dt
        )
        try:
            figures.figure_stack_example(data, first_pair(), cfg, out / "stack_example.png")
        except TrainingDiverged as e:  # the figure needs seed 0's two predictors
            if log:
                log(f"stack_example.png not drawn: {e}")
    elif write and spec.kind == "real":
        figures.figure_real_scenes(data.val, first_pair(), cfg, out / "real_scenes.png")
    return res, results_markdown(spec, res)


def check_outputs(names, out_dir, overwrite: bool, ours=()) -> None:
    """Before any work: out_dir must be writable, and no file a run of these tables would write may
    exist already unless overwrite or it is in ours (runs.refuse_existing). OutputRefused naming the
    folder or the files."""
    out = pathlib.Path(out_dir).resolve()

    def inside(folder):
        return folder == out or folder in out.parents

    # before check_writable makes the folder
    if REAL.name in names and inside(ROOT) and not inside(ROOT / "runs"):
        raise OutputRefused(
            f"--out {out_dir}: the real-scene results derive from the Waymo Open Dataset, whose "
            "licence forbids committing them; inside this repository they go under runs/ "
            f"(git-ignored; default {REAL_OUT}/), or write them outside it"
        )
    try:
        check_writable(out_dir, "--out")
    except ValueError as e:
        raise OutputRefused(str(e)) from None
    refuse_existing(planned_outputs(out_dir, {n: SPECS[n].figures for n in names}), overwrite, ours)


def render_markdown(name: str, out_dir="results") -> pathlib.Path:
    """Re-write out_dir/<name>.md from out_dir/<name>.json, running nothing: for when the way a
    table is written changes (e.g. the claim lines) but its numbers do not. Returns the
    path written."""
    src, _, section, _ = rendered(name, out_dir)
    write_atomic(src.with_suffix(".md"), table_file_markdown(SPECS[name], section))
    return src.with_suffix(".md")


def rendered(name: str, out_dir) -> tuple:
    """(out_dir/<name>.json, its contents, its section's markdown, the Config of its learning
    curves or None), every field render reads checked: ValueError naming the file and the field,
    before anything is written."""
    if name not in SPECS:
        raise ValueError(f"name: {name!r} is not an experiment ({', '.join(SPECS)})")
    src = pathlib.Path(out_dir) / f"{name}.json"
    if not src.exists():
        raise ValueError(f"out_dir: no {src} to render {name} from")
    saved = read_results(src)
    spec = SPECS[name]
    try:
        section = section_markdown(spec, saved["meta"], results_markdown(spec, saved["results"]))
        config = saved["meta"].get("config")
        cfg = None
        if "learning_curves.png" in spec.figures and has_curves(saved["results"]):
            cfg = Config(**{k: tuple(v) if isinstance(v, list) else v for k, v in config.items()})
    except KeyError as e:
        raise ValueError(f"{src}: not a {name} table's results (field {e} missing)") from None
    except (TypeError, ValueError, IndexError, AttributeError, ZeroDivisionError) as e:
        why = " ".join(str(e).split())[:200]
        raise ValueError(f"{src}: not a {name} table's results ({why})") from None
    return src, saved, section, cfg


def render_outputs(
    name: str, out_dir="results", data=None, cfg: Config | None = None, log=print
) -> list:
    """Re-write the .md files and learning curves (their reference lines when `data` is given) of an
    earlier run of `name` ('all': every table and report.md) from its JSON files in out_dir,
    training nothing; every file is read and checked before the first is written. Returns the
    paths."""
    names = EXPERIMENTS if name == "all" else (name,)
    out = pathlib.Path(out_dir)
    done = {one: rendered(one, out) for one in names}
    written = []
    sections = []
    for one, (src, saved, section, cfg_run) in done.items():
        spec = SPECS[one]
        write_atomic(src.with_suffix(".md"), table_file_markdown(spec, section))
        written.append(src.with_suffix(".md"))
        if cfg_run is not None:  # (no learning curves in older runs)
            ref = (
                figures.learning_curve_reference(data, cfg_run, CURVE_SAMPLES)
                if data is not None
                else None
            )
            figures.figure_learning_curves(saved["results"], out / "learning_curves.png", ref)
            written.append(out / "learning_curves.png")
        sections.append((spec.title, section, [f for f in spec.figures if (out / f).exists()]))
    if name == "all":
        metas = [saved["meta"] for _, saved, _, _ in done.values()]
        tables = {one: saved["results"] for one, (_, saved, _, _) in done.items()}
        written.append(write_report(out, sections, metas, rendered=True, tables=tables))
    if log:
        log("rendered: " + ", ".join(str(p) for p in written))
    return written


def run_experiment(
    name,
    data,
    cfg: Config,
    seeds,
    epochs,
    out_dir="results",
    command="",
    log=print,
    overwrite=False,
    device="cpu",
    write=True,
    jobs=1,
    progress_every=2.0,
):
    """Run one table (or 'all', each predictor trained once for every table) on `device`, writing
    out_dir/<name>.json (results, the full Config, the device, the git commit), .md and the figures
    (for 'all', report.md too) unless write=False (torchrun's other ranks). Every piece is kept in
    out_dir/.runs/: re-running the command resumes it. A progress bar while log and write.
    OutputRefused when a file it would write exists, unless overwrite or this same run wrote
    it as is."""
    names = EXPERIMENTS if name == "all" else (name,)
    out = pathlib.Path(out_dir)
    per_table = {one: table_seeds(SPECS[one], seeds) for one in names}
    seeds = tuple(seeds) if seeds is not None else None
    processes = dist.get_world_size() if dist.is_available() and dist.is_initialized() else 1
    # under torchrun every rank must train the same pieces together: nothing is kept or
    # resumed there
    root = out / RUNS_DIR if write and processes == 1 else None
    # no run wrote outputs here: check before hashing the data
    if root is None or not (root / "outputs").is_dir():
        check_outputs(names, out_dir, overwrite)
    store = RunStore(
        root, run_key(data, cfg, epochs, device), {n: spec_key(SPECS[n]) for n in names}
    )
    manifest = outputs_manifest(out, name, seeds or (), store.key)
    check_outputs(
        names, out_dir, overwrite, ours=ours_files(out, [manifest]) if root is not None else ()
    )
    sections = []
    metas = []
    models = {}
    tables = {}
    all_pieces = [(one, p) for one in names for p in table_pieces(SPECS[one], per_table[one])]
    # worker processes only where there are seeds to share out (the goal table has one run per row)
    jobs = (
        max(1, min(jobs, len({p.seed for _, p in all_pieces}))) if write and processes == 1 else 1
    )
    if store.root is not None and log:
        log(
            f"run key {store.key[:16]}: {len(all_pieces)} pieces (table, method, seed), kept in "
            f"{out / RUNS_DIR} as they finish"
            + (f"; {jobs} worker processes of one thread" if jobs > 1 else "")
        )
    with progress(store, all_pieces, progress_every, disable=not (log and write)) as bar:
        log = above(bar, log) if log else log
        units = (
            work_units(names, per_table, store)
            if jobs > 1 and store.root is not None and len(names) > 1
            else []
        )
        # every table's pieces in one pool of workers (then each table below finds its pieces done)
        if units:
            if log:
                log(
                    f"{sum(len(u) for _, u in units)} pieces in {len(units)} units (table, seed) "
                    f"over {jobs} worker processes, one thread each"
                )
            in_workers(units, data, cfg, epochs, device, store, jobs, log is not None)
        for one in names:
            spec = SPECS[one]
            t0 = time.time()
            seeds_one = per_table[one]
            res, table = run_table(
                spec, data, cfg, seeds_one, epochs, out, log, models, device, write, store, jobs
            )
            tables[one] = res
            threads = (
                f"{torch.get_num_threads()} threads"
                if jobs == 1
                else f"1 thread per process, {jobs} worker processes (--jobs)"
            )
            timings = [store.timing(one, p) for p in table_pieces(spec, seeds_one)]
            piece_time = {}
            # the table's computing time, summed over its pieces, whenever they ran
            if timings and all(timings):
                piece_time = dict(
                    piece_seconds=sum(t["seconds"] for t in timings),
                    piece_cpu_seconds=sum(t["cpu_seconds"] for t in timings),
                    pieces=len(timings),
                )
            computed_on = collections.Counter(t["machine"] for t in timings if t and "machine" in t)
            if len(computed_on) > 1:  # not all on one machine (a run resumed on another host, say)
                piece_time["computed_on"] = dict(computed_on)
            meta = dict(
                experiment=one,
                command=command,
                seeds=list(seeds_one),
                epochs=epochs,
                seconds=time.time() - t0,
                **piece_time,
                date=time.strftime("%Y-%m-%d"),
                train=len(data.train),
                val=len(data.val),
                data_seeds=list(seeds_one) if data.train_draws is not None else None,
                machine=f"{machine()}, torch {torch.__version__}, {threads}"
                + (f" per process, {processes} processes (DDP)" if processes > 1 else ""),
                device=str(device),
                git_commit=git_commit(),
                config=dataclasses.asdict(cfg),
            )
            md = section_markdown(spec, meta, table) if write else table
            if write:
                write_atomic(
                    out / f"{one}.json",
                    results_json(dict(meta=meta, results=res), str(out / f"{one}.json")),
                )
                write_atomic(out / f"{one}.md", table_file_markdown(spec, md))
                if store.root is not None:
                    record_outputs(
                        manifest,
                        [out / f"{one}.json", out / f"{one}.md"] + [out / f for f in spec.figures],
                    )
                metas.append(meta)
                if log:
                    log(f"\n{spec.title}\n{table}")
            sections.append((spec.title, md, list(spec.figures)))
    timings = [store.timing(one, p) for one, p in all_pieces] if store.root is not None else []
    if log and timings and all(timings):
        total = sum(t["seconds"] for t in timings)
        log(
            f"computing time summed over the {len(timings)} pieces (whenever they ran): "
            f"{tqdm.format_interval(total)}"
            + (
                f", {tqdm.format_interval(total / jobs)} of wall time on {jobs} workers sharing "
                "it evenly"
                if jobs > 1
                else ""
            )
        )
    if name == "all" and write:
        report = write_report(out, sections, metas, tables=tables)
        if store.root is not None:
            record_outputs(manifest, [report])
        if log:
            log(f"report: {report}")
    return sections


class RealData(NamedTuple):
    """Training samples (synthetic), and the real samples as the validation side, grouped
    by scene."""

    train: data_synth.Scenarios
    val: data_synth.Scenarios
    val_scenes: None = None  # no closed loop on the real logs
    val_groups: dict = {}  # {scene name: number of its samples}, in the order of val
    # the synthetic training draws, one per seed (Dataset.train_for)
    train_draws: tuple | None = None

    train_for = data_synth.Dataset.train_for


def real_data(data, phases=(0,), cache_dir="data_cache", log=print) -> RealData:
    """data's (synthetic) training side, and the Waymo samples (fetched on the first call) as the
    validation side."""
    real, report = waymo.load_waymo_scenarios(cache_dir, tuple(phases), log=log)
    log(
        f"real: {report['samples']} samples from {report['files']} Waymo logs "
        f"({len(tuple(phases))} 2 Hz phase(s) each), training on {len(data.train)} synthetic "
        f"samples. {waymo.WAYMO_LICENCE}"
    )
    return RealData(data.train, real, None, report["samples_per_scene"], data.train_draws)


def start_distributed(device: torch.device) -> torch.device:
    """Join torchrun's process group (named by its environment): gloo on CPUs, nccl on GPUs, each
    rank on its own, cuda:LOCAL_RANK. Returns this rank's device; train_stack then trains with
    DistributedDataParallel."""
    if device.type == "cuda":
        local = int(os.environ.get("LOCAL_RANK", 0))
        if local >= torch.cuda.device_count():
            raise ValueError(
                f"--device {device}: rank {local} of this machine needs cuda:{local}, but there "
                f"are {torch.cuda.device_count()} CUDA devices; start at most that many "
                "processes per machine"
            )
        device = torch.device("cuda", local)
        torch.cuda.set_device(device)
        dist.init_process_group("nccl", device_id=device)
    elif device.type == "cpu":
        dist.init_process_group("gloo")
    else:
        raise ValueError(
            f"--device {device}: torchrun trains on cpu (gloo) or cuda (nccl), not {device.type}"
        )
    return device


def data_options(ap) -> None:
    """experiments.py's options of what a table trains on: seeds, epochs, the data."""
    ap.add_argument(
        "--phases",
        type=bounded(int, 1, waymo.WAYMO_PHASES, "--phases"),
        default=1,
        help="real: how many of the five 2 Hz clocks of each 10 Hz log give samples (default 1: "
        "78 samples)",
    )
    ap.add_argument(
        "--seeds",
        type=bounded(int, 1, 100, "--seeds"),
        default=None,
        help="training seeds per method, at most 100 (default: each table's own, 10 for Table 1 "
        "and 5 for the others)",
    )
    ap.add_argument(
        "--epochs",
        type=bounded(float, 0, 1000, "--epochs"),
        default=40.0,
        help="training epochs per method (default 40, the committed tables': the paper's 20 "
        "left Standard short of its plateau on this data, results/epochs20/; fractions allowed; "
        "at most 1000)",
    )
    ap.add_argument(
        "--n",
        "--samples",
        type=bounded(int, 10, data_synth.MAX_SAMPLES, "--n"),
        default=10000,
        help="synthetic scenarios per training draw (each seed trains on the training scenes, "
        f"85 %%, of its own draw; default 10000, at most {data_synth.MAX_SAMPLES:,}); under "
        "torchrun write --samples (torchrun's own parser takes --n for an abbreviation of its "
        "options)",
    )
    ap.add_argument(
        "--val",
        type=bounded(int, 10, data_synth.MAX_SAMPLES, "--val"),
        default=VAL_N,
        help=f"samples of the common validation set every method and seed is evaluated on (default "
        f"{VAL_N:,}; scenes of data seed {VAL_SEED}, which no training draw holds)",
    )
    ap.add_argument(
        "--data",
        help="a nuScenes folder (real, or written by data_synth.py) instead of synthetic data",
    )


def parser() -> argparse.ArgumentParser:
    """experiments.py's command line."""
    ap = argparse.ArgumentParser(
        description="DiffStack (CoRL 2022): the paper's tables, run on this machine. "
        "Under torchrun, on N processes: training with DistributedDataParallel."
    )
    ap.add_argument(
        "--experiment",
        choices=EXPERIMENTS + (REAL.name, "all"),  # (required, but by --validation-spread)
        help="a table of the paper (results/<name>.json, .md, figures); all: every one, and "
        "results/report.md; real: the synthetic-trained stack on three real Waymo scenes "
        f"(downloaded once into data_cache/waymo; outputs to {REAL_OUT}/, never results/)",
    )
    data_options(ap)
    ap.add_argument("--out", help=f"where the results go (default results/; for real, {REAL_OUT}/)")
    ap.add_argument(
        "--render",
        action="store_true",
        help="train nothing: re-write the .md files, the report and the learning curves of an "
        "earlier run from its JSON files in --out (after a change to how results are written)",
    )
    ap.add_argument(
        "--validation-spread",
        action="store_true",
        help="train nothing: print GT prediction's relative hindsight cost on 5 unseen "
        "validation draws at about 1,500 samples and at --val's default (validation_spread); "
        "about 2 minutes",
    )
    add_shared_options(
        ap,
        threads="torch threads (default 2, or 1 when other work keeps a core busy)",
        jobs="worker processes, one thread each, running a table's seeds in parallel (default: "
        f"the machine's cores, here {os.cpu_count()}; 1: one process with --threads threads; 1 "
        "under torchrun)",
        device="where training, evaluation and the stack run: cpu (default), cuda, cuda:N or "
        "mps; the data is made and cached on the CPU",
        overwrite="replace result files that exist already in --out (without it, the run refuses "
        "to start)",
        set="override a Config field, e.g. --set beta=2 (repeatable)",
    )
    return ap


def main(argv=None):
    # Under torchrun every process runs main: all ranks train together (DDP) and evaluate alike;
    # rank 0 prints, writes
    rank, world, misuse = ranks()
    if misuse:  # every process says it: none of them can reach the others
        print(f"experiments.py: error: {misuse}", file=sys.stderr)
        sys.exit(2)
    if world > 1:  # a rank ends with the torchrun that started it, as a --jobs worker with its run
        die_with_parent(os.getppid())
    ap = parser()
    # the same errors come up on every rank: rank 0 says what they are, the others exit alike
    if rank != 0:
        ap.error = lambda message: sys.exit(2)
    args = ap.parse_args(argv)
    if args.validation_spread:
        return print(validation_spread())
    if args.experiment is None:
        ap.error("the following arguments are required: --experiment")
    names = EXPERIMENTS if args.experiment == "all" else (args.experiment,)
    args.out = args.out or (REAL_OUT if args.experiment == REAL.name else "results")
    launcher = (
        f"torchrun --nproc_per_node {world} experiments.py"
        if world > 1
        else "python experiments.py"
    )
    command = command_line(launcher, argv if argv is not None else sys.argv[1:])
    held = contextlib.ExitStack()
    # rank 0 holds --out from the checks to the end: one run per folder (runs.folder_lock); the
    # project's errors and a file's (a NaN result, a bad JSON) are one line
    with (
        held,
        one_line(ap, "the pieces finished so far are kept, and the same command resumes the run"),
    ):
        return _main(ap, args, names, world, rank, command, held)


def _main(ap, args, names, world, rank, command, held):
    seeds = range(args.seeds) if args.seeds is not None else None  # (None: each table's own count)
    # derived files only, from the JSON an earlier run wrote: nothing it made is lost
    if args.render:
        missing = [
            f"{args.out}/{n}.json"
            for n in names
            if not pathlib.Path(args.out, f"{n}.json").exists()
        ]
        if missing:
            ap.error(f"--render: no results to render from: {', '.join(missing)} missing")
        try:
            # (its validation scenes draw the learning curves' reference lines)
            if args.data is not None:
                lab_data.nuscenes_version(args.data)
            held.enter_context(folder_lock(args.out, command))
        except ValueError as e:
            ap.error(str(e))
        data = (
            experiment_data(args.n, (0,), args.val, log=print)
            if args.data is None
            else lab_data.load_data(args.data, args.n, log=print)
        )
        return render_outputs(args.experiment, args.out, data)
    try:  # everything that can be checked before the data is made and the first model trained
        cfg = config_with(Config(), args.set)
        if cfg.batch_size % world:
            raise ValueError(
                f"--set batch_size={cfg.batch_size}: a training batch must split evenly over the "
                f"{world} processes torchrun started; choose a multiple of {world}"
            )
        if args.jobs is not None and args.jobs > 1 and world > 1:
            raise ValueError(
                f"--jobs {args.jobs}: under torchrun the processes train together (DDP); run "
                "without --jobs"
            )
        if args.data is not None:  # before --out is made: a folder that holds a nuScenes version
            lab_data.nuscenes_version(args.data)
        check_outputs(
            names,
            args.out,
            args.overwrite,  # an earlier run's files may be ours: run_experiment decides
            ours=ours_files(args.out, pathlib.Path(args.out, RUNS_DIR, "outputs").glob("*.json")),
        )
        # synthetic data, a folder's parse, Waymo
        check_writable("data_cache", "the data cache (./data_cache)")
        if rank == 0:
            held.enter_context(folder_lock(args.out, command))
        device = start_distributed(args.device) if world > 1 else args.device
    except ValueError as e:
        ap.error(str(e))
    threads, why = (args.threads, "--threads") if args.threads else default_threads()
    torch.set_num_threads(threads)
    if rank == 0:
        print(f"torch threads: {threads} ({why}; --threads N to choose)", flush=True)
    # flushed line by line: a run's log is often a file (a long run in the background), read
    # while it runs
    log = functools.partial(print, flush=True) if rank == 0 else (lambda *a, **k: None)

    def load():  # (the data, None), or (None, why it cannot be made)
        try:
            most = max(len(table_seeds(SPECS[one], seeds)) for one in names)
            data = (
                experiment_data(args.n, range(most), args.val, log=log)
                if args.data is None
                else lab_data.load_data(args.data, args.n, log=log)
            )
            if args.experiment == REAL.name:
                data = real_data(data, range(args.phases), log=log)
            if "closed_loop" in names:
                closed_loop_scenes(data.val_scenes, cfg)
            return data, None
        except (ValueError, OSError) as e:  # (OSError: a file, or the Waymo download offline)
            return None, str(e)

    # Rank 0 makes (or reads) the data caches first, the others then read them: one process
    # generates or parses, and if it fails the others hear of it (a broadcast) instead of waiting
    # for it at the first training step.
    data, error = load() if rank == 0 else (None, None)
    if world > 1:
        verdict = [error]
        dist.broadcast_object_list(verdict, src=0)
        error = verdict[0]
        if rank != 0 and error is None:
            data, error = load()
    if error is not None:
        if world > 1:
            dist.destroy_process_group()
        ap.error(error)
    try:
        return run_experiment(
            args.experiment,
            data,
            cfg,
            seeds,
            args.epochs,
            args.out,
            command,
            log=log,
            overwrite=args.overwrite,
            device=device,
            write=rank == 0,
            jobs=args.jobs or (1 if world > 1 else os.cpu_count() or 1),
        )
    finally:
        if world > 1:
            dist.destroy_process_group()
