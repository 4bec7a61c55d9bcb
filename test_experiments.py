"""Tests of experiments.py and specs.py: the paper's tables as specs, cost learning, the closed
loop, the ablations, the report and the command line. Every test runs on one thread."""

import dataclasses
import json
import math
import statistics
import time

import pytest
import torch

from lab import data as lab_data
import data_synth
from lab import nuscenes
import diffstack as ds
import experiments as ex
from lab import tables as lt
import figures
from lab import report, runs, stats
import specs
import train as tr

TINY = dict(pred_modes=5, pred_dec_hidden=16, pred_enc_hidden=8, pred_latent_hidden=8)


def run_of(data, cfg, epochs, tmp_path) -> lt.Run:
    """A run of one table's pieces, quiet, its store in tmp_path (lt.run_table's context)."""
    return lt.Run(data, cfg, epochs, runs.RunStore(tmp_path / ".runs", "k"), log=None)


# ---------------------------------------------------------------------------------------------
# The command line
# ---------------------------------------------------------------------------------------------


def test_nuscenes_folder_trains_through_the_cli(tmp_path):
    scenes = data_synth.generate_scenes(4, seed=3)
    nuscenes.write_nuscenes(scenes, tmp_path / "nusc")
    ex.main(
        [
            "--experiment",
            "il",
            "--data",
            str(tmp_path / "nusc"),
            "--seeds",
            "1",
            "--epochs",
            "1",
            "--threads",
            "1",
            "--out",
            str(tmp_path / "out"),
        ]
    )
    res = json.loads((tmp_path / "out" / "il.json").read_text())
    assert set(res["results"]) == {"No prediction", "Standard", "DiffStack", "GT prediction"}
    assert "MSE" in (tmp_path / "out" / "il.md").read_text()


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--experiment", "nonsense"], "invalid choice"),
        (["--experiment", "rl", "--data", "/no/such/folder"], "is not a folder"),
        ([], "--experiment"),
        (["--experiment", "rl", "--seeds", "0"], "--seeds"),
        (["--experiment", "rl", "--set", "no_such_field=1"], "no_such_field"),
        (["--experiment", "rl", "--set", "beta=warm"], "beta"),
    ],
)
def test_bad_cli_input_exits_with_a_message(argv, message, capsys, tmp_path):
    with pytest.raises(SystemExit) as e:
        # a fresh --out: results/ holds committed results
        ex.main(argv + (["--out", str(tmp_path)] if argv else []))
    assert e.value.code != 0 and message in capsys.readouterr().err


def test_a_data_folder_that_is_no_nuscenes_folder_is_refused_before_out_is_made(capsys, tmp_path):
    (tmp_path / "empty").mkdir()
    for data, why in (
        ("no-such", "is not a folder"),
        ("empty", "holds no nuScenes version folder"),
    ):
        with pytest.raises(SystemExit):
            ex.main(
                [
                    "--experiment",
                    "rl",
                    "--data",
                    str(tmp_path / data),
                    "--out",
                    str(tmp_path / "new"),
                ]
            )
        assert (
            why in capsys.readouterr().err.strip().splitlines()[-1]
            and not (tmp_path / "new").exists()
        )
    # --render too: a one-line error, not a traceback from inside the loader
    (tmp_path / "old").mkdir()
    (tmp_path / "old" / "rl.json").write_text("{}")
    with pytest.raises(SystemExit):
        ex.main(
            [
                "--experiment",
                "rl",
                "--render",
                "--out",
                str(tmp_path / "old"),
                "--data",
                str(tmp_path / "empty"),
            ]
        )
    assert "holds no nuScenes version folder" in capsys.readouterr().err


# ---------------------------------------------------------------------------------------------
# Cost learning, closed loop, ablations, figures
# ---------------------------------------------------------------------------------------------

TINY10 = dict(
    pred_modes=5, pred_dec_hidden=16, pred_enc_hidden=16, pred_latent_hidden=16, batch_size=32
)


@pytest.fixture(scope="module")
def clean():
    """A small dataset whose logs carry no tracking noise: 30 scenes, the last 5 for validation."""
    scfg = data_synth.SynthConfig(pos_noise=0.0, yaw_noise=0.0)
    return data_synth.make_dataset(120, scfg, seed=3), scfg


# ---------------------------------------------------------------------------------------------
# The tables' data: a training draw per seed, one common validation set
# ---------------------------------------------------------------------------------------------


def _samples(batch) -> set:
    return {bytes(row.numpy()) for row in batch.ego_fut.reshape(len(batch), -1)}


def test_each_seed_trains_on_its_own_draw_and_every_one_is_judged_on_one_validation_set(
    tmp_path, monkeypatch
):
    data = ex.experiment_data(200, range(3), n_val=300, cache_dir=tmp_path, log=None)
    assert len(data.train_draws) == 3 and len(data.val) == 300 and data.train is data.train_draws[0]
    assert all(data.train_for(s) is data.train_draws[s] for s in range(3))
    assert torch.equal(
        data.train_draws[2].ego_fut,
        lab_data.load_data(None, 200, 2, tmp_path, log=None).train.ego_fut,
    )
    val, draws = _samples(data.val), [_samples(d) for d in data.train_draws]
    # no validation sample comes from a training draw
    assert len(val) == 300 and not any(d & val for d in draws)
    assert not (draws[0] & draws[1]) and not (draws[1] & draws[2])  # the draws differ
    # the closed loop's scenes too
    assert all(name.startswith(f"synth-{ex.VAL_SEED}-") for name in data.val_scenes.names)
    with pytest.raises(ValueError, match=r"--seeds: training seeds must be 0\.\.999"):
        ex.experiment_data(200, range(1001), cache_dir=tmp_path, log=None)
    # training seed s trains on draw s (train_predictor -> train_stack)
    seen = []
    monkeypatch.setattr(tr, "train_stack", lambda model, train, *a, **k: seen.append(train))
    ex.compare_methods(
        data._replace(val=data.val[:20]),
        ds.Config(**TINY10),
        "rl",
        (tr.Method("Standard"),),
        (0, 1, 2),
        0.1,
        log=None,
    )
    assert [id(t) for t in seen] == [id(d) for d in data.train_draws]


