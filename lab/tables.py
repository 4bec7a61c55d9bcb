"""Running the paper's tables (experiments.py's command line hands over here): each table cut into
(method, seed) pieces, computed alone (in worker processes with --jobs), kept as they finish and
resumed by a re-run (lab/runs.py), then assembled, written and rendered; torchrun's ranks."""

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
from lab.cli import torch_threads
from lab.ddp import Shard
from lab.report import has_curves, results_markdown, section_markdown, table_file_markdown
from lab.report import write_report
from specs import CURVE_SAMPLES, EXPERIMENTS, GOALS, REAL, REAL_OUT, SPECS, TableSpec
from specs import COST_WEIGHTS_ROW
from train import GT_PREDICTION, NO_PREDICTION, TrainingDiverged


class Piece(NamedTuple):
    """One result of a table: a method and a seed; section: the ablation's section or the goal."""

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
    """The seeds given, else the spec's own count (Table 1: 10, the others 5)."""
    return tuple(range(spec.seeds)) if seeds is None else tuple(seeds)


def table_sections(spec: TableSpec) -> list:
    """(title, run_stack options, rows) per section: the ablation's (each with No and GT
    prediction), the goal table's goals, else one untitled."""
    if spec.kind == "goal":
        return [(goal, {}, spec.methods) for goal in GOALS]
    sections = [(t, kw, (NO_PREDICTION, *ms, GT_PREDICTION)) for t, kw, ms in spec.sections]
    return sections or [(None, {}, spec.methods)]


def _seeds(m, seeds) -> tuple:  # every seed for a method that trains, else the first
    return tuple(seeds) if m.predictor == "learned" else tuple(seeds)[:1]


def table_pieces(spec: TableSpec, seeds) -> list:
    return [
        Piece(m.name, s, title)
        for title, _, methods in table_sections(spec)
        for m in methods
        for s in _seeds(m, seeds)
    ]


@dataclasses.dataclass
class Run:
    """What the pieces of a run share, named as experiments.py's functions take them."""

    data: object
    cfg: Config
    epochs: float
    store: runs.RunStore
    device: object = "cpu"
    log: object = print
    models: dict = dataclasses.field(default_factory=dict)


def _open_loop(run: Run, spec: TableSpec, piece: Piece, m, stack_kw: dict) -> tuple:
    on = dict(setting=spec.setting, pred_offset=spec.pred_offset, **stack_kw)
    rows = ex.open_loop_experiment(methods=(m,), seeds=(piece.seed,), **on, **vars(run))
    return rows[m.name][0], None


def _cost(run: Run, spec: TableSpec, piece: Piece, m, stack_kw: dict) -> tuple:
    return ex.cost_learning_seed(seed=piece.seed, **vars(run)), None


def _closed_loop(run: Run, spec: TableSpec, piece: Piece, m, stack_kw: dict) -> tuple:
    """One method and seed in the closed loop, its rollout kept for the figure."""
    scenes = closed_loop_scenes(run.data.val_scenes, run.cfg)
    r, roll, per_scene = ex.closed_loop_run(m, piece.seed, scenes, **vars(run))
    return r, dict(rollout=dataclasses.asdict(roll), per_scene=per_scene)


def _goal(run: Run, spec: TableSpec, piece: Piece, m, stack_kw: dict) -> tuple:
    cfg = dataclasses.replace(run.cfg, goal=piece.section)
    return ex.goal_breakdown(run.data.val, m, cfg, run.device), None


def _relative(spec: TableSpec, rows: dict) -> dict:
    return ex.add_relative(rows, spec.setting)


def _cost_rows(spec: TableSpec, rows: dict) -> dict:
    """Table 3's rows, hand-tuned and learned, from its pieces (a diverged seed in both)."""
    seeds = rows[COST_WEIGHTS_ROW.name]
    return {name: [r.get(name, r) for r in seeds] for name in ("Hand-tuned", "Learned")}


