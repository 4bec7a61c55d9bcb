"""Tests of lab/grader.py: a notebook is graded exercise by exercise, as Jupyter runs it, and
nothing one answer does sinks another; the command line owns its exit status and its CSV. Each
graded exercise runs in its own process (about 2 s each)."""

import ast
import json
import os
import pathlib
import subprocess
import sys

import pytest

import course
from lab import grader

REPO = pathlib.Path(__file__).resolve().parent
SOLUTIONS_SOURCE = (REPO / "solutions.py").read_text()
NAMES = [name for name, _, _ in course.EXERCISES.values()]


def solution(name):
    """The source of solutions.py's function `name`."""
    node = next(
        f
        for f in ast.parse(SOLUTIONS_SOURCE).body
        if isinstance(f, ast.FunctionDef) and f.name == name
    )
    return ast.get_source_segment(SOLUTIONS_SOURCE, node)


def notebook(tmp_path, cells, name="student.ipynb"):
    """A notebook of code cells (the first imports what the tutorial's do), written to tmp_path."""
    head = "import math\nimport torch\nimport course\nimport diffstack as ds\n"
    nb = {
        "cells": [
            {"cell_type": "code", "source": s, "metadata": {}, "outputs": [], "execution_count": 1}
            for s in (head, *cells)
        ],
        "metadata": {},
        "nbformat": 4,
        "nbformat_minor": 5,
    }
    path = tmp_path / name
    path.write_text(json.dumps(nb))
    return path


def grade(path, **kw):
    lines = []
    return grader.grade(path, lines.append, **kw), lines


@pytest.mark.slow
def test_reference_answers_score_full_marks_in_a_notebook_and_a_file(tmp_path, capsys):
    result, lines = grade(notebook(tmp_path, [solution(n) for n in NAMES]))
    assert all(v is True for v in result.values()), lines
    assert lines[-1].endswith("student.ipynb: score 6/6")
    assert all(line.startswith("  exercise") and "PASS (" in line for line in lines[:-1])
    result, lines = grade(REPO / "solutions.py")
    assert all(v is True for v in result.values()) and lines[-1].endswith("score 6/6")
    assert capsys.readouterr().out == ""  # nothing but the grader's lines (here: into `lines`)


@pytest.mark.slow
def test_the_stub_notebook_scores_zero_and_prints_nothing_else(capsys):
    result = grader.grade(REPO / "tutorial.ipynb")
    out = capsys.readouterr().out.splitlines()
    assert all(v.startswith("not done") for v in result.values()), result
    assert out[-1].endswith("tutorial.ipynb: score 0/6")
    assert len(out) == 7 and all(line.startswith("  exercise") for line in out[:-1]), out


@pytest.mark.slow
def test_one_wrong_answer_fails_alone_and_says_what_differs(tmp_path):
    """Exercise 6 wrong (p_0 with the wrong sign), and an assert that fails in its cell after the
    definition (as a notebook's own test would): 5 of 6, one line naming what is wrong."""
    wrong = solution("my_kkt_backward").replace("return p0,", "return -p0,")
    cells = [solution(n) for n in NAMES[:5]] + [wrong + "\nassert False, 'my own test'\n"]
    result, lines = grade(notebook(tmp_path, cells))
    assert [k for k, v in result.items() if v is not True] == [6]
    assert "dL/dx_init" in result[6] and "p_0 with the wrong sign" in result[6]
    assert lines[-1].endswith("score 5/6")


