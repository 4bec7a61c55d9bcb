"""The course's grader, `python -m lab.grader submissions/*.ipynb --csv grades.csv`: each check runs
here, the answer in a child of its own (check): a failure is the answer's, the verdict is ours."""

import argparse
import ast
import concurrent.futures
import contextlib
import csv
import io
import os
import resource
import signal
import subprocess
import sys
import tempfile
import threading
import time
import tokenize
import warnings
from multiprocessing.connection import Connection, Pipe
from pathlib import Path

import nbformat
import torch

import course
from lab import cli, runs

TIMEOUT = 120.0  # seconds per exercise (the checks take about a second)
MEMORY = 2**31  # bytes an answer's process may map beyond its imports (the checks need MBs)
ANSWERS = {name for name, _, _ in course.EXERCISES.values()}
_LIVE, _STOP, _HERE = set(), threading.Event(), threading.local()  # the answers' processes


def cell_python(cell: str, modules: dict) -> str:
    """A cell's Python as the kernel runs it (%%bash left out, %%writefile NAME.py into modules)."""
    from IPython.core.inputtransformer2 import TransformerManager

    lines = cell.splitlines(keepends=True)
    first = next((i for i, line in enumerate(lines) if line.strip()), None)
    if first is not None and lines[first].lstrip().startswith("%%"):
        magic = lines[first].lstrip()[2:].split() or [""]
        if magic[0] == "writefile" and magic[-1].endswith(".py"):
            modules[Path(magic[-1]).name] = "".join(lines[first + 1 :])
        if magic[0] not in ("time", "timeit", "capture", "prun"):  # (%%bash's body is not Python)
            return ""
        lines[first] = "\n"  # (keeps the line numbers)
    return TransformerManager().transform_cell("".join(lines))


def _calls_something(node) -> bool:
    """Whether evaluating it calls a function (a lambda's body is not evaluated)."""
    if isinstance(node, ast.Call):
        return True
    children = [node.args] if isinstance(node, ast.Lambda) else ast.iter_child_nodes(node)
    return any(_calls_something(c) for c in children)


def _names(node) -> list:
    """The names a statement binds (an import's, a def's or class's, an assignment's)."""
    if isinstance(node, (ast.Import, ast.ImportFrom)):
        return [(a.asname or a.name).split(".")[0] for a in node.names]
    if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
        return [node.name]
    targets = [t for t in getattr(node, "targets", [getattr(node, "target", None)]) if t]
    return [n.id for t in targets for n in ast.walk(t) if isinstance(n, ast.Name)]


def _kept(node) -> bool:
    """A definition: an import (not of solutions), def, class, or assignment calling nothing or
    binding an exercise's name."""
    if isinstance(node, (ast.Import, ast.ImportFrom)):
        return "solutions" not in [(getattr(node, "module", "") or "").split(".")[0], *_names(node)]
    if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
        return True
    assigns = isinstance(node, (ast.Assign, ast.AnnAssign)) and node.value is not None
    return assigns and (not _calls_something(node.value) or not ANSWERS.isdisjoint(_names(node)))


def definitions(path) -> dict | str:
    """A file's definitions as running each cell leaves them: code [(cell, code, names)], modules,
    dropped {name: cell}, unparsed [why]; or the one line why the file cannot be graded."""
    path, read = Path(path), dict(code=[], modules={}, dropped={}, unparsed=[])
    try:
        if path.suffix == ".ipynb":
            with warnings.catch_warnings():  # (a cell without an id is read all the same)
                warnings.simplefilter("ignore")
                nb = nbformat.read(path, 4)
            cells = [c.source for c in nb.cells if c.cell_type == "code"]
            sources = [cell_python(c, read["modules"]) for c in cells]
        else:
            with tokenize.open(path) as f:  # (a byte-order mark, a coding line)
                sources = [f.read()]
        for i, source in enumerate(sources):
            where = f"{path.name}, code cell {i + 1}" if path.suffix == ".ipynb" else str(path)
            try:
                tree = ast.parse(source)
            except SyntaxError as e:
                if path.suffix != ".ipynb":
                    raise
                read["unparsed"].append(f"{where} does not parse: {e.msg}, line {e.lineno}")
                continue
            lines = source.splitlines(keepends=True)
            for node in tree.body:
                if not _kept(node):
                    read["dropped"].update(dict.fromkeys(_names(node), where))
                    continue
                start = (getattr(node, "decorator_list", None) or [node])[0].lineno
                code = "\n" * (start - 1) + "".join(lines[start - 1 : node.end_lineno])
                read["code"].append((where, code, _names(node)))
    except Exception as e:  # any reason (JSON nested too deep, an expression too long, ...)
        what = "not a notebook that Jupyter can read" if path.suffix == ".ipynb" else ""
        why = (str(e).splitlines() or [""])[0]
        return f"{what or 'the file does not run'} ({type(e).__name__}: {why})"[:300]
    return read


