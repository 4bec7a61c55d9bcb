"""The run machinery under experiments.py, ignorant of tables: checked JSON, atomic writes, the run
key and provenance, a run's pieces kept in <out>/.runs/<table>/<key>/<stem>.json as they are made
and resumed (RunStore), worker processes, one run per output folder, outputs never replaced. The key
hashes all that sets the numbers (Config, epochs, data, code, device, the spec), not the seeds."""

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
import pickle
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
ROOT = pathlib.Path(__file__).resolve().parent.parent  # the repository


def sha(*parts) -> str:
    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()


def sha256_of(path) -> str:
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def load_tensors(path, what: str):
    """torch.load(path, weights_only=True), or one ValueError naming the file: missing, damaged, or
    holding objects other than tensors (torch's advice to load those unsafely is not repeated)."""
    try:
        return torch.load(path, weights_only=True)
    except pickle.UnpicklingError:
        raise ValueError(f"{path}: not {what} (it holds objects other than tensors)") from None
    except (OSError, RuntimeError, EOFError, ValueError) as e:
        raise ValueError(f"{path}: not {what} ({' '.join(str(e).split())[:160]})") from None


def to_json(o):
    """json.dumps' default for results: a tensor as a list, anything else as its str."""
    return o.tolist() if torch.is_tensor(o) else str(o)


def load_json(path, what: str):
    """The JSON in path (`what`), or one ValueError naming the file: unreadable, not JSON, nested
    too deeply, or holding NaN or infinity."""
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


def read_results(path) -> dict:
    """A results file of experiments.py, its header's meta fields checked and no null in its
    results; ValueError naming the file and the field otherwise."""
    what = "a results file of python experiments.py"
    saved = load_json(path, what)
    if not isinstance(saved, dict) or not {"meta", "results"} <= saved.keys():
        raise ValueError(f"{path}: not {what} (no 'meta' and 'results')")
    meta, results = saved["meta"], saved["results"]
    if not isinstance(meta, dict) or not isinstance(results, dict):
        raise ValueError(f"{path}: not {what} ('meta' and 'results' must be objects)")
    for field in ("command", "date", "machine", "seconds"):
        kind, name = ((int, float), "a number") if field == "seconds" else (str, "text")
        if not isinstance(meta.get(field), kind) or isinstance(meta.get(field), bool):
            raise ValueError(f"{path}: meta.{field} is missing or not {name}")
    stack = [(results, "results")]
    while stack:  # a result is numbers, text and lists and objects of them: never null
        o, where = stack.pop()
        if o is None:
            raise ValueError(f"{path}: {where} is null, where a result belongs")
        items = o.items() if isinstance(o, dict) else enumerate(o) if isinstance(o, list) else ()
        stack += [(v, f"{where}[{k}]" if isinstance(k, int) else f"{where}.{k}") for k, v in items]
    return saved


def write_json(path, obj, **dumps) -> None:
    """obj as JSON in path, atomically (tensors as lists); NaN or infinity: ValueError, no file."""
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


def _nbytes(obj) -> int:
    """About how many bytes torch.save writes for obj: its tensors' data."""
    if torch.is_tensor(obj):
        return obj.numel() * obj.element_size()
    items = obj.values() if isinstance(obj, dict) else obj if isinstance(obj, (list, tuple)) else ()
    return sum(_nbytes(v) for v in items)


def remove_stale_temporaries(folder) -> None:
    """Remove write_file_atomic's .NAME.pidPID-*.tmp in folder whose writer PID is gone (killed)."""
    for tmp in pathlib.Path(folder).glob(".*.pid*-*.tmp"):
        try:  # (signal 0: whether the process exists)
            os.kill(int(tmp.name.rpartition(".pid")[2].partition("-")[0]), 0)
        except ProcessLookupError:
            shutil.rmtree(tmp, ignore_errors=True)
        except (ValueError, OverflowError, OSError):  # no PID, or another user's process: alive
            pass