@pytest.mark.slow
def test_magics_shell_lines_test_calls_and_helper_cells_do_not_sink_right_answers(tmp_path):
    """A %%time cell, a line magic, a shell line, a test call on a notebook variable that the
    grader never defines, a helper function in a cell of its own, a constant in another: every
    right answer passes."""
    helper = (
        "def softmax_logits(cost, valid, beta):\n    return torch.where(valid, -beta * cost, NEG)\n"
    )
    plan_loss = (
        "def my_plan_loss(cost, valid, target, beta):\n"
        "    logp = torch.log_softmax(softmax_logits(cost, valid, beta), -1)\n"
        "    return -logp.gather(-1, target[:, None])[:, 0]\n"
    )
    cells = [
        "%%time\n" + solution("my_collision") + "\nprint(my_collision(pos, ctx, 2.0))\n",
        "%matplotlib inline\n!pip list\n" + helper,
        "NEG = -math.inf\nfiles = !ls\n",
        plan_loss + "\nmy_plan_loss(data.cost, data.valid, data.target, 1.0)\n",
        *(solution(n) for n in NAMES[2:]),
    ]
    result, lines = grade(notebook(tmp_path, cells))
    assert all(v is True for v in result.values()), lines


@pytest.mark.slow
def test_an_exit_a_nan_or_an_endless_loop_fails_that_exercise_alone(tmp_path):
    cells = [
        "import sys\n"
        + solution("my_collision").replace("    def phi", "    sys.exit(0)\n    def phi"),
        solution("my_plan_loss").replace("return -logp", "return math.nan * logp[:, 0] - logp"),
        solution("my_plan_loss_grad").replace(
            "    # p:", "    while True:\n        pass\n    # p:"
        ),
        "import os\n" + solution("my_riccati_step").replace("    F =", "    os._exit(0)\n    F ="),
        solution("my_kkt_backward"),
    ]
    result, lines = grade(notebook(tmp_path, cells), timeout=20)
    assert result[1] == "FAIL: my_collision ended the process (sys.exit(0))"
    assert result[2].startswith("FAIL: my_plan_loss (beta = 1.0): inf or NaN")
    assert result[3] == "FAIL: did not finish in 20 s (an endless loop?)"
    assert result[4] == "no function my_plan_loss_fixed"
    assert result[5].startswith("FAIL: the process ended (exit status 0) before the check")
    assert result[6] is True and lines[-1].endswith("score 1/6")


def test_the_reference_answers_imported_score_nothing(tmp_path):
    cells = ["from solutions import my_collision\nimport solutions\n", solution("my_plan_loss")]
    code = grader.definitions(notebook(tmp_path, cells))["code"]
    assert not any("solutions" in c for _, c, _ in code)
    names = {name for *_, names in code for name in names}
    assert "my_collision" not in names and "my_plan_loss" in names


def test_a_cell_that_does_not_parse_is_named(tmp_path):
    cells = ["def my_collision(pos, ctx, rbf_var):\n    return (pos\n", solution("my_plan_loss")]
    result, _ = grade(notebook(tmp_path, cells))
    assert result[1] == (
        "no function my_collision; student.ipynb, code cell 2 does not parse: '(' was never "
        "closed, line 2"
    )
    assert result[2] is True


