"""The course's grader, `python -m lab.grader submissions/*.ipynb --csv grades.csv`: every file read
first, a notebook as Jupyter runs it but only its definitions; then each exercise's check
(course.EXERCISES) runs here on the answer, which runs in a process of its own (check): an error,
a time-out or an exit fails that exercise alone, and the verdict is never the answer's."""

import argparse
import ast
import concurrent.futures
import contextlib
import csv
import io
import math
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
from pathlib import Path

import nbformat
import torch

import course
from lab import cli, runs

TIMEOUT = 120.0  # seconds per exercise (the checks take about a second)
MEMORY = 2**31  # bytes an answer's process may map beyond its imports (the checks need MBs)
# cell magics whose body is Python that the kernel runs (the others' is not Python: %%bash, ...)
PYTHON_CELL_MAGICS = ("time", "timeit", "capture", "prun")
ANSWERS = {name for name, _, _ in course.EXERCISES.values()}
_LIVE, _STOP, _HERE = set(), threading.Event(), threading.local()  # the answers' processes


def cell_python(cell: str, modules: dict) -> str:
    """A cell's Python as the kernel runs it: %%time dropped, a cell under another cell magic
    (%%bash) left out, %%writefile NAME.py's text into modules[NAME.py], line magics and shell
    lines (%pip, x = !ls) as IPython's calls (not run)."""
    from IPython.core.inputtransformer2 import TransformerManager

    lines = cell.splitlines(keepends=True)
    first = next((i for i, line in enumerate(lines) if line.strip()), None)
    if first is not None and lines[first].lstrip().startswith("%%"):
        magic = lines[first].lstrip()[2:].split() or [""]
        if magic[0] == "writefile" and magic[-1].endswith(".py"):
            modules[Path(magic[-1]).name] = "".join(lines[first + 1 :])
        if magic[0] not in PYTHON_CELL_MAGICS:
            return ""
        lines[first] = "\n"  # (keeps the line numbers)
    return TransformerManager().transform_cell("".join(lines))


def _calls_something(node) -> bool:
    """Whether evaluating the expression calls a function (a lambda's body is not evaluated)."""
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
    """Whether a cell's statement is a definition: an import (not of the reference answers,
    solutions.py), a function, a class, an assignment that calls nothing (a constant, a lambda)
    or that binds an exercise's name."""
    if isinstance(node, (ast.Import, ast.ImportFrom)):
        return "solutions" not in [(getattr(node, "module", "") or "").split(".")[0], *_names(node)]
    if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
        return True
    assigns = isinstance(node, (ast.Assign, ast.AnnAssign)) and node.value is not None
    return assigns and (not _calls_something(node.value) or not ANSWERS.isdisjoint(_names(node)))


def definitions(path) -> dict | str:
    """What a file defines, as Jupyter has it after running every cell (a .py file, read as Python
    reads it, is one cell): code, [(cell, statement _kept keeps, the names it binds)]; modules, the
    %%writefile NAME.py cells; dropped, {name: cell} that only left-out statements bind; unparsed,
    why each cell that does not parse. Or the one line that says why the file cannot be graded."""
    try:
        return _definitions(Path(path), dict(code=[], modules={}, dropped={}, unparsed=[]))
    except Exception as e:  # any reason (JSON nested too deep, an expression too long, ...)
        why = (str(e).splitlines() or [""])[0]
        what = "not a notebook that Jupyter can read" if Path(path).suffix == ".ipynb" else ""
        return f"{what or 'the file does not run'} ({type(e).__name__}: {why})"[:300]


