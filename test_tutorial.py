"""Tests of the course: tutorial.py (jupytext percent format) is the notebook's source, tutorial.ipynb is made from
it, and the notebook runs top to bottom."""
import ast
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
    """tutorial.ipynb holds exactly the cells of tutorial.py (regenerate: jupytext --update --to ipynb tutorial.py)."""
    source = jupytext.read(REPO / "tutorial.py")
    notebook = nbformat.read(REPO / "tutorial.ipynb", as_version=4)
    assert cell_sources(source) == cell_sources(notebook)


def test_the_comparison_catches_a_changed_cell():
    source = jupytext.read(REPO / "tutorial.py")
    changed = jupytext.read(REPO / "tutorial.py")
    changed.cells[3].source += "\nprint('drift')"
    assert cell_sources(source) != cell_sources(changed)


def test_tutorial_notebook_runs_in_quick_mode(monkeypatch):
    """The student notebook (tutorial.py) with solutions.py injected executes top to bottom from a fresh kernel in
    quick mode (cwd = the repository) with no error, every exercise check passes, and every checkpoint it prints
    agrees with its expected value. About 2 minutes on 2 shared cores."""
    nb = jupytext.read(REPO / "tutorial.py")
    monkeypatch.setenv("DIFFSTACK_QUICK", "1")  # the notebook's parameters cell reads it; the kernel inherits it
    monkeypatch.setenv("DIFFSTACK_SOLUTIONS", "1")  # the exercises use solutions.py's answers
    client = nbclient.NotebookClient(nb, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(REPO)}})
    client.execute()  # raises CellExecutionError (naming the cell) on the first error
    text = "".join(o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.outputs)
    assert "QUICK = True" in text and "solutions.py injected" in text
    for number in SOLUTIONS:
        assert f"EXERCISE {number}: PASS" in text, f"exercise {number} did not pass in the notebook"
    checks = [line for line in text.splitlines() if line.startswith(("CHECKPOINT", "CHECK ", "CLAIM "))]
    assert len(checks) >= 14, checks
    assert all(line.endswith("OK") for line in checks), checks  # (a failed one raises: the cell errors first)


def tutorial_checks():
    """The notebook's check functions (checkpoint, check_order, check_claim): course.py's, which tutorial.py imports."""
    tree = ast.parse((REPO / "tutorial.py").read_text())
    imported = {a.name for node in tree.body if isinstance(node, ast.ImportFrom) and node.module == "course"
                for a in node.names}
    assert {"checkpoint", "check_order", "check_claim"} <= imported, sorted(imported)
    return {name: getattr(course, name) for name in ("CheckpointError", "checkpoint", "check_order", "check_claim")}


def test_the_notebook_checks_stop_on_a_wrong_value(tmp_path, monkeypatch, capsys):
    """A checkpoint off its value, an ordering the other way round, a claim whose verdict the text gets wrong: each
    raises (the notebook stops at that cell), each right one passes."""
    t = tutorial_checks()
    t["checkpoint"]("x", 1.0, 1.0, 1e-9)
    with pytest.raises(t["CheckpointError"], match="measured 1.1"):
        t["checkpoint"]("x", 1.1, 1.0, 0.05)
    t["check_order"]("o", {"GT": -2.0, "none": 0.0}, ["GT", "none"])
    with pytest.raises(t["CheckpointError"], match="GT -2 is not below none -2.5"):
        t["check_order"]("o", {"GT": -2.0, "none": -2.5}, ["GT", "none"])
    with pytest.raises(t["CheckpointError"], match="margin 0.1"):
        t["check_order"]("o", {"a": 1.0, "b": 1.05}, ["a", "b"], margin=0.1)
    runs = lambda *v: [{"rel_mse": x, "ade": 1.0, "nll": 1.0, "converged": 1.0, "rel_plan_loss": 0.0} for x in v]  # noqa: E731
    (tmp_path / "results").mkdir()
    (tmp_path / "results" / "il.json").write_text(json.dumps(dict(results=dict(
        Standard=runs(1.0, 2.0, 3.0), DiffStack=runs(0.0, 1.1, 1.9)))))
    monkeypatch.chdir(tmp_path)
    t["check_claim"]("il", "DiffStack", "Standard", "MSE (x1e-2)", "reproduced")
    with pytest.raises(t["CheckpointError"], match="update the text"):
        t["check_claim"]("il", "DiffStack", "Standard", "MSE (x1e-2)", "not reproduced")