def _send(conn, obj) -> None:
    torch.save(obj, data := io.BytesIO())
    conn.send_bytes(data.getbuffer())


def _receive(conn, trusted=False):
    """A message; the answer's (not trusted) read as tensors, numbers and lists only."""
    return torch.load(io.BytesIO(conn.recv_bytes(MEMORY)), weights_only=not trusted)


def serve(fd) -> None:
    """The answer's process: the definitions run one by one (a failure named), then the calls."""
    conn, folder, graph = Connection(fd), tempfile.mkdtemp(), None
    used = int(Path("/proc/self/statm").read_text().split()[0]) * os.sysconf("SC_PAGE_SIZE")
    resource.setrlimit(resource.RLIMIT_AS, (used + MEMORY, used + MEMORY))
    sys.modules["solutions"] = None  # an answer's `import solutions` fails
    (spec,) = _receive(conn, trusted=True)
    for name, text in spec["modules"].items():
        Path(folder, name).write_text(text)
    sys.path[:0] = [folder, str(runs.ROOT)]
    os.chdir(folder)
    space = {"__name__": "answers", "SOLUTIONS": False}
    why = {
        n: f"uses {n}, which the notebook computes by a call ({w}), which the grader does not "
        "run: define it inside the function"
        for n, w in spec["dropped"].items()
    }
    for where, code, names in spec["code"]:
        try:
            exec(compile(code, where, "exec"), space)
        except (Exception, SystemExit) as e:  # a definition that needs a value from the analysis
            failed = f"{code.strip().splitlines()[0]} failed ({type(e).__name__}: {e}) in {where}"
            why.update(dict.fromkeys(names, f"needs {', '.join(names)}, but {failed}"))
    fn = space.get(spec["name"])
    _send(conn, ["ok", None if callable(fn) else why.get(spec["name"], "not a function")])
    while True:
        kind, args, grads, quiet = _receive(conn, trusted=True)
        try:
            if kind == "grad":
                reply = list(torch.autograd.grad(graph[0], graph[1], args, allow_unused=True))
            else:
                args = [a.requires_grad_() if i in grads else a for i, a in enumerate(args)]
                with course.no_autograd(quiet) if quiet else contextlib.nullcontext():
                    reply = fn(*args)
                on = torch.is_tensor(reply) and reply.requires_grad and bool(grads)
                graph = (reply, [args[i] for i in grads]) if on else None
                reply = [reply.detach() if torch.is_tensor(reply) else reply, on]
            _send(conn, ["ok", reply])
        except (Exception, SystemExit) as e:
            said = why[e.name] if isinstance(e, NameError) and e.name in why else str(e)
            _send(conn, ["error", type(e).__name__, said, getattr(e, "code", None)])


class _Ended(BaseException):
    """The answer's process ended, or was killed, before the check finished."""


class _Remote(torch.autograd.Function):
    """An answer's output here whose backward pass runs in the answer's process."""

    @staticmethod
    def forward(ctx, ask, out, *inputs):
        ctx.ask = ask
        return out.clone()

    @staticmethod
    def backward(ctx, grad):
        return None, None, *ctx.ask("grad", grad, [], None)


