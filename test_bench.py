"""Tests of lab/bench.py: the quick run and its JSON file, the command line's errors, a missing
peer's hint, the bounded LQR's problems, reference and gradients (mpc.pytorch's parts skipped where
it is not installed).

    python -m pytest -q test_bench.py        # about half a minute on 2 cores

No test asserts a timing: they check that the figures exist, are positive and are written
where promised.
"""

import importlib.util
import json
import math
import sys

import pytest
import torch

import diffstack
from lab import bench

HINT = "pip install --no-deps mpc==0.0.6"


def installed(name):
    return importlib.util.find_spec(name) is not None


@pytest.mark.slow
def test_quick_run_writes_json(tmp_path, capsys):
    path = tmp_path / "b.json"
    threads_before = torch.get_num_threads()
    doc = bench.main(["--quick", "--threads", "1", "--json", str(path), "--skip-closed-loop"])
    out = capsys.readouterr().out
    assert torch.get_num_threads() == threads_before  # main() leaves the process as it found it
    on_disk = json.loads(path.read_text())
    assert on_disk["figures"] == json.loads(json.dumps(doc["figures"]))
    # the temporary file was renamed away
    assert not [p for p in tmp_path.iterdir() if p.name != "b.json"]
    # the headline keys
    step = on_disk["stack_step_ms_1thread"]
    assert isinstance(step, float) and math.isfinite(step) and step > 0
    # a slope: noise at --quick sizes may make it < 0
    assert isinstance(on_disk["controller_ms_per_problem"], float)
    assert {"ilqr_forward_f64_B%d" % (bench.QUICK["batch"] * k) for k in (1, 2)} <= {
        f["key"] for f in on_disk["figures"]
    }
    assert "speedup_vs_mpc_pytorch" in on_disk
    if installed("mpc"):
        assert (
            isinstance(on_disk["speedup_vs_mpc_pytorch"], float)
            and on_disk["speedup_vs_mpc_pytorch"] > 0
        )
    else:
        assert on_disk["speedup_vs_mpc_pytorch"] is None and on_disk["mpc_pytorch"] is None
        assert out.count(HINT) == 1
    # every figure: positive, at the one thread asked for, nothing from the skipped closed loop
    keys = {f["key"] for f in on_disk["figures"]}
    assert {
        "ilqr_forward_f64",
        "kkt_backward_f64",
        "ilqr_forward_f32",
        "kkt_backward_f32",
        "candidates",
        "predictor_train",
        "predictor_eval",
        "stack_step",
        "stack_scene_plan",
        "stack_predict",
        "stack_plan",
        "stack_control",
        "stack_backward",
    } <= keys
    assert not any(k.startswith("closed_loop") for k in keys)
    for f in on_disk["figures"]:
        assert f["threads"] == 1 and f["runs"] >= 1 and f["median_ms"] > 0 and f["iqr_ms"] >= 0, f
    assert [f["median_ms"] for f in on_disk["figures"] if f["key"] == "stack_step"] == [step]
    assert on_disk["meta"]["batch"] == bench.QUICK["batch"] and on_disk["meta"]["threads"] == [1]
    assert on_disk["meta"]["device"] == "cpu"
    # one markdown table of our figures, one row per figure
    assert sum(line.startswith("| benchmark |") for line in out.splitlines()) == 1
    assert (
        sum(line.startswith("| ") and "perf_counter lap" in line for line in out.splitlines()) == 4
    )
    assert "Traceback" not in out
    # the bounded LQR, at --batch with its iterations capped: no bound active at umax 1e4, where
    # every solver converges in one LQR step (and a second to see the step vanish)
    table = on_disk["bounded_lqr"]["table"]
    assert {(t["umax"], t["solver"]) for t in table} >= {
        (u, f"diffstack, {k}") for u in bench.LQR_UMAX for k in bench.LQR_SETTINGS
    }
    for t in table:
        assert t["batch"] == bench.QUICK["batch"] and t["us_per_problem_stage"] > 0
        if t["umax"] == 1e4:
            assert t["converged"] == t["batch"] and t["iterations_max"] == 2
    assert {f"lqr_diffstack_tight_umax{u:g}_fwd_bwd" for u in bench.LQR_UMAX} <= keys