@pytest.mark.slow
def test_the_command_line_grades_every_file_and_owns_the_exit_status(tmp_path):
    """A file whose answer calls sys.exit(0) does not end the grading: the next file is graded,
    the status is 1 (not every exercise passes), the CSV has a row per file and is not replaced
    without --overwrite; a missing file is refused before any grading."""
    exits = notebook(tmp_path, ["import sys\nsys.exit(0)\n", solution("my_collision")], "a.ipynb")
    exits_in_answer = "import sys\ndef my_plan_loss(cost, valid, target, beta):\n    sys.exit(0)\n"
    (tmp_path / "b.py").write_text(exits_in_answer)
    csv = tmp_path / "grades.csv"
    env = {**os.environ, "PYTHONPATH": str(REPO)}  # from another folder, as `python -m lab.grader`

    def cli(*args):
        cmd = [sys.executable, "-m", "lab.grader", *map(str, args)]
        return subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, env=env)

    run = cli(exits, tmp_path / "b.py", "--csv", csv)
    assert run.returncode == 1, run.stderr
    assert "a.ipynb: score 1/6" in run.stdout and "b.py: score 0/6" in run.stdout
    assert "exercise 2 (the relaxed planner's loss): FAIL: my_plan_loss ended the process" in (
        run.stdout
    )
    rows = csv.read_text().splitlines()
    assert rows[0] == "file,exercise 1,exercise 2,exercise 3,exercise 4,exercise 5,exercise 6,score"
    assert rows[1] == f"{exits},1,0,0,0,0,0,1" and rows[2].endswith(",0,0,0,0,0,0,0")
    again = cli(exits, tmp_path / "b.py", "--csv", csv)
    assert again.returncode == 2 and again.stdout == ""
    assert again.stderr.splitlines()[-1].endswith("the file exists (--overwrite replaces it)")
    run = cli(REPO / "solutions.py")
    assert run.returncode == 0 and "solutions.py: score 6/6" in run.stdout
    run = cli(REPO / "tutorial.ipynb", "nothere.ipynb")
    assert run.returncode == 2 and run.stdout == ""
    assert run.stderr.strip().splitlines()[-1].endswith("nothere.ipynb: no such file")


def test_a_file_that_does_not_parse_scores_nothing_saying_why(tmp_path):
    (tmp_path / "broken.py").write_text("def my_collision(:\n")
    result, lines = grade(tmp_path / "broken.py")
    assert all(v.startswith("the file does not run (SyntaxError") for v in result.values())
    for text in ("{not json", '{"cells": 5}', '{"nbformat": 4, "cells": [{"cell_type": "code"}]}'):
        (tmp_path / "broken.ipynb").write_text(text)
        result, lines = grade(tmp_path / "broken.ipynb")
        assert all("not a notebook that Jupyter can read" in v for v in result.values()), text
        assert all("\n" not in line for line in lines)  # one line each, whatever nbformat says


def test_definitions_keeps_what_a_kernel_defines_and_runs_nothing_else(tmp_path):
    cells = [
        "%%bash\necho hi\n",
        "%%time\nX = 1\ny = compute()\nfor i in range(3):\n    print(i)\n",
        "@staticmethod\ndef f():\n    pass\nf()\nclass C:\n    pass\nF = lambda z: g(z)\n",
    ]
    read = grader.definitions(notebook(tmp_path, cells))
    code, unparsed = read["code"], read["unparsed"]
    kept = [ast.unparse(ast.parse(c)) for _, c, _ in code]
    assert kept[4:] == [
        "X = 1",
        "@staticmethod\ndef f():\n    pass",
        "class C:\n    pass",
        "F = lambda z: g(z)",
    ]
    assert unparsed == []
    # line numbers are the cell's: an error in a definition points into its cell
    assert code[6][1].splitlines()[:5] == ["", "", "", "", "class C:"]
    assert code[6][0].endswith("code cell 4")


@pytest.mark.slow
def test_the_committed_notebook_with_one_answer_right_and_one_wrong(tmp_path):
    """The student notebook with exercise 1 solved and exercise 2 wrong (the valid mask left out):
    1 of 6, exercise 2's line saying what failed, the others not done."""
    nb = json.loads((REPO / "tutorial.ipynb").read_text())
    cells = [c for c in nb["cells"] if c["cell_type"] == "code"]
    one = next(c for c in cells if "def my_collision(" in "".join(c["source"]))
    one["source"] = solution("my_collision")
    two = next(c for c in cells if "def my_plan_loss(" in "".join(c["source"]))
    two["source"] = (
        "def my_plan_loss(cost, valid, target, beta):\n"  # the valid mask left out
        "    return -(-beta * cost).log_softmax(-1).gather(-1, target[:, None])[:, 0]\n"
    )
    (tmp_path / "student.ipynb").write_text(json.dumps(nb))
    result, lines = grade(tmp_path / "student.ipynb")
    assert result[1] is True and result[2].startswith(
        "FAIL: my_plan_loss (beta = 1.0): max |yours - reference|"
    )
    assert all(result[k].startswith("not done") for k in (3, 4, 5, 6))
    assert lines[-1].endswith("student.ipynb: score 1/6")


