"""Running the paper's tables (experiments.py's command line hands over here): each table cut into
pieces, one (method, seed) result each, computed alone (in worker processes with --jobs), kept as
they finish and resumed by a re-run (lab/runs.py), assembled into the table, its files written and
rendered; real Waymo scenes; torchrun's ranks. What differs between the kinds of table is in KINDS:
kind -> (one piece, by experiments.py's function; the table from its pieces)."""

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
import tempfile
import time
from typing import NamedTuple

import torch
import torch.distributed as dist
from tqdm import tqdm

from lab import data as lab_data
from lab import waymo
import data_synth
import experiments as ex
from experiments import closed_loop_scenes, experiment_data, validation_spread
import figures
from diffstack import Config
from lab import runs
from lab.cli import add_shared_options, bounded, check_writable, config_with, machine
from lab.report import has_curves, results_markdown, section_markdown, table_file_markdown
from lab.report import write_report
from specs import CURVE_SAMPLES, EXPERIMENTS, GOALS, REAL, REAL_OUT, SPECS, TableSpec
from train import GT_PREDICTION, NO_PREDICTION, TrainingDiverged


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

        head = f"{slug(self.section)}--" if self.section is not None else ""
        return f"{head}{slug(self.method)}-seed{self.seed}"


def table_seeds(spec: TableSpec, seeds=None) -> tuple:
    """The training seeds of a table: those given, else the spec's own count (Table 1: 10, the
    others 5)."""
    return tuple(range(spec.seeds)) if seeds is None else tuple(seeds)


def table_sections(spec: TableSpec) -> list:
    """A table's sections, (title, run_stack options, rows): the ablation's, each between its own
    No prediction and GT prediction; the goal table's goals; one untitled section elsewhere."""
    if spec.kind == "goal":
        return [(goal, {}, spec.methods) for goal in GOALS]
    sections = [(t, kw, (NO_PREDICTION, *ms, GT_PREDICTION)) for t, kw, ms in spec.sections]
    return sections or [(None, {}, spec.methods)]


def _seeds(m, seeds) -> tuple:
    """The seeds a method runs: every one when it trains, the first only otherwise."""
    return tuple(seeds) if m.predictor == "learned" else tuple(seeds)[:1]


def table_pieces(spec: TableSpec, seeds) -> list:
    """Every piece of a table, in the order a one-process run makes them."""
    return [
        Piece(m.name, s, title)
        for title, _, methods in table_sections(spec)
        for m in methods
        for s in _seeds(m, seeds)
    ]


@dataclasses.dataclass
class Run:
    """What the pieces of one run share: the data, Config, epochs and device, the store that keeps
    the pieces and the predictors they train (runs.RunStore), the log (None: quiet), and the
    predictors trained so far in this process (shared by the tables of one run). Its fields are
    named as experiments.py's functions name them: **vars(run) passes them all."""

    data: object
    cfg: Config
    epochs: float
    store: runs.RunStore
    device: object = "cpu"
    log: object = print
    models: dict = dataclasses.field(default_factory=dict)


def _open_loop(run: Run, spec: TableSpec, piece: Piece, m, stack_kw: dict) -> tuple:
    """Tables 1, 2 and 4, an ablation section, the real scenes: one method and seed, open loop."""
    on = dict(setting=spec.setting, pred_offset=spec.pred_offset, **stack_kw)
    rows = ex.open_loop_experiment(methods=(m,), seeds=(piece.seed,), **on, **vars(run))
    return rows[m.name][0], None


def _cost(run: Run, spec: TableSpec, piece: Piece, m, stack_kw: dict) -> tuple:
    """Table 3: one seed's cost weights, hand-tuned and learned."""
    return ex.cost_learning_seed(seed=piece.seed, **vars(run)), None


def _closed_loop(run: Run, spec: TableSpec, piece: Piece, m, stack_kw: dict) -> tuple:
    """Table 5: one method and seed in the closed loop, its rollout kept for the figure."""
    scenes = closed_loop_scenes(run.data.val_scenes, run.cfg)
    r, roll, per_scene = ex.closed_loop_run(m, piece.seed, scenes, **vars(run))
    return r, dict(rollout=dataclasses.asdict(roll), per_scene=per_scene)


