"""Tests of the course: tutorial.py (jupytext percent format) is the notebook's source,
tutorial.ipynb is made from it, and the notebook runs top to bottom."""

import ast
import dataclasses
import json
import math
import pathlib

import jupytext
import nbclient
import nbformat
import pytest
import torch

import course
import solutions

REPO = pathlib.Path(__file__).resolve().parent


def cell_sources(nb):
    return [(c.cell_type, c.source) for c in nb.cells]


def test_notebook_is_made_from_tutorial_py():
    """tutorial.ipynb holds exactly the cells of tutorial.py (regenerate: jupytext --update --to
    ipynb tutorial.py)."""
    source = jupytext.read(REPO / "tutorial.py")
    notebook = nbformat.read(REPO / "tutorial.ipynb", as_version=4)
    assert cell_sources(source) == cell_sources(notebook)


def test_the_comparison_catches_a_changed_cell():
    source = jupytext.read(REPO / "tutorial.py")
    changed = jupytext.read(REPO / "tutorial.py")
    changed.cells[3].source += "\nprint('drift')"
    assert cell_sources(source) != cell_sources(changed)


@pytest.mark.slow
def test_tutorial_notebook_runs_in_quick_mode(monkeypatch):
    """The student notebook (tutorial.py) with solutions.py injected executes top to bottom from a
    fresh kernel in quick mode (cwd = the repository) with no error, every exercise check passes,
    and every checkpoint it prints agrees with its expected value. About 2 minutes on 2
    shared cores."""
    nb = jupytext.read(REPO / "tutorial.py")
    # the notebook's parameters cell reads it; the kernel inherits it
    monkeypatch.setenv("DIFFSTACK_QUICK", "1")
    monkeypatch.setenv("DIFFSTACK_SOLUTIONS", "1")  # the exercises use solutions.py's answers
    client = nbclient.NotebookClient(
        nb, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(REPO)}}
    )
    client.execute()  # raises CellExecutionError (naming the cell) on the first error
    text = "".join(o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.outputs)
    assert "QUICK = True" in text and "solutions.py injected" in text
    for number in SOLUTIONS:
        assert f"EXERCISE {number}: PASS" in text, f"exercise {number} did not pass in the notebook"
    checks = [
        line for line in text.splitlines() if line.startswith(("CHECKPOINT", "CHECK ", "CLAIM "))
    ]
    assert len(checks) >= 14, checks
    # (a failed one raises: the cell errors first)
    assert all(line.endswith("OK") for line in checks), checks


def tutorial_checks():
    """The notebook's check functions (checkpoint, check_order, check_claim): course.py's, which
    tutorial.py imports."""
    tree = ast.parse((REPO / "tutorial.py").read_text())
    imported = {
        a.name
        for node in tree.body
        if isinstance(node, ast.ImportFrom) and node.module == "course"
        for a in node.names
    }
    assert {"checkpoint", "check_order", "check_claim"} <= imported, sorted(imported)
    return {
        name: getattr(course, name)
        for name in ("CheckpointError", "checkpoint", "check_order", "check_claim")
    }


def test_the_notebook_checks_stop_on_a_wrong_value(tmp_path, monkeypatch, capsys):
    """A checkpoint off its value, an ordering the other way round, a claim whose verdict the text
    gets wrong: each raises (the notebook stops at that cell), each right one passes."""
    t = tutorial_checks()
    t["checkpoint"]("x", 1.0, 1.0, 1e-9)
    with pytest.raises(t["CheckpointError"], match="measured 1.1"):
        t["checkpoint"]("x", 1.1, 1.0, 0.05)
    t["check_order"]("o", {"GT": -2.0, "none": 0.0}, ["GT", "none"])
    with pytest.raises(t["CheckpointError"], match="GT -2 is not below none -2.5"):
        t["check_order"]("o", {"GT": -2.0, "none": -2.5}, ["GT", "none"])
    with pytest.raises(t["CheckpointError"], match="margin 0.1"):
        t["check_order"]("o", {"a": 1.0, "b": 1.05}, ["a", "b"], margin=0.1)

    def runs(*v):
        return [
            {"rel_mse": x, "ade": 1.0, "nll": 1.0, "converged": 1.0, "rel_plan_loss": 0.0}
            for x in v
        ]

    (tmp_path / "results").mkdir()
    (tmp_path / "results" / "il.json").write_text(
        json.dumps(dict(results=dict(Standard=runs(1.0, 2.0, 3.0), DiffStack=runs(0.0, 1.1, 1.9))))
    )
    monkeypatch.chdir(tmp_path)
    t["check_claim"]("il", "DiffStack", "Standard", "MSE (x1e-2)", "reproduced")
    with pytest.raises(t["CheckpointError"], match="update the text"):
        t["check_claim"]("il", "DiffStack", "Standard", "MSE (x1e-2)", "not reproduced")


