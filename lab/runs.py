"""The run machinery under experiments.py, ignorant of tables: JSON read with checks and written
without NaN, atomic writes, provenance (the run key: config, data, code, device; the git commit), a
run's pieces kept on disk as they finish and resumed (RunStore), the worker processes
(concurrent.futures), one run per output folder (filelock), never replacing outputs a run did not
make.

A piece is one result of a run under a name (a table): anything with a `stem` (its file name) and
`_asdict()` (lab.tables.Piece). A run's pieces live in <out>/.runs/<name>/<name key>/<stem>.json (a
.pt of tensors beside it where it has some), written atomically the moment the piece is made. The
name key hashes the run key and the name; the run key, everything that determines the numbers: the
Config, the epochs, the data (its tensors), the code (code_version) and the device. Re-running the
same command loads the finished pieces and computes only the missing ones; another config, data or
code is another key, so nothing of another run is mixed in. The seeds are not part of the key (a
piece is one seed), nor is the thread count (it moves only the last digits)."""

from __future__ import annotations

import ast
import contextlib
import dataclasses
import errno
import functools
import hashlib
import json
import multiprocessing
import os
import pathlib
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool

import filelock
import torch

RUNS_DIR = ".runs"
# the repository: this file is lab/runs.py
ROOT = pathlib.Path(__file__).resolve().parent.parent


def sha(*parts) -> str:
    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()


def to_json(o):
    """json.dumps' default for results: a tensor as a list, anything else as its str."""
    return o.tolist() if torch.is_tensor(o) else str(o)


def load_json(path, what: str):
    """The JSON document in path, or one ValueError naming the file and what is wrong: unreadable,
    not JSON (json's message says where), nested deeper than the parser goes, or holding NaN or
    infinity (which the project never writes). what: what the file should be, for the message."""
    path = pathlib.Path(path)

    def constant(name):
        raise ValueError(f"it holds {name}, which no file of the project holds")

    try:
        return json.loads(path.read_text(), parse_constant=constant)
    except OSError as e:
        raise ValueError(f"{path}: cannot read it ({e.strerror or e})") from None
    except RecursionError:
        raise ValueError(f"{path}: not {what} (nested too deeply)") from None
    except ValueError as e:  # (UnicodeDecodeError and JSONDecodeError too)
        raise ValueError(f"{path}: not {what} ({e})") from None


RESULTS_META = {"command": "text", "date": "text", "machine": "text", "seconds": "number"}
_KINDS = {"text": str, "number": (int, float)}


def read_results(path) -> dict:
    """A results file an earlier run wrote ({'meta': ..., 'results': ...}, meta with the fields a
    table's header shows); ValueError naming the file and the field otherwise."""
    what = "a results file of python experiments.py"
    saved = load_json(path, what)
    if not isinstance(saved, dict) or not {"meta", "results"} <= saved.keys():
        raise ValueError(f"{path}: not {what} (no 'meta' and 'results')")
    meta, results = saved["meta"], saved["results"]
    if not isinstance(meta, dict) or not isinstance(results, dict):
        raise ValueError(f"{path}: not {what} ('meta' and 'results' must be objects)")
    for field, kind in RESULTS_META.items():
        if not isinstance(meta.get(field), _KINDS[kind]) or isinstance(meta.get(field), bool):
            raise ValueError(f"{path}: meta.{field} is missing or not {kind}")
    stack = [(results, "results")]
    while stack:  # a result is numbers, text and lists and objects of them: never null
        o, where = stack.pop()
        if o is None:
            raise ValueError(f"{path}: {where} is null, where a result belongs")
        items = o.items() if isinstance(o, dict) else enumerate(o) if isinstance(o, list) else ()
        stack += [(v, f"{where}[{k}]" if isinstance(k, int) else f"{where}.{k}") for k, v in items]
    return saved