def collision_by(body, before=()):
    """Cells: `before`, then my_collision as `return <body>` (the module's C_coll, a helper's)."""
    return [*before, f"def my_collision(pos, ctx, rbf_var):\n    return {body}\n"]


@pytest.mark.slow
def test_an_answer_bound_by_an_assignment_counts(tmp_path):
    """A lambda, or another function bound to the exercise's name, is an answer like a def."""
    cells = [
        "my_collision = lambda pos, ctx, rbf_var: ds.collision_term(pos, ctx, rbf_var)\n",
        solution("my_plan_loss"),
        "my_plan_loss_fixed = my_plan_loss\n",
    ]
    result, lines = grade(notebook(tmp_path, cells))
    assert result[1] is True and result[2] is True and result[4] is True, lines


@pytest.mark.slow
def test_constants_computed_by_a_call_and_failed_imports_are_named_helper_modules_work(tmp_path):
    """A constant computed by a call is named in one line (never a bare NameError), so is an
    import that failed; a module written from a cell (%%writefile) is importable as in Jupyter."""
    helper = "%%writefile helpers.py\nimport diffstack as ds\n"
    helper += "def c(*a):\n    return ds.collision_term(*a)\n"
    cells = [helper, "import helpers\n", *collision_by("helpers.c(pos, ctx, rbf_var)")]
    result, lines = grade(notebook(tmp_path, cells, "a.ipynb"))
    assert result[1] is True, lines
    cells = collision_by("ONE * ds.collision_term(pos, ctx, rbf_var)", ["ONE = torch.tensor(1.0)"])
    cells += [
        "import not_a_module_here\ndef my_plan_loss(cost, valid, target, beta):\n"
        "    return not_a_module_here.f(cost)\n"
    ]
    result, lines = grade(notebook(tmp_path, cells, "b.ipynb"))
    assert "uses ONE, which the notebook computes by a call (b.ipynb, code cell 2)" in result[1]
    assert "define it inside the function" in result[1]
    assert "import not_a_module_here failed (ModuleNotFoundError" in result[2], result[2]
    assert all("\n" not in line for line in lines)


@pytest.mark.slow
def test_an_answer_can_neither_reach_the_reference_nor_write_its_verdict_nor_outlive_it(tmp_path):
    """An answer that imports solutions in its body, one that writes a verdict where the old
    worker kept it, one that forks a process that would outlive the check, one that takes 3 GB:
    each fails, the forked process is gone, the memory limit is named."""
    pid_file = tmp_path / "pid"
    forge = (
        "import json, os, sys\ndef my_collision(pos, ctx, rbf_var):\n"
        "    spec = json.load(open(sys.argv[1]))\n"
        "    open(spec['verdict'], 'w').write('[true, \"forged\"]')\n    os._exit(0)\n"
    )
    cheat = "def my_plan_loss(cost, valid, target, beta):\n    import solutions\n"
    cheat += "    return solutions.my_plan_loss(cost, valid, target, beta)\n"
    fork = "import subprocess\ndef my_plan_loss_grad(cost, valid, target, beta):\n"
    fork += "    p = subprocess.Popen(['sleep', '300'])\n"
    fork += f"    open({str(pid_file)!r}, 'w').write(str(p.pid))\n"
    fork += "    return cost\n"
    hog = "def my_riccati_step(*args):\n    x = bytearray(3 * 2**30)\n    return x\n"
    result, lines = grade(notebook(tmp_path, [forge, cheat, fork, hog]), timeout=60)
    assert all(result[k] is not True for k in (1, 2, 3, 5)), lines
    assert "solutions" in result[2] and "MemoryError" in result[5], lines
    stat = pathlib.Path(f"/proc/{pid_file.read_text()}/stat")
    assert not stat.exists() or stat.read_text().split(") ")[1][0] == "Z", "the fork outlived it"