@pytest.mark.slow
def test_bounded_lqr_alone_writes_its_json(tmp_path, capsys):
    path = tmp_path / "lqr.json"
    doc = bench.main(["--bounded-lqr", "--quick", "--json", str(path)])
    out = capsys.readouterr().out
    assert json.loads(path.read_text())["bounded_lqr"] == json.loads(json.dumps(doc["bounded_lqr"]))
    assert set(doc) == {"bounded_lqr", "figures", "meta"}
    assert "Published (i7-8665U laptop, up to 4 threads; not measured here)" in out
    if not installed("mpc"):
        assert out.count(HINT) == 1 and doc["bounded_lqr"]["gradient_vs_mpc"] == {}


@pytest.mark.parametrize(
    "args, name",
    [
        (["--batch", "0"], "--batch"),
        (["--batch", "-3"], "--batch"),
        (["--threads", "0"], "--threads"),
        (["--threads", "1", "-2"], "--threads"),
        (["--reps", "-1"], "--reps"),
        (["--reps", "0"], "--reps"),
        (["--reps", "two"], "--reps"),
        (["--device", "gpu"], "--device"),
    ],
)
def test_bad_arguments_exit_2_naming_the_argument(args, name, capsys):
    with pytest.raises(SystemExit) as e:
        bench.main(["--quick", "--skip-closed-loop", *args])
    assert e.value.code == 2
    err = capsys.readouterr().err
    last = err.strip().splitlines()[-1]
    assert f"argument {name}" in last and "Traceback" not in err


def test_a_json_path_no_file_can_take_is_refused_before_any_work(tmp_path, monkeypatch, capsys):
    (tmp_path / "afile").write_text("")
    monkeypatch.setattr(bench, "run", lambda *a, **k: pytest.fail("work started"))
    for path in (tmp_path / "afile" / "b.json", tmp_path):  # under a file; a folder
        with pytest.raises(SystemExit) as e:
            bench.main(["--quick", "--json", str(path)])
        assert e.value.code == 2
        last = capsys.readouterr().err.strip().splitlines()[-1]
        assert "argument --json" in last and str(tmp_path) in last  # naming the folder or the path


def test_a_gpu_this_machine_lacks_is_refused_before_any_work(monkeypatch, capsys):
    # the same on a machine with a GPU
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(bench, "run", lambda *a, **k: pytest.fail("work started"))
    with pytest.raises(SystemExit) as e:
        bench.main(["--quick", "--device", "cuda"])
    assert e.value.code == 2
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert "argument --device" in last and "no CUDA device here" in last


def test_mps_is_refused_before_any_work(monkeypatch, capsys):
    # as on a Mac: there, it has no float64
    monkeypatch.setattr(torch.backends.mps, "is_available", lambda: True)
    monkeypatch.setattr(bench, "run", lambda *a, **k: pytest.fail("work started"))
    with pytest.raises(SystemExit) as e:
        bench.main(["--quick", "--device", "mps"])
    assert e.value.code == 2 and "argument --device: mps has no float64" in capsys.readouterr().err


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_quick_run_on_cuda(tmp_path, capsys):
    doc = bench.main(
        ["--quick", "--threads", "1", "--device", "cuda", "--json", str(tmp_path / "b.json")]
    )
    out = capsys.readouterr().out
    assert (
        doc["meta"]["device"] == "cuda"
        and torch.cuda.get_device_name() in doc["meta"]["device_name"]
    )
    keys = {f["key"] for f in doc["figures"]}
    assert {
        "ilqr_forward_f64",
        "kkt_backward_f64",
        "stack_step",
        "predictor_train",
        "candidates",
    } <= keys
    assert all(f["median_ms"] > 0 for f in doc["figures"])
    # the peers and the closed loop, compared on the CPU, are left out, saying so
    assert doc["speedup_vs_mpc_pytorch"] is None
    assert not any(k.startswith("closed_loop") for k in keys) and "are left out" in out