def _goal(run: Run, spec: TableSpec, piece: Piece, m, stack_kw: dict) -> tuple:
    """The goal table: No prediction or GT prediction under one goal, by behaviour."""
    cfg = dataclasses.replace(run.cfg, goal=piece.section)
    return ex.goal_breakdown(run.data.val, m, cfg, run.device), None


def _relative(spec: TableSpec, rows: dict) -> dict:
    return ex.add_relative(rows, spec.setting)


def _cost_rows(spec: TableSpec, rows: dict) -> dict:
    """Table 3's rows, hand-tuned and learned, from its pieces (a diverged seed in both)."""
    seeds = rows[spec.methods[0].name]
    return {name: [r.get(name, r) for r in seeds] for name in ("Hand-tuned", "Learned")}


# kind -> (piece(run, spec, piece, method, run_stack options) -> (result, extra tensors or None),
#          table(spec, {row: [result per seed]}) -> the table's results)
KINDS = {
    "open_loop": (_open_loop, _relative),
    "real": (_open_loop, _relative),
    "ablation": (_open_loop, _relative),
    "cost": (_cost, _cost_rows),
    "closed_loop": (_closed_loop, lambda spec, rows: ex.closed_loop_relative(rows)),
    "goal": (_goal, lambda spec, rows: rows),
}


def compute_piece(run: Run, spec: TableSpec, piece: Piece) -> tuple:
    """Train (or take from run.models or the store) and evaluate one piece: (its result, tensors to
    keep beside it or None, its timing: seconds, CPU seconds and the machine, as the same seed gives
    other numbers on another kind of processor). A training that diverges is a result too
    ({'diverged': why}: a resumed run does not retrain it, and the table names the seed it leaves
    out), and so is an evaluation that gives NaN or infinity (never written in a result)."""
    _, stack_kw, methods = next(s for s in table_sections(spec) if s[0] == piece.section)
    m = next(m for m in methods if m.name == piece.method)
    t0, c0 = time.time(), time.process_time()
    try:
        result, extra = KINDS[spec.kind][0](run, spec, piece, m, stack_kw)
        try:
            json.dumps(result, default=runs.to_json, allow_nan=False)
        except ValueError:
            raise TrainingDiverged(f"{piece.stem}: its evaluation gave NaN or infinity") from None
    except TrainingDiverged as e:
        if run.log:
            run.log(f"  {piece.stem}: {e}")
        result, extra = dict(diverged=str(e)), None
    cpu = time.process_time() - c0
    return result, extra, dict(seconds=time.time() - t0, cpu_seconds=cpu, machine=machine())


def assemble(spec: TableSpec, results: dict, seeds) -> dict:
    """A table's results from its pieces {Piece: result}, as one run of its experiment gives them:
    per section (where it has several), {row: [result per seed]} made a table by its kind
    (relative to No prediction, say)."""
    table = KINDS[spec.kind][1]
    sections = {
        title: table(
            spec,
            {m.name: [results[Piece(m.name, s, title)] for s in _seeds(m, seeds)] for m in methods},
        )
        for title, _, methods in table_sections(spec)
    }
    return sections[None] if None in sections else sections


def work_units(tables: list, store: runs.RunStore) -> list:
    """The missing pieces of tables [(spec, seeds)] as units (spec, pieces), one per (table,
    section, seed): the longest (the ablation's) first, so that the short ones fill the workers at
    the end; within a table the seeds alternate, so that two workers never train the same predictor
    side by side (the later units load it from the store)."""
    units = []
    for spec, seeds in sorted(tables, key=lambda t: not t[0].sections):
        missing = [p for p in table_pieces(spec, seeds) if not store.has(spec.name, p)]
        units += [
            (spec, unit)
            for section in dict.fromkeys(p.section for p in missing)
            for seed in seeds
            if (unit := [p for p in missing if p.section == section and p.seed == seed])
        ]
    return units