def test_validation_spread_evaluates_gt_prediction_on_unseen_draws_at_both_sizes(tmp_path):
    md = ex.validation_spread(draws=2, n=300, cache_dir=tmp_path, log=None)
    head, _, small, large = md.splitlines()
    assert (
        f"data seed {ex.VAL_SEED + 1} | data seed {ex.VAL_SEED + 2} | mean" in head
        and large.startswith("| 300 |")
    )
    # the second draw, its validation side
    data = lab_data.load_data(None, 300, ex.VAL_SEED + 2, tmp_path, log=None)
    gt, no = (
        next(m for m in specs.TABLE1_METHODS if m.name == n)
        for n in ("GT prediction", "No prediction")
    )
    rel = ex.add_relative(
        {m.name: [tr.evaluate_stack(None, data.val, m, ds.Config(), "rl")] for m in (no, gt)}, "rl"
    )
    assert small.split(" | ")[2] == f"{rel['GT prediction'][0]['rel_hindsight']:.2f}"


def test_validation_spread_needs_no_experiment_on_the_command_line(monkeypatch, capsys):
    monkeypatch.setattr(lt, "validation_spread", lambda *a, **k: "the table")
    ex.main(["--validation-spread"])
    assert capsys.readouterr().out.strip() == "the table"
    with pytest.raises(SystemExit):
        ex.main([])
    assert "the following arguments are required: --experiment" in capsys.readouterr().err


def test_table_1_runs_10_seeds_and_the_others_5_unless_the_command_says(tmp_path, monkeypatch):
    assert lt.table_seeds(specs.TABLE1) == tuple(range(10)) and specs.TABLE1.seeds == 10
    assert {lt.table_seeds(specs.SPECS[n]) for n in specs.EXPERIMENTS if n != "rl"} == {
        tuple(range(5))
    }
    assert lt.table_seeds(specs.TABLE1, range(3)) == (0, 1, 2)
    asked = {}
    data = data_synth.Dataset(None, None)
    monkeypatch.setattr(
        lt, "experiment_data", lambda n, seeds, *a, **k: asked.update(draws=tuple(seeds)) or data
    )
    monkeypatch.setattr(
        lt, "run_experiment", lambda name, data, cfg, seeds, *a, **k: asked.update(seeds=seeds)
    )
    monkeypatch.setattr(lt, "closed_loop_scenes", lambda *a: None)
    ex.main(["--experiment", "all", "--out", str(tmp_path / "a")])
    assert asked == {"draws": tuple(range(10)), "seeds": None}  # a draw for each of Table 1's seeds
    ex.main(["--experiment", "il", "--out", str(tmp_path / "b")])
    assert asked == {"draws": tuple(range(5)), "seeds": None}
    ex.main(["--experiment", "all", "--seeds", "2", "--out", str(tmp_path / "c")])
    assert asked["draws"] == (0, 1) and tuple(asked["seeds"]) == (0, 1)


def test_a_table_records_its_validation_count_and_training_draws(clean, tmp_path):
    data, _ = clean
    cfg = ds.Config(**TINY10)
    draws = (data.train[:32], data.train[32:64])
    small = data_synth.Dataset(draws[0], data.val[:16], None, draws)
    lt.run_experiment("cost", small, cfg, (0, 1), 0.25, tmp_path, "test", log=None)
    meta = json.loads((tmp_path / "cost.json").read_text())["meta"]
    assert meta["val"] == 16 and meta["data_seeds"] == [0, 1]


# ---------------------------------------------------------------------------------------------
# Cost learning
# ---------------------------------------------------------------------------------------------


def test_cost_weights_recover_hand_tuned_and_collision_psi_is_fixed():
    cfg = ds.Config()
    cw = tr.CostWeights(cfg)
    assert torch.allclose(cw(), ds.cost_weights(cfg), rtol=1e-6, atol=0)
    assert cw.alpha.item() == 1.0
    assert {n for n, _ in cw.named_parameters()} == {"psi", "log_alpha"}  # psi_1 is a buffer
    (cw() * torch.tensor([1.0, 2.0, -1.0, 3.0, 0.5])).sum().backward()
    assert cw.w_coll.grad is None
    assert cw.psi.grad.abs().min() > 0 and cw.log_alpha.grad.abs() > 0
    # w'_1 stays the collision weight and w'_2..5 keep their sum c, whatever psi is
    with torch.no_grad():
        cw.psi.add_(torch.tensor([0.3, -0.2, 0.1, -0.4]))
    w0 = ds.cost_weights(cfg)
    assert cw.normalised()[0] == w0[0] and torch.allclose(cw.normalised()[1:].sum(), w0[1:].sum())
    assert not torch.allclose(cw.normalised()[1:], w0[1:])


def test_controller_gradient_reaches_the_cost_weights(clean):
    data, _ = clean
    cfg = ds.Config()
    cw = tr.CostWeights(cfg)
    out = ds.run_stack(data.val[:16], None, tr.Method("GT prediction", "gt"), cfg, "il", w=cw())
    keep = out.plannable.to(out.l_ctr.dtype)
    # the plannable mean, as in training
    ((out.l_ctr * keep).sum() / keep.sum().clamp_min(1)).backward()
    assert (
        torch.isfinite(cw.psi.grad).all()
        and cw.psi.grad.abs().sum() > 0
        and cw.log_alpha.grad.abs() > 0
    )


def test_cost_scale_stays_positive_when_driven_toward_zero():
    # the loss sum(w) pushes alpha down at every step; an unconstrained alpha would pass zero in ~1
    # step of lr 1
    cw = tr.CostWeights(ds.Config())
    opt = torch.optim.SGD(cw.parameters(), lr=1.0)
    for _ in range(50):
        opt.zero_grad()
        cw().sum().backward()
        opt.step()
    assert 0 < cw.alpha.item() < 0.05 and (cw() > 0).all()


def test_controller_solution_does_not_depend_on_the_cost_scale(clean):
    # why alpha is not identified (CostWeights): argmin alpha C is the same for every alpha > 0
    data, _ = clean
    cfg = ds.Config()
    w = ds.cost_weights(cfg)
    out = [
        ds.run_stack(data.val[:16], None, tr.Method("GT prediction", "gt"), cfg, "il", w=s * w)
        for s in (1.0, 0.3)
    ]
    assert out[0].plannable.any()
    assert torch.allclose(out[0].u, out[1].u, rtol=0, atol=1e-5)
    assert not torch.allclose(out[0].cand_cost, out[1].cand_cost)  # the costs themselves do scale


# ---------------------------------------------------------------------------------------------
# Closed loop
# ---------------------------------------------------------------------------------------------


def test_frame_round_trip():
    g = torch.Generator().manual_seed(0)
    origin = torch.randn(3, 4, generator=g, dtype=torch.float64) * 10
    world = torch.randn(3, 5, 4, generator=g, dtype=torch.float64) * 10
    back = ex.from_frame(data_synth._to_frame(world, origin), origin)
    assert torch.allclose(back[..., :2], world[..., :2], atol=1e-10)
    assert torch.allclose(
        torch.cos(back[..., 2] - world[..., 2]), torch.ones(3, 5, dtype=torch.float64)
    )