# --- the exercises: solutions pass their checks, known-wrong answers fail them --------------------

SOLUTIONS = {
    1: solutions.my_collision,
    2: solutions.my_plan_loss,
    3: solutions.my_plan_loss_grad,
    4: solutions.my_plan_loss_fixed,
    5: solutions.my_riccati_step,
    6: solutions.my_kkt_backward,
}


def _phi(d2, var):
    return torch.exp(-d2 / (2 * var))


def _coll(
    pos, ctx, var, use_pred_mask=True, use_others_mask=True, mean_position=False, uniform=False
):
    probs = torch.full_like(ctx.probs, 1 / ctx.probs.shape[1]) if uniform else ctx.probs
    if mean_position:  # phi of the distance to the modes' mean: drops their spread
        mu = (probs[:, :, None, None] * ctx.preds).sum(1)
        expected = ((pos - mu[:, None]) ** 2).sum(-1)
    else:
        expected = (
            probs[:, None, :, None] * ((pos[:, :, None] - ctx.preds[:, None]) ** 2).sum(-1)
        ).sum(2)
    pm = ctx.pred_mask[:, None] if use_pred_mask else 1.0
    om = ctx.others_mask[:, None] if use_others_mask else torch.ones_like(ctx.others_mask)[:, None]
    return pm * _phi(expected, var).sum(-1) + (
        om * _phi(((pos[:, :, None] - ctx.others[:, None]) ** 2).sum(-1), var).sum(-1)
    ).sum(-1)


def _plan_loss(
    cost, valid, target, beta, use_beta=True, use_valid=True, stable=True, sign=1.0, shift=0
):
    b = beta if use_beta else 1.0
    logits = torch.where(valid, -b * cost, -math.inf) if use_valid else -b * cost
    target = (target + shift).clamp(0, cost.shape[-1] - 1)
    if stable:
        logp = logits - torch.logsumexp(logits, -1, keepdim=True)
    else:
        e = torch.exp(logits)
        logp = torch.log(e / e.sum(-1, keepdim=True))
    return -sign * logp.gather(-1, target[:, None])[:, 0]


def _riccati(mutation):
    def fn(P, p, H_t, g_t, A_t, B_t, n):
        k, K, P_new, p_new = solutions.my_riccati_step(P, p, H_t, g_t, A_t, B_t, n)
        F = torch.cat([A_t, B_t], -1)
        Q = H_t + F.transpose(-1, -2) @ P @ F
        if mutation == "P_new = Q_ss":
            P_new = Q[:, :n, :n]
        elif mutation == "P_new unchanged":
            P_new = P
        elif mutation == "K sign":
            K = -K
        elif mutation == "p_new without the Q_su k term":
            p_new = p_new - (Q[:, :n, n:] @ k[..., None])[..., 0]
        elif mutation == "Q without F'PF":
            return solutions.my_riccati_step(torch.zeros_like(P), p, H_t, g_t, A_t, B_t, n)
        return k, K, P_new, p_new

    return fn


def _plan_grad(mutation):
    def fn(cost, valid, target, beta):
        g = solutions.my_plan_loss_grad(cost, valid, target, beta)
        if mutation == "no beta":
            return g / beta
        if mutation == "sign":
            return -g
        if mutation == "softmax over invalid candidates too":
            p = torch.softmax(-beta * cost, -1)
            return beta * (torch.nn.functional.one_hot(target, cost.shape[-1]).to(cost.dtype) - p)
        if mutation == "one-hot only":
            return beta * torch.nn.functional.one_hot(target, cost.shape[-1]).to(cost.dtype)
        if mutation == "divided by B":
            return g / len(cost)
        return g

    return fn