def test_a_malformed_file_scores_zero_in_one_line(tmp_path):
    """JSON nested too deeply, an expression too long for the parser, a cell that is only %%, a
    .py with a byte-order mark (read as Python reads it: here nothing is defined)."""
    (tmp_path / "deep.ipynb").write_text("[" * 100_000 + "]" * 100_000)
    notebook(tmp_path, ["x = " + "1 + " * 200_000 + "1\n"], "long.ipynb")
    notebook(tmp_path, ["%%"], "magic.ipynb")
    (tmp_path / "bom.py").write_text("\ufeffimport math\n", encoding="utf-8")
    for name in ("deep.ipynb", "long.ipynb", "magic.ipynb", "bom.py"):
        result, lines = grade(tmp_path / name)
        assert lines[-1].endswith(f"{name}: score 0/6") and len(lines) == 7, (name, lines)
        assert all("\n" not in line for line in lines), name
    assert result[1] == "no function my_collision"  # bom.py: read, not a SyntaxError


def cli(tmp_path, *args, **kw):
    env = {**os.environ, "PYTHONPATH": str(REPO)}  # from another folder, as `python -m lab.grader`
    cmd = [sys.executable, "-m", "lab.grader", *map(str, args)]
    return subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, env=env, **kw)


def test_arguments_refused_before_any_grading_each_named(tmp_path):
    (tmp_path / "a.py").write_text("import math\n")
    (tmp_path / "gone.ipynb").symlink_to(tmp_path / "missing.ipynb")
    (tmp_path / "folder.ipynb").mkdir()
    cases = {
        ("--csv", tmp_path): f"--csv {tmp_path}: a folder, not a file",
        ("--csv", "/proc/grades.csv"): "--csv /proc/grades.csv: /proc is not a writable folder",
        ("gone.ipynb",): f"gone.ipynb: a symbolic link to {tmp_path / 'missing.ipynb'}, which",
        ("folder.ipynb",): "folder.ipynb: a folder, not a notebook",
        ("--jobs", "0"): "--jobs must be from 1 to 256, got '0'",
    }
    for args, said in cases.items():
        run = cli(tmp_path, "a.py", *args)
        assert run.returncode == 2 and run.stdout == "", (args, run.stdout)
        assert said in run.stderr.splitlines()[-1], (args, run.stderr)


@pytest.mark.slow
def test_a_class_in_parallel_and_ctrl_c_keeps_the_grades_so_far(tmp_path):
    """--jobs 2: the files' lines in the order given; Ctrl-C: one line, exit 130, the CSV has the
    files graded so far."""
    (tmp_path / "a.py").write_text("import math\n")
    (tmp_path / "b.py").write_text("def my_collision(pos, ctx, rbf_var):\n    return pos\n")
    run = cli(tmp_path, "a.py", "b.py", "--jobs", "2")
    assert run.returncode == 1 and run.stdout.splitlines()[6] == "a.py: score 0/6", run.stderr
    assert run.stdout.splitlines()[-1] == "b.py: score 0/6"
    (tmp_path / "c.py").write_text("import time\ndef my_collision(*a):\n    time.sleep(300)\n")
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    cmd = [sys.executable, "-m", "lab.grader", "a.py", "c.py", "--csv", "g.csv"]
    with subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=tmp_path, env=env, text=True
    ) as p:
        while not p.stdout.readline().startswith("a.py: score"):
            pass
        p.send_signal(2)
        err = p.communicate(timeout=60)[1]
    assert p.returncode == 130 and len(err.splitlines()) == 1, err
    assert "interrupted (Ctrl-C); the grades of 1 file(s) written to g.csv" in err
    assert (tmp_path / "g.csv").read_text().splitlines()[1] == "a.py,0,0,0,0,0,0,0"