def _in_worker(run: Run, table: str, pieces: list) -> None:
    """A worker process's unit: some pieces of a table (named: a spec holds lambdas, which do not
    pickle) computed and kept on one thread, its log lines tagged with the table and seed."""
    torch.set_num_threads(1)
    tag = f"[{table} seed {pieces[0].seed}]"
    run = dataclasses.replace(
        run, log=functools.partial(print, tag, flush=True) if run.log else None
    )
    for piece in pieces:
        run.store.save(table, piece, *compute_piece(run, SPECS[table], piece))


def compute_pieces(run: Run, tables: list, jobs: int, bar) -> None:
    """The missing pieces of tables [(spec, seeds)], each kept in the store as it finishes: in
    `jobs` worker processes of one thread each where there are several units (work_units), else
    here one after another (sharing run.models). bar: the progress bar they count on."""
    units = work_units(tables, run.store)
    if jobs > 1 and len(units) > 1:
        shipped = dataclasses.replace(run, log=print if run.log else None, models={})
        work = [(shipped, spec.name, pieces) for spec, pieces in units]
        runs.in_workers(_in_worker, work, jobs, lambda u, _: bar.update(len(u[2])), run.store.root)
        return
    for spec, seeds in tables:  # in the order of the table
        for piece in [p for p in table_pieces(spec, seeds) if not run.store.has(spec.name, p)]:
            run.store.save(spec.name, piece, *compute_piece(run, spec, piece))
            bar.update()


def run_table(spec: TableSpec, run: Run, seeds, out_dir="results", write=True, jobs=1, bar=None):
    """Train and evaluate what a table's spec declares (its missing pieces: compute_pieces), its
    figures into out_dir if `write`. Returns (results, markdown table)."""
    seeds = tuple(seeds)
    compute_pieces(run, [(spec, seeds)], jobs, bar or tqdm(disable=True))
    loaded = {p: run.store.load(spec.name, p) for p in table_pieces(spec, seeds)}
    res = assemble(spec, {p: r for p, (r, _) in loaded.items()}, seeds)
    if write:
        draw_figures(spec, run, res, loaded, seeds, pathlib.Path(out_dir))
    return res, results_markdown(spec, res)


def draw_figures(spec: TableSpec, run: Run, res: dict, loaded: dict, seeds, out) -> None:
    """The figures a table's spec names, into out: from its results, the closed loop's from the
    rollouts its pieces kept, the stack example and the real scenes with the first seed's Standard
    and DiffStack (trained or loaded again)."""
    data, cfg = run.data, run.cfg
    if "cost_weights.png" in spec.figures:
        figures.figure_cost_weights(res, out / "cost_weights.png")
    if "learning_curves.png" in spec.figures and has_curves(res):
        ref = figures.learning_curve_reference(data, cfg, CURVE_SAMPLES)
        figures.figure_learning_curves(res, out / "learning_curves.png", ref)
    if "closed_loop.png" in spec.figures:  # the first seed's rollouts (a diverged one has none)
        rollouts = {
            p.method: (ex.Rollout(**extra["rollout"]), extra["per_scene"])
            for p, (_, extra) in loaded.items()
            if p.seed == seeds[0] and extra is not None
        }
        scenes = closed_loop_scenes(data.val_scenes, cfg)
        figures.figure_closed_loop(scenes, rollouts, out / "closed_loop.png", cfg.dt)
    pair = [f for f in ("stack_example.png", "real_scenes.png") if f in spec.figures]
    try:  # the first seed's Standard and DiffStack
        models = {
            m.name: ex.trained_predictor(m, setting="rl", seed=seeds[0], **vars(run))
            for m in (spec.methods[1:3] if pair else ())
        }
    except TrainingDiverged as e:
        if run.log:
            run.log(f"{', '.join(pair)} not drawn: {e}")
        return
    if "stack_example.png" in pair:
        figures.figure_stack_example(data, models, cfg, out / "stack_example.png")
    if "real_scenes.png" in pair:
        figures.figure_real_scenes(data.val, models, cfg, out / "real_scenes.png")