def test_missing_peer_prints_one_line_hint(monkeypatch, capsys):
    # None in sys.modules makes `import mpc` raise ImportError, installed or not
    monkeypatch.setitem(sys.modules, "mpc", None)
    monkeypatch.setitem(sys.modules, "mpc.mpc", None)
    assert bench.compare_mpc(B=4, threads=(1,), reps=1) is None
    captured = capsys.readouterr()
    lines = captured.out.strip().splitlines()
    assert len(lines) == 1 and HINT in lines[0] and "/tmp/peers/bin/python -m lab.bench" in lines[0]
    assert "Traceback" not in captured.out + captured.err


@pytest.mark.parametrize("peer", ["ours", "mpc"])
def test_the_timed_solves_give_finite_gradients(peer):
    # at the timed settings each solve gives a gradient to x_init and the reference
    if peer == "mpc" and not installed("mpc"):
        pytest.skip("mpc is not installed (a peer, never a dependency)")
    P = bench.tracking_problem(8)
    x_init, x_ref = P["x_init"].clone().requires_grad_(), P["x_ref"].clone().requires_grad_()
    x, u = (bench.ours_solve if peer == "ours" else bench.mpc_solve)(P, x_init, x_ref, 5, 0.01)
    assert x.shape == (8, 7, 4) and u.shape == (8, 6, 2)
    x[:, -1, :2].sum().backward()
    assert torch.isfinite(x_init.grad).all() and torch.isfinite(x_ref.grad).all()
    assert x_ref.grad.abs().sum() > 0


def test_tracking_problem_is_reproducible():
    a, b, c = (
        bench.tracking_problem(8, seed=3),
        bench.tracking_problem(8, seed=3),
        bench.tracking_problem(8, seed=4),
    )
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert not torch.equal(a["x_init"], c["x_init"])
    # the reference is a rollout of its controls, and costs nothing to track
    assert a["x_ref"].shape == (8, 7, 4) and a["u_ref"].shape == (8, 6, 2)
    zero = bench.TrackingCost()(a["x_ref"], a["u_ref"], a["x_ref"], a["u_ref"], a["Q"], a["R"])
    assert torch.equal(zero, torch.zeros(8, dtype=torch.float64))


# ---- the bounded LQR of differentiable_nmpc ----------------------------------------------------


def lqr_subset(umax, rows, horizon=bench.LQR_N):
    """The benchmark's problems `rows` at umax (the same system, their own x0)."""
    P = bench.bounded_lqr_problem(umax, horizon=horizon)
    P["x_init"], P["u_init"] = P["x_init"][rows], P["u_init"][rows]
    return P


def reference_first_controls(P):
    """sum of u_0 over the problems, from the reference solver (scipy's bvls, the true solution
    map, active set and all): independent of ours."""
    M, q = bench.condensed_qp(P)
    return bench.reference_controls(M, q, P["lo"], P["hi"])[:, 0].sum()


TIGHT = dict(iters=100, tol=1e-9)
ACTIVE_ROWS = [4, 12, 19, 21]  # at umax 1: 5, 5, 29 and 25 bounds active, and our solver converges


def assert_directional_gradients(P, args, rel_step, first_controls):
    """args' .grad (x_init, A, B, b, H) against central differences of first_controls(P moved
    along a random direction, H's kept symmetric), step rel_step times the parameter's largest."""
    g = torch.Generator().manual_seed(0)
    for name, arg in zip(("x_init", "A", "B", "b", "H"), args):
        v = torch.randn(arg.shape, generator=g, dtype=torch.float64)
        if name == "H":
            v = v + v.T  # H stays symmetric
        h = rel_step * P[name].abs().max().item()

        def at(s):
            return first_controls(dict(P, **{name: P[name] + s * h * v}))

        fd = (at(1) - at(-1)) / (2 * h)
        ours = (arg.grad * v).sum()
        assert abs(ours - fd) <= 1e-6 * max(1.0, abs(fd)), (name, ours.item(), fd.item())