def _kkt(mutation):
    """Exercise 6's answer with one plausible mistake (the rollout and the LQR call as a student
    would write them)."""
    import diffstack as ds

    def fn(A, B, H, grad_x, grad_u, free, n):
        gu = torch.cat([grad_u, torch.zeros_like(grad_u[:, :1])], 1)
        if mutation == "grad_u left out":
            gu = torch.zeros_like(gu)
        elif mutation == "grad_u a step late":
            gu = torch.cat([torch.zeros_like(grad_u[:, :1]), grad_u], 1)
        hold = torch.ones_like(free) if mutation == "the active set ignored" else free
        k, K, _, p0 = ds.lqr_backward(A, B, H, torch.cat([grad_x, gu], -1), free=hold)
        dx = [
            torch.ones_like(grad_x[:, 0])
            if mutation == "dx_0 = 1"
            else torch.zeros_like(grad_x[:, 0])
        ]
        du = []
        for t in range(A.shape[1]):
            Kt = (
                K[:, t].transpose(-1, -2).reshape(K[:, t].shape)
                if mutation == "K transposed"
                else K[:, t]
            )
            du.append(
                k[:, t]
                if mutation == "feed-forward only"
                else k[:, t] + (Kt @ dx[-1][..., None])[..., 0]
            )
            dx.append((A[:, t] @ dx[-1][..., None] + B[:, t] @ du[-1][..., None])[..., 0])
        if mutation == "states a step early":
            dx = dx[1:] + [dx[-1]]
        du.append(torch.zeros_like(du[0]))
        d = torch.cat([torch.stack(dx, 1), torch.stack(du, 1)], -1)
        if mutation == "p_0 sign":
            p0 = -p0
        if mutation == "d sign":
            d = -d
        if mutation == "dL/dx_init = dx_0":
            p0 = dx[0]
        return p0, d

    return fn


def _renormalised(cost, valid, target, beta):
    """A softmax over every candidate, renormalised over the valid ones: right in float64 on
    moderate costs, NaN in float32 when an invalid candidate is far cheaper."""
    p = torch.softmax(-beta * cost, -1) * valid
    return -torch.log((p / p.sum(-1, keepdim=True)).gather(-1, target[:, None])[:, 0])


def _notebook_buggy():
    """tutorial.py's buggy_plan_loss (exercise 4), as the student reads it."""
    tree = ast.parse((REPO / "tutorial.py").read_text())
    node = next(
        f for f in tree.body if isinstance(f, ast.FunctionDef) and f.name == "buggy_plan_loss"
    )
    space = {"torch": torch, "math": math}
    exec(compile(ast.Module([node], []), "tutorial.py", "exec"), space)
    return space["buggy_plan_loss"]


WRONG = {
    "1: pred_mask ignored": (1, lambda pos, ctx, v: _coll(pos, ctx, v, use_pred_mask=False)),
    "1: others_mask ignored": (1, lambda pos, ctx, v: _coll(pos, ctx, v, use_others_mask=False)),
    "1: phi of the distance to the modes' mean": (
        1,
        lambda pos, ctx, v: _coll(pos, ctx, v, mean_position=True),
    ),
    "1: probabilities ignored": (1, lambda pos, ctx, v: _coll(pos, ctx, v, uniform=True)),
    "1: rbf_var fixed at 2": (1, lambda pos, ctx, v: _coll(pos, ctx, 2.0)),
    "1: a mean over the steps": (1, lambda pos, ctx, v: _coll(pos, ctx, v) / pos.shape[2]),
    "2: beta ignored": (2, lambda c, v, t, b: _plan_loss(c, v, t, b, use_beta=False)),
    "2: valid mask ignored": (2, lambda c, v, t, b: _plan_loss(c, v, t, b, use_valid=False)),
    "2: unstable softmax": (2, lambda c, v, t, b: _plan_loss(c, v, t, b, stable=False)),
    "2: +log p instead of -log p": (2, lambda c, v, t, b: _plan_loss(c, v, t, b, sign=-1.0)),
    "2: no gradient (detached)": (2, lambda c, v, t, b: _plan_loss(c.detach(), v, t, b)),
    "2: the target off by one": (2, lambda c, v, t, b: _plan_loss(c, v, t, b, shift=1)),
    "2: a softmax over all candidates, renormalised": (2, lambda *a: _renormalised(*a)),
    "4: the notebook's buggy_plan_loss, unchanged": (4, lambda *a: _notebook_buggy()(*a)),
    "4: buggy_plan_loss computed in float64": (
        4,
        lambda c, v, t, b: _notebook_buggy()(c.double(), v, t, b).to(c.dtype),
    ),
    **{
        f"5: {m}": (5, _riccati(m))
        for m in (
            "P_new = Q_ss",
            "P_new unchanged",
            "K sign",
            "p_new without the Q_su k term",
            "Q without F'PF",
        )
    },
    **{
        f"3: {m}": (3, _plan_grad(m))
        for m in (
            "no beta",
            "sign",
            "softmax over invalid candidates too",
            "one-hot only",
            "divided by B",
        )
    },
    **{
        f"6: {m}": (6, _kkt(m))
        for m in (
            "grad_u left out",
            "grad_u a step late",
            "the active set ignored",
            "dx_0 = 1",
            "K transposed",
            "feed-forward only",
            "states a step early",
            "p_0 sign",
            "d sign",
            "dL/dx_init = dx_0",
        )
    },
}