def _definitions(path, read):
    if path.suffix != ".ipynb":
        with tokenize.open(path) as f:  # (a byte-order mark, a coding line)
            sources = [(str(path), f.read())]
    else:
        with warnings.catch_warnings():  # (a cell without an id is read all the same)
            warnings.simplefilter("ignore")
            cells = [c.source for c in nbformat.read(path, 4).cells if c.cell_type == "code"]
        cells = [cell_python(c, read["modules"]) for c in cells]
        sources = [(f"{path.name}, code cell {i + 1}", c) for i, c in enumerate(cells)]
    for where, source in sources:
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
            start = min([node.lineno] + [d.lineno for d in getattr(node, "decorator_list", [])])
            code = "\n" * (start - 1) + "".join(lines[start - 1 : node.end_lineno])
            read["code"].append((where, code, _names(node)))
    return read


def _send(stream, obj) -> None:
    data = io.BytesIO()
    torch.save(obj, data)
    stream.write(len(data.getvalue()).to_bytes(8, "big") + data.getvalue())
    stream.flush()


def _receive(stream, trusted=False):
    """A message _send wrote; the answer's (not trusted) as tensors, numbers and lists only."""
    size = int.from_bytes(stream.read(8) or b"\0", "big")
    data = stream.read(size) if 0 < size <= MEMORY else b""
    if not data or len(data) < size:
        raise EOFError
    return torch.load(io.BytesIO(data), weights_only=not trusted)


def serve() -> None:
    """The answer's process: its memory limited, `solutions` unimportable, the student's definitions
    run each alone (one that fails is left out, as a failed cell), then the check's calls of the
    answer, each message read from stdin, its output (or error) written back."""
    used = int(Path("/proc/self/statm").read_text().split()[0]) * os.sysconf("SC_PAGE_SIZE")
    resource.setrlimit(resource.RLIMIT_AS, (used + MEMORY, used + MEMORY))
    sys.modules["solutions"] = None  # an answer's `import solutions` fails
    into, out = sys.stdin.buffer, os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)  # the answers' prints to stderr: stdout is the grader's
    (spec,), folder, graph = _receive(into, trusted=True), tempfile.mkdtemp(), None
    for name, text in spec["modules"].items():
        Path(folder, name).write_text(text)
    sys.path.insert(0, folder)
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
            first = code.strip().splitlines()[0]
            failed = f"{first} failed ({type(e).__name__}: {e}) in {where}"
            why.update(dict.fromkeys(names, f"needs {', '.join(names)}, but {failed}"))
    fn = space.get(spec["name"])
    _send(out, ["ok", None if callable(fn) else why.get(spec["name"], "not a function")])
    while True:
        kind, args, grads, quiet = _receive(into, trusted=True)
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
            _send(out, ["ok", reply])
        except (Exception, SystemExit) as e:
            said = why[e.name] if isinstance(e, NameError) and e.name in why else str(e)
            _send(out, ["error", type(e).__name__, said, getattr(e, "code", None)])


class _Ended(BaseException):
    """The answer's process ended (or was killed) before the check finished."""


class _Remote(torch.autograd.Function):
    """An answer's output here whose backward pass is computed in the answer's process."""

    @staticmethod
    def forward(ctx, answer, out, *inputs):
        ctx.answer = answer
        return out.clone()

    @staticmethod
    def backward(ctx, grad):
        return None, None, *ctx.answer.ask("grad", grad, [], None)


class _Answer:
    """The student's function as a check calls it: each call runs in the answer's process."""

    def __init__(self, process):
        self.process = process

    def ask(self, *message):
        try:
            _send(self.process.stdin, list(message))
            reply = _receive(self.process.stdout)
        except (OSError, EOFError):
            raise _Ended from None
        except Exception as e:  # (what torch.load refuses: objects other than tensors, lists)
            raise TypeError(f"returned what the grader does not read ({e})"[:200]) from None
        if reply[0] == "ok":
            return reply[1]
        kind, said, code = reply[1:]
        errors = {"NotImplementedError": NotImplementedError, "Forbidden": course.Forbidden}
        if kind == "SystemExit":
            raise SystemExit(code)
        raise errors.get(kind, type(str(kind), (Exception,), {}))(said)

    def __call__(self, *args):
        grads = [i for i, a in enumerate(args) if torch.is_tensor(a) and a.requires_grad]
        sent = [a.detach() if torch.is_tensor(a) else a for a in args]
        out, graph = self.ask("call", sent, grads, getattr(_HERE, "quiet", None))
        return _Remote.apply(self, out, *(args[i] for i in grads)) if graph else out


