"""The run machinery under experiments.py, ignorant of tables: a run's pieces kept on disk as they
finish and resumed (RunStore), atomic writes, provenance (the run key: config, data, code, device;
the git commit), refusing to overwrite outputs a run did not make, the worker pool, and the
progress bar.

A piece is one result of a run under a name (a table): anything with a `stem` (its file name) and
`_asdict()` (a NamedTuple; experiments.Piece). A run's pieces live next to its outputs, in
<out>/.runs/<name>/<name key>/<piece stem>.json (with a .pt of tensors beside it where it has some),
written atomically the moment the piece is made. The name key is a hash of the run key and the name;
the run key, of everything that determines the numbers: the Config, the epochs, the data (a hash of
its tensors), the code (a hash of the modules that make numbers, code_version) and the device.
Re-running the same command loads the finished pieces and computes only the missing ones; any change
to the config, data or code is another key, so nothing of another run is mixed in. The seeds are not
part of the key (a piece is one seed), nor is the thread count (it moves only the last digits,
README Usage). Trained models go in <out>/.runs/models/<run key>/ (RunStore.model_path).
"""

from __future__ import annotations

import ast
import contextlib
import dataclasses
import errno
import fcntl
import functools
import hashlib
import json
import math
import os
import pathlib
import shutil
import subprocess
import sys
import tempfile
import threading
import time

import torch
from tqdm import tqdm

RUNS_DIR = ".runs"
# the repository: this file is lab/runs.py
ROOT = pathlib.Path(__file__).resolve().parent.parent


def sha(*parts) -> str:
    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()


def to_json(o):
    """json.dumps' default for results: a tensor as a list, anything else as its str."""
    return o.tolist() if torch.is_tensor(o) else str(o)


MAX_JSON_BYTES = 512 * 2**20  # the largest JSON file the project reads (its results: a few MB)
MAX_JSON_DEPTH = 32  # and the deepest nesting (its results: 9)


def load_json(path, what: str):
    """The JSON document in path, or one ValueError naming the file and what is wrong: unreadable,
    larger than MAX_JSON_BYTES, not JSON, nested deeper than MAX_JSON_DEPTH, or holding NaN or
    infinity (which the project never writes). what: what the file should be, for the message."""
    path = pathlib.Path(path)

    def constant(name):
        raise ValueError(f"it holds {name}, which no file of the project holds")

    try:
        if path.stat().st_size > MAX_JSON_BYTES:
            raise ValueError(f"larger than {MAX_JSON_BYTES // 2**20} MB")
        doc = json.loads(path.read_text(), parse_constant=constant)
    except OSError as e:
        raise ValueError(f"{path}: cannot read it ({e.strerror or e})") from None
    except RecursionError:
        raise ValueError(f"{path}: not {what} (nested too deeply)") from None
    except ValueError as e:  # (UnicodeDecodeError and JSONDecodeError too)
        raise ValueError(f"{path}: not {what} ({e})") from None
    stack = [(doc, 0)]
    while stack:
        o, depth = stack.pop()
        if depth > MAX_JSON_DEPTH:
            raise ValueError(f"{path}: not {what} (nested deeper than {MAX_JSON_DEPTH} levels)")
        items = o.values() if isinstance(o, dict) else o if isinstance(o, list) else ()
        stack += [(v, depth + 1) for v in items]
    return doc


RESULTS_META = {"command": "text", "date": "text", "machine": "text", "seconds": "number"}
_KINDS = {"text": str, "number": (int, float)}