def table_meta(run: Run, spec: TableSpec, seeds, command: str, seconds: float, jobs: int) -> dict:
    """A table's provenance (the meta of its results file): the command, seeds, data, machine,
    threads, device, commit and Config, and its computing time summed over its pieces whenever they
    ran (with the count per machine where they ran on more than one)."""
    meta = dict(experiment=spec.name, command=command, seeds=list(seeds), epochs=run.epochs)
    meta.update(seconds=seconds)
    timings = [run.store.timing(spec.name, p) for p in table_pieces(spec, seeds)]
    if all(timings):
        meta.update(piece_seconds=sum(t["seconds"] for t in timings))
        meta.update(piece_cpu_seconds=sum(t["cpu_seconds"] for t in timings), pieces=len(timings))
        computed_on = collections.Counter(t["machine"] for t in timings if "machine" in t)
        if len(computed_on) > 1:  # not all on one machine (a run resumed on another host, say)
            meta.update(computed_on=dict(computed_on))
    world = dist.get_world_size() if dist.is_available() and dist.is_initialized() else 1
    threads = f"1 thread per process, {jobs} worker processes (--jobs)"
    threads = f"{torch.get_num_threads()} threads" if jobs == 1 else threads
    threads += f" per process, {world} processes (DDP)" if world > 1 else ""
    data = run.data
    meta.update(date=time.strftime("%Y-%m-%d"), train=len(data.train), val=len(data.val))
    meta.update(data_seeds=list(seeds) if data.train_draws is not None else None)
    meta.update(machine=f"{machine()}, torch {torch.__version__}, {threads}")
    meta.update(device=str(run.device), git_commit=runs.git_commit())
    return dict(meta, config=dataclasses.asdict(run.cfg))


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
):
    """Run one table (or 'all', each predictor trained once for every table) on `device`, writing
    out_dir/<name>.json (results, the full Config, the device, the git commit), .md and the figures
    (for 'all', report.md too) unless write=False (torchrun's other ranks). Every piece is kept in
    out_dir/.runs/: re-running the command resumes it. A progress bar while log and write.
    OutputRefused when a file it would write exists, unless overwrite or this same run wrote it as
    it is."""
    t0 = time.time()
    names = EXPERIMENTS if name == "all" else (name,)
    out = pathlib.Path(out_dir)
    tables = [(SPECS[one], table_seeds(SPECS[one], seeds)) for one in names]
    check_outputs(names, out, overwrite)
    # under torchrun every rank trains the same pieces together: nothing is kept or resumed there
    keep = write and not (dist.is_available() and dist.is_initialized())
    key = runs.run_key(data, cfg, epochs, device)
    with contextlib.ExitStack() as stack:
        root = out / runs.RUNS_DIR if keep else stack.enter_context(tempfile.TemporaryDirectory())
        store = runs.RunStore(root, key, {n: ex.spec_key(SPECS[n]) for n in names})
        run = Run(data, cfg, epochs, store, device, log)
        pieces = [(s.name, p) for s, seeds_one in tables for p in table_pieces(s, seeds_one)]
        # worker processes only where there are seeds to share out (the goal table: one per row)
        jobs = max(1, min(jobs, len({p.seed for _, p in pieces}))) if keep else 1
        reused = [(t, p) for t, p in pieces if store.has(t, p)]
        if log:
            _log_start(run, pieces, reused, jobs)
        desc = f"pieces ({len(reused)} reused)"
        bar = tqdm(
            total=len(pieces),
            initial=len(reused),
            unit="piece",
            desc=desc,
            disable=not (log and write),
        )
        run.log = runs.above(stack.enter_context(bar), log) if log else None
        # every piece first (in one pool of workers), then the files: a stopped run has written
        # none, and its re-run replaces nothing
        compute_pieces(run, tables, jobs, bar)
        sections, metas, results = [], [], {}
        for spec, seeds_one in tables:
            results[spec.name], table = run_table(spec, run, seeds_one, out, write)
            if write:
                metas.append(table_meta(run, spec, seeds_one, command, time.time() - t0, jobs))
                sections.append(_write_table(spec, run, out, metas[-1], results[spec.name], table))
        if name == "all" and write:
            report = write_report(out, sections, metas, tables=results)
            if log:
                run.log(f"report: {report}")