def write_json(path, obj, **dumps) -> None:
    """obj as JSON in path (write_atomic; tensors as lists); a NaN or infinity is refused
    (json.dumps' allow_nan=False): ValueError naming the file, and nothing is written."""
    try:
        text = json.dumps(obj, default=to_json, allow_nan=False, **dumps)
    except ValueError as e:
        raise ValueError(f"{path}: {e}; a result is never written with NaN or infinity") from None
    write_atomic(path, text)


# the process's umask, read once at import (reading it means setting it) and put back
_UMASK = os.umask(0o022)
os.umask(_UMASK)


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
    after the file). The file gets the permissions open() would give (mkstemp's 0600 is no use in
    a shared lab folder)."""
    path = pathlib.Path(path)
    folder = tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    tmp = os.path.join(folder, path.name)
    try:
        write(tmp)
        os.chmod(tmp, 0o666 & ~_UMASK)
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


def write_atomic(path, text: str) -> None:
    """Write text to path through a temporary file and a rename (replace_atomic)."""
    replace_atomic(path, lambda tmp: pathlib.Path(tmp).write_text(text), len(text.encode()))


def write_file_atomic(path, write) -> None:
    """write(temporary path) then a rename onto path (replace_atomic), for writers that take a
    path (a figure's savefig)."""
    replace_atomic(path, write, 0)


def save_atomic(obj, path) -> None:
    """torch.save through a temporary file and a rename (replace_atomic)."""
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    replace_atomic(path, lambda tmp: torch.save(obj, tmp), _nbytes(obj))


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


# parsing the modules takes about 0.4 s; a run asks once per work unit
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
    not. (ast.unparse is Python's own: under another Python version the same code may read as new,
    a new run, never a mixed one.)"""
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
    """The key of a run (cfg: a dataclass): the same key, the same numbers (at the same thread
    count)."""
    parts = dict(config=dataclasses.asdict(cfg), epochs=float(epochs), device=str(device))
    return sha(dict(parts, data=data_fingerprint(data), code=code_version()))


def command_line(launcher: str, argv) -> str:
    """The command as a result records it: absolute paths inside the repository made relative to
    it, so that the record reads the same on every machine (`--out /home/me/diffstack/results` ->
    `--out results`)."""

    def rel(token):
        key, eq, value = token.partition("=") if token.startswith("--") else ("", "", token)
        path = pathlib.Path(value)
        if path.is_absolute() and path.resolve().is_relative_to(ROOT):
            value = str(path.resolve().relative_to(ROOT)) or "."
        return key + eq + value

    return " ".join([launcher, *(rel(t) for t in argv)])


def git_commit() -> str | None:
    """The commit the code was run from, '+dirty' when the work tree differs from it; None
    outside git."""

    def git(*args):
        return subprocess.run(
            ["git", *args], cwd=ROOT, capture_output=True, text=True, check=True
        ).stdout.strip()

    try:
        head, dirty = git("rev-parse", "HEAD"), git("status", "--porcelain", "--untracked-files=no")
    except (OSError, subprocess.CalledProcessError):
        return None
    return head + ("+dirty" if dirty else "")


class RunStore:
    """A run's pieces and models, under root (<out>/.runs; a temporary folder where nothing is kept,
    under torchrun)."""

    def __init__(self, root, key: str, table_keys: dict | None = None):
        self.root = pathlib.Path(root)
        self.key = key
        # {table: what its spec sets that moves numbers (by value)}: part of its folder's key
        self.table_keys = table_keys or {}

    def table_dir(self, table: str) -> pathlib.Path:
        return self.root / table / sha(self.key, table, self.table_keys.get(table))[:16]

    def path(self, table: str, piece) -> pathlib.Path:
        return self.table_dir(table) / f"{piece.stem}.json"

    def has(self, table: str, piece) -> bool:
        """Whether the piece is finished; one whose file cannot be read (a disk error, an edit) is
        named on stderr, set aside as <piece>.corrupt and computed again."""
        path = self.path(table, piece)
        try:
            return path.exists() and isinstance(self._read(table, piece).get("result"), dict)
        except (ValueError, AttributeError) as e:
            corrupt = path.with_suffix(".corrupt")
            print(
                f"{path}: not a finished piece ({e}); set aside as {corrupt.name}", file=sys.stderr
            )
            os.replace(path, corrupt)
            return False

    def _read(self, table: str, piece) -> dict:
        return load_json(self.path(table, piece), "a piece of a run")

    def load(self, table: str, piece) -> tuple:
        """(result, extra) of a finished piece."""
        saved = self._read(table, piece)
        pt = self.path(table, piece).with_suffix(".pt")
        return saved["result"], torch.load(pt, weights_only=True) if saved.get("extra") else None

    def timing(self, table: str, piece) -> dict | None:
        """How long a finished piece took to compute and where (the timing it was saved with)."""
        timing = self._read(table, piece).get("timing")
        return timing if isinstance(timing, dict) else None

    def save(self, table: str, piece, result: dict, extra=None, timing=None) -> None:
        """The piece's result (JSON, write_json; its extra tensors first, in a .pt beside it),
        atomically; timing: how long it took and where."""
        path = self.path(table, piece)
        path.parent.mkdir(parents=True, exist_ok=True)
        if extra is not None:
            save_atomic(extra, path.with_suffix(".pt"))
        saved = dict(table=table, piece=piece._asdict(), key=self.key, extra=extra is not None)
        write_json(path, dict(saved, timing=timing, result=result), indent=1)

    def model_path(self, train_key) -> pathlib.Path:
        """Where a model trained the way train_key says is kept."""
        return self.root / "models" / self.key[:16] / f"{sha(repr(train_key))[:16]}.pt"


class WorkerDied(ValueError):
    """A worker process of the run ended without its result (killed, out of memory): the run stops,
    saying so."""


def die_with_parent(parent: int) -> None:
    """Have the kernel end this process (SIGKILL) when its parent ends, however it ends (Linux
    prctl PR_SET_PDEATHSIG): a worker's initializer, and torchrun's ranks', so that none outlives
    the run it belongs to and writes pieces for nobody."""
    import ctypes

    libc = ctypes.CDLL(None, use_errno=True)
    if hasattr(libc, "prctl"):  # (Linux; elsewhere a worker may outlive a run killed with -9)
        libc.prctl(1, signal.SIGKILL)  # 1: PR_SET_PDEATHSIG
    if os.getppid() != parent:  # the parent ended before the prctl
        os._exit(1)


def pool(jobs: int) -> ProcessPoolExecutor:
    """A pool of `jobs` worker processes (spawned: a fresh interpreter each) that die with this
    one."""
    spawn = multiprocessing.get_context("spawn")
    return ProcessPoolExecutor(jobs, spawn, initializer=die_with_parent, initargs=(os.getpid(),))


def in_workers(work, units: list, jobs: int, done, kept) -> None:
    """work(*unit) for each unit, in `jobs` worker processes (pool) in the order given; done(unit,
    its result) here as each one finishes. A worker's error stops the run and is raised; a worker
    that ended without one (killed, out of memory) is one WorkerDied line; Ctrl-C (or SIGINT to
    this process alone) ends the workers at once, not after their units. kept: where the finished
    work is kept, for the message."""
    with pool(min(jobs, len(units))) as workers:
        futures = {workers.submit(work, *unit): unit for unit in units}
        try:
            for future in as_completed(futures):
                done(futures[future], future.result())
        except BaseException as e:
            workers.shutdown(wait=False, cancel_futures=True)
            for worker in multiprocessing.active_children():
                worker.terminate()
            if isinstance(e, BrokenProcessPool):
                raise WorkerDied(
                    f"a worker process died ({e}); the run stops here: the same command resumes it "
                    f"from the pieces kept in {kept}"
                ) from None
            raise


def above(bar, log):
    """log, writing above the bar: the bar is cleared first and drawn again after
    (tqdm.external_write_mode)."""

    def write(*a, **k):
        with bar.external_write_mode():
            log(*a, **k)

    return write


def ranks() -> tuple:
    """(rank, world size) from the launcher's environment (1 process: 0, 1), and why they cannot
    be used or None: RANK and WORLD_SIZE that neither torchrun (TORCHELASTIC_RUN_ID) nor a launcher
    giving the rendezvous (MASTER_ADDR, MASTER_PORT) set, or that are no numbers."""
    given = {k: os.environ[k] for k in ("RANK", "WORLD_SIZE") if k in os.environ}
    said = " ".join(f"{k}={v}" for k, v in given.items())
    try:
        rank, world = int(given.get("RANK", 0)), int(given.get("WORLD_SIZE", 1))
    except ValueError:
        return 0, 1, f"{said}: not numbers"
    env = set(os.environ)
    launched = "TORCHELASTIC_RUN_ID" in env or {"MASTER_ADDR", "MASTER_PORT"} <= env
    if (world != 1 or rank != 0) and not launched:
        why = (
            f"{said} are set, but no launcher started this process (torchrun sets them with the "
            "rendezvous): run it under torchrun --nproc_per_node N, or unset them"
        )
        return 0, 1, why
    if not 0 <= rank < world:
        return 0, 1, f"RANK={rank} is not below WORLD_SIZE={world}"
    return rank, world, None


def default_threads(most: int = 2) -> tuple:
    """(torch threads, why): `most`, fixed. On a machine where other work keeps a core busy, two
    threads that wait on each other run slowly: pass --threads 1 there (docs/reproducibility.md)."""
    return most, "the default"


class OutputRefused(ValueError):
    """A run's refusal to start: a bad --out, a folder another run holds, or result files it would
    replace. The CLI prints it as one line."""


@contextlib.contextmanager
def folder_lock(folder, command: str, lock_name: str = ".lock"):
    """Hold `folder` for one run: an exclusive lock (filelock's, flock underneath) on folder/.lock
    for as long as the block runs, the holder (PID, command, start time) written into the lock file.
    A second run on the same folder is refused with an OutputRefused naming the holder; the
    operating system releases a lock with the process that held it, so one left by a killed run is
    taken over. Re-entrant (one lock per path in a process): a run that holds the folder already
    (--out data_cache, where the data cache is made too) goes on holding it. lock_name: the lock
    file in folder (another name holds a part of the folder: write_folder's target)."""
    path = pathlib.Path(folder) / lock_name
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        lock = filelock.FileLock(
            path, is_singleton=True, thread_local=False, preserve_lock_file=True
        )
        ours = lock.is_locked  # (by this process, in an outer block)
        lock.acquire(blocking=False)
    except filelock.Timeout:
        try:
            holder = json.loads(path.read_text())
        except (OSError, ValueError):
            holder = None
        holder = holder if isinstance(holder, dict) else {}
        raise OutputRefused(
            f"{folder}: another run is writing here (PID {holder.get('pid', '?')}, "
            f"`{holder.get('command', '?')}`, since {holder.get('start', '?')}); wait for it to "
            "end, or use another folder"
        ) from None
    except OSError as e:
        raise OutputRefused(f"{folder}: cannot hold it for this run ({e.strerror or e})") from None
    try:
        if not ours:
            start = time.strftime("%Y-%m-%d %H:%M:%S")
            path.write_text(json.dumps(dict(pid=os.getpid(), command=command, start=start)))
        yield
    finally:
        lock.release()


def write_folder(root, write, who: str, files, overwrite: bool, also=None) -> None:
    """A folder of several files written whole: write(tmp) fills a temporary sibling, renamed into
    place when complete, while a lock on the target (.<name>.lock beside it) refuses a second
    writer. An interrupted or killed write leaves the old folder (a killed writer's sibling is
    removed by the next). files: those the writer makes, which only overwrite replaces; a folder
    holding any other file (besides those directly in `also`) is never replaced. who: the writer,
    for the messages."""
    root = pathlib.Path(root)
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