@contextlib.contextmanager
def _no_autograd(name):
    """course.no_autograd for the grader's threads: the calls within it run under it there."""
    if not getattr(_HERE, "grading", False):
        with _NO_AUTOGRAD(name):
            yield
        return
    _HERE.quiet = name
    try:
        yield
    finally:
        _HERE.quiet = None


_NO_AUTOGRAD, course.no_autograd = course.no_autograd, _no_autograd


def _kill(process) -> None:
    with contextlib.suppress(ProcessLookupError):
        os.killpg(process.pid, signal.SIGKILL)


def check(number, answers, timeout):
    """One exercise's check, here, on the answer in a fresh process of its own session (serve),
    killed whole after the check or at the time limit: (True, what it measured) or (False, why)."""
    name, start = course.EXERCISES[number][0], time.monotonic()
    python_path = os.pathsep.join([str(runs.ROOT), *filter(None, [os.environ.get("PYTHONPATH")])])
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": python_path}  # one thread a check
    cmd = [sys.executable, "-c", "from lab import grader\ngrader.serve()"]
    pipes = dict(stdin=subprocess.PIPE, stdout=subprocess.PIPE, cwd=runs.ROOT, env=env)
    with tempfile.TemporaryFile() as err:
        process = subprocess.Popen(cmd, stderr=err, start_new_session=True, **pipes)
        _LIVE.add(process)
        timer = threading.Timer(timeout, _kill, [process])
        timer.start()
        try:
            if _STOP.is_set():
                raise KeyboardInterrupt
            answer, _HERE.grading = _Answer(process), True
            spec = {key: answers[key] for key in ("code", "modules", "dropped")}
            broken = answer.ask({**spec, "name": name})
            if broken:
                raise AssertionError(f"{name} is defined, but does not run on its own: {broken}")
            return True, course.CHECKS[number](answer)
        except _Ended:
            if time.monotonic() - start >= timeout:
                return False, f"FAIL: did not finish in {timeout:g} s (an endless loop?)"
            err.seek(0)
            last = [line for line in err.read().decode(errors="replace").splitlines() if line]
            return False, (
                f"FAIL: the process ended (exit status {process.wait()}) before the check "
                f"finished: {name} exits or crashes ({last[-1] if last else 'nothing on stderr'})"
            )
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
            timer.cancel()
            _kill(process)
            process.wait()
            _LIVE.discard(process)


def grade(path, out=print, timeout=TIMEOUT, answers=None) -> dict:
    """Grade the answers in `path` (a notebook or a .py file; answers: definitions(path) if read
    before): each exercise's check (check). Prints a line per exercise (PASS with the error
    measured, not done, or what failed) and the score; returns {number: True, or why not}."""
    path = Path(path)
    answers, result = definitions(path) if answers is None else answers, {}
    for k, (name, title, _) in course.EXERCISES.items():
        if isinstance(answers, str):
            passed, said = False, answers
        elif not any(name in names for _, _, names in answers["code"]):
            passed, said = (
                False,
                f"no function {name}" + "".join(f"; {u}" for u in answers["unparsed"]),
            )
        else:
            passed, said = check(k, answers, timeout)
        result[k] = True if passed else said
        out(f"  exercise {k} ({title}): {f'PASS ({said})' if passed else said}")
    out(f"{path}: score {sum(v is True for v in result.values())}/{len(course.EXERCISES)}")
    return result