def read_results(path, meta_fields=RESULTS_META) -> dict:
    """A results file an earlier run wrote ({'meta': ..., 'results': ...}, meta with the fields of
    meta_fields {name: 'text' or 'number'}, by default those a table's header shows); ValueError
    naming the file and the field otherwise."""
    what = "a results file of python experiments.py"
    saved = load_json(path, what)
    if not isinstance(saved, dict) or not {"meta", "results"} <= saved.keys():
        raise ValueError(f"{path}: not {what} (no 'meta' and 'results')")
    meta, results = saved["meta"], saved["results"]
    if not isinstance(meta, dict) or not isinstance(results, dict):
        raise ValueError(f"{path}: not {what} ('meta' and 'results' must be objects)")
    for field, kind in meta_fields.items():
        if not isinstance(meta.get(field), _KINDS[kind]) or isinstance(meta.get(field), bool):
            raise ValueError(f"{path}: meta.{field} is missing or not {kind}")
    stack = [(results, "results")]
    while stack:  # a result is numbers, text and lists and objects of them: never null
        o, where = stack.pop()
        if o is None:
            raise ValueError(f"{path}: {where} is null, where a result belongs")
        items = o.items() if isinstance(o, dict) else enumerate(o) if isinstance(o, list) else ()
        stack += [
            (v, f"{where}[{k!r}]" if isinstance(k, int) else f"{where}.{k}") for k, v in items
        ]
    return saved


def first_non_finite(o, keys=()) -> tuple | None:
    """(the keys down to it, the value) of the first NaN or infinite number in o (nested dicts and
    lists), or None when every one is finite."""
    if isinstance(o, float) and not math.isfinite(o):
        return keys, o
    items = o.items() if isinstance(o, dict) else enumerate(o) if isinstance(o, list) else ()
    for k, v in items:
        if (found := first_non_finite(v, (*keys, k))) is not None:
            return found
    return None


def results_json(obj, name: str) -> str:
    """obj as the text of the result file `name`; ValueError naming the first NaN or infinity,
    never written."""
    try:
        return json.dumps(obj, indent=1, default=to_json, allow_nan=False)
    except ValueError:
        found = first_non_finite(json.loads(json.dumps(obj, default=to_json)))
        where = "a value" if found is None else "".join(f"[{k!r}]" for k in found[0])
        raise ValueError(
            f"{name}: {where}{'' if found is None else f' = {found[1]}'} is not finite; a result "
            "is never written with NaN or infinity"
        ) from None


# ============================================================================================
# Atomic writes
# ============================================================================================


# the process's umask, read once at import (reading it means setting it) and put back
_UMASK = os.umask(0o022)
os.umask(_UMASK)


def _usual_permissions(path) -> None:
    """The permissions open() would have given a new file (0666 less the umask): mkstemp makes its
    files 0600, and a result only its owner can read is no use in a shared lab folder."""
    os.chmod(path, 0o666 & ~_UMASK)


class DiskFull(OSError):
    """A write that found its disk full: one line naming the file and the space it needs."""

    def __str__(self):
        return self.args[0]


def _nbytes(obj) -> int:
    """About how many bytes torch.save writes for obj: its tensors' data."""
    if torch.is_tensor(obj):
        return obj.numel() * obj.element_size()
    items = obj.values() if isinstance(obj, dict) else obj if isinstance(obj, (list, tuple)) else ()
    return sum(_nbytes(v) for v in items)


def replace_atomic(path, write, needed: int) -> None:
    """write(a temporary file of the same name, in a temporary folder beside path), then rename it
    onto path: a kill mid-write leaves the old file intact, a failed write leaves nothing behind,
    and a full disk is one DiskFull line naming the file and the space it needs (about `needed`
    bytes). The same name keeps a figure's format and torch.save's bytes (its archive is named
    after the file)."""
    path = pathlib.Path(path)
    folder = tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    tmp = os.path.join(folder, path.name)
    try:
        write(tmp)
        _usual_permissions(tmp)
        os.replace(tmp, path)
    except BaseException as e:
        shutil.rmtree(folder, ignore_errors=True)
        free = shutil.disk_usage(path.parent).free
        # torch.save reports a full disk as a RuntimeError ("file write failed")
        full = isinstance(e, OSError) and e.errno in (errno.ENOSPC, errno.EDQUOT)
        if full or (isinstance(e, RuntimeError) and free < needed + 2**20):
            raise DiskFull(
                f"{path}: cannot write it, {os.strerror(errno.ENOSPC)} (it needs about "
                f"{max(needed, 1) / 2**20:.1f} MB, {free / 2**20:.1f} MB are free); nothing of it "
                "was written, and an earlier version of it, if any, is kept"
            ) from None
        raise
    os.rmdir(folder)