# --- the exercises: solutions pass their checks, known-wrong answers fail them ----------------------------------

SOLUTIONS = {1: solutions.my_collision, 2: solutions.my_plan_loss, 3: solutions.my_riccati_step,
             4: solutions.my_plan_loss_grad}


def _phi(d2, var):
    return torch.exp(-d2 / (2 * var))


def _coll(pos, ctx, var, use_pred_mask=True, use_others_mask=True, mean_position=False, uniform=False):
    probs = torch.full_like(ctx.probs, 1 / ctx.probs.shape[1]) if uniform else ctx.probs
    if mean_position:  # phi of the distance to the modes' mean: drops their spread
        mu = (probs[:, :, None, None] * ctx.preds).sum(1)
        expected = ((pos - mu[:, None]) ** 2).sum(-1)
    else:
        expected = (probs[:, None, :, None] * ((pos[:, :, None] - ctx.preds[:, None]) ** 2).sum(-1)).sum(2)
    pm = ctx.pred_mask[:, None] if use_pred_mask else 1.0
    om = ctx.others_mask[:, None] if use_others_mask else torch.ones_like(ctx.others_mask)[:, None]
    return pm * _phi(expected, var).sum(-1) + (om * _phi(((pos[:, :, None] - ctx.others[:, None]) ** 2).sum(-1), var).sum(-1)).sum(-1)


def _plan_loss(cost, valid, target, beta, use_beta=True, use_valid=True, stable=True, sign=1.0):
    b = beta if use_beta else 1.0
    logits = torch.where(valid, -b * cost, -math.inf) if use_valid else -b * cost
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
        return g
    return fn


WRONG = {
    "1: pred_mask ignored": (1, lambda pos, ctx, v: _coll(pos, ctx, v, use_pred_mask=False)),
    "1: others_mask ignored": (1, lambda pos, ctx, v: _coll(pos, ctx, v, use_others_mask=False)),
    "1: phi of the distance to the modes' mean": (1, lambda pos, ctx, v: _coll(pos, ctx, v, mean_position=True)),
    "1: probabilities ignored": (1, lambda pos, ctx, v: _coll(pos, ctx, v, uniform=True)),
    "1: rbf_var fixed at 2": (1, lambda pos, ctx, v: _coll(pos, ctx, 2.0)),
    "2: beta ignored": (2, lambda c, v, t, b: _plan_loss(c, v, t, b, use_beta=False)),
    "2: valid mask ignored": (2, lambda c, v, t, b: _plan_loss(c, v, t, b, use_valid=False)),
    "2: unstable softmax": (2, lambda c, v, t, b: _plan_loss(c, v, t, b, stable=False)),
    "2: +log p instead of -log p": (2, lambda c, v, t, b: _plan_loss(c, v, t, b, sign=-1.0)),
    "2: no gradient (detached)": (2, lambda c, v, t, b: _plan_loss(c.detach(), v, t, b)),
    **{f"3: {m}": (3, _riccati(m)) for m in ("P_new = Q_ss", "P_new unchanged", "K sign",
                                             "p_new without the Q_su k term", "Q without F'PF")},
    **{f"4: {m}": (4, _plan_grad(m)) for m in ("no beta", "sign", "softmax over invalid candidates too", "one-hot only")},
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


def test_a_stub_is_reported_as_not_done(capsys):
    def my_collision(pos, ctx, rbf_var):
        raise NotImplementedError
    assert not course.exercise(1, course.check_collision, my_collision)
    assert "EXERCISE 1: not done yet" in capsys.readouterr().out


def test_the_student_notebook_holds_stubs_not_solutions():
    """Every exercise function in tutorial.py only raises NotImplementedError; solutions.py defines each of them."""
    tree = ast.parse((REPO / "tutorial.py").read_text())
    stubs = {f.name: f for f in ast.walk(tree) if isinstance(f, ast.FunctionDef) and f.name.startswith("my_")}
    assert set(stubs) == {f.__name__ for f in SOLUTIONS.values()}, sorted(stubs)
    for f in stubs.values():
        body = [s for s in f.body if not (isinstance(s, ast.Expr) and isinstance(s.value, ast.Constant))]
        assert len(body) == 1 and isinstance(body[0], ast.Raise), f"{f.name} in tutorial.py is not a stub"
        assert "NotImplementedError" in ast.unparse(body[0])