def _log_start(run: Run, pieces: list, reused: list, jobs: int) -> None:
    """The run's first lines: its key, where its pieces are kept, and those an earlier run of the
    same key finished, named."""
    workers = f"; {jobs} worker processes of one thread" if jobs > 1 else ""
    run.log(
        f"run key {run.store.key[:16]}: {len(pieces)} pieces (table, method, seed), kept in "
        f"{run.store.root} as they finish{workers}"
    )
    for table in dict.fromkeys(t for t, _ in reused):
        done = [p.stem for t, p in reused if t == table]
        run.log(
            f"{table}: {len(done)} of {sum(t == table for t, _ in pieces)} pieces done by an "
            f"earlier run of the same key, reused from {run.store.table_dir(table)}: "
            + ", ".join(done)
        )


def _write_table(spec: TableSpec, run: Run, out, meta: dict, res: dict, table: str) -> tuple:
    """A table's files, <name>.json (its meta and results) and <name>.md; its section of the
    report."""
    md = section_markdown(spec, meta, table)
    files = [out / f"{spec.name}.json", out / f"{spec.name}.md"]
    runs.write_json(files[0], dict(meta=meta, results=res), indent=1)
    runs.write_atomic(files[1], table_file_markdown(spec, md))
    if run.log:
        run.log(f"\n{spec.title}\n{table}")
    return spec.title, md, list(spec.figures)


def check_outputs(names, out_dir, overwrite: bool) -> None:
    """Before any work: out_dir must be writable, and no file a run of these tables would write
    (each table's <name>.json and .md, its figures, report.md where there are several) may exist
    already unless overwrite. OutputRefused naming the folder or the files."""
    out = pathlib.Path(out_dir).resolve()

    def inside(folder):
        return folder == out or folder in out.parents

    # before check_writable makes the folder
    if REAL.name in names and inside(runs.ROOT) and not inside(runs.ROOT / "runs"):
        raise runs.OutputRefused(
            f"--out {out_dir}: the real-scene results derive from the Waymo Open Dataset, whose "
            "licence forbids committing them; inside this repository they go under runs/ "
            f"(git-ignored; default {REAL_OUT}/), or write them outside it"
        )
    try:
        check_writable(out_dir, "--out")
    except ValueError as e:
        raise runs.OutputRefused(str(e)) from None
    out = pathlib.Path(out_dir)
    files = [out / f"{n}{ext}" for n in names for ext in (".json", ".md")]
    files += [out / f for n in names for f in SPECS[n].figures]
    files += [out / "report.md"] if len(names) > 1 else []
    existing = [str(f) for f in files if f.exists()]
    if existing and not overwrite:  # a run never replaces a result it did not make
        raise runs.OutputRefused(
            f"--out: {len(existing)} result file(s) of this run exist already and are kept: "
            f"{', '.join(existing[:6])}{' ...' if len(existing) > 6 else ''}; pass --overwrite to "
            f"replace them, or choose another --out"
        )


def rendered(name: str, out_dir) -> tuple:
    """(out_dir/<name>.json, its contents, its section's markdown, the Config of its learning
    curves or None), every field render reads checked: ValueError naming the file and the field,
    before anything is written."""
    if name not in SPECS:
        raise ValueError(f"name: {name!r} is not an experiment ({', '.join(SPECS)})")
    src = pathlib.Path(out_dir) / f"{name}.json"
    if not src.exists():
        raise ValueError(f"{src}: missing, nothing to render {name} from")
    saved = runs.read_results(src)
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


def render_outputs(name: str, out_dir="results", data=None, log=print) -> list:
    """Re-write the .md files and learning curves (their reference lines when `data`, a function
    that gives the data, is given) of an earlier run of `name` ('all': every table and report.md)
    from its JSON files in out_dir, training nothing; every file is read and checked before the
    first is written. Returns the paths."""
    names = EXPERIMENTS if name == "all" else (name,)
    out = pathlib.Path(out_dir)
    done = {one: rendered(one, out) for one in names}
    written, sections = [], []
    for one, (src, saved, section, cfg) in done.items():
        spec = SPECS[one]
        runs.write_atomic(src.with_suffix(".md"), table_file_markdown(spec, section))
        written.append(src.with_suffix(".md"))
        if cfg is not None:  # (no learning curves in older runs)
            ref = figures.learning_curve_reference(data(), cfg, CURVE_SAMPLES) if data else None
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