@contextlib.contextmanager
def _no_autograd(name):
    """course.no_autograd in a check here: the answer's calls within it run under it, there."""
    _HERE.quiet = name
    try:
        with contextlib.nullcontext() if getattr(_HERE, "grading", False) else _NO_AUTOGRAD(name):
            yield
    finally:
        _HERE.quiet = None


_NO_AUTOGRAD, course.no_autograd = course.no_autograd, _no_autograd


def _kill(process) -> None:
    with contextlib.suppress(ProcessLookupError):
        os.killpg(process.pid, signal.SIGKILL)


def check(number, answers, timeout):
    """One check here, the answer in a fresh child of its own session killed whole after it or at
    the time limit, only its outputs back: (True, what it measured) or (False, why)."""
    name, (ours, theirs), deadline = course.EXERCISES[number][0], Pipe(), time.monotonic() + timeout

    def ask(*message):
        try:
            _send(ours, list(message))
            if not ours.poll(max(0, deadline - time.monotonic())):
                raise EOFError  # the time limit
            reply = _receive(ours)
        except (OSError, EOFError):
            _kill(process)
            raise _Ended from None
        except Exception as e:  # (what torch.load refuses: objects other than tensors, lists)
            raise TypeError(f"returned what the grader does not read ({e})"[:200]) from None
        if reply[0] == "ok":
            return reply[1]
        if reply[1] == "SystemExit":
            raise SystemExit(reply[3])
        errors = {"NotImplementedError": NotImplementedError, "Forbidden": course.Forbidden}
        raise errors.get(reply[1], type(str(reply[1]), (Exception,), {}))(reply[2])

    def answer(*args):  # the student's function as the check calls it
        grads = [i for i, a in enumerate(args) if torch.is_tensor(a) and a.requires_grad]
        sent = [a.detach() if torch.is_tensor(a) else a for a in args]
        out, graph = ask("call", sent, grads, getattr(_HERE, "quiet", None))
        return _Remote.apply(ask, out, *(args[i] for i in grads)) if graph else out

    cmd = [sys.executable, "-c", f"from lab import grader\ngrader.serve({theirs.fileno()})"]
    with tempfile.TemporaryFile() as err, ours, theirs:
        fds = dict(stdout=err, stderr=err, pass_fds=[theirs.fileno()])
        env = {**os.environ, "OMP_NUM_THREADS": "1"}  # one thread a check
        process = subprocess.Popen(cmd, cwd=runs.ROOT, env=env, start_new_session=True, **fds)
        theirs.close()
        _LIVE.add(process)
        _HERE.grading = True
        try:
            if _STOP.is_set():
                raise KeyboardInterrupt
            broken = ask({**answers, "name": name})
            if broken:
                raise AssertionError(f"{name} is defined, but does not run on its own: {broken}")
            return True, course.CHECKS[number](answer)
        except _Ended:
            if time.monotonic() >= deadline:
                return False, f"FAIL: did not finish in {timeout:g} s (an endless loop?)"
            err.seek(0)
            last = (err.read().decode(errors="replace").strip() or "nothing on stderr").splitlines()
            ended = f"the process ended (exit status {process.wait()}) before the check finished"
            return False, f"FAIL: {ended}: {name} exits or crashes ({last[-1]})"
        except NotImplementedError:
            return False, "not done (the stub still raises NotImplementedError)"
        except AssertionError as e:
            return False, f"FAIL: {e}"
        except SystemExit as e:
            return False, f"FAIL: {name} ended the process (sys.exit({e.code!r}))"
        except Exception as e:  # an answer that breaks the check itself (a strange return value)
            return False, f"FAIL: {name} broke the check: {type(e).__name__}: {e}"
        finally:
            _HERE.grading = False
            _kill(process)
            process.wait()
            _LIVE.discard(process)