def write_file_atomic(path, write, needed: int = 0) -> None:
    """write(a file of path's name in a temporary folder beside it: a figure's format kept), then
    rename it onto path: a kill leaves the old file (the next writer removes the temporary), a full
    disk is one DiskFull line. The file gets open()'s permissions, not mkstemp's 0600."""
    path = pathlib.Path(path)
    remove_stale_temporaries(path.parent)
    prefix = f".{path.name}.pid{os.getpid()}-"  # (the PID: remove_stale_temporaries reads it)
    folder = tempfile.mkdtemp(prefix=prefix, suffix=".tmp", dir=path.parent)
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
    write_file_atomic(path, lambda tmp: pathlib.Path(tmp).write_text(text), len(text.encode()))


def save_atomic(obj, path) -> None:
    """torch.save, atomically (write_file_atomic)."""
    pathlib.Path(path).parent.mkdir(parents=True, exist_ok=True)
    write_file_atomic(path, lambda tmp: torch.save(obj, tmp), _nbytes(obj))


# The modules whose code makes a run's numbers. specs.py is not one: what a table's spec sets that
# moves numbers is in the table's own key, by value (experiments.spec_key); the rest is text.
NUMBER_MODULES = ("diffstack.py", "train.py", "data_synth.py", "experiments.py", "lab/ddp.py")
NUMBER_MODULES += ("lab/data.py", "lab/nuscenes.py", "lab/waymo.py", "lab/tables.py")


class _NoText(ast.NodeTransformer):
    """Drops text for people: a statement that is only a string (a docstring); a string or f-string
    with a space in it (a message) becomes ''. One without a space ('rl', f'rel_{key}') is code."""

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


@functools.lru_cache(maxsize=8)  # (parsing the modules takes about 0.4 s)
def code_of(source: str) -> str:
    """A module's code without comments, layout and text (_NoText), as ast.unparse writes it."""
    tree = _NoText().visit(ast.parse(source))
    for node in ast.walk(tree):
        if getattr(node, "body", None) == []:  # a function or class that held only its docstring
            node.body = [ast.Pass()]
    return ast.unparse(tree)


def code_version() -> str:
    """A hash of the code of NUMBER_MODULES (code_of): a commit of the README, the tests or a log
    line is the same run. (Another Python's ast.unparse may read as new code: a new run.)"""
    h = hashlib.sha256()
    for name in NUMBER_MODULES:
        h.update(name.encode() + b"\0" + code_of((ROOT / name).read_text()).encode() + b"\0")
    return f"sha256:{h.hexdigest()[:16]}"