def test_log_replay_agents_are_the_log_and_the_ego_follows_the_dynamics(clean):
    """A fixed control policy on noise-free logs: every step's sample, mapped back to the world,
    shows the logged agents exactly, the simulated ego history and the logged goal; the ego moves by
    the unicycle."""
    data, scfg = clean
    cfg = ds.Config()
    scenes = data.val_scenes
    S, T = len(scenes), cfg.horizon
    # u_fix: (S, 2)
    u_fix = torch.stack([torch.linspace(-0.03, 0.03, S), torch.linspace(-0.3, 0.3, S)], -1).double()
    seen = []

    def policy(batch):
        seen.append(batch)
        # u: (S, T, 2): only u[:, 0] is applied
        u = u_fix[:, None] + 0.01 * torch.arange(T, dtype=torch.float64)[:, None]
        return (
            ds.unicycle_rollout(batch.ego_hist[:, -1], u, cfg.dt),
            u,
            torch.zeros(S),
            torch.ones(S, dtype=torch.bool),
        )

    roll = ex.simulate(scenes, policy, cfg, 10.0, scfg=scfg, dtype=torch.float64)
    N = 20
    f0 = roll.start_frame
    H = scfg.hist
    assert roll.ego.shape == (S, N + 1, 4) and len(seen) == N and f0 == H
    # the ego: the unicycle driven by the fixed controls from the logged state at f0
    # ref: (S, N+1, 4)
    ref = ds.unicycle_rollout(scenes.ego[:, f0], u_fix[:, None].expand(S, N, 2), cfg.dt)
    assert torch.allclose(roll.ego[..., :2], ref[..., :2], atol=1e-8)
    assert torch.allclose(
        torch.cos(roll.ego[..., 2] - ref[..., 2]), torch.ones(S, N + 1, dtype=torch.float64)
    )
    assert torch.allclose(roll.controls, u_fix[:, None].expand(S, N, 2))
    pred = scenes.pred_idx[:, f0]
    ar = torch.arange(S)
    for k, b in enumerate(seen):
        origin = roll.ego[:, k]
        win = torch.arange(f0 + k - H, f0 + k + T + 1)  # the sample's frames
        agent = torch.cat([b.agent_hist, b.agent_fut], 1)
        assert torch.allclose(
            ex.from_frame(agent, origin)[..., :2], scenes.agents[ar, pred][:, win, :2], atol=1e-9
        )
        # others: (S, A, 2) each a logged agent at t0
        others = ex.from_frame(b.others_hist[:, :, -1], origin)[..., :2]
        # d: (S, A)
        d = (others[:, :, None] - scenes.agents[:, None, :, f0 + k, :2]).norm(dim=-1).min(-1).values
        assert (d[b.others_mask] < 1e-9).all()
        # sim_hist: (S, H+1, 4)
        sim_hist = torch.cat([scenes.ego[:, f0 + k - H : f0], roll.ego[:, : k + 1]], 1)[:, -H - 1 :]
        assert torch.allclose(
            ex.from_frame(b.ego_hist, origin)[..., :2], sim_hist[..., :2], atol=1e-9
        )
        assert torch.allclose(
            ex.from_frame(b.goal[:, None], origin)[:, 0, :2],
            scenes.ego[:, f0 + k + T, :2],
            atol=1e-9,
        )


def test_gt_prediction_closed_loop_stays_near_the_log(clean):
    data, scfg = clean
    cfg = ds.Config()
    scenes = data.val_scenes
    roll = ex.simulate(
        scenes, ex.stack_policy(None, tr.Method("GT prediction", "gt"), cfg), cfg, 10.0, scfg=scfg
    )
    m = ex.closed_loop_metrics(scenes, roll, cfg)
    assert all(torch.isfinite(v).all() for v in m.values())
    assert (m["deviation"] < 2.0).all() and (m["plannable"] > 0.9).all()
    assert torch.allclose(m["trajectory"], m["collision"] + m["lane"] + m["control"])
    # the applied control is the first of the controller's trajectory, so the ego lies on
    # each step's plan
    assert torch.allclose(roll.plans[:, :, 1, :2], roll.ego[:, 1:, :2], atol=1e-3)


def test_metrics_on_the_logged_trajectory_have_zero_deviation(clean):
    data, _ = clean
    cfg = ds.Config()
    scenes = data.val_scenes
    S = len(scenes)
    N = 4
    f0 = 8
    ego = scenes.ego[:, f0 : f0 + N + 1]
    roll = ex.Rollout(
        ego,
        torch.zeros(S, N, 2, dtype=torch.float64),
        torch.zeros(S, N, 7, 4, dtype=torch.float64),
        torch.ones(S, N, dtype=torch.float64),
        torch.ones(S, N, dtype=torch.bool),
        f0,
    )
    m = ex.closed_loop_metrics(scenes, roll, cfg)
    assert torch.allclose(m["deviation"], torch.zeros(S, dtype=torch.float64))
    assert (m["control"] == 0).all() and torch.allclose(
        m["open_loop"], torch.ones(S, dtype=torch.float64)
    )
    # one agent placed on the ego at every step adds exactly w1 phi(0) = w1 to the collision
    # cost per step
    on_ego = dict(scenes.tensors(), names=scenes.names)
    on_ego["agents"] = scenes.agents.clone()
    on_ego["agents"][:, 0, f0 + 1 : f0 + N + 1] = ego[:, 1:]
    on_ego["agents_mask"] = scenes.agents_mask.clone()
    on_ego["agents_mask"][:, 0] = True
    m2 = ex.closed_loop_metrics(data_synth.Scenes(**on_ego), roll, cfg)
    moved_away = scenes.agents_mask[:, 0, f0 + 1 : f0 + N + 1].double() * torch.exp(
        -((ego[:, 1:, :2] - scenes.agents[:, 0, f0 + 1 : f0 + N + 1, :2]) ** 2).sum(-1)
        / (2 * cfg.rbf_var)
    )
    assert torch.allclose(m2["collision"] - m["collision"], cfg.w_coll * (1 - moved_away.mean(-1)))


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(sim_time=-1.0), "sim_time"),
        (dict(sim_time=0.0), "sim_time"),
        (dict(sim_time=1.2), "sim_time"),
        (dict(sim_time=20.0), "start_frame"),
        (dict(start_frame=3), "start_frame"),
        (dict(dt=0.1), "dt"),
    ],
)
def test_simulate_bad_input_names_the_argument(clean, kw, match):
    (data, scfg) = clean
    cfg = ds.Config(dt=kw.pop("dt", 0.5))

    def never(b):
        return pytest.fail("the policy must not run on bad input")

    with pytest.raises(ValueError, match=match):
        ex.simulate(data.val_scenes, never, cfg, scfg=scfg, **kw)