# kind -> (piece(run, spec, piece, method, run_stack options) -> (result, tensors to keep or None),
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
    """(result, tensors or None, timing) of a piece; a divergence is a result: {'diverged': why}."""
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
    """A table's results from its pieces {Piece: result}, per section where it has several."""
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
    """The missing pieces of tables [(spec, seeds)] as units (spec, pieces) of one (table, section,
    seed): the ablation's first (short ones fill the workers at the end), the seeds alternating (no
    two workers train the same predictor side by side)."""
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
    """A worker's unit, on one thread (the table by name: a spec's lambdas do not pickle)."""
    torch.set_num_threads(1)
    tag = f"[{table} seed {pieces[0].seed}]"
    run = dataclasses.replace(
        run, log=functools.partial(print, tag, flush=True) if run.log else None
    )
    for piece in pieces:
        run.store.save(table, piece, *compute_piece(run, SPECS[table], piece))


def compute_pieces(run: Run, tables: list, jobs: int, bar) -> None:
    """The missing pieces of tables [(spec, seeds)], each kept as it finishes, in `jobs` workers."""
    units = work_units(tables, run.store)
    if jobs > 1 and len(units) > 1:
        shipped = dataclasses.replace(run, log=print if run.log else None, models={})
        work = [(shipped, spec.name, pieces) for spec, pieces in units]
        runs.in_workers(_in_worker, work, jobs, lambda u, _: bar.update(len(u[2])), run.store.root)
        return
    for spec, seeds in tables:
        for piece in [p for p in table_pieces(spec, seeds) if not run.store.has(spec.name, p)]:
            run.store.save(spec.name, piece, *compute_piece(run, spec, piece))
            bar.update()


def run_table(spec: TableSpec, run: Run, seeds, out_dir="results", write=True, jobs=1, bar=None):
    """A table's missing pieces computed, its figures drawn if `write`: (results, markdown)."""
    seeds = tuple(seeds)
    compute_pieces(run, [(spec, seeds)], jobs, bar or tqdm(disable=True))
    loaded = {p: run.store.load(spec.name, p) for p in table_pieces(spec, seeds)}
    res = assemble(spec, {p: r for p, (r, _) in loaded.items()}, seeds)
    if write:
        draw_figures(spec, run, res, loaded, seeds, pathlib.Path(out_dir))
    return res, results_markdown(spec, res)


def draw_figures(spec: TableSpec, run: Run, res: dict, loaded: dict, seeds, out) -> None:
    """The figures a spec names: from its results, the kept rollouts, or the first seed's models."""
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
    try:
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
    """A table's provenance, and the computing time summed over its pieces (and their machines)."""
    meta = dict(experiment=spec.name, command=command, seeds=list(seeds), epochs=run.epochs)
    meta.update(seconds=seconds)
    timings = [run.store.read(spec.name, p).get("timing") for p in table_pieces(spec, seeds)]
    if all(timings):
        meta.update(piece_seconds=sum(t["seconds"] for t in timings))
        meta.update(piece_cpu_seconds=sum(t["cpu_seconds"] for t in timings), pieces=len(timings))
        computed_on = collections.Counter(t["machine"] for t in timings if "machine" in t)
        if len(computed_on) > 1:
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
    """Run one table (or 'all', each predictor trained once) into out_dir (write=False: torchrun's
    other ranks), every piece kept in out_dir/.runs/; OutputRefused where a file exists."""
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
            workers = f"; {jobs} worker processes of one thread" if jobs > 1 else ""
            log(f"run key {key[:16]}: {len(pieces)} pieces, kept in {root} as they end{workers}")
        for table in dict.fromkeys(t for t, _ in reused) if log else ():
            done = [p.stem for t, p in reused if t == table]
            log(
                f"{table}: {len(done)} of {sum(t == table for t, _ in pieces)} pieces done by an "
                f"earlier run, reused from {store.table_dir(table)}: {', '.join(done)}"
            )
        desc, show = f"pieces ({len(reused)} reused)", log and write
        bar = tqdm(
            total=len(pieces), initial=len(reused), unit="piece", desc=desc, disable=not show
        )
        stack.enter_context(bar)

        def above_bar(*a, **k):
            with bar.external_write_mode():
                log(*a, **k)

        run.log = above_bar if log else None
        # every piece first, then the files, listed first: a run stopped among them resumes
        compute_pieces(run, tables, jobs, bar)
        if write:
            runs.write_json(out / WRITING, [str(f) for f in output_files(names, out)])
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
        if write:
            (out / WRITING).unlink()