@pytest.mark.parametrize("number", sorted(SOLUTIONS))
def test_solutions_pass_their_checks(number, capsys):
    assert course.exercise(number, course.CHECKS[number], SOLUTIONS[number])
    assert f"EXERCISE {number}: PASS" in capsys.readouterr().out


@pytest.mark.parametrize("name", sorted(WRONG))
def test_checks_catch_known_wrong_answers(name):
    number, wrong = WRONG[name]
    with pytest.raises(AssertionError):
        course.CHECKS[number](wrong)


DIAGNOSES = {
    "1: pred_mask ignored": "it ignores pred_mask",
    "1: others_mask ignored": "it ignores others_mask",
    "1: probabilities ignored": "Scored alone, the predicted vehicle's term",
    "1: a mean over the steps": "a mean over the T = 6 steps, where eq. (3) sums them",
    "2: +log p instead of -log p": "Yours is -1 times the reference: the sign is flipped",
    "2: the target off by one": "Yours is the loss of candidate n* +1",
    "2: a softmax over all candidates, renormalised": "in float32, an invalid candidate 200",
    "3: divided by B": "Yours is 0.125 times the reference: divided by B = 8",
    "3: no beta": "Yours is 3.333 times the reference: beta left out",
    "5: K sign": "K (feedback gain): max |yours - reference| = 3.56 (allowed 2e-08). Yours is -1",
    "6: p_0 sign": "dL/dx_init: max |yours - reference| = 4.62 (allowed 2e-09). Yours is -1 times "
    "the reference: p_0 with the wrong sign",
    "6: the active set ignored": "At the held controls yours is not 0",
    "6: feed-forward only": "It differs first at stage t = 1 (of 0..5), in its free controls.",
    "6: states a step early": "It differs first at stage t = 0 (of 0..5), in its state entries.",
}


@pytest.mark.parametrize("name", sorted(DIAGNOSES))
def test_a_failure_says_what_is_wrong(name):
    """The message names the term, the ratio or sign, the stage, the held or free entries: each
    known mistake gets its own diagnosis, not one fixed hint."""
    number, wrong = WRONG[name]
    with pytest.raises(AssertionError) as failed:
        course.CHECKS[number](wrong)
    assert DIAGNOSES[name] in str(failed.value), str(failed.value)


def test_a_right_answer_gets_no_diagnosis_it_does_not_deserve():
    """A right answer passes, and a wrong one with no simple relation to the reference gets no
    invented ratio."""
    with pytest.raises(AssertionError) as failed:
        course.CHECKS[3](WRONG["3: one-hot only"][1])
    assert "times the reference" not in str(failed.value)


def _in_float32(fn):
    """fn computed in float32: every floating input (a CostContext's fields too) cast down, the
    outputs as they come."""

    def down(a):
        if isinstance(a, torch.Tensor):
            return a.float() if a.is_floating_point() else a
        if dataclasses.is_dataclass(a):
            return type(a)(*(down(t) for t in a.tensors()))
        return a

    def wrapped(*args):
        return fn(*(down(a) for a in args))

    wrapped.__name__ = fn.__name__
    return wrapped


@pytest.mark.parametrize("number", sorted(SOLUTIONS))
def test_a_right_answer_in_float32_passes(number, capsys):
    """The checks judge the answer, not its float type: each solution computed in float32 passes
    (its rounding, magnified by the problem's conditioning, is allowed), while the wrong answers
    above fail in float64."""
    assert course.exercise(number, course.CHECKS[number], _in_float32(SOLUTIONS[number]))


@pytest.mark.parametrize("name", sorted(WRONG))
def test_known_wrong_answers_fail_in_float32_too(name):
    number, wrong = WRONG[name]
    with pytest.raises(AssertionError):
        course.CHECKS[number](_in_float32(wrong))