def write_atomic(path: pathlib.Path, text: str) -> None:
    """Write text to path through a temporary file and a rename (replace_atomic)."""

    def write(tmp):
        with open(tmp, "w") as f:
            f.write(text)

    replace_atomic(path, write, len(text.encode()))


def write_file_atomic(path, write) -> None:
    """write(temporary path) then a rename onto path (replace_atomic), for writers that take a
    path (a figure's savefig)."""
    replace_atomic(path, write, 0)


def save_atomic(obj, path) -> None:
    """torch.save through a temporary file and a rename (replace_atomic)."""
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    replace_atomic(path, lambda tmp: torch.save(obj, tmp), _nbytes(obj))


# ============================================================================================
# Provenance: the run key, the git commit
# ============================================================================================


# The modules whose code makes a run's numbers. specs.py is not one: what a table's spec sets that
# moves numbers (its methods, setting, offset, sections) is part of the table's own key, by value
# (experiments.spec_key), and its titles, columns and the paper's numbers are text.
NUMBER_MODULES = (
    "diffstack.py",
    "train.py",
    "lab/ddp.py",
    "data_synth.py",
    "lab/data.py",
    "lab/nuscenes.py",
    "lab/waymo.py",
    "experiments.py",
    "lab/tables.py",
)


class _NoText(ast.NodeTransformer):
    """Drops what is text for people: every statement that is a string and nothing else (a
    docstring, or a field's docstring in Config), and every string or f-string with a space in its
    text (a log line, an error message, a title, markdown), which becomes ''. A string without a
    space (a key, a name such as 'rl', 'distance' or f'rel_{key}') is code."""

    def visit_Expr(self, node):
        if isinstance(node.value, ast.Constant) and isinstance(node.value.value, str):
            return None
        return self.generic_visit(node)

    def visit_JoinedStr(self, node):
        parts = [v.value for v in node.values if isinstance(v, ast.Constant)]
        return ast.Constant("") if any(c.isspace() for p in parts for c in p) else node

    def visit_Constant(self, node):
        if isinstance(node.value, str) and any(c.isspace() for c in node.value):
            return ast.Constant("")
        return node


# parsing the three modules takes about 0.4 s; a run asks once per work unit
@functools.lru_cache(maxsize=8)
def code_of(source: str) -> str:
    """A module's code without what cannot change a number: its comments, layout and text. The
    source is parsed, its text dropped (_NoText: docstrings, log lines, messages, titles) and the
    tree written back out by ast.unparse, so a re-wrapped line or an edited comment, docstring, log
    line or title gives the same code; any other change does not."""
    tree = _NoText().visit(ast.parse(source))
    for node in ast.walk(tree):
        if getattr(node, "body", None) == []:  # a function or class that held only its docstring
            node.body = [ast.Pass()]
    return ast.unparse(tree)


def code_version() -> str:
    """The code a run's numbers come from: a hash of the code of the modules that make them
    (NUMBER_MODULES, as code_of reads them), so that any change to their code is a new run, while a
    commit of the README, the tests or the notebook, or of a comment, docstring or log line, is
    not.
    (ast.unparse is Python's own: under another Python version the same code may read as new, a new
    run, never a mixed one.)"""
    h = hashlib.sha256()
    for name in NUMBER_MODULES:
        h.update(name.encode() + b"\0" + code_of((ROOT / name).read_text()).encode() + b"\0")
    return f"sha256:{h.hexdigest()[:16]}"