def real_data(data, phases=(0,), cache_dir="data_cache", log=print) -> data_synth.Dataset:
    """data's (synthetic) training side, and the Waymo samples (fetched on the first call) as the
    validation side (no scene logs: no closed loop)."""
    real, report = waymo.load_waymo_scenarios(cache_dir, tuple(phases), log=log)
    log(
        f"real: {report['samples']} samples from {report['files']} Waymo logs "
        f"({len(tuple(phases))} 2 Hz phase(s) each), training on {len(data.train)} synthetic "
        f"samples. {waymo.WAYMO_LICENCE}"
    )
    return data_synth.Dataset(data.train, real, None, data.train_draws)


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
    ap.add_argument(
        "--phases",
        type=bounded(int, 1, waymo.WAYMO_PHASES, "--phases"),
        default=1,
        help="real: how many of the five 2 Hz clocks of each 10 Hz log give samples (default 1)",
    )
    ap.add_argument(
        "--seeds",
        type=bounded(int, 1, 100, "--seeds"),
        help="training seeds per method, 1-100 (default: 10 for Table 1, 5 for the others)",
    )
    ap.add_argument(
        "--epochs",
        type=bounded(float, 0, 1000, "--epochs"),
        default=40.0,
        help="training epochs per method, in (0, 1000] (default 40, the committed tables')",
    )
    ap.add_argument(
        "--n",
        "--samples",
        type=bounded(int, 10, data_synth.MAX_SAMPLES, "--n"),
        default=10000,
        help="synthetic scenarios per training draw (default 10000; each seed trains on the 85 %% "
        "of its own draw's scenes); under torchrun --samples (torchrun's parser takes --n)",
    )
    ap.add_argument(
        "--val",
        type=bounded(int, 10, data_synth.MAX_SAMPLES, "--val"),
        default=ex.VAL_N,
        help=f"samples of the common validation set of every method and seed (default "
        f"{ex.VAL_N:,}; data seed {ex.VAL_SEED}, which no training draw holds)",
    )
    ap.add_argument("--data", help="a nuScenes folder (real, or data_synth.py's) for the data")
    ap.add_argument("--out", help=f"where the results go (default results/; real: {REAL_OUT}/)")
    ap.add_argument(
        "--render",
        action="store_true",
        help="train nothing: re-write the .md files, the report and the learning curves of an "
        "earlier run from its JSON files in --out",
    )
    ap.add_argument(
        "--validation-spread",
        action="store_true",
        help="train nothing: print GT prediction's relative hindsight cost on 5 unseen "
        "validation draws at 1,500 samples and at --val's default (about 2 minutes)",
    )
    add_shared_options(
        ap,
        threads="torch threads (default 2; 1 on a machine where other work keeps a core busy)",
        jobs="worker processes of one thread each, running a table's seeds side by side "
        f"(default: the machine's cores, here {os.cpu_count()}; 1 under torchrun)",
        device="where training, evaluation and the stack run: cpu (default), cuda, cuda:N or mps",
        overwrite="replace result files in --out (without it, the run refuses to start)",
        set="override a Config field, e.g. --set beta=2 (repeatable)",
    )
    return ap