# ---------------------------------------------------------------------------------------------
# Experiments end to end, tiny
# ---------------------------------------------------------------------------------------------


def test_experiments_end_to_end_tiny(clean, tmp_path):
    data, _ = clean
    cfg = ds.Config(**TINY10)
    small = data_synth.Dataset(data.train[:64], data.val[:32], data.val_scenes[:3])
    res, table = lt.run_table(
        specs.TABLES["cost"], run_of(small, cfg, 1.0, tmp_path), (0,), tmp_path
    )
    assert set(res) == {"Hand-tuned", "Learned"} and "Learned" in table
    assert res["Hand-tuned"][0]["w"] == pytest.approx([5.0, 0.5, 0.3, 0.3, 1.0], rel=1e-5)
    # Table 3 as the paper: w'_1 fixed at 5, w'_2..5 moved but summing to 2.1
    learned = res["Learned"][0]["w"]
    assert learned[0] == 5.0 and sum(learned[1:]) == pytest.approx(2.1, rel=1e-6)
    assert max(abs(a - b) for a, b in zip(learned[1:], (0.5, 0.3, 0.3, 1.0))) > 1e-4
    res, table = lt.run_table(
        specs.TABLES["closed_loop"], run_of(small, cfg, 0.5, tmp_path), (0,), tmp_path
    )
    assert list(res) == ["No prediction", "Standard", "DiffStack", "GT prediction"]
    assert res["No prediction"][0]["rel_trajectory"] == 0 and math.isfinite(
        res["DiffStack"][0]["rel_trajectory"]
    )
    written = report.write_report(
        tmp_path, [("Closed loop", table, ["closed_loop.png", "stack_example.png"])]
    )
    for f in ("cost_weights.png", "closed_loop.png", "stack_example.png"):
        assert (tmp_path / f).stat().st_size > 10_000
    assert "![closed_loop.png](closed_loop.png)" in written.read_text()


def test_ablation_table_has_a_reference_pair_per_section(clean, tmp_path, monkeypatch):
    data, _ = clean
    cfg = ds.Config(**TINY10)
    small = data_synth.Dataset(data.train[:32], data.val[:16])
    no_planner, dt01 = specs.ABLATION_SECTIONS[1], specs.ABLATION_SECTIONS[-1]
    # the shortest section and dt = 0.1 s
    spec = dataclasses.replace(specs.TABLES["ablation"], sections=(no_planner, dt01))
    trained = []
    train = tr.train_stack
    monkeypatch.setattr(
        tr,
        "train_stack",
        lambda model, data, m, *a, **k: (trained.append(m.losses), train(model, data, m, *a, **k))[
            1
        ],
    )
    res, table = lt.run_table(spec, run_of(small, cfg, 1.0, tmp_path), (0,), tmp_path)
    assert list(res) == [no_planner[0], dt01[0]] and "dt = 0.1 s" in dt01[0]
    for rows in res.values():
        assert list(rows) == ["No prediction", "Standard", "DiffStack", "GT prediction"]
    # Standard never sees the stack: trained once, shared
    assert trained == [(1, 0, 0), (1, 0, 1), (1, 1, 1)]
    assert res[dt01[0]]["Standard"][0]["ade"] == res[no_planner[0]]["Standard"][0]["ade"]
    line = next(ln for ln in table.splitlines() if ln.startswith("| DiffStack"))
    # no planner: L_plan does not apply
    assert line.split("|")[1:4] == [" DiffStack ", " 1 ", " -- "]


@pytest.mark.slow
def test_all_trains_each_predictor_once_and_shares_it(clean, tmp_path, monkeypatch):
    """--experiment all: a predictor trained the same way is trained once and reused by every table
    (Standard: Tables 1, 3, 4, 5 and each ablation section); the report links every figure."""
    data, _ = clean
    cfg = ds.Config(**TINY10)
    small = data_synth.Dataset(data.train[:32], data.val[:16], data.val_scenes[:2])
    trained = []
    train = tr.train_stack

    def counting(
        model, data, m, cfg, setting, epochs, seed, log, pred_offset=0.0, on_epoch=None, **kw
    ):
        trained.append(
            (
                m.losses,
                m.weighting,
                setting if m.losses[1:] != (0, 0) else None,
                pred_offset,
                tuple(sorted(kw.items())),
                m.train_plan_weights,
            )
        )
        return train(
            model, data, m, cfg, setting, epochs, seed, log, pred_offset, on_epoch=on_epoch, **kw
        )

    monkeypatch.setattr(tr, "train_stack", counting)
    lt.run_experiment("all", small, cfg, (0,), 0.5, tmp_path, "test", log=lambda s: None)
    assert len(trained) == len(set(trained))
    assert trained.count(((1, 0, 0), "standard", None, 0.0, (), None)) == 1
    # the dt = 0.1 s section
    assert ((1, 1, 1), "standard", "rl", 0.0, (("plan_dt", 0.1),), None) in trained
    # the ablation's prior-weights row
    assert ((1, 1, 1), "standard", "rl", 0.0, (), "prior") in trained
    # no L_pred: Table 1 and the ablation
    assert trained.count(((0, 1, 1), "standard", "rl", 0.0, (), None)) == 1
    report = (tmp_path / "report.md").read_text()
    for f in ("cost_weights.png", "closed_loop.png", "stack_example.png"):
        assert f"({f})" in report and (tmp_path / f).exists()
    for name in specs.EXPERIMENTS:
        assert json.loads((tmp_path / f"{name}.json").read_text())["meta"]["experiment"] == name