def data_fingerprint(data) -> str:
    """A hash of the data's tensors (each part of `data` with a tensors() dict; a part that is a
    dict or None, as JSON): the same samples give the same fingerprint whichever file or folder they
    came from. About 0.1 s for 10 000 samples."""
    h = hashlib.sha256()
    for part in data:
        if part is None or isinstance(part, dict):
            h.update(json.dumps(part, sort_keys=True).encode())
            continue
        # (a tuple: the training draws, one per seed)
        for one in part if isinstance(part, tuple) else (part,):
            for name, t in sorted(one.tensors().items()):
                h.update(f"{name} {t.dtype} {tuple(t.shape)}".encode())
                h.update(t.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


def run_key(data, cfg, epochs, device="cpu") -> str:
    """The key of a run (cfg: a dataclass): the same key, the same numbers (at the same
    thread count)."""
    return sha(
        dict(
            config=dataclasses.asdict(cfg),
            epochs=float(epochs),
            data=data_fingerprint(data),
            code=code_version(),
            device=str(device),
        )
    )


def command_line(launcher: str, argv) -> str:
    """The command as a result records it: absolute paths inside the repository made relative to it,
    so that the record reads the same on every machine (`--out /home/me/diffstack/results` -> `--out
    results`)."""
    root = ROOT

    def rel(token):
        key, eq, value = token.partition("=") if token.startswith("--") else ("", "", token)
        path = pathlib.Path(value)
        if path.is_absolute() and path.resolve().is_relative_to(root):
            value = str(path.resolve().relative_to(root)) or "."
        return key + eq + value

    return " ".join([launcher, *(rel(t) for t in argv)])


def git_commit() -> str | None:
    """The commit the code was run from, '+dirty' when the work tree differs from it; None
    outside git."""
    try:
        head = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=ROOT,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None
    return head + ("+dirty" if dirty else "")


# ============================================================================================
# The store of a run's pieces
# ============================================================================================


class RunStore:
    """A run's pieces and models: under root (<out>/.runs) on disk, or in memory when root is None
    (nothing is resumed)."""

    def __init__(self, root, key: str, table_keys: dict | None = None):
        self.root = pathlib.Path(root) if root is not None else None
        self.key = key
        # {table: what its spec sets that moves numbers (by value)}: part of its folder's key
        self.table_keys = table_keys or {}
        self.memory = {}

    def table_dir(self, table: str) -> pathlib.Path:
        return self.root / table / sha(self.key, table, self.table_keys.get(table))[:16]

    def path(self, table: str, piece) -> pathlib.Path:
        return self.table_dir(table) / f"{piece.stem}.json"

    def has(self, table: str, piece) -> bool:
        """Whether the piece is finished; one whose file cannot be read (a disk error, an edit) is
        named on stderr, set aside as <piece>.corrupt and computed again."""
        if self.root is None:
            return (table, piece) in self.memory
        path = self.path(table, piece)
        try:
            return path.exists() and isinstance(
                load_json(path, "a piece of a run").get("result"), dict
            )
        except (OSError, ValueError, AttributeError) as e:
            print(
                f"{path}: not a finished piece ({e}); set aside as "
                f"{path.with_suffix('.corrupt').name}, computed again",
                file=sys.stderr,
            )
            os.replace(path, path.with_suffix(".corrupt"))
            return False

    def load(self, table: str, piece):
        """(result, extra) of a finished piece, or None."""
        if self.root is None:
            return self.memory.get((table, piece))
        path = self.path(table, piece)
        if not path.exists():
            return None
        saved = load_json(path, "a piece of a run")
        extra = (
            torch.load(path.with_suffix(".pt"), weights_only=True) if saved.get("extra") else None
        )
        return saved["result"], extra

    def timing(self, table: str, piece) -> dict | None:
        """How long a finished piece took to compute and where (the timing it was saved with), or
        None (not finished, or in memory)."""
        if self.root is None or not self.path(table, piece).exists():
            return None
        timing = load_json(self.path(table, piece), "a piece of a run").get("timing")
        return timing if isinstance(timing, dict) else None

    def save(self, table: str, piece, result: dict, extra=None, about=None, timing=None) -> None:
        """The piece's result (JSON; its extra tensors first, in a .pt beside it), atomically;
        about: what the key stands for, written once per table folder (run.json); timing: how long
        it took (see `timing`)."""
        if self.root is None:
            self.memory[(table, piece)] = (json.loads(json.dumps(result, default=to_json)), extra)
            return
        path = self.path(table, piece)
        path.parent.mkdir(parents=True, exist_ok=True)
        if about is not None and not (path.parent / "run.json").exists():
            write_atomic(path.parent / "run.json", json.dumps(about, indent=1, default=str))
        if extra is not None:
            save_atomic(extra, path.with_suffix(".pt"))
        write_atomic(
            path,
            json.dumps(
                dict(
                    table=table,
                    piece=piece._asdict(),
                    key=self.key,
                    extra=extra is not None,
                    timing=timing,
                    result=result,
                ),
                indent=1,
                default=to_json,
            ),
        )

    def model_path(self, train_key) -> pathlib.Path | None:
        """Where a model trained the way train_key says is kept (None: in memory only)."""
        return (
            None
            if self.root is None
            else self.root / "models" / self.key[:16] / f"{sha(repr(train_key))[:16]}.pt"
        )


# ============================================================================================
# Worker processes, progress
# ============================================================================================


class WorkerDied(ValueError):
    """A worker process of the run ended without its result (killed, out of memory): the run stops,
    saying so."""


def die_with_parent(parent: int) -> None:
    """A worker process's initializer: a thread that ends the worker once its parent is gone (killed
    with SIGKILL, say), so that no worker outlives the run it belongs to and writes pieces
    for nobody."""

    def watch():
        while os.getppid() == parent:
            time.sleep(0.5)
        os._exit(1)

    threading.Thread(target=watch, daemon=True).start()


def pool(jobs: int):
    """A pool of `jobs` worker processes (spawned: a fresh interpreter each) that die with
    this one."""
    from concurrent.futures import ProcessPoolExecutor

    return ProcessPoolExecutor(
        jobs,
        mp_context=torch.multiprocessing.get_context("spawn"),
        initializer=die_with_parent,
        initargs=(os.getpid(),),
    )


def _worker(compute, table: str, pieces: list, store: RunStore, about, verbose: bool) -> int:
    """A worker process: compute and save some pieces of one table into the store (its root and
    keys), on one thread. Returns how many."""
    torch.set_num_threads(1)
    store = RunStore(store.root, store.key, store.table_keys)
    models = {}
    log = (
        (lambda text: print(f"[{table} seed {pieces[0].seed}] {text}", flush=True))
        if verbose
        else None
    )
    for piece in pieces:
        result, extra, timing = compute(table, piece, log, models, store)
        store.save(table, piece, result, extra, about, timing)
    return len(pieces)


def compute_in_workers(compute, units: list, store: RunStore, jobs: int, abouts=None, verbose=True):
    """Compute units of work, each (table name, pieces of one seed), in `jobs` worker processes of
    one thread each, in the order given; each piece is saved in `store` (on disk) as it finishes.
    compute(table, piece, log, models, store) -> (result, extra, timing) makes a piece: a picklable
    callable (a module's function, or a functools.partial of one), `models` a dict the pieces of one
    unit share. abouts: {table: what its key stands for} (RunStore.save). Raises the first worker's
    error; WorkerDied when a worker ended without one."""
    from concurrent.futures import FIRST_EXCEPTION, wait
    from concurrent.futures.process import BrokenProcessPool

    abouts = abouts or {}
    with pool(min(jobs, len(units))) as workers:
        futures = [
            workers.submit(_worker, compute, name, ps, store, abouts.get(name), verbose)
            for name, ps in units
        ]
        try:
            finished, _ = wait(futures, return_when=FIRST_EXCEPTION)
        except BaseException:
            # Ctrl-C (or SIGINT to this process alone): stop the workers now, not after their pieces
            workers.shutdown(wait=False, cancel_futures=True)
            for worker in torch.multiprocessing.active_children():
                worker.terminate()
            raise
        for f in finished:
            if f.exception() is not None:
                workers.shutdown(cancel_futures=True)
                if isinstance(f.exception(), BrokenProcessPool):
                    raise WorkerDied(
                        f"a worker process died ({f.exception()}); the run stops here: the same "
                        f"command resumes it from the pieces kept in {store.root}"
                    ) from None
                raise f.exception()


@contextlib.contextmanager
def progress(store: RunStore, pieces: list, every: float = 2.0, disable: bool = False, **bar_kw):
    """A tqdm bar over pieces [(table, piece)], for the length of the with block: those the store
    has at the start count as done (reused), and the store is polled every `every` seconds (and at
    the end) for those finished since, in this process or in worker processes. Yields the bar."""

    def done():
        return sum(store.has(t, p) for t, p in pieces)

    reused = done()
    bar = tqdm(
        total=len(pieces),
        initial=reused,
        unit="piece",
        desc=f"pieces ({reused} reused)",
        disable=disable,
        **bar_kw,
    )
    stop = threading.Event()

    def poll():
        if not bar.disable:
            bar.update(done() - bar.n)

    def run():
        while not stop.wait(every):
            poll()

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    try:
        yield bar
    finally:
        stop.set()
        thread.join()
        poll()
        bar.close()


def above(bar, log):
    """log, writing above the bar: the bar is cleared first and drawn again after
    (tqdm.external_write_mode)."""

    def write(*a, **k):
        with bar.external_write_mode():
            log(*a, **k)

    return write


# ============================================================================================
# Outputs: refusing to replace a file a run did not write
# ============================================================================================


def ranks() -> tuple:
    """(rank, world size) from the launcher's environment (1 process: 0, 1), and why they cannot
    be used or None: RANK and WORLD_SIZE that neither torchrun (TORCHELASTIC_RUN_ID) nor a launcher
    giving the rendezvous (MASTER_ADDR, MASTER_PORT) set, or that are no numbers."""
    names = ("RANK", "WORLD_SIZE")
    given = {k: os.environ[k] for k in names if k in os.environ}
    try:
        rank, world = int(given.get("RANK", 0)), int(given.get("WORLD_SIZE", 1))
    except ValueError:
        return 0, 1, f"{' '.join(f'{k}={v}' for k, v in given.items())}: not numbers"
    launched = "TORCHELASTIC_RUN_ID" in os.environ or {"MASTER_ADDR", "MASTER_PORT"} <= set(
        os.environ
    )
    if (world != 1 or rank != 0) and not launched:
        return (
            0,
            1,
            f"{' '.join(f'{k}={v}' for k, v in given.items())} are set, but no launcher started "
            "this process (torchrun sets them with the rendezvous): run it under torchrun "
            "--nproc_per_node N, or unset them",
        )
    if not 0 <= rank < world:
        return 0, 1, f"RANK={rank} is not below WORLD_SIZE={world}"
    return rank, world, None


def free_cores(seconds: float = 0.3) -> float:
    """How many of this machine's cores other work leaves idle, from /proc/stat over `seconds`
    (where there is none: the load average); 0 .. os.cpu_count()."""
    cores = os.cpu_count() or 1

    def idle_total():
        with open("/proc/stat") as f:
            ticks = [int(v) for v in f.readline().split()[1:]]
        return ticks[3] + ticks[4], sum(ticks)  # idle + iowait, all

    try:
        idle0, total0 = idle_total()
        time.sleep(seconds)
        idle1, total1 = idle_total()
        return cores * (idle1 - idle0) / max(total1 - total0, 1)
    except (OSError, ValueError, IndexError):
        return max(cores - os.getloadavg()[0], 0.0)


def default_threads(most: int = 2) -> tuple:
    """(torch threads, why): `most`, or fewer when other work keeps cores busy. Threads that wait
    on each other at every operation run many times slower when one of them is descheduled (two
    threads on 2 cores with one busy: 483 s for --quick, one thread 68 s)."""
    free = free_cores()
    threads = max(1, min(most, round(free)))
    busy = (os.cpu_count() or 1) - free
    why = (
        f"{busy:.1f} of {os.cpu_count()} cores are busy with other work"
        if threads < most
        else "the default"
    )
    return threads, why


def write_folder(root, write, who: str, files, overwrite: bool, also=None) -> None:
    """A folder of several files written whole: write(tmp) fills a temporary sibling, renamed into
    place when complete, while a lock on the target (.<name>.lock beside it) refuses a second
    writer. An interrupted or killed write leaves the old folder (a killed writer's sibling is
    removed by the next). files: those the writer makes, which only overwrite replaces; a folder
    holding any other file (besides those directly in `also`) is never replaced. who: the writer,
    for the messages."""
    root = pathlib.Path(root)
    root.parent.mkdir(parents=True, exist_ok=True)
    with folder_lock(root.parent, f"{who} {root}", f".{root.name}.lock"):
        existing = [str(p) for p in files if p.exists()]
        if existing and not overwrite:
            raise FileExistsError(
                f"{who}: {existing[0]} exists ({len(existing)} files would be replaced); pass "
                "overwrite=True (CLI: --overwrite)"
            )
        ours = {str(p) for p in files}
        found = sorted(p for p in root.rglob("*") if p.is_file()) if root.is_dir() else []
        foreign = [p for p in found if str(p) not in ours and p.parent != also]
        if foreign:
            raise FileExistsError(
                f"{who}: {foreign[0]} is no file of what it writes ({len(foreign)} such); {root} "
                "is written whole, replacing what is in it: write elsewhere"
            )
        for stale in root.parent.glob(f".{root.name}.writing-*"):
            shutil.rmtree(stale)
        tmp = root.parent / f".{root.name}.writing-{os.getpid()}"
        try:
            write(tmp)
            if root.is_dir() and any(root.iterdir()):  # aside, then the new one in, then away
                old = root.parent / f".{root.name}.old-{os.getpid()}"
                os.rename(root, old)
                os.rename(tmp, root)
                shutil.rmtree(old)
            else:
                os.rename(tmp, root)  # (onto an empty folder too)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise


_HELD = {}  # the folders this process holds: resolved path -> how many blocks hold it


@contextlib.contextmanager
def folder_lock(folder, command: str, lock_name: str = ".lock"):
    """Hold `folder` for one run: an exclusive lock (flock) on folder/.lock for as long as the block
    runs. A second run on the same folder is refused with an OutputRefused naming the holder (its
    PID, command and start time); the operating system releases a lock with the process that held
    it, so one left by a killed run is taken over. Re-entrant: a run that holds the folder already
    (--out data_cache, where the data cache is made too) goes on holding it. lock_name: the lock
    file in folder (another name holds a part of the folder: write_nuscenes' target)."""
    folder = pathlib.Path(folder)
    held = str(folder.resolve() / lock_name)
    if held in _HELD:  # this process holds it already
        _HELD[held] += 1
        try:
            yield
        finally:
            _HELD[held] -= 1
        return
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd = os.open(folder / lock_name, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as e:
        raise OutputRefused(f"{folder}: cannot hold it for this run ({e.strerror or e})") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        try:
            holder = json.loads(os.read(fd, 65536) or b"{}")
        except ValueError:
            holder = {}
        os.close(fd)
        raise OutputRefused(
            f"{folder}: another run is writing here (PID {holder.get('pid', '?')}, "
            f"`{holder.get('command', '?')}`, since {holder.get('start', '?')}); wait for it to "
            "end, or use another folder"
        ) from None
    try:
        os.ftruncate(fd, 0)
        os.pwrite(
            fd,
            json.dumps(
                dict(pid=os.getpid(), command=command, start=time.strftime("%Y-%m-%d %H:%M:%S"))
            ).encode(),
            0,
        )
        _HELD[held] = 1
        yield
    finally:
        _HELD.pop(held, None)
        os.close(fd)  # (closing the descriptor releases the lock)


@contextlib.contextmanager
def one_line(ap, interrupted: str = "nothing half-written is left"):
    """A CLI's top level (ap: its argparse parser): the project's errors (all ValueError) and a
    file's (OSError) become one line naming the argument or file, exit 2 as argparse's own; Ctrl-C
    one line saying what is kept, exit 130."""
    try:
        yield
    except (ValueError, OSError) as e:
        ap.error(str(e))
    except KeyboardInterrupt:
        print(f"{ap.prog}: interrupted (Ctrl-C); {interrupted}", file=sys.stderr)
        sys.exit(130)


class OutputRefused(ValueError):
    """A run's refusal to start: a bad --out, or result files it would replace. The CLI prints it as
    one line."""


def planned_outputs(out_dir, figures: dict) -> list:
    """Every file a run of some tables writes in out_dir: figures {table name: its figure file
    names}; each table's <name>.json and .md, its figures, and report.md where there are
    several tables."""
    out = pathlib.Path(out_dir)
    files = [out / f"{n}{ext}" for n in figures for ext in (".json", ".md")]
    files += [out / f for fs in figures.values() for f in fs]
    return files + ([out / "report.md"] if len(figures) > 1 else [])


def refuse_existing(files, overwrite: bool, ours=()) -> None:
    """OutputRefused naming them if any of files exists already, unless overwrite (a run never
    replaces a result it did not make) or it is in ours (files this same run wrote before it was
    interrupted, unchanged since: ours_files)."""
    existing = [str(f) for f in files if f.exists() and f not in set(ours)]
    if existing and not overwrite:
        raise OutputRefused(
            f"--out: {len(existing)} result file(s) of this run exist already and are kept: "
            f"{', '.join(existing[:6])}{' ...' if len(existing) > 6 else ''}; pass --overwrite to "
            f"replace them, or choose another --out"
        )


def outputs_manifest(out_dir, name, seeds, key) -> pathlib.Path:
    """Where a run (experiment name, seeds, run key) lists the outputs it wrote, with
    their sha256."""
    return pathlib.Path(out_dir) / RUNS_DIR / "outputs" / f"{sha(name, list(seeds), key)[:16]}.json"


def _manifest(path) -> dict:
    """A run's manifest {file name: sha256} ({} when there is none)."""
    if not pathlib.Path(path).exists():
        return {}
    made = load_json(path, "a manifest of a run's outputs")
    if not isinstance(made, dict) or not all(isinstance(v, str) for v in made.values()):
        raise ValueError(f"{path}: not a manifest of a run's outputs ({{file: sha256}})")
    return made


def _file_sha(path) -> str:
    return hashlib.sha256(pathlib.Path(path).read_bytes()).hexdigest()


def record_outputs(manifest: pathlib.Path, files) -> None:
    """Add files (as they are now) to a run's manifest of the outputs it wrote."""
    made = _manifest(manifest)
    made.update({pathlib.Path(f).name: _file_sha(f) for f in files if pathlib.Path(f).exists()})
    manifest.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(manifest, json.dumps(made, indent=1, sort_keys=True))


def ours_files(out_dir, manifests) -> set:
    """The files of out_dir that one of these manifests lists and that are unchanged since that run
    wrote them."""
    ours = set()
    for manifest in manifests:
        made = _manifest(manifest)
        for fname, sha_ in made.items():
            f = pathlib.Path(out_dir) / fname
            if f.exists() and _file_sha(f) == sha_:
                ours.add(f)
    return ours