def test_a_wrong_shape_or_an_error_inside_the_answer_is_reported_as_such():
    def flat(pos, ctx, rbf_var):  # (B, N, 1) instead of (B, N)
        return solutions.my_collision(pos, ctx, rbf_var)[..., None]

    with pytest.raises(AssertionError, match=r"my_collision: shape \(6, 7, 1\), expected \(6, 7\)"):
        course.check_collision(flat)

    # sums the modes against the time axis: a RuntimeError inside it
    def broadcast_error(pos, ctx, rbf_var):
        return (pos[:, :, None] - ctx.preds[:, None].transpose(-2, -3)).sum()

    with pytest.raises(
        AssertionError,
        match=r"my_collision raised RuntimeError: .* \(its inputs: \(6, 7, 6, 2\), "
        r"CostContext, float; it should return C_coll of shape \(B, N\)\)",
    ):
        course.check_collision(broadcast_error)

    def three(P, p, H_t, g_t, A_t, B_t, n):
        return solutions.my_riccati_step(P, p, H_t, g_t, A_t, B_t, n)[:3]

    with pytest.raises(
        AssertionError, match=r"my_riccati_step: returned tuple of 3, expected the four"
    ):
        course.check_riccati(three)


def test_a_stub_is_reported_as_not_done(capsys):
    def my_collision(pos, ctx, rbf_var):
        raise NotImplementedError

    assert not course.exercise(1, course.check_collision, my_collision)
    assert "EXERCISE 1: not done yet" in capsys.readouterr().out


def test_the_student_notebook_holds_stubs_not_solutions():
    """Every exercise function in tutorial.py only raises NotImplementedError; solutions.py defines
    each of them."""
    tree = ast.parse((REPO / "tutorial.py").read_text())
    stubs = {
        f.name: f
        for f in ast.walk(tree)
        if isinstance(f, ast.FunctionDef) and f.name.startswith("my_")
    }
    assert set(stubs) == {f.__name__ for f in SOLUTIONS.values()}, sorted(stubs)
    for f in stubs.values():
        body = [
            s for s in f.body if not (isinstance(s, ast.Expr) and isinstance(s.value, ast.Constant))
        ]
        assert len(body) == 1 and isinstance(body[0], ast.Raise), (
            f"{f.name} in tutorial.py is not a stub"
        )
        assert "NotImplementedError" in ast.unparse(body[0])


def test_no_stored_output_shows_an_answer():
    """tutorial.ipynb's outputs hold neither the module's functions that answer exercises (shown
    only once an exercise passes) nor a check message that names exercise 4's fix."""
    import diffstack as ds

    nb = nbformat.read(REPO / "tutorial.ipynb", as_version=4)
    text = json.dumps([c.get("outputs", []) for c in nb.cells])
    for fn in (ds.collision_term, ds.plan_loss, ds.lqr_backward, ds.kkt_backward):
        assert f"def {fn.__name__}(" not in text, fn.__name__
    assert "EXERCISE 4: not done yet" in text and "logsumexp" not in text


def test_a_wrong_answer_cannot_stop_run_all(capsys):
    """Every call of a student's my_* function in tutorial.py is made by course.exercise (which
    prints FAIL and returns False), inside a try that catches Exception, or once it has passed."""
    tree = ast.parse((REPO / "tutorial.py").read_text())
    parent = {c: p for p in ast.walk(tree) for c in ast.iter_child_nodes(p)}
    for call in ast.walk(tree):
        if not (isinstance(call, ast.Call) and getattr(call.func, "id", "").startswith("my_")):
            continue
        node, safe = call, False
        while node in parent and not safe:
            node = parent[node]
            caught = isinstance(node, ast.Try) and any(
                ast.unparse(h.type) == "Exception" for h in node.handlers
            )
            safe = caught or (isinstance(node, ast.If) and ast.unparse(node.test) == "ex3_done")
        assert safe, f"line {call.lineno}: {ast.unparse(call)} can stop the notebook"
    assert not course.exercise(1, course.check_collision, lambda pos, ctx, v: pos[..., 0, 0])
    assert "EXERCISE 1: FAIL ✗ AssertionError: my_collision" in capsys.readouterr().out


# ---------------------------------------------------------------------------------------------
# The course as a student sees it: JupyterLab in a real (headless) browser, Run All, a slider.
# ---------------------------------------------------------------------------------------------

BROWSER_HOW = "apt-get install chromium chromium-driver; pip install selenium"
# the prompts of the code cells ('[12]:', '[*]:', '[ ]:') and the kernel's state
_LAB_STATE_JS = """
const cells = [...document.querySelectorAll('.jp-Notebook .jp-CodeCell')];
const status = document.querySelector('.jp-Notebook-ExecutionIndicator');
return {
  prompts: cells.map(c => (c.querySelector('.jp-InputPrompt') || {}).textContent || ''),
  status: status ? status.getAttribute('data-status') : null,
};
"""