def test_bounded_lqr_problems_have_bounds_active_at_umax_1_only():
    for umax, active in ((1e4, False), (1.0, True)):
        P = bench.bounded_lqr_problem(umax)
        assert P["x_init"].shape == (128, 8) and P["A"].shape == (8, 8) and P["B"].shape == (8, 4)
        M, q = bench.condensed_qp(P)
        ref = bench.reference_controls(M, q, P["lo"], P["hi"])
        # the reference is the solution: no control would move
        assert bench.kkt_residual(ref, M, q, P["lo"], P["hi"]).max() < 1e-8
        assert bool((ref.abs() > umax - 1e-9).any()) == active
    with pytest.raises(ValueError, match="umax"):
        bench.bounded_lqr_problem(2.0)


def test_kkt_residual_catches_a_control_off_the_solution():
    P = lqr_subset(1.0, [0, 1])
    M, q = bench.condensed_qp(P)
    ref = bench.reference_controls(M, q, P["lo"], P["hi"])
    free = (ref.abs() < 0.5).nonzero()[0]  # a control well inside the box
    wrong = ref.clone()
    wrong[tuple(free)] += 1e-4
    res = bench.kkt_residual(wrong, M, q, P["lo"], P["hi"])
    assert res[free[0]] > 1e-5 and res[1 - free[0]] < 1e-8


