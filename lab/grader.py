"""The course's grader, `python -m lab.grader submissions/*.ipynb --csv grades.csv`: each exercise's
check (course.EXERCISES) on a student's answers in its own Python process with a time limit, so that
an error, a NaN, a time-out or an exit in one answer fails that exercise alone. A notebook is read
as Jupyter runs it, and only its definitions are kept: its test calls and analyses need values the
grader never makes. It runs the students' code: grade in a throwaway container or VM."""

import argparse
import ast
import csv
import io
import json
import math
import os
import subprocess
import sys
import tempfile
import warnings
from pathlib import Path

import nbformat

import course
from lab import runs

TIMEOUT = 120.0  # seconds per exercise (the checks take about a second)
# cell magics whose body is Python that the kernel runs (the others' is not Python: %%bash, ...)
PYTHON_CELL_MAGICS = ("time", "timeit", "capture", "prun")


def cell_python(cell: str) -> str:
    """A cell's Python as the kernel runs it: %%time dropped, a cell under another cell magic
    (%%bash) left out, line magics and shell lines (%pip, x = !ls) as IPython's calls (not run)."""
    from IPython.core.inputtransformer2 import TransformerManager

    lines = cell.splitlines(keepends=True)
    first = next((i for i, line in enumerate(lines) if line.strip()), None)
    if first is not None and lines[first].lstrip().startswith("%%"):
        if lines[first].lstrip()[2:].split(maxsplit=1)[0] not in PYTHON_CELL_MAGICS:
            return ""
        lines[first] = "\n"  # (keeps the line numbers)
    return TransformerManager().transform_cell("".join(lines))


def _calls_something(node) -> bool:
    """Whether evaluating the expression calls a function (a lambda's body is not evaluated)."""
    if isinstance(node, ast.Call):
        return True
    children = [node.args] if isinstance(node, ast.Lambda) else ast.iter_child_nodes(node)
    return any(_calls_something(c) for c in children)


def _kept(node) -> bool:
    """Whether a cell's statement is a definition: an import (not of the reference answers,
    solutions.py), a function, a class, an assignment that calls nothing (a constant, a lambda)."""
    if isinstance(node, ast.ImportFrom):
        return (node.module or "").split(".")[0] != "solutions"
    if isinstance(node, ast.Import):
        return not any(a.name == "solutions" for a in node.names)
    if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
        return True
    assigns = isinstance(node, (ast.Assign, ast.AnnAssign)) and node.value is not None
    return assigns and not _calls_something(node.value)


def definitions(path) -> tuple[list, list]:
    """What a student's file defines, as Jupyter has it after running every cell: each code
    cell's statements that _kept keeps (a .py file is one cell), with the cell's line numbers; its
    test calls and analyses are left out. Returns ([(where, code)], [a cell that does not parse, and
    why]); SyntaxError for a .py file that does not parse, ValueError for an unreadable notebook."""
    path, kept, unparsed = Path(path), [], []
    if path.suffix != ".ipynb":
        sources = [(str(path), path.read_text())]
    else:
        try:
            with warnings.catch_warnings():  # (a cell without an id is read all the same)
                warnings.simplefilter("ignore")
                cells = [c.source for c in nbformat.read(path, 4).cells if c.cell_type == "code"]
        except Exception as e:  # nbformat's reasons are of many kinds (JSON, schema, structure)
            why = (str(e).splitlines() or [""])[0]
            raise ValueError(f"not a notebook that Jupyter can read ({type(e).__name__}: {why})")
        sources = [(f"{path.name}, code cell {i + 1}", cell_python(c)) for i, c in enumerate(cells)]
    for where, source in sources:
        try:
            tree = ast.parse(source)
        except SyntaxError as e:
            if path.suffix != ".ipynb":
                raise
            unparsed.append(f"{where} does not parse: {e.msg}, line {e.lineno}")
            continue
        lines = source.splitlines(keepends=True)
        for node in filter(_kept, tree.body):
            start = min([node.lineno] + [d.lineno for d in getattr(node, "decorator_list", [])])
            kept.append((where, "\n" * (start - 1) + "".join(lines[start - 1 : node.end_lineno])))
    return kept, unparsed


def _defines(code, name) -> bool:
    defs = (ast.FunctionDef, ast.AsyncFunctionDef)
    return any(isinstance(n, defs) and n.name == name for _, c in code for n in ast.parse(c).body)