def grade(path, out=print, timeout=TIMEOUT, answers=None) -> dict:
    """A line per exercise of `path` (answers: definitions(path), read before), then the score."""
    answers, result = answers or definitions(path), {}
    for k, (name, title, _) in course.EXERCISES.items():
        if isinstance(answers, str):
            passed, said = False, answers
        elif not any(name in names for _, _, names in answers["code"]):
            passed, said = False, "; ".join([f"no function {name}", *answers["unparsed"]])
        else:
            passed, said = check(k, answers, timeout)
        result[k] = True if passed else said
        out(f"  exercise {k} ({title}): {f'PASS ({said})' if passed else said}")
    out(f"{path}: score {sum(v is True for v in result.values())}/{len(course.EXERCISES)}")
    return result


def main(argv=None):
    ap = argparse.ArgumentParser(
        prog="python -m lab.grader",
        description="Grade the my_* functions in each notebook or .py file. It runs the students' "
        "code: grade in a throwaway container or VM. Exit status 0 if all exercises pass, else 1.",
    )
    ap.add_argument("files", nargs="+", help="notebooks (.ipynb) or Python files with the answers")
    seconds = cli.bounded(float, 0, 86400, "--timeout")
    ap.add_argument("--timeout", type=seconds, default=TIMEOUT, help="per check (%(default)g s)")
    jobs = cli.bounded(int, 1, 256, "--jobs")
    ap.add_argument("--jobs", type=jobs, default=1, help="files graded at once (%(default)s)")
    ap.add_argument("--csv", type=Path, help="also write the grades to this CSV, a row per file")
    ap.add_argument("--overwrite", action="store_true", help="let --csv replace an existing file")
    args = ap.parse_args(argv)
    for f in map(Path, args.files):  # every argument checked before any grading
        if f.is_symlink() and not f.exists():
            ap.error(f"{f}: a symbolic link to {os.readlink(f)}, which does not exist")
        if not f.exists():
            ap.error(f"{f}: no such file")
        if f.suffix not in (".ipynb", ".py") or not f.is_file():
            what = "a folder, not" if f.is_dir() else "not"
            ap.error(f"{f}: {what} a notebook (.ipynb) or a Python file (.py)")
    if args.csv is not None:
        if args.csv.is_dir():
            ap.error(f"--csv {args.csv}: a folder, not a file")
        if args.csv.exists() and not args.overwrite:
            ap.error(f"--csv {args.csv}: the file exists (--overwrite replaces it)")
        if not args.csv.resolve().parent.is_dir():
            ap.error(f"--csv {args.csv}: no folder {args.csv.parent}")
        with runs.one_line(ap):
            cli.check_writable(args.csv.resolve().parent, f"--csv {args.csv}")
    answers = {f: definitions(f) for f in args.files}  # every file read before any answer runs
    lines, graded = {f: [] for f in args.files}, {}
    pool = concurrent.futures.ThreadPoolExecutor(args.jobs)
    jobs = [pool.submit(grade, f, lines[f].append, args.timeout, answers[f]) for f in args.files]
    with runs.one_line(ap, "no grades file is half-written"):
        try:
            for f, job in zip(args.files, jobs):
                graded[f] = job.result()
                print(*lines[f], sep="\n", flush=True)
        except KeyboardInterrupt:
            _STOP.set()
            for process in list(_LIVE):
                _kill(process)
        finally:
            pool.shutdown(cancel_futures=True)
        if args.csv is not None:
            rows = csv.writer(text := io.StringIO())
            rows.writerow(["file", *(f"exercise {k}" for k in course.EXERCISES), "score"])
            for f, result in graded.items():
                passed = [int(result[k] is True) for k in course.EXERCISES]
                rows.writerow([f, *passed, sum(passed)])
            runs.write_atomic(args.csv, text.getvalue())
    kept = f"written to {args.csv}" if args.csv else "printed above"
    if _STOP.is_set():
        said = f"interrupted (Ctrl-C); the grades of {len(graded)} file(s) {kept}"
        print(f"{ap.prog}: {said}", file=sys.stderr)
        return 130
    if args.csv is not None:
        print(f"grades of {len(graded)} file(s) {kept}")
    return 0 if all(v is True for g in graded.values() for v in g.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