def _browser_or_skip():
    """(webdriver module, chromium path, chromedriver path), or a one-line skip saying how to get
    them."""
    import shutil

    try:
        from selenium import webdriver
    except ImportError:
        pytest.skip(f"browser test: no selenium here ({BROWSER_HOW})")
    browser = next(
        filter(None, map(shutil.which, ("chromium", "chromium-browser", "google-chrome"))), None
    )
    driver = shutil.which("chromedriver")
    if browser is None or driver is None:
        found = (("chromium", browser), ("chromedriver", driver))
        missing = " and ".join(name for name, path in found if not path)
        pytest.skip(f"browser test: no {missing} here ({BROWSER_HOW})")
    return webdriver, browser, driver


def _free_port():
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _start_lab(folder, port, token, log):
    """`jupyter lab` on port, serving folder (the kernel's cwd; the repository on PYTHONPATH, quick
    mode, no solutions: the student's notebook), in its own process group; returns the Popen once
    the server answers."""
    import os
    import subprocess
    import sys
    import time
    import urllib.request

    settings = folder / ".lab-settings"
    quiet = {  # no news or update toast over the notebook
        "@jupyterlab/apputils-extension/notification.jupyterlab-settings": {
            "fetchNews": "false",
            "checkForUpdates": False,
            "doNotDisturbMode": True,
        },
    }
    for name, value in quiet.items():
        (settings / name).parent.mkdir(parents=True, exist_ok=True)
        (settings / name).write_text(json.dumps(value))
    env = dict(os.environ, DIFFSTACK_QUICK="1", PYTHONPATH=str(REPO))
    env.pop("DIFFSTACK_SOLUTIONS", None)
    env.update(
        JUPYTERLAB_SETTINGS_DIR=str(settings),
        JUPYTERLAB_WORKSPACES_DIR=str(folder / ".lab-workspaces"),
        JUPYTER_RUNTIME_DIR=str(folder / ".jupyter-runtime"),
    )
    server = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "jupyter",
            "lab",
            "--no-browser",
            "--ip=127.0.0.1",
            "--allow-root",  # CI runs as root
            "--LabApp.extension_manager=readonly",  # no look-up of extensions in a registry
            f"--port={port}",
            "--ServerApp.port_retries=0",
            f"--IdentityProvider.token={token}",
            f"--ServerApp.root_dir={folder}",
        ],
        cwd=folder,
        env=env,
        stdout=log,
        stderr=subprocess.STDOUT,
        start_new_session=True,  # its own process group: the kernel is ended with it
    )
    deadline = time.time() + 120
    while True:
        try:
            url = f"http://127.0.0.1:{port}/api/status?token={token}"
            with urllib.request.urlopen(url, timeout=5) as r:
                if r.status == 200:
                    return server
        except OSError:
            pass
        if server.poll() is not None or time.time() > deadline:
            _stop(server, port, token)
            raise AssertionError(f"jupyter lab did not start: {log.name}")
        time.sleep(0.5)


def _descendants(pid):
    """The ids of pid's children, their children, ... (from /proc: no extra package)."""
    import pathlib as pl

    children = {}
    for stat in pl.Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        children.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    found, todo = [], [pid]
    while todo:
        kids = children.get(todo.pop(), [])
        found += kids
        todo += kids
    return found