def check_in_this_process(spec_file):
    """The grader's worker: the student's definitions run each alone (one that fails is left out,
    as a failed cell), then one exercise's check; its verdict written as JSON (an exit fails it)."""
    spec = json.loads(Path(spec_file).read_text())
    sys.path.append(spec["folder"])  # the student's own modules, after the course's
    space = {"__name__": "answers", "SOLUTIONS": False}
    for where, code in spec["code"]:
        try:
            exec(compile(code, where, "exec"), space)
        except (Exception, SystemExit):  # a definition that needs a value from the analysis
            pass
    name, number = spec["name"], spec["number"]
    try:
        if not callable(space.get(name)):
            raise AssertionError(f"{name} is defined, but its definition does not run on its own")
        verdict = [True, course.CHECKS[number](space[name])]
    except NotImplementedError:
        verdict = [False, "not done (the stub still raises NotImplementedError)"]
    except AssertionError as e:
        verdict = [False, f"FAIL: {e}"]
    except SystemExit as e:
        verdict = [False, f"FAIL: {name} ended the process (sys.exit({e.code!r}))"]
    except Exception as e:  # an answer that breaks the check itself (a strange return value)
        verdict = [False, f"FAIL: {name} broke the check: {type(e).__name__}: {e}"]
    runs.write_atomic(Path(spec["verdict"]), json.dumps(verdict))


def check_in_a_process(number, code, folder, tmp, timeout):
    """One exercise's check in a fresh process (check_in_this_process): (True, what it
    measured) or (False, why not: its failure, a time-out, an exit before its verdict)."""
    name = course.EXERCISES[number][0]
    spec, verdict = Path(tmp) / f"spec{number}.json", Path(tmp) / f"verdict{number}.json"
    about = dict(name=name, number=number, code=code, folder=str(folder), verdict=str(verdict))
    spec.write_text(json.dumps(about))
    worker = "import sys\nfrom lab import grader\ngrader.check_in_this_process(sys.argv[1])"
    python_path = os.pathsep.join([str(runs.ROOT), *filter(None, [os.environ.get("PYTHONPATH")])])
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": python_path}  # one thread a check
    quiet = dict(stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, cwd=runs.ROOT, env=env)
    with open(Path(tmp) / f"stderr{number}.txt", "w+") as err:
        try:
            cmd = [sys.executable, "-c", worker, str(spec)]
            run = subprocess.run(cmd, stderr=err, timeout=timeout, **quiet)
        except subprocess.TimeoutExpired:
            return False, f"FAIL: did not finish in {timeout:g} s (an endless loop?)"
        if verdict.is_file():
            return tuple(json.loads(verdict.read_text()))
        err.seek(0)
        last = [line for line in err.read().splitlines() if line.strip()][-1:]
    return False, (
        f"FAIL: the process ended (exit status {run.returncode}) before the check finished: "
        f"{name} exits or crashes ({last[0] if last else 'nothing on stderr'})"
    )


def grade(path, out=print, timeout=TIMEOUT) -> dict:
    """Grade the answers in `path` (a notebook or a .py file): the student's definitions, then
    each exercise's check in its own process. Prints a line per exercise (PASS with the error
    measured, not done, or what failed) and the score; returns {number: True, or why not}."""
    path = Path(path)
    try:
        code, unparsed = definitions(path)
    except (SyntaxError, ValueError, OSError) as e:  # nothing to grade, saying why
        code, unparsed, broken = None, [], f"the file does not run: {type(e).__name__}: {e}"
    result = {}
    with tempfile.TemporaryDirectory() as tmp:
        for k, (name, title, _) in course.EXERCISES.items():
            if code is None:
                passed, said = False, broken
            elif not _defines(code, name):
                passed, said = False, f"no function {name}" + "".join(f"; {u}" for u in unparsed)
            else:
                passed, said = check_in_a_process(k, code, path.resolve().parent, tmp, timeout)
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


def main(argv=None):
    ap = argparse.ArgumentParser(
        prog="python -m lab.grader",
        description="Grade the course's exercises in each file (a tutorial.ipynb, or a .py that "
        "defines the my_* functions): a line per exercise, the score. It runs the students' code: "
        "grade in a throwaway container or VM. Exit status 0 when every exercise passes, else 1.",
    )
    ap.add_argument("files", nargs="+", help="notebooks (.ipynb) or Python files with the answers")
    ap.add_argument("--timeout", type=float, default=TIMEOUT, help="per check, in s (%(default)g)")
    ap.add_argument("--csv", help="also write the grades to this CSV file, a row per file")
    ap.add_argument("--overwrite", action="store_true", help="let --csv replace an existing file")
    args = ap.parse_args(argv)
    for f in args.files:
        if not Path(f).is_file():
            ap.error(f"{f}: no such file")
        if Path(f).suffix not in (".ipynb", ".py"):
            ap.error(f"{f}: not a notebook (.ipynb) or a Python file (.py)")
    if not 0 < args.timeout < math.inf:
        ap.error(f"--timeout {args.timeout:g}: a number of seconds above 0")
    if args.csv is not None:
        if Path(args.csv).exists() and not args.overwrite:
            ap.error(f"--csv {args.csv}: the file exists (--overwrite replaces it)")
        if not Path(args.csv).resolve().parent.is_dir():
            ap.error(f"--csv {args.csv}: no folder {Path(args.csv).parent}")
    with runs.one_line(ap, "no grades file is half-written"):
        graded = {f: grade(f, timeout=args.timeout) for f in args.files}
        if args.csv is not None:
            write_grades(graded, args.csv)
            print(f"grades of {len(graded)} file(s) written to {args.csv}")
    return 0 if all(v is True for g in graded.values() for v in g.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