def main(argv=None):
    # Under torchrun every process runs main: all ranks train together (DDP) and evaluate alike;
    # rank 0 prints and writes
    rank, world, misuse = runs.ranks()
    if misuse:  # every process says it: none of them can reach the others
        print(f"experiments.py: error: {misuse}", file=sys.stderr)
        sys.exit(2)
    if world > 1:  # a rank ends with the torchrun that started it, as a --jobs worker with its run
        runs.die_with_parent(os.getppid())
    ap = parser()
    if rank != 0:  # the same errors come up on every rank: rank 0 says them, the others exit alike
        ap.error = lambda message: sys.exit(2)
    args = ap.parse_args(argv)
    if args.validation_spread:
        return print(validation_spread())
    if args.experiment is None:
        ap.error("the following arguments are required: --experiment")
    args.out = args.out or (REAL_OUT if args.experiment == REAL.name else "results")
    launcher = f"torchrun --nproc_per_node {world} " if world > 1 else "python "
    command = runs.command_line(launcher + "experiments.py", sys.argv[1:] if argv is None else argv)
    # --out is held from the checks to the end (runs.folder_lock: one run per folder); the project's
    # errors and a file's (a NaN result, a bad JSON) are one line
    kept = "the pieces finished so far are kept, and the same command resumes the run"
    with contextlib.ExitStack() as held, runs.one_line(ap, kept):
        if args.data is not None:  # before --out is made: a folder that holds a nuScenes version
            lab_data.nuscenes_version(args.data)
        if args.render:  # derived files only, from the JSON an earlier run wrote
            held.enter_context(runs.folder_lock(args.out, command))
            return render_outputs(args.experiment, args.out, lambda: _load(args, (0,), print))
        return _main(args, world, rank, command, held)


def _main(args, world: int, rank: int, command: str, held):
    """experiments.py's run: everything that can be checked before the data is made and the first
    model trained, then the data (rank 0 first), then the tables."""
    names = EXPERIMENTS if args.experiment == "all" else (args.experiment,)
    seeds = range(args.seeds) if args.seeds is not None else None  # (None: each table's own count)
    cfg = config_with(Config(), args.set)
    if cfg.batch_size % world:
        raise ValueError(
            f"--set batch_size={cfg.batch_size}: a training batch must split evenly over the "
            f"{world} processes torchrun started; choose a multiple of {world}"
        )
    if args.jobs is not None and args.jobs > 1 and world > 1:
        raise ValueError(f"--jobs {args.jobs}: under torchrun the processes train together (DDP)")
    check_outputs(names, args.out, args.overwrite)
    check_writable("data_cache", "the data cache (./data_cache)")  # synthetic, nuScenes, Waymo
    if rank == 0:
        held.enter_context(runs.folder_lock(args.out, command))
    device = start_distributed(args.device) if world > 1 else args.device
    threads, why = (args.threads, "--threads") if args.threads else runs.default_threads()
    torch.set_num_threads(threads)
    # flushed line by line: a run's log is often a file, read while it runs
    log = functools.partial(print, flush=True) if rank == 0 else (lambda *a, **k: None)
    log(f"torch threads: {threads} ({why}; --threads N to choose)")

    def load():  # (the data, None), or (None, why it cannot be made)
        try:
            data = _load(args, range(max(len(table_seeds(SPECS[n], seeds)) for n in names)), log)
            if "closed_loop" in names:
                closed_loop_scenes(data.val_scenes, cfg)
            return data, None
        except (ValueError, OSError) as e:  # (OSError: a file, or the Waymo download offline)
            return None, str(e)

    try:
        # Rank 0 makes (or reads) the data caches first, the others then read them: one process
        # generates or parses, and if it fails the others hear of it (a broadcast) instead of
        # waiting for it at the first training step.
        data, error = load() if rank == 0 else (None, None)
        if world > 1:
            verdict = [error]
            dist.broadcast_object_list(verdict, src=0)
            error = verdict[0]
            if rank != 0 and error is None:
                data, error = load()
        if error is not None:
            raise ValueError(error)
        jobs = args.jobs or (1 if world > 1 else os.cpu_count() or 1)
        opts = dict(overwrite=args.overwrite, device=device, write=rank == 0, jobs=jobs)
        return run_experiment(
            args.experiment, data, cfg, seeds, args.epochs, args.out, command, log, **opts
        )
    finally:
        if world > 1:
            dist.destroy_process_group()


def _load(args, seeds, log):
    """The data a command names: synthetic (a training draw per seed: experiment_data) or a
    nuScenes folder, the Waymo scenes as validation for `real`."""
    if args.data is None:
        data = experiment_data(args.n, seeds, args.val, log=log)
    else:
        data = lab_data.load_data(args.data, args.n, log=log)
    return real_data(data, range(args.phases), log=log) if args.experiment == REAL.name else data