def test_affine_lqr_gradient_matches_the_library_backward():
    # x_init and H through diffstack.ilqr_solve's own KKT backward: AffineLQR must agree
    P = lqr_subset(1.0, ACTIVE_ROWS)
    _, u, _, (x_init, A, B, b, H) = bench.ours_lqr(P, TIGHT, grad=True)
    u[:, 0].sum().backward()
    x_init2, H2 = P["x_init"].clone().requires_grad_(), P["H"].clone().requires_grad_()
    _, u2, conv = diffstack.ilqr_solve(
        bench.StageQuadratic(),
        bench.Affine(P["A"], P["B"], P["b"]),
        x_init2,
        P["u_init"],
        (H2,),
        P["lo"],
        P["hi"],
        **TIGHT,
    )
    u2[:, 0].sum().backward()
    assert conv.all() and torch.equal(u, u2)
    assert torch.allclose(x_init.grad, x_init2.grad, rtol=1e-10, atol=1e-12)
    assert torch.allclose(H.grad, H2.grad, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("umax, rows", [(1.0, [1, 3, 4, 7]), (1e4, [0, 1, 2, 3])])
def test_affine_lqr_gradient_matches_finite_differences(umax, rows):
    # d(sum u_0) / d(x_init, A, B, b, H) along a random direction per block, against central
    # differences of the reference solver's solution; umax 1.0: 9, 12, 8 and 20 bounds active,
    # which the KKT backward holds. Horizon 8, not 20: the system's spectral radius is 1.8, and
    # over 20 steps the condensed QP's condition number (1e11) leaves its solution some 1e-7
    # absolute, too coarse for differences; over 8 it is 9e4.
    P = lqr_subset(umax, rows, horizon=8)
    M, q = bench.condensed_qp(P)
    ref = bench.reference_controls(M, q, P["lo"], P["hi"])
    _, u, _, args = bench.ours_lqr(P, TIGHT, grad=True)
    assert bench.kkt_residual(u.detach(), M, q, P["lo"], P["hi"]).max() < 1e-8
    assert ((ref.abs() > umax - 1e-9).sum() >= 40) == (umax == 1.0)
    u[:, 0].sum().backward()
    assert_directional_gradients(P, args, 1e-5, reference_first_controls)


def test_json_never_replaces_a_file_bench_did_not_make(tmp_path, monkeypatch, capsys):
    ran = []

    def fake_run(*a, **k):
        ran.append(1)
        return dict(meta={}, figures=[])

    monkeypatch.setattr(bench, "run", fake_run)
    committed = tmp_path / "goal.json"
    committed.write_text('{"meta": {"command": "python experiments.py"}, "results": {}}')
    with pytest.raises(SystemExit) as e:
        bench.main(["--quick", "--json", str(committed)])
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert e.value.code == 2 and ran == []
    assert f"argument --json: {committed} exists and is no lab.bench result" in err
    assert "--overwrite" in err and "goal.json" in committed.read_text() + str(committed)
    assert json.loads(committed.read_text())["meta"]["command"] == "python experiments.py"
    # an earlier bench result is replaced; anything else with --overwrite
    bench.main(["--quick", "--json", str(committed), "--overwrite"])
    assert json.loads(committed.read_text())["meta"]["command"].startswith("python -m lab.bench")
    bench.main(["--quick", "--json", str(committed)])
    assert len(ran) == 2


# ---- diffstack.active_set: where iLQR stalls on the bounded LQR ---------------------------------

ACTIVE_SET = bench.LQR_SETTINGS["active set"]  # 2 iLQR iterations, then active_set
STALLED = [0, 1, 3]  # at umax 1 iLQR alone stalls here past 100 iterations (docs/performance.md)


def affine_lqr(P, settings, grad=False):
    """AffineLQR's x, u, converged, iterations and its parameters (x_init, A, B, b, H)."""
    args = bench.lqr_args(P, grad)
    return (*bench.AffineLQR.apply(settings, P["lo"], P["hi"], P["u_init"], *args), args)


def test_active_set_solves_problems_where_ilqr_stalls():
    # iLQR alone (100 iterations, the finer line search) stays off the solution and says so;
    # active_set after 2 iterations lands on the reference with no control left to move
    P = lqr_subset(1.0, STALLED)
    M, q = bench.condensed_qp(P)
    ref = bench.reference_controls(M, q, P["lo"], P["hi"])
    _, u_old, conv_old, _, _ = affine_lqr(P, dict(iters=100, tol=1e-6, ls_steps=20, ls_decay=2.0))
    assert not conv_old.any()
    assert (bench.kkt_residual(u_old, M, q, P["lo"], P["hi"]) > 1e-2).all()
    _, u, conv, iters, _ = affine_lqr(P, ACTIVE_SET)
    assert conv.all() and (iters > 2).all()  # converged in active_set, after iLQR's 2
    assert bench.kkt_residual(u, M, q, P["lo"], P["hi"]).max() < 1e-8
    assert (u - ref).abs().max() < 1e-5  # the reference's own accuracy here (1e-6)
    assert ((u.abs() > 1 - 1e-9) == (ref.abs() > 1 - 1e-9)).all()  # the same active set
    # fed a wrong answer, the check fails: a free control moved by 1e-4
    wrong = u.clone()
    free = (u.abs() < 0.5).nonzero()[0]
    wrong[tuple(free)] += 1e-4
    assert bench.kkt_residual(wrong, M, q, P["lo"], P["hi"])[free[0]] > 1e-6


def test_active_set_reports_the_problems_it_has_not_converged():
    # with too few iterations allowed, the unconverged keep iLQR's controls (inside the box), are
    # reported so, and pass no gradient; the converged ones match a full run's
    P = lqr_subset(1.0, [0, 1, 2, 3, 4, 5])
    _, u_ilqr, conv_ilqr, _, _ = affine_lqr(P, dict(ACTIVE_SET, refine=0))
    _, u_full, conv_full, _, _ = affine_lqr(P, ACTIVE_SET)
    _, u, conv, _, (x_init, *_) = affine_lqr(P, dict(ACTIVE_SET, refine=5), grad=True)
    assert not conv_ilqr.any() and conv_full.all()
    assert conv.any() and not conv.all()
    assert torch.equal(u[~conv], u_ilqr[~conv]) and (u.abs() <= 1).all()
    assert torch.allclose(u[conv], u_full[conv], rtol=0, atol=1e-12)
    u[:, 0].sum().backward()
    assert (x_init.grad[~conv] == 0).all() and (x_init.grad[conv] != 0).any()


@pytest.mark.parametrize("umax, rows", [(1.0, [1, 3, 4, 7]), (1e4, [0, 1, 2, 3])])
def test_affine_lqr_gradient_matches_finite_differences_at_n_20(umax, rows):
    # the published horizon, N = 20, with active_set: at umax 1.0, 66 bounds active. Over 20 steps
    # scipy's reference is too coarse for differences (it errs by 1e-3 to 0.5 here, measured);
    # ours is exact (projected-Newton residual < 1e-8, checked at every perturbed point), so the
    # differences are of our own solution map; it agrees with the reference to 1e-5
    P = lqr_subset(umax, rows)
    M, q = bench.condensed_qp(P)
    ref = bench.reference_controls(M, q, P["lo"], P["hi"])
    _, u, conv, _, args = affine_lqr(P, ACTIVE_SET, grad=True)
    assert conv.all() and (u.detach() - ref).abs().max() < 1e-5
    assert ((ref.abs() > umax - 1e-9).sum() >= 60) == (umax == 1.0)
    u[:, 0].sum().backward()

    def first_controls(Ps):  # ours, checked exact at every perturbed point
        _, u_s, conv_s, _, _ = affine_lqr(Ps, ACTIVE_SET)
        M_s, q_s = bench.condensed_qp(Ps)
        assert conv_s.all() and bench.kkt_residual(u_s, M_s, q_s, P["lo"], P["hi"]).max() < 1e-8
        return u_s[:, 0].sum()

    assert_directional_gradients(P, args, 1e-6, first_controls)


def test_active_set_converges_on_all_128_problems():
    # the published benchmark, both umax: every problem converged by the benchmark's own test
    # (the projected-Newton residual below 1e-6) and at the reference's controls
    for umax in bench.LQR_UMAX:
        P = bench.bounded_lqr_problem(umax)
        M, q = bench.condensed_qp(P)
        ref = bench.reference_controls(M, q, P["lo"], P["hi"])
        _, u, conv, _, _ = affine_lqr(P, ACTIVE_SET)
        residual = bench.kkt_residual(u, M, q, P["lo"], P["hi"])
        assert conv.all() and residual.max() < bench.LQR_CONVERGED, umax
        assert (u - ref).abs().max() < 1e-5, umax


def test_ilqr_solve_with_refine_is_affine_lqrs_solve_and_gradient():
    # the researcher's call, diffstack.ilqr_solve (refine 100 by default): the same solution as
    # AffineLQR's, converged where iLQR alone stalls, and the same x_init and H gradients
    P = lqr_subset(1.0, STALLED)
    _, u, conv, _, (x_init, _, _, _, H) = affine_lqr(P, ACTIVE_SET, grad=True)
    u[:, 0].sum().backward()
    x_init2, H2 = P["x_init"].clone().requires_grad_(), P["H"].clone().requires_grad_()
    dynamics = bench.Affine(P["A"], P["B"], P["b"])
    args = (bench.StageQuadratic(), dynamics, x_init2, P["u_init"], (H2,), P["lo"], P["hi"])
    settings = {k: v for k, v in ACTIVE_SET.items() if k != "refine"}  # refine: the default
    _, u2, conv2 = diffstack.ilqr_solve(*args, **settings)
    u2[:, 0].sum().backward()
    assert conv.all() and conv2.all() and torch.equal(u, u2)
    assert torch.allclose(x_init.grad, x_init2.grad, rtol=1e-10, atol=1e-12)
    assert torch.allclose(H.grad, H2.grad, rtol=1e-10, atol=1e-12)
    _, _, conv3 = diffstack.ilqr_solve(*args, **dict(ACTIVE_SET, refine=0))
    assert not conv3.any()  # without it, iLQR's 2 iterations have not converged