def _write_table(spec: TableSpec, run: Run, out, meta: dict, res: dict, table: str) -> tuple:
    """<name>.json and <name>.md; returns its section of the report."""
    md = section_markdown(spec, meta, table)
    runs.write_json(out / f"{spec.name}.json", dict(meta=meta, results=res), indent=1)
    runs.write_atomic(out / f"{spec.name}.md", table_file_markdown(spec, md))
    if run.log:
        run.log(f"\n{spec.title}\n{table}")
    return spec.title, md, list(spec.figures)


WRITING = ".writing.json"  # the files a run is writing, until every one is written


def output_files(names, out) -> list:
    files = [out / f"{n}{ext}" for n in names for ext in (".json", ".md")]
    files += [out / f for n in names for f in SPECS[n].figures]
    return files + ([out / "report.md"] if len(names) > 1 else [])


def check_outputs(names, out_dir, overwrite: bool) -> None:
    """Before any work, OutputRefused unless out_dir takes its files (real scenes: under runs/)."""
    out = pathlib.Path(out_dir).resolve()

    def inside(folder):
        return folder == out or folder in out.parents

    if REAL.name in names and inside(runs.ROOT) and not inside(runs.ROOT / "runs"):
        raise runs.OutputRefused(
            f"--out {out_dir}: the real scenes' results derive from Waymo's data, whose licence "
            f"forbids committing them; in this repository they go under runs/ (default {REAL_OUT})"
        )
    try:
        check_writable(out_dir, "--out")
    except ValueError as e:
        raise runs.OutputRefused(str(e)) from None
    half, files = pathlib.Path(out_dir) / WRITING, output_files(names, pathlib.Path(out_dir))
    stopped = runs.load_json(half, "a list of files") if half.exists() else []  # a stopped run's
    existing = [str(f) for f in files if f.exists() and str(f) not in stopped]
    if existing and not overwrite:  # a run never replaces a result it did not make
        raise runs.OutputRefused(
            f"--out: {len(existing)} result file(s) exist and are kept: {', '.join(existing[:6])}"
            f"{' ...' if len(existing) > 6 else ''}; pass --overwrite, or choose another --out"
        )


def rendered(name: str, out_dir) -> tuple:
    """(out_dir/<name>.json, its contents, markdown, curves' Config or None), or ValueError."""
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
    """--render: the .md files, learning curves and report of `name` from its JSON; the paths."""
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


def start_distributed(device: torch.device) -> torch.device:
    """Join torchrun's process group (gloo on CPUs, nccl on cuda:LOCAL_RANK): this rank's device."""
    if device.type == "cuda":
        local = int(os.environ.get("LOCAL_RANK", 0))
        if local >= torch.cuda.device_count():
            raise ValueError(f"--device {device}: rank {local} has no cuda:{local} here")
        device = torch.device("cuda", local)
        torch.cuda.set_device(device)
        dist.init_process_group("nccl", device_id=device)
    elif device.type == "cpu":
        dist.init_process_group("gloo")
    else:
        raise ValueError(f"--device {device}: torchrun trains on cpu or cuda")
    return device


def parser() -> argparse.ArgumentParser:
    """experiments.py's command line."""
    ap = argparse.ArgumentParser(description="DiffStack (CoRL 2022): the paper's tables, run here.")
    ap.add_argument(
        "--experiment",
        choices=EXPERIMENTS + (REAL.name, "all"),  # (required, but by --validation-spread)
        help=f"a table; all: every one and the report; real: Waymo's scenes (into {REAL_OUT}/)",
    )
    phases = bounded(int, 1, waymo.WAYMO_PHASES, "--phases")
    ap.add_argument("--phases", type=phases, default=1, help="real: 2 Hz phases per log")
    seeds = bounded(int, 1, 100, "--seeds")
    ap.add_argument("--seeds", type=seeds, help="seeds per method (default: Table 1 10, others 5)")
    epochs = bounded(float, 0, 1000, "--epochs")
    ap.add_argument("--epochs", type=epochs, default=40.0, help="training epochs (default 40)")
    n, n_help = bounded(int, 10, data_synth.MAX_SAMPLES, "--n"), "scenarios per training draw"
    ap.add_argument(
        "--n", "--samples", type=n, default=10000, help=n_help + " (torchrun: --samples)"
    )
    val = bounded(int, 10, data_synth.MAX_SAMPLES, "--val")
    ap.add_argument("--val", type=val, default=ex.VAL_N, help="validation samples")
    ap.add_argument("--data", help="a nuScenes folder (real, or data_synth.py's) for the data")
    ap.add_argument("--out", help=f"where the results go (default results/; real: {REAL_OUT}/)")
    render = "train nothing: re-write the .md files, report and curves from --out's JSON"
    ap.add_argument("--render", action="store_true", help=render)
    spread = "train nothing: GT prediction's hindsight cost on 5 validation draws"
    ap.add_argument("--validation-spread", action="store_true", help=spread)
    add_shared_options(
        ap,
        threads="torch threads (default 2)",
        jobs="worker processes of one thread (default: the machine's cores; 1 under torchrun)",
        device="cpu (default), cuda, cuda:N or mps",
        overwrite="replace result files in --out",
        set="override a Config field, e.g. --set beta=2 (repeatable)",
    )
    return ap