def data_fingerprint(data) -> str:
    """A hash of the data's tensors (a dict or None: its JSON), whichever file they came from."""
    h = hashlib.sha256()
    for part in data:
        if part is None or isinstance(part, dict):
            h.update(json.dumps(part, sort_keys=True).encode())
            continue
        for one in part if isinstance(part, tuple) else (part,):  # (a tuple: the training draws)
            for name, t in sorted(one.tensors().items()):
                h.update(f"{name} {t.dtype} {tuple(t.shape)}".encode())
                h.update(t.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


def run_key(data, cfg, epochs, device="cpu") -> str:
    """The same key, the same numbers (at the same thread count)."""
    parts = dict(config=dataclasses.asdict(cfg), epochs=float(epochs), device=str(device))
    return sha(dict(parts, data=data_fingerprint(data), code=code_version()))


def command_line(launcher: str, argv) -> str:
    """The command as a result records it: paths inside the repository relative to it."""

    def rel(token):
        key, eq, value = token.partition("=") if token.startswith("--") else ("", "", token)
        path = pathlib.Path(value)
        if path.is_absolute() and path.resolve().is_relative_to(ROOT):
            value = str(path.resolve().relative_to(ROOT)) or "."
        return key + eq + value

    return " ".join([launcher, *(rel(t) for t in argv)])


def git_commit() -> str | None:
    """The commit the code runs from, '+dirty' when the work tree differs; None outside git."""

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
    """A run's pieces and models under root; table_keys: {table: its spec's part of the key}."""

    def __init__(self, root, key: str, table_keys: dict | None = None):
        self.root, self.key, self.table_keys = pathlib.Path(root), key, table_keys or {}

    def table_dir(self, table: str) -> pathlib.Path:
        return self.root / table / sha(self.key, table, self.table_keys.get(table))[:16]

    def path(self, table: str, piece) -> pathlib.Path:
        return self.table_dir(table) / f"{piece.stem}.json"

    def has(self, table: str, piece) -> bool:
        """Whether the piece is finished and whole (load); a damaged one is put aside (.corrupt)."""
        path = self.path(table, piece)
        try:
            return path.exists() and bool(self.load(table, piece))
        except ValueError as e:
            print(f"{path}: not a finished piece ({e}); set aside as .corrupt", file=sys.stderr)
            os.replace(path, path.with_suffix(".corrupt"))
            with contextlib.suppress(FileNotFoundError):
                os.replace(path.with_suffix(".pt"), path.with_suffix(".pt.corrupt"))
            return False

    def read(self, table: str, piece) -> dict:
        """A finished piece's file: its result, timing (seconds, CPU seconds, machine) and more."""
        return load_json(self.path(table, piece), "a piece of a run")

    def load(self, table: str, piece) -> tuple:
        """(result, extra tensors or None) of a finished piece, checked by sha256: ValueError."""
        saved, pt = self.read(table, piece), self.path(table, piece).with_suffix(".pt")
        if not isinstance(saved, dict) or not isinstance(saved.get("result"), dict):
            raise ValueError("no result")
        extra = load_tensors(pt, "a piece's tensors") if saved.get("extra") else None
        if saved.get("sha256") != sha(saved["result"], extra is not None and sha256_of(pt)):
            raise ValueError(f"its result or {pt.name} changed since it was written (sha256)")
        return saved["result"], extra

    def save(self, table: str, piece, result: dict, extra=None, timing=None) -> None:
        """The piece's result as JSON (extra tensors first, in a .pt beside it), and sha256."""
        path = self.path(table, piece)
        path.parent.mkdir(parents=True, exist_ok=True)
        if extra is not None:
            save_atomic(extra, path.with_suffix(".pt"))
        result = json.loads(json.dumps(result, default=to_json))  # (as it reads back)
        digest = sha(result, extra is not None and sha256_of(path.with_suffix(".pt")))
        saved = dict(table=table, piece=piece._asdict(), key=self.key, extra=extra is not None)
        write_json(path, dict(saved, timing=timing, result=result, sha256=digest), indent=1)

    def model_path(self, train_key) -> pathlib.Path:
        return self.root / "models" / self.key[:16] / f"{sha(repr(train_key))[:16]}.pt"


class WorkerDied(ValueError):
    """A worker process ended without its result (killed, out of memory): the run stops."""


def die_with_parent(parent: int) -> None:
    """SIGKILL this process when its parent ends (PR_SET_PDEATHSIG): none writes for nobody."""
    import ctypes

    libc = ctypes.CDLL(None, use_errno=True)
    if hasattr(libc, "prctl"):  # (Linux; elsewhere a worker may outlive a run killed with -9)
        libc.prctl(1, signal.SIGKILL)  # 1: PR_SET_PDEATHSIG
    if os.getppid() != parent:  # the parent ended before the prctl
        os._exit(1)


def in_workers(work, units: list, jobs: int, done, kept) -> None:
    """work(*unit) in `jobs` spawned workers that die with this one, done(unit, result) here as each
    finishes; a dead worker is one WorkerDied line naming `kept`; Ctrl-C ends the workers now."""
    spawn = multiprocessing.get_context("spawn")
    init = dict(initializer=die_with_parent, initargs=(os.getpid(),))
    with ProcessPoolExecutor(min(jobs, len(units)), spawn, **init) as workers:
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


def ranks() -> tuple:
    """(rank, world size, None) from torchrun's environment, or (0, 1, why not)."""
    given = {k: os.environ[k] for k in ("RANK", "WORLD_SIZE") if k in os.environ}
    said = " ".join(f"{k}={v}" for k, v in given.items())
    try:
        rank, world = int(given.get("RANK", 0)), int(given.get("WORLD_SIZE", 1))
    except ValueError:
        return 0, 1, f"{said}: not numbers"
    env = set(os.environ)
    launched = "TORCHELASTIC_RUN_ID" in env or {"MASTER_ADDR", "MASTER_PORT"} <= env
    if (world != 1 or rank != 0) and not launched:
        why = f"{said} are set, but no launcher started this process: use torchrun or unset them"
        return 0, 1, why
    if not 0 <= rank < world:
        return 0, 1, f"RANK={rank} is not below WORLD_SIZE={world}"
    return rank, world, None


class OutputRefused(ValueError):
    """A run's refusal to start: a bad --out, a folder another run holds, files it would replace."""


@contextlib.contextmanager
def folder_lock(folder, command: str, lock_name: str = ".lock"):
    """Hold `folder` for one run (filelock, the holder written in folder/<lock_name>); a second run
    is refused naming it. The OS releases it with its process; re-entrant (--out data_cache)."""
    path = pathlib.Path(folder) / lock_name
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        lock = filelock.FileLock(
            path, is_singleton=True, thread_local=False, preserve_lock_file=True
        )
        ours = lock.is_locked  # (by this process, in an outer block)
        lock.acquire(blocking=False)
    except filelock.Timeout:
        holder = {}
        with contextlib.suppress(ValueError):  # (unreadable, not JSON: load_json)
            holder = load_json(path, "a lock's holder")
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
            fd = os.open(path, os.O_WRONLY | os.O_TRUNC | getattr(os, "O_NOFOLLOW", 0))  # (held)
            with open(fd, "w") as f:
                f.write(json.dumps(dict(pid=os.getpid(), command=command, start=start)))
        yield
    finally:
        lock.release()


def refuse_current_folder(root, who: str) -> None:
    """OutputRefused if root is not empty and is or holds the current folder (no rename of it)."""
    real = pathlib.Path(root).resolve()
    if pathlib.Path.cwd().is_relative_to(real) and any(real.iterdir()):
        why = "the current folder or one holding it; give a new folder"
        raise OutputRefused(f"{who}: refusing to replace '{root}', {why}")


def write_folder(root, write, who: str, files, overwrite: bool, also=None) -> None:
    """A folder written whole: write(tmp) fills a temporary sibling, renamed into place, under a
    lock. files: those the writer (`who`) makes, replaced only with overwrite; a folder holding any
    other file (but directly in `also`) is never replaced."""
    refuse_current_folder(root, who)
    root, real = pathlib.Path(root), pathlib.Path(root).resolve()  # (a symlink: its target)
    with folder_lock(real.parent, f"{who} {root}", f".{real.name}.lock"):
        for stale in real.parent.glob(f".{real.name}.old-*"):  # killed between its renames
            if real.exists():
                shutil.rmtree(stale)
            else:
                os.rename(stale, real)
        for stale in real.parent.glob(f".{real.name}.writing-*"):  # a killed writer's
            shutil.rmtree(stale)
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
        tmp = real.parent / f".{real.name}.writing-{os.getpid()}"
        try:
            write(tmp)
            if real.is_dir() and any(real.iterdir()):  # aside, then the new one in, then away
                old = real.parent / f".{real.name}.old-{os.getpid()}"
                os.rename(real, old)
                os.rename(tmp, real)
                shutil.rmtree(old)
            elif real == pathlib.Path.cwd():  # (`.`: filled, so that it stays the shell's folder)
                for p in tmp.iterdir():
                    os.rename(p, real / p.name)
            else:
                os.rename(tmp, real)  # (onto an empty folder too)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)


@contextlib.contextmanager
def one_line(ap, interrupted: str = "nothing half-written is left"):
    """A CLI's top level: ValueError and OSError as argparse's one line, exit 2; Ctrl-C exit 130."""
    try:
        yield
    except (ValueError, OSError) as e:
        ap.error(str(e))
    except KeyboardInterrupt:
        print(f"{ap.prog}: interrupted (Ctrl-C); {interrupted}", file=sys.stderr)
        sys.exit(130)
