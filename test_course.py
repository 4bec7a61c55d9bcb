"""Tests of course.py's helpers: exercise 3's check refuses autograd however it is reached, the
gradient-check helper catches a wrong gradient, the interactive planner computes what it draws.
(The exercises' checks on right and wrong answers: test_tutorial.py; the grader: test_grader.py.)"""

import math
import sys

import pytest
import torch

import course


def test_exercise_3_refuses_autograd_however_it_is_reached():
    import solutions

    def via_grad(cost, valid, target, beta):
        c = cost.clone().requires_grad_()
        with torch.enable_grad():
            return torch.autograd.grad(solutions.my_plan_loss(c, valid, target, beta).sum(), c)[0]

    from torch.autograd import grad as imported_grad

    def via_imported_name(cost, valid, target, beta):
        c = cost.clone().requires_grad_()
        with torch.enable_grad():
            return imported_grad(solutions.my_plan_loss(c, valid, target, beta).sum(), c)[0]

    def via_func(cost, valid, target, beta):
        def loss(c):
            return solutions.my_plan_loss(c, valid, target, beta).sum()

        return torch.func.grad(loss)(cost)

    with pytest.raises(course.Forbidden, match=r"used autograd \(torch.autograd.grad\)"):
        course.check_plan_grad(via_grad)
    with pytest.raises(course.Forbidden, match="recorded a graph for autograd"):
        course.check_plan_grad(via_imported_name)
    with pytest.raises(course.Forbidden, match=r"used autograd \(torch.func.grad\)"):
        course.check_plan_grad(via_func)
    assert torch.autograd.grad is not None and torch.Tensor.backward.__name__ == "backward"
    assert course.check_plan_grad(solutions.my_plan_loss_grad).startswith("against autograd")


def test_the_gradient_check_helper_catches_a_wrong_gradient():
    x = torch.tensor([[0.3, -1.2], [2.0, 0.5]], dtype=torch.float64)

    def f(v):
        return (v**3).sum() + v[0, 1] * v[1, 0]

    right = 3 * x**2 + torch.tensor([[0.0, 2.0], [-1.2, 0.0]], dtype=torch.float64)
    said = []
    assert course.grad_check(f, x, right, out=said.append) < 1e-8
    assert said[0].startswith("gradient check: largest relative error")
    assert course.grad_check(f, x, 2 * x**2, out=said.append) > 1e-2  # a wrong derivative
    assert course.grad_check(f, x, right.T, out=said.append) > 1e-2  # transposed
    assert torch.equal(x, torch.tensor([[0.3, -1.2], [2.0, 0.5]], dtype=torch.float64))


def test_the_interactive_planner_computes_what_it_draws(monkeypatch):
    """planner_view: p_n a softmax over the valid candidates, the plan their argmin, and
    dL_plan/dŝ equal to central differences of L_plan in the prediction's shift (float64); without
    ipywidgets the cell draws its static figure and returns None."""
    import data_synth
    import diffstack as ds

    data = data_synth.make_dataset(200, seed=0)
    cfg = ds.Config()
    ex = data.val[torch.tensor([course.first_of(data.val, "cut_in")])].to(torch.float64)
    for shift, beta in (((0.0, 0.0), 1.0), ((1.0, -1.5), 3.0)):
        v = course.planner_view(ex, cfg, shift, beta)
        valid = v["cands"].valid[0]
        assert abs(v["p"].sum().item() - 1) < 1e-12 and (v["p"][~valid] == 0).all()
        assert v["plan"] == int(torch.where(valid, v["cost"], math.inf).argmin())
        assert abs(v["l_plan"] + math.log(v["p"][v["target"]])) < 1e-9
        for axis in (0, 1):
            h = 1e-4
            up, down = (
                course.planner_view(
                    ex, cfg, tuple(s + d * h * (j == axis) for j, s in enumerate(shift)), beta
                )["l_plan"]
                for d in (1, -1)
            )
            fd = (up - down) / (2 * h)
            assert abs(fd - v["grad"][:, axis].sum().item()) <= 1e-6 * max(1.0, abs(fd))
    import matplotlib

    matplotlib.use("Agg")
    monkeypatch.setitem(sys.modules, "ipywidgets", None)  # import ipywidgets fails
    assert course.interactive_planner(ex, cfg, [((0.0, 0.0), 1.0)]) is None


def test_the_module_answer_is_shown_only_once_the_exercise_passes(monkeypatch, capsys):
    """course.exercise shows `reveal`'s source after a PASS, never for a stub or a wrong answer;
    exercise 4's message on the notebook's buggy loss says what is wrong, not the fix."""
    import diffstack as ds
    import solutions

    shown = []
    monkeypatch.setattr(course, "display", shown.append)

    def stub(*args):
        raise NotImplementedError

    assert not course.exercise(2, course.check_plan_loss, stub, reveal=ds.plan_loss)
    assert not course.exercise(2, course.check_plan_loss, lambda c, v, t, b: -c[:, 0], ds.plan_loss)
    assert "EXERCISE 2: FAIL ✗ AssertionError: my_plan_loss" in capsys.readouterr().out
    assert shown == []
    assert course.exercise(2, course.check_plan_loss, solutions.my_plan_loss, ds.plan_loss)
    assert len(shown) == 1 and "def plan_loss(" in shown[0].data

    def buggy(cost, valid, target, beta):  # tutorial.py's buggy_plan_loss
        p = torch.softmax(-beta * cost, -1)
        p = p * valid / (p * valid).sum(-1, keepdim=True)
        return -torch.log(p.gather(-1, target[:, None])[:, 0])

    course.show_failure(course.check_plan_loss_fixed, buggy)
    said = capsys.readouterr().out.split("the check says:")[-1]
    assert "float32" in said and "inf or NaN" in said
    assert not any(w in said for w in ("logsumexp", "-inf", "underflow", "renormalis", "Leave"))