def _stop(server, port, token):
    """The server asked to shut down (it ends its kernels), then its process group and every
    process it started (a kernel runs in a session of its own) killed if still there."""
    import os
    import signal
    import subprocess
    import urllib.request

    started = _descendants(server.pid)
    try:
        url = f"http://127.0.0.1:{port}/api/shutdown?token={token}"
        urllib.request.urlopen(urllib.request.Request(url, method="POST"), timeout=10).close()
        server.wait(timeout=30)
    except (OSError, subprocess.TimeoutExpired):
        pass
    for pid in started:
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    try:
        os.killpg(server.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    server.wait()


def _full_page_screenshot(driver, path):
    """The whole notebook in one image: the lab scrolls the notebook inside a panel as high as the
    window, so the window is made as high as the notebook (scrolled to its top), then restored.
    Cells drawn for the first time measure taller than estimated: made higher until all fit."""
    import base64

    from selenium.webdriver.support.ui import WebDriverWait

    height_js = (
        "const o = document.querySelector('.jp-Notebook .jp-WindowedPanel-outer');"
        "const i = document.querySelector('.jp-Notebook .jp-WindowedPanel-inner');"
        "o.scrollTop = 0;"  # the cells' height, and the lab's bars above and below
        "return [i.offsetHeight + window.innerHeight - o.clientHeight + 20, window.innerHeight];"
    )
    try:
        for _ in range(6):
            height, now = driver.execute_script(height_js)
            if height <= now or now >= 60000:
                break
            height = min(height, 60000)
            metrics = {"width": 1400, "height": height, "deviceScaleFactor": 1, "mobile": False}
            driver.execute_cdp_cmd("Emulation.setDeviceMetricsOverride", metrics)
            WebDriverWait(driver, 30, poll_frequency=0.2).until(  # the lab laid out anew
                lambda d, h=height: d.execute_script(height_js)[1] == h
            )
            driver.execute_async_script(  # two frames drawn: the cells brought into view painted
                "const done = arguments[arguments.length - 1];"
                "requestAnimationFrame(() => requestAnimationFrame(() => setTimeout(done, 500)));"
            )
        path.parent.mkdir(parents=True, exist_ok=True)
        shot = driver.execute_cdp_cmd("Page.captureScreenshot", {"format": "png"})
        path.write_bytes(base64.b64decode(shot["data"]))
    finally:
        driver.execute_cdp_cmd("Emulation.clearDeviceMetricsOverride", {})


def _menu(driver, top, label):
    """Click the menu bar's `top`, then its item `label`."""
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import WebDriverWait

    bar = driver.find_elements(By.CSS_SELECTOR, ".lm-MenuBar-item")
    next(e for e in bar if e.text.strip() == top).click()
    path = "//li[contains(@class, 'lm-Menu-item')][.//div[contains(@class, 'lm-Menu-itemLabel')]"
    WebDriverWait(driver, 30, poll_frequency=0.2).until(
        lambda d: d.find_element(By.XPATH, f"{path}[normalize-space()='{label}']]"),
        f"no item {label!r} in the menu {top!r}",
    ).click()


_FIND_CELL_JS = """
return [...document.querySelectorAll('.jp-Notebook .jp-CodeCell')].find(
  c => (c.querySelector('.jp-InputArea-editor') || {}).textContent.includes(arguments[0]));
"""
# the outputs that show an error (a traceback), whatever renders them, named by their cell
_ERRORS_JS = """
return [...document.querySelectorAll('.jp-Notebook .jp-CodeCell')].flatMap((c, i) =>
  [...c.querySelectorAll('.jp-OutputArea-output')]
    .filter(o => o.getAttribute('data-mime-type') === 'application/vnd.jupyter.error'
                 || o.textContent.includes('Traceback (most recent call last)'))
    .map(o => `code cell ${i} ${c.querySelector('.jp-InputPrompt').textContent}\n`
              + o.textContent.slice(-400)));
"""


@pytest.mark.slow
def test_the_course_in_jupyterlab_in_a_browser(tmp_path):
    """The course as a student sees it: tutorial.ipynb opened in JupyterLab in headless Chromium
    (quick mode, the exercises' stubs), Run > Run All Cells; every code cell runs, none shows a
    traceback, and a slider of the interactive cell (§4, course.interactive_planner) redraws its
    figure. A screenshot of the whole page goes to $DIFFSTACK_SCREENSHOT (default: tmp_path), the
    interactive cell's beside it (*_slider.png); $DIFFSTACK_NOTEBOOK opens another notebook (a
    student's) in place of the repository's. 55-85 s on 2 shared cores; run it alone
    with `python -m pytest -q test_tutorial.py -k browser`."""
    import os
    import re
    import secrets
    import shutil

    webdriver, browser, chromedriver = _browser_or_skip()
    from selenium.common.exceptions import StaleElementReferenceException
    from selenium.webdriver.chrome.service import Service
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys
    from selenium.webdriver.support.ui import WebDriverWait

    def until(seconds, condition, message):  # an element redrawn meanwhile: look again
        wait = WebDriverWait(
            driver, seconds, poll_frequency=0.5, ignored_exceptions=[StaleElementReferenceException]
        )
        return wait.until(condition, message)

    run_timeout = float(os.environ.get("DIFFSTACK_BROWSER_TIMEOUT", 1200))  # Run All, under load
    shot = pathlib.Path(os.environ.get("DIFFSTACK_SCREENSHOT") or tmp_path / "tutorial_lab.png")
    folder = tmp_path / "course"  # what the lab serves: the notebook and the tables it reads
    (folder / "results").mkdir(parents=True)
    notebook = pathlib.Path(os.environ.get("DIFFSTACK_NOTEBOOK") or REPO / "tutorial.ipynb")
    shutil.copy(notebook, folder / "tutorial.ipynb")
    for f in (REPO / "results").iterdir():
        if f.is_file():
            shutil.copy(f, folder / "results")
    stored = nbformat.read(folder / "tutorial.ipynb", as_version=4)
    n_code = sum(c.cell_type == "code" for c in stored.cells)
    port, token = _free_port(), secrets.token_hex(16)
    with open(tmp_path / "lab.log", "w") as log:
        server = _start_lab(folder, port, token, log)
        driver, passed = None, False
        try:
            options = webdriver.ChromeOptions()
            options.binary_location = browser
            for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage"):
                options.add_argument(arg)  # no sandbox: CI runs as root
            options.add_argument("--window-size=1400,1000")
            service = Service(chromedriver, log_output=str(tmp_path / "chromedriver.log"))
            driver = webdriver.Chrome(options=options, service=service)
            driver.get(f"http://127.0.0.1:{port}/lab/tree/tutorial.ipynb?reset&token={token}")

            def state():
                return driver.execute_script(_LAB_STATE_JS)

            def loaded(_):
                s = state()
                return len(s["prompts"]) == n_code and s["status"] == "idle"

            WebDriverWait(driver, 300, poll_frequency=0.5).until(
                loaded, "the notebook did not open with an idle kernel in 5 minutes"
            )
            # Edit > Clear Outputs of All Cells (the stored ones would pass for this run's), then
            # Run > Run All Cells, as a student does it
            _menu(driver, "Edit", "Clear Outputs of All Cells")
            WebDriverWait(driver, 60, poll_frequency=0.5).until(
                lambda _: not any(re.fullmatch(r"\[\d+\]:", p) for p in state()["prompts"]),
                "Clear Outputs of All Cells left a cell's execution count",
            )
            _menu(driver, "Run", "Run All Cells")

            def finished(_):  # the kernel idle, the first cell run, none queued or running
                s = state()
                ran = re.fullmatch(r"\[\d+\]:", s["prompts"][0])
                return s["status"] == "idle" and ran and "[*]:" not in s["prompts"]

            WebDriverWait(driver, run_timeout, poll_frequency=2).until(
                finished, f"Run All did not finish in {run_timeout:.0f} s"
            )
            prompts = state()["prompts"]
            not_run = [i for i, p in enumerate(prompts) if not re.fullmatch(r"\[\d+\]:", p)]
            errors = driver.execute_script(_ERRORS_JS)
            assert not errors, f"{len(errors)} output(s) show a traceback; the first, {errors[0]}"
            assert not not_run, f"Run All stopped: code cells {not_run} did not run"

            # the interactive cell: its first slider moved one step, its figure redrawn
            cell = driver.execute_script(_FIND_CELL_JS, "course.interactive_planner(")
            assert cell is not None, "no code cell calls course.interactive_planner"
            driver.execute_script("arguments[0].scrollIntoView({block: 'center'})", cell)
            handles = cell.find_elements(By.CSS_SELECTOR, ".widget-slider .noUi-handle")
            assert handles, (
                "the interactive cell shows no slider: course.interactive_planner's widget is "
                "not displayed in JupyterLab (ipywidgets)"
            )

            def figure():
                imgs = cell.find_elements(By.CSS_SELECTOR, ".widget-interact img")
                return imgs[-1].get_attribute("src") if imgs else None

            before = until(120, lambda _: figure(), "the interactive cell shows no figure")
            readout = cell.find_elements(By.CSS_SELECTOR, ".widget-slider .widget-readout")[0]
            value = readout.text
            handles[0].send_keys(Keys.ARROW_RIGHT)  # the focused handle moves one step
            until(30, lambda _: readout.text != value, f"the slider did not move (still {value})")
            until(
                300,
                lambda _: figure() not in (None, before),
                f"the figure did not change when the slider moved from {value} to {readout.text}",
            )
            widget = cell.find_element(By.CSS_SELECTOR, ".widget-interact")
            driver.execute_script("arguments[0].scrollIntoView({block: 'center'})", widget)
            widget.screenshot(str(shot.with_name(shot.stem + "_slider.png")))
            passed = True
        finally:
            try:
                if driver is not None:
                    try:
                        _full_page_screenshot(driver, shot)
                        print(f"screenshot: {shot}")
                    except Exception as e:  # a failed test's own error is the one to show
                        if passed:
                            raise
                        print(f"no screenshot: {e!r}")
                    finally:
                        driver.quit()
            finally:
                _stop(server, port, token)