def write_grades(graded, csv_path):
    """The class's grades as CSV, written atomically: a row per file, 1/0 per exercise, score."""
    rows = csv.writer(text := io.StringIO())
    rows.writerow(["file", *(f"exercise {k}" for k in course.EXERCISES), "score"])
    for f, result in graded.items():
        passed = [int(result[k] is True) for k in course.EXERCISES]
        rows.writerow([f, *passed, sum(passed)])
    runs.write_atomic(Path(csv_path), text.getvalue())


def check_arguments(ap, args) -> None:
    """Every file and --csv checked before any grading: argparse's one line naming what is wrong."""
    for f in args.files:
        if Path(f).is_symlink() and not Path(f).exists():
            ap.error(f"{f}: a symbolic link to {os.readlink(f)}, which does not exist")
        if Path(f).is_dir():
            ap.error(f"{f}: a folder, not a notebook (.ipynb) or a Python file (.py)")
        if not Path(f).is_file():
            ap.error(f"{f}: no such file")
        if Path(f).suffix not in (".ipynb", ".py"):
            ap.error(f"{f}: not a notebook (.ipynb) or a Python file (.py)")
    if not 0 < args.timeout < math.inf:
        ap.error(f"--timeout {args.timeout:g}: a number of seconds above 0")
    if args.jobs < 1:
        ap.error(f"--jobs {args.jobs}: a number of processes above 0")
    if args.csv is not None:
        if Path(args.csv).is_dir():
            ap.error(f"--csv {args.csv}: a folder, not a file")
        if Path(args.csv).exists() and not args.overwrite:
            ap.error(f"--csv {args.csv}: the file exists (--overwrite replaces it)")
        if not Path(args.csv).resolve().parent.is_dir():
            ap.error(f"--csv {args.csv}: no folder {Path(args.csv).parent}")
        with runs.one_line(ap):
            cli.check_writable(Path(args.csv).resolve().parent, f"--csv {args.csv}")


def main(argv=None):
    ap = argparse.ArgumentParser(
        prog="python -m lab.grader",
        description="Grade the course's exercises in each file (a tutorial.ipynb, or a .py that "
        "defines the my_* functions): a line per exercise, the score. It runs the students' code: "
        "grade in a throwaway container or VM. Exit status 0 when every exercise passes, else 1.",
    )
    ap.add_argument("files", nargs="+", help="notebooks (.ipynb) or Python files with the answers")
    ap.add_argument("--timeout", type=float, default=TIMEOUT, help="per check, in s (%(default)g)")
    ap.add_argument("--jobs", type=int, default=1, help="files graded at once (%(default)s)")
    ap.add_argument("--csv", help="also write the grades to this CSV file, a row per file")
    ap.add_argument("--overwrite", action="store_true", help="let --csv replace an existing file")
    args = ap.parse_args(argv)
    check_arguments(ap, args)
    answers = {f: definitions(f) for f in args.files}  # every file read before any answer runs
    graded, pool = {}, concurrent.futures.ThreadPoolExecutor(args.jobs)
    with runs.one_line(ap, "no grades file is half-written"):
        try:
            lines = {f: [] for f in args.files}
            jobs = {
                f: pool.submit(grade, f, lines[f].append, args.timeout, answers[f])
                for f in args.files
            }
            for f, job in jobs.items():
                graded[f] = job.result()
                print(*lines[f], sep="\n", flush=True)
        except KeyboardInterrupt:
            _STOP.set()
            for process in list(_LIVE):
                _kill(process)
            if args.csv is not None:
                write_grades(graded, args.csv)
            kept = f"written to {args.csv}" if args.csv else "printed above"
            print(
                f"{ap.prog}: interrupted (Ctrl-C); the grades of {len(graded)} file(s) {kept}",
                file=sys.stderr,
            )
            return 130
        finally:
            pool.shutdown(cancel_futures=True)
        if args.csv is not None:
            write_grades(graded, args.csv)
            print(f"grades of {len(graded)} file(s) written to {args.csv}")
    return 0 if all(v is True for g in graded.values() for v in g.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