def test_closed_loop_experiment_through_the_cli(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # the synthetic data cache goes to tmp_path/data_cache
    tiny = ds.Config(**TINY)
    monkeypatch.setattr(lt, "Config", lambda: tiny)  # what main() builds
    ex.main(
        [
            "--experiment",
            "closed_loop",
            "--n",
            "60",
            "--val",
            "200",
            "--seeds",
            "1",
            "--epochs",
            "1",
            "--threads",
            "1",
            "--out",
            "out",
        ]
    )
    res = json.loads((tmp_path / "out" / "closed_loop.json").read_text())
    assert (
        res["meta"]["experiment"] == "closed_loop"
        and (tmp_path / "out" / "closed_loop.png").exists()
    )
    assert "Trajectory" in (tmp_path / "out" / "closed_loop.md").read_text()


def test_gap_closed_share_and_no_gap():
    """The share of the Standard -> GT gap DiffStack closes, per seed; undefined (nan, and the table
    says so) when Standard already costs what GT prediction does."""
    res = {
        "GT prediction": [{"rel_hindsight": -2.0}],
        "Standard": [{"rel_hindsight": 0.0}, {"rel_hindsight": 2.0}],
        "DiffStack": [{"rel_hindsight": -1.0}, {"rel_hindsight": 0.0}],
    }
    m, s = ex.gap_closed(res)
    assert m == pytest.approx(0.5) and s == pytest.approx(0.0)  # both seeds close half of their gap
    res["Standard"] = [{"rel_hindsight": -2.0}]
    assert all(math.isnan(v) for v in ex.gap_closed(res))


# ---------------------------------------------------------------------------------------------
# The paper's claims: paired differences over seeds
# ---------------------------------------------------------------------------------------------


def _p_four_dof(t: float) -> float:
    """The two-sided p-value of Student's t with 4 degrees of freedom (5 seeds), in closed form:
    F(t) = 1/2 + 3/4 x (1 - x^2 / 3), x = t / sqrt(4 + t^2) -- independent of scipy."""
    x = abs(t) / math.sqrt(4 + t * t)
    return 2 * (0.5 - 0.75 * x * (1 - x * x / 3))


def test_paired_difference_is_a_two_sided_t_test():
    """Differences -1.0, -1.2, -0.8, -1.1, -0.9: mean -1.0, s.d. sqrt(0.025),
    s.e. sqrt(0.025 / 5) = 0.0707, t = -14.1."""
    p = stats.paired_difference([2.0, 2.0, 2.0, 2.0, 2.0], [1.0, 0.8, 1.2, 0.9, 1.1])
    assert p.mean == pytest.approx(-1.0) and p.se == pytest.approx(math.sqrt(0.025 / 5))
    assert p.t == pytest.approx(-1.0 / math.sqrt(0.025 / 5)) and (p.better, p.worse, p.n) == (
        5,
        0,
        5,
    )
    assert p.p == pytest.approx(_p_four_dof(p.t), rel=1e-9) and p.p < 0.001
    assert stats.claim_verdict(p) == "reproduced"


def test_beyond_two_standard_errors_is_not_yet_p_below_5_percent():
    """5 seeds at t = -2.6 (Table 1's hindsight claim once): past two standard errors, but with 4
    degrees of freedom a two-sided 5 % test needs |t| > 2.776, so p = 0.060: not reproduced.
    Differences -1 + 0.5 k, k = -2..2 scaled."""
    d = [-1.0, -0.5, 0.0, 0.5, 1.0]
    sd = statistics.stdev(d)
    shift = 2.6 * sd / math.sqrt(5)  # the mean that gives t = -2.6
    p = stats.paired_difference([0.0] * 5, [x - shift for x in d])
    assert p.t == pytest.approx(-2.6) and p.mean < -2 * p.se
    assert p.p == pytest.approx(_p_four_dof(-2.6), rel=1e-9) == pytest.approx(0.0600, abs=5e-4)
    assert stats.claim_verdict(p) == "not reproduced"
    shift = 2.9 * sd / math.sqrt(5)  # t = -2.9: p = 0.044
    assert (
        stats.claim_verdict(stats.paired_difference([0.0] * 5, [x - shift for x in d]))
        == "reproduced"
    )


def test_paired_difference_not_significant_or_the_other_way():
    """Table 4's case: better on average, worse in two seeds. Differences -3, -3, -3, +1, +1: mean
    -1.4, s.d. sqrt(4.8), s.e. 0.980, t = -1.43 -- the unpaired means would look apart, the paired
    test says no."""
    p = stats.paired_difference([0.0] * 5, [-3.0, -3.0, -3.0, 1.0, 1.0])
    assert p.mean == pytest.approx(-1.4) and p.se == pytest.approx(math.sqrt(4.8 / 5))
    assert p.t == pytest.approx(-1.4 / math.sqrt(4.8 / 5)) and (p.better, p.worse) == (3, 2)
    assert p.p == pytest.approx(_p_four_dof(p.t), rel=1e-9) and p.p > 0.2
    assert stats.claim_verdict(p) == "not reproduced"
    p = stats.paired_difference([0.0] * 5, [1.0, 1.1, 0.9, 1.05, 0.95])  # significantly worse
    assert p.p < 0.05 and stats.claim_verdict(p) == "contradicted (the other way)"


def test_paired_difference_without_spread_and_bad_input():
    # the same difference in every seed: s.e. 0, t = -inf, p = 0, reproduced; no difference at all:
    # t undefined, not
    p = stats.paired_difference([1.0, 2.0, 3.0], [0.5, 1.5, 2.5])
    assert p.se == 0 and p.t == -math.inf and p.p == 0 and stats.claim_verdict(p) == "reproduced"
    p = stats.paired_difference([1.0, 2.0], [1.0, 2.0])
    assert p.se == 0 and math.isnan(p.t) and math.isnan(p.p) and (p.better, p.worse) == (0, 0)
    assert stats.claim_verdict(p) == "not reproduced"
    # one seed: no s.e.
    assert stats.claim_verdict(stats.paired_difference([1.0], [0.0])).startswith("untested")
    with pytest.raises(ValueError, match="method: 2 seeds, but baseline has 3"):
        stats.paired_difference([1.0, 2.0, 3.0], [1.0, 2.0])


def test_a_claim_that_the_method_is_higher_against_a_baseline_of_one_run():
    """Table 5's "the standard stack performs worse than no prediction": direction +1, and No
    prediction (nothing to train, one run) pairs with every seed of Standard."""
    p = stats.paired_difference([0.0] * 5, [1.0, 1.1, 0.9, 1.05, 0.95])
    assert (
        stats.claim_verdict(p, direction=1) == "reproduced"
        and stats.claim_verdict(p) == "contradicted (the other way)"
    )
    res = {
        "No prediction": [{"rel_trajectory": 0.0}],
        "Standard": [{"rel_trajectory": x} for x in (1.0, 1.2, 0.8, 1.1, -0.1)],
    }
    higher = specs.Claim("Standard", "No prediction", "Trajectory cost (x1e-2)", direction=1)
    line = ex.claim_line(higher, specs.TABLE5, res)
    assert "4 of 5 seeds higher, 1 lower" in line and line.endswith("): reproduced"), line
    assert ex.claim_line(dataclasses.replace(higher, direction=-1), specs.TABLE5, res).endswith(
        "contradicted (the other way)"
    )


def test_table_markdown_carries_the_claim_lines(tmp_path):
    """A table's markdown (and --render's file, re-made from its JSON) has one line per claim of
    the paper."""

    def runs(*v):
        return [
            {"rel_hindsight": x, "rel_plan_loss": x, "ade": 1.0, "nll": 1.0, "converged": 1.0}
            for x in v
        ]

    res = {
        "No prediction": runs(0, 0, 0),
        "Standard": runs(1.0, 2.0, 3.0),
        "DiffStack": runs(0.0, 0.9, 2.1),
        "GT prediction": runs(-2, -2, -2),
    }
    md = report.results_markdown(specs.TABLE1, res)
    assert (
        "DiffStack vs Standard, hindsight cost (x1e-2): paired difference -1.00 ± 0.06 (t = "
        "-17.32, p = 0.003, 3 of 3 seeds better): reproduced"
    ) in md
    assert "DiffStack vs Standard, planning loss (x1e-2): paired difference" in md
    meta = dict(
        command="python experiments.py --experiment rl", date="2026-01-01", machine="m", seconds=1.0
    )
    (tmp_path / "rl.json").write_text(json.dumps(dict(meta=meta, results=res)))
    lt.render_outputs("rl", tmp_path, log=None)
    text = (tmp_path / "rl.md").read_text()
    assert (
        text.startswith("# Table 1")
        and md in text
        and "`python experiments.py --experiment rl` (2026-01-01, m, 1 s)" in text
    )
    # an ablation: one line per section, named
    abl = {
        title: {"Standard": runs(1.0, 2.0), "DiffStack": runs(1.5, 2.5)}
        for title, _, _ in specs.ABLATION_SECTIONS
    }
    md = report.results_markdown(specs.TABLE6, abl)
    assert md.count("DiffStack vs Standard, hindsight cost") == len(specs.ABLATION_SECTIONS)
    assert (
        "Loss weights: DiffStack vs Standard, hindsight cost (x1e-2): paired difference 0.50 ± 0.00"
        in md
    )
    with pytest.raises(ValueError, match="name: 'nope'"):
        lt.render_outputs("nope", tmp_path)


# ---------------------------------------------------------------------------------------------
# The breakdown by behaviour, the goal table, learning curves, re-rendering
# ---------------------------------------------------------------------------------------------


def _by(**hindsight):
    return {b: dict(n=10, hindsight=h, mse=h, plan_loss=h) for b, h in hindsight.items()}


def test_behaviour_breakdown_is_relative_to_no_prediction_per_behaviour():
    res = {
        "No prediction": [dict(n=20, hindsight=1.0, by_behaviour=_by(cut_in=1.5, keep_lane=0.5))],
        "Standard": [
            dict(n=20, hindsight=0.99, by_behaviour=_by(cut_in=1.49, keep_lane=0.49)),
            dict(n=20, hindsight=1.01, by_behaviour=_by(cut_in=1.47, keep_lane=0.55)),
        ],
        "GT prediction": [dict(n=20, hindsight=0.9, by_behaviour=_by(cut_in=1.5, keep_lane=0.3))],
    }
    md = ex.behaviour_markdown(specs.TABLE1, res)
    rows = {
        ln.split("|")[1].strip(): [c.strip() for c in ln.split("|")[2:-1]]
        for ln in md.splitlines()
        if ln.startswith("| ")
    }
    assert rows["Behaviour (scenes)"] == ["Standard", "GT prediction"]
    assert rows["cut_in (10)"] == ["-2.00 ± 1.00", "0.00 ± 0.00"]
    assert rows["keep_lane (10)"] == ["2.00 ± 3.00", "-20.00 ± 0.00"]
    assert rows["all (20)"] == ["0.00 ± 1.00", "-10.00 ± 0.00"]
    # real data: none
    assert ex.behaviour_markdown(specs.TABLE1, {"No prediction": [dict(n=1, hindsight=1.0)]}) == ""


def test_work_units_put_the_longest_first_and_never_one_seed_twice_at_once(tmp_path):
    store = runs.RunStore(tmp_path, "k")
    names = ("rl", "ablation", "il")
    tables = [(specs.SPECS[n], (0, 1, 2)) for n in names]
    units = [(spec.name, ps) for spec, ps in lt.work_units(tables, store)]
    assert units[0][0] == "ablation" and {n for n, _ in units[-3:]} == {"il"}
    assert all(len({p.seed for p in ps}) == 1 for _, ps in units)  # one seed per unit
    seeds = [ps[0].seed for _, ps in units]
    # two workers never start the same seed side by side
    assert all(a != b for a, b in zip(seeds, seeds[1:]))
    every = [(n, p) for n in names for p in lt.table_pieces(specs.SPECS[n], (0, 1, 2))]
    assert sorted((n, p) for n, ps in units for p in ps) == sorted(every)
    done = units[0][1][0]
    store.save("ablation", done, {"x": 1})
    assert ("ablation", done) not in [
        (spec.name, p) for spec, ps in lt.work_units(tables, store) for p in ps
    ]


def test_the_code_version_follows_the_number_making_modules_only(tmp_path, monkeypatch):
    assert set(runs.NUMBER_MODULES) == {
        "diffstack.py",
        "train.py",
        "lab/ddp.py",
        "data_synth.py",
        "lab/data.py",
        "lab/nuscenes.py",
        "lab/waymo.py",
        "experiments.py",
        "lab/tables.py",
    }
    (tmp_path / "lab").mkdir()
    for name in runs.NUMBER_MODULES + ("README.md", "test_x.py", "tutorial.py", "specs.py"):
        (tmp_path / name).write_text(f"# {name}\nx = 1\n")
    monkeypatch.setattr(runs, "ROOT", tmp_path)
    versions = {runs.code_version()}
    # the tests, the docs, the notebook, the specs' text: the same run
    for name in ("README.md", "test_x.py", "tutorial.py", "specs.py"):
        (tmp_path / name).write_text("# edited\nx = 2\n")
        assert runs.code_version() in versions
    for name in runs.NUMBER_MODULES:  # each module that makes numbers: a new run
        (tmp_path / name).write_text(f"# {name}\nx = 2\n")
        versions.add(runs.code_version())
    assert len(versions) == 1 + len(runs.NUMBER_MODULES)


def _distance_like(batch):
    """A weighting defined as a function, as a user's Method(weighting=...) would be."""
    return tr.distance_weights(batch)


def test_a_tables_key_follows_its_numbers_not_its_text(tmp_path):
    """A table's folder of kept pieces is keyed on what its spec sets that moves numbers (rows,
    setting, offset, sections), by value: a new title or column header keeps every piece, a changed
    row or offset is a new folder. A callable weighting is keyed by its name, never by the object
    (whose text holds a memory address that differs in every process)."""
    spec = specs.TABLE2

    def folder(s):
        return runs.RunStore(tmp_path, "k", {s.name: ex.spec_key(s)}).table_dir(s.name)

    same = dataclasses.replace(spec, title="Table 2, retitled", columns=spec.columns[:2])
    assert folder(same) == folder(spec)
    for changed in (
        dataclasses.replace(spec, pred_offset=2.0),
        dataclasses.replace(spec, methods=spec.methods[:-1]),
        dataclasses.replace(
            spec, methods=(*spec.methods[:2], tr.Method("DiffStack-biased", losses=(1, 0, 1)))
        ),
    ):
        assert folder(changed) != folder(spec)
    m = tr.Method("Mine", weighting=_distance_like)
    key = ex.training_key(m, ds.Config(), "rl", 1.0, 0)
    assert "0x" not in repr(key) and key == ex.training_key(
        tr.Method("Mine", weighting=_distance_like), ds.Config(), "rl", 1.0, 0
    )
    assert key[1] == "test_experiments._distance_like"


CODE = '''"""A module."""
import math
import statistics


def f(x, scale=2.0):
    """Twice x."""
    return scale * math.sqrt(x)  # a comment
'''

SAME_CODE = '''"""A module, its docstring edited."""
import math
import statistics


def f(x,
      scale=2.0):
    # a new comment
    """Twice x, said otherwise."""
    return (scale
            * math.sqrt(x))
'''


def test_the_code_version_ignores_comments_docstrings_and_layout(tmp_path, monkeypatch):
    """An edited comment or docstring or a re-wrapped line is the same run (hours of pieces kept); a
    changed number, name or string is a new one. (SAME_CODE's comment stands before the docstring:
    the string is then still the function's first statement, its docstring.)"""
    (tmp_path / "lab").mkdir()
    for name in runs.NUMBER_MODULES:
        (tmp_path / name).write_text(CODE)
    monkeypatch.setattr(runs, "ROOT", tmp_path)
    before = runs.code_version()
    (tmp_path / "diffstack.py").write_text(SAME_CODE)
    assert runs.code_version() == before
    for edit in (
        ("2.0", "3.0"),
        ("sqrt", "exp"),
        ("scale *", "scale +"),
        ('"""Twice x."""\n', '"""Twice x."""\n    x = x\n'),
        ("# a comment", "+ len('a string')"),
    ):
        (tmp_path / "diffstack.py").write_text(CODE.replace(*edit))
        assert runs.code_version() != before, edit
    # a string without a space is code (a key, a name); one with a space, or an f-string, is
    # text (a log line, a message, a title): editing it is the same run
    assert runs.code_of('x = "a"\n') != runs.code_of('x = "b"\n')
    assert runs.code_of('if s == "rl":\n    y = 1\n') != runs.code_of('if s == "il":\n    y = 1\n')
    for text, typo in (
        ('log(f"step {i} of {n}")\n', 'log(f"setp {i} of {n}")\n'),
        (
            'raise ValueError("--epochs: expected a number")\n',
            'raise ValueError("--epochs: a number")\n',
        ),
        (
            'TITLE = "Table 1: reinforcement learning"\n',
            'TITLE = "Table 1: reinforcment learning"\n',
        ),
        ('f(x, "| Method | ADE |")\n', 'f(x, "| Method | ADE (m) |")\n'),
    ):
        assert runs.code_of(text) == runs.code_of(typo), text
    assert runs.code_of('k = f"rel_{key}"\n') != runs.code_of('k = f"abs_{key}"\n')
    assert runs.code_of('def g():\n    """Doc."""\n') == runs.code_of("def g():\n    pass\n")
    # a dataclass field's docstring (Config's) is a string statement too; the field's
    # default is code
    field = 'class C:\n    x: float = 1.0\n    """The x, in m."""\n'
    assert runs.code_of(field) == runs.code_of(field.replace("in m", "in metres"))
    assert runs.code_of(field) != runs.code_of(field.replace("1.0", "2.0"))


def test_the_goal_table_shows_what_a_perfect_prediction_saves_and_why(clean, tmp_path):
    """The goal table runs No and GT prediction under both goals; the cost terms add up to the
    hindsight cost."""
    data, _ = clean
    cfg = ds.Config()
    res, md = lt.run_table(specs.GOAL_TABLE, run_of(data, cfg, 1.0, tmp_path), (0, 1), tmp_path)
    assert list(res) == list(specs.GOALS) and all(
        list(rows) == ["No prediction", "GT prediction"] for rows in res.values()
    )
    for rows in res.values():
        for per_seed in rows.values():
            assert len(per_seed) == 1  # nothing trained: one run
            for b in per_seed[0]["by_behaviour"].values():
                assert (
                    sum(b["terms"]) == pytest.approx(b["hindsight"], rel=1e-4)
                    and 0 <= b["close"] <= 1
                )
        gt, none = rows["GT prediction"][0]["hindsight"], rows["No prediction"][0]["hindsight"]
        assert gt <= none + 1e-6  # with the GT future, the plan is the best candidate in hindsight
    assert md.count("**Goal:") == 2 and "share of GT's saving" in md


def test_the_report_says_when_and_where_its_tables_ran_not_when_it_was_written(tmp_path):
    metas = [
        dict(
            date="2026-11-24",
            machine="x86_64, 2 cores, 1 thread per process, 2 worker processes (--jobs)",
            device="cpu",
        ),
        dict(
            date="2026-11-25",
            machine="x86_64, 2 cores, 1 thread per process, 2 worker processes (--jobs)",
            device="cpu",
        ),
        dict(date="2026-11-25", machine="aarch64, 8 cores, 2 threads", device="cuda"),
    ]
    header = report.write_report(tmp_path, [("T", "table", [])], metas).read_text().splitlines()[2]
    assert header == (
        "Tables made 2026-11-24 to 2026-11-25 on x86_64, 2 cores, 1 thread per process, 2 worker "
        # each once, in order
        "processes (--jobs); aarch64, 8 cores, 2 threads, device cpu, cuda"
    )
    # a run resumed on another machine
    metas[0]["computed_on"] = {"x86_64, AVX512": 3, "x86_64, AVX2": 2}
    header = (
        report.write_report(tmp_path, [("T", "table", [])], metas[:1], rendered=True)
        .read_text()
        .splitlines()[2]
    )
    assert (
        header.startswith("Tables made 2026-11-24 on x86_64")
        and "device cpu (pieces computed on several" in header
    )
    assert header.endswith(f"(rendered {time.strftime('%Y-%m-%d')} from their JSON files)")


def test_render_rewrites_every_derived_output_from_the_json(clean, tmp_path):
    """--render: the .md files, the learning curves and the report again from the JSON,
    nothing trained."""
    data, _ = clean
    cfg = ds.Config(**TINY10)
    small = data_synth.Dataset(data.train[:64], data.val[:16], data.val_scenes[:2])
    lt.run_experiment("rl", small, cfg, (0, 1), 1.0, tmp_path, "test", log=None)
    assert (tmp_path / "learning_curves.png").exists()
    res = json.loads((tmp_path / "rl.json").read_text())["results"]
    assert [c["epoch"] for c in res["DiffStack"][0]["curve"]] == [0.0, 1.0]
    md = (tmp_path / "rl.md").read_text()
    for f in ("rl.md", "learning_curves.png"):
        (tmp_path / f).unlink()
    with pytest.raises(SystemExit):  # nothing to render from
        ex.main(["--experiment", "all", "--render", "--out", str(tmp_path)])
    ex.main(
        ["--experiment", "rl", "--render", "--out", str(tmp_path), "--n", "100", "--val", "100"]
    )
    assert (tmp_path / "rl.md").read_text() == md and (tmp_path / "learning_curves.png").exists()
    # results from before the curves existed: their tables re-rendered, no empty figure drawn
    saved = json.loads((tmp_path / "rl.json").read_text())
    for per_seed in saved["results"].values():
        for r in per_seed:
            r.pop("curve", None)
    (tmp_path / "rl.json").write_text(json.dumps(saved))
    (tmp_path / "learning_curves.png").unlink()
    lt.render_outputs("rl", tmp_path, log=None)
    assert (
        not (tmp_path / "learning_curves.png").exists()
        and "Learning curves" not in (tmp_path / "rl.md").read_text()
    )


def test_the_cost_weights_figure_writes_a_scale_it_cannot_draw(tmp_path):
    # a negative alpha (Table 3 at 20 epochs) has no bar on the log axis: the figure must say
    # so, not drop it
    def run(w, a):
        return dict(w=w, alpha=a)

    hand = [run([5.0, 0.5, 0.3, 0.3, 1.0], 1.0)] * 2
    assert (
        figures.figure_cost_weights(
            {"Hand-tuned": hand, "Learned": [run([4.0, 1.3, 0.8, 0.8, 0.2], 0.5)] * 2},
            tmp_path / "a.png",
        )
        == []
    )
    notes = figures.figure_cost_weights(
        {
            "Hand-tuned": hand,
            "Learned": [
                run([4.0, 1.3, 0.8, 0.8, 0.2], -0.04),
                run([4.0, 1.3, 0.8, 0.8, 0.2], -0.05),
            ],
        },
        tmp_path / "b.png",
    )
    assert notes == ["Learned alpha = -0.045"] and (tmp_path / "b.png").exists()


# ---------------------------------------------------------------------------------------------
# Nothing not finite in what users read: one seed, every seed diverged
# ---------------------------------------------------------------------------------------------


def _open_loop_runs(*v, curve=False):
    runs = [
        {"rel_hindsight": x, "rel_plan_loss": x, "ade": 1.0 + x, "nll": 1.0, "converged": 1.0}
        for x in v
    ]
    for r in runs if curve else ():
        r["curve"] = [
            dict(epoch=e, step=e, ade=2.0 - 0.1 * e, hindsight=1.0 - 0.01 * e) for e in range(5)
        ]
    return runs


def test_a_one_seed_table_says_its_standard_errors_are_not_available():
    res = {
        "No prediction": _open_loop_runs(0.0),
        "Standard": _open_loop_runs(1.0, curve=True),
        "DiffStack": _open_loop_runs(0.5, curve=True),
        "GT prediction": _open_loop_runs(-2.0),
    }
    md = report.results_markdown(specs.TABLE1, res)
    card = report.claims_card({"rl": res})
    for text in (md, card):
        assert "nan" not in text.lower() and "inf" not in text.lower(), text
    rows = {ln.split("|")[1].strip(): ln for ln in md.splitlines() if ln.startswith("| ")}
    assert "| 1.00 ± n/a (1 seed) |" in rows["Standard"]
    assert "| 0.00 ± 0.00 |" in rows["No prediction"]  # nothing trained: the same every seed
    assert "paired difference -0.50 ± n/a (1 seed) (one seed" in md
    assert "untested (one seed: no standard error)" in md
    assert "DiffStack closes 17 ± n/a (1 seed) % of the Standard" in md


def test_a_table_whose_trained_rows_all_diverged_names_them_and_tests_nothing():
    gone = [
        {"diverged": "Standard, seed 0: training diverged at step 3 of 4: L_pred is not finite"}
    ]
    res = {
        "No prediction": _open_loop_runs(0.0),
        "Standard": gone,
        "DiffStack": [{"diverged": "DiffStack, seed 0: its learning curve holds 1.nll, infinite"}],
        "GT prediction": _open_loop_runs(-2.0),
    }
    md = report.results_markdown(specs.TABLE1, res)
    card = report.claims_card({"rl": res})
    for text in (md, card):
        assert "nan" not in text.lower() and "inf " not in text.lower(), text
    assert (
        "DiffStack vs Standard, hindsight cost (x1e-2): untested (no seed trained both rows; 2 "
        in md
    )
    assert "No gap closed is given: every seed of Standard or DiffStack diverged." in md
    assert "Diverged, left out of the means: DiffStack, seed 0: its learning curve holds" in md
    assert "untested (no seed trained both rows)" in card


def test_closed_loop_needs_long_enough_scenes():
    scenes = data_synth.make_dataset(120, seed=5).val_scenes
    assert len(ex.closed_loop_scenes(scenes, ds.Config())) == len(scenes)
    cut = {
        k: (
            v[:, :20]
            if k in ("ego", "pred_idx")
            else v[:, :, :20]
            if k in ("agents", "agents_mask")
            else v
        )
        for k, v in scenes.tensors().items()
    }
    short = data_synth.Scenes(**cut, names=scenes.names)
    with pytest.raises(
        ValueError,
        match=r"at least 34 frames .* the data has \d+ validation scene\(s\) of 20 frames",
    ):
        ex.closed_loop_scenes(short, ds.Config())
    with pytest.raises(ValueError, match="of 0 .*|0 validation"):
        ex.closed_loop_scenes(scenes[:0], ds.Config())