def main(argv=None):
    # Under torchrun every process runs main: the ranks train together (DDP), rank 0 writes
    rank, world, misuse = runs.ranks()
    if misuse:  # every process says it: none of them can reach the others
        print(f"experiments.py: error: {misuse}", file=sys.stderr)
        sys.exit(2)
    if world > 1:  # a rank ends with the torchrun that started it
        runs.die_with_parent(os.getppid())
    ap = parser()
    if rank != 0:  # the same errors come up on every rank: rank 0 says them
        ap.error = lambda message: sys.exit(2)
    args = ap.parse_args(argv)
    if args.validation_spread:
        return print(validation_spread())
    if args.experiment is None:
        ap.error("the following arguments are required: --experiment")
    args.out = args.out or (REAL_OUT if args.experiment == REAL.name else "results")
    launcher = f"torchrun --nproc_per_node {world} " if world > 1 else "python "
    command = runs.command_line(launcher + "experiments.py", sys.argv[1:] if argv is None else argv)
    kept = "the pieces finished so far are kept, and the same command resumes the run"
    with contextlib.ExitStack() as held, runs.one_line(ap, kept):
        if args.data is not None:  # before --out is made: a folder that holds a nuScenes version
            lab_data.nuscenes_version(args.data)
        if args.render:
            held.enter_context(runs.folder_lock(args.out, command))
            return render_outputs(args.experiment, args.out, lambda: _load(args, (0,), print))
        return _main(args, world, rank, command, held)


def _main(args, world: int, rank: int, command: str, held):
    """Every check before the data, then the data (rank 0 first), then the tables."""
    names = EXPERIMENTS if args.experiment == "all" else (args.experiment,)
    seeds = range(args.seeds) if args.seeds is not None else None  # (None: each table's own)
    cfg = config_with(Config(), args.set)
    Shard(0, world).check_split(cfg.batch_size)
    if args.jobs is not None and args.jobs > 1 and world > 1:
        raise ValueError(f"--jobs {args.jobs}: under torchrun the processes train together (DDP)")
    check_outputs(names, args.out, args.overwrite)
    check_writable("data_cache", "the data cache (./data_cache)")
    if rank == 0:
        held.enter_context(runs.folder_lock(args.out, command))
    device = start_distributed(args.device) if world > 1 else args.device
    # flushed line by line: a run's log is often a file, read while it runs
    log = functools.partial(print, flush=True) if rank == 0 else (lambda *a, **k: None)
    torch.set_num_threads(torch_threads(args.threads, log))

    def load():  # (the data, None), or (None, why it cannot be made)
        try:
            data = _load(args, range(max(len(table_seeds(SPECS[n], seeds)) for n in names)), log)
            if "closed_loop" in names:
                closed_loop_scenes(data.val_scenes, cfg)
            return data, None
        except (ValueError, OSError) as e:  # (OSError: a file, or the Waymo download offline)
            return None, str(e)

    try:
        # rank 0 makes (or reads) the data first, then the others read it; its error is broadcast
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
    """The data a command names: synthetic (experiment_data) or nuScenes; `real`: Waymo's as val."""
    if args.data is None:
        data = experiment_data(args.n, seeds, args.val, log=log)
    else:
        data = lab_data.load_data(args.data, args.n, log=log)
    if args.experiment != REAL.name:
        return data
    real, report = waymo.load_waymo_scenarios("data_cache", tuple(range(args.phases)), log=log)
    log(f"real: {report['samples']} Waymo samples, training on {len(data.train)} synthetic samples")
    log(waymo.WAYMO_LICENCE)
    return data_synth.Dataset(data.train, real, None, data.train_draws)
