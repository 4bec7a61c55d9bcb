"""Bad input gets a clear error that names the culprit, and no result is ever lost (diffstack.py,
experiments.py).

One test per class of bad input: each asserts the exception type (or the CLI's exit code 2) and that
the message names the argument, field or file. The nuScenes loader and the data CLI have their own
file, test_real_data.py.
"""

import dataclasses
import json
import math
import os
import pathlib
import subprocess
import sys

import pytest
import torch

import data_synth
import diffstack as ds
import experiments as ex
from lab import tables as lt
from lab import checks, runs
from lab import data as lab_data
import specs
import train as tr
from lab import quick as lq
from conftest import TINY


@pytest.fixture(scope="module")
def batch():
    return data_synth.make_dataset(120, seed=5).val[:8]


def cli_error(main, argv, capsys) -> str:
    """Run a CLI that must refuse argv: exit code 2, and the message on stderr."""
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2
    return capsys.readouterr().err


# ---------------------------------------------------------------------------------------------
# Nothing lost: experiments refuse to replace results, check --out and the cache first,
# write atomically
# ---------------------------------------------------------------------------------------------


def test_existing_results_are_never_replaced_without_overwrite(tmp_path, capsys):
    (tmp_path / "rl.json").write_text('{"mine": 1}')
    err = cli_error(ex.main, ["--experiment", "rl", "--out", str(tmp_path), "--n", "10"], capsys)
    assert "rl.json" in err and "--overwrite" in err
    assert (tmp_path / "rl.json").read_text() == '{"mine": 1}'
    # 'all' also protects the report and the figures
    (tmp_path / "rl.json").unlink()
    (tmp_path / "closed_loop.png").write_bytes(b"png")
    with pytest.raises(ValueError, match="closed_loop.png"):
        lt.check_outputs(specs.EXPERIMENTS, tmp_path, overwrite=False)
    lt.check_outputs(specs.EXPERIMENTS, tmp_path, overwrite=True)  # --overwrite lets the run start
    # an unrelated file does not block another table
    lt.check_outputs(("rl",), tmp_path, overwrite=False)


def test_run_experiment_refuses_before_training(tmp_path, monkeypatch):
    (tmp_path / "il.md").write_text("# mine")
    monkeypatch.setattr(lt, "run_table", lambda *a, **k: pytest.fail("no work may start"))
    with pytest.raises(ValueError, match="il.md"):
        lt.run_experiment("il", None, ds.Config(), (0,), 1.0, tmp_path)


def test_unwritable_out_and_cache_are_refused_before_any_work(tmp_path, monkeypatch, capsys):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    monkeypatch.setattr(lab_data, "load_data", lambda *a, **k: pytest.fail("no data may be made"))
    err = cli_error(ex.main, ["--experiment", "rl", "--out", str(blocker / "out")], capsys)
    assert "--out" in err and "a_file" in err
    monkeypatch.chdir(tmp_path)
    (tmp_path / "data_cache").write_text("a file where the cache folder should be")
    err = cli_error(ex.main, ["--experiment", "rl", "--out", str(tmp_path / "out")], capsys)
    assert "data cache" in err
    err = cli_error(lq.main, ["--quick"], capsys)
    assert "data cache" in err


def test_one_run_per_output_folder_and_a_killed_runs_lock_is_taken_over(
    tmp_path, monkeypatch, capsys, lock_held_elsewhere
):
    """A second run on a folder another run holds is refused before any work, naming the holder
    (PID, command); when the holder is killed (SIGKILL), the next run takes the folder over."""
    out = tmp_path / "out"
    with lock_held_elsewhere(out, "the other run") as holder:
        monkeypatch.setattr(
            lab_data, "load_data", lambda *a, **k: pytest.fail("no data may be made")
        )
        for argv in (
            ["--experiment", "rl", "--out", str(out), "--n", "100"],
            ["--experiment", "rl", "--out", str(out)],
        ):
            err = cli_error(ex.main, argv, capsys)
            assert f"PID {holder.pid}" in err and "the other run" in err and str(out) in err
        (out / "rl.json").write_text("{}")
        # --render writes too
        err = cli_error(ex.main, ["--experiment", "rl", "--render", "--out", str(out)], capsys)
        assert f"PID {holder.pid}" in err
    with runs.folder_lock(out, "this run"):  # the killed run's lock, taken over
        assert json.loads((out / ".lock").read_text())["pid"] == os.getpid()


def test_a_run_holding_a_folder_may_hold_it_again_inside(tmp_path):
    # --out data_cache: the run holds its output folder, and making the data cache holds the same
    # folder again (spelled another way); another process is still refused while the run holds it
    out = tmp_path / "data_cache"
    with runs.folder_lock(out, "the run"):
        with runs.folder_lock(tmp_path / "x" / ".." / "data_cache", "the data cache"):
            assert json.loads((out / ".lock").read_text())["command"] == "the run"
        other = subprocess.run(
            [
                sys.executable,
                "-c",
                "import sys\nfrom lab import runs\n"
                "with runs.folder_lock(sys.argv[1], 'other'): pass",
                str(out),
            ],
            cwd=runs.ROOT,
            capture_output=True,
            text=True,
        )
        assert other.returncode != 0 and "another run is writing here" in other.stderr
    with runs.folder_lock(out, "the next run"):  # released when the outer block ended
        pass


def test_a_kill_mid_write_leaves_the_old_result(tmp_path, monkeypatch):
    path = tmp_path / "rl.json"
    path.write_text("old")

    def killed(src, dst):
        # the process dies between writing the temporary file and the rename
        raise KeyboardInterrupt

    monkeypatch.setattr(os, "replace", killed)
    with pytest.raises(KeyboardInterrupt):
        runs.write_atomic(path, json.dumps({"new": 1}))
    assert path.read_text() == "old"
    # and no half-written temporary file is left
    assert [p.name for p in tmp_path.iterdir()] == ["rl.json"]


def test_atomic_writes_give_results_the_usual_permissions(tmp_path, monkeypatch):
    """A result written through a temporary file (mkstemp: 0600) ends up readable as open() would
    have made it (0666 less the umask), so that others in a shared lab folder can read it; a plain
    file is the reference."""
    # the umask lab/runs.py read at import, here the common one
    monkeypatch.setattr(runs, "_UMASK", 0o022)
    old = os.umask(0o022)
    try:
        (tmp_path / "plain.txt").write_text("x")
        runs.write_atomic(tmp_path / "rl.json", "{}")
        runs.save_atomic({"w": 1}, tmp_path / "model.pt")
    finally:
        os.umask(old)

    def mode(name):
        return (tmp_path / name).stat().st_mode & 0o777

    assert mode("plain.txt") == 0o644
    assert mode("rl.json") == mode("model.pt") == mode("plain.txt")


# ---------------------------------------------------------------------------------------------
# The command lines: numbers finite, positive and bounded; --quick takes no flag it would ignore
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "argv, culprit",
    [
        (["--epochs", "nan"], "--epochs"),
        (["--epochs", "inf"], "--epochs"),
        (["--epochs", "0"], "--epochs"),
        (["--epochs", "1e9"], "--epochs"),
        (["--threads", "0"], "--threads"),
        (["--seeds", "0"], "--seeds"),
        (["--seeds", "1000"], "--seeds"),
        (["--n", "5"], "--n"),
        (["--n", "100000000"], "--n"),
        (["--n", "1e8"], "--n"),
        (["--set", "dt=0"], "dt"),
        (["--set", "horizon=-1"], "horizon"),
        (["--set", "dt=10"], "dt is the data's (0.5)"),
        (["--set", "dt=0.001"], "dt is the data's (0.5)"),
        (["--set", "horizon=7"], "horizon is the data's (6)"),
        (["--set", "hist_len=4"], "hist_len is the data's (8)"),
        (["--set", "nope=1"], "nope"),
    ],
)
def test_experiments_cli_numbers(argv, culprit, capsys, tmp_path):
    err = cli_error(ex.main, ["--experiment", "rl", "--out", str(tmp_path), *argv], capsys)
    assert culprit in err.splitlines()[-1]


@pytest.mark.parametrize(
    "flag", [["--data", "x"], ["--n", "100"], ["--epochs", "2"], ["--out", "x"], ["--seeds", "2"]]
)
def test_quick_rejects_the_flags_it_does_not_take(flag, capsys):
    err = cli_error(lq.main, ["--quick", *flag], capsys)
    assert flag[0] in err


def test_quick_threads_bounds(capsys):
    assert "--threads" in cli_error(lq.main, ["--quick", "--threads", "0"], capsys)
    assert "--threads" in cli_error(lq.main, ["--quick", "--threads", "two"], capsys)


# ---------------------------------------------------------------------------------------------
# Config and Method: refused at construction, naming the field
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "field, value",
    [
        ("dt", 0.0),
        ("dt", -0.5),
        ("dt", math.nan),
        ("horizon", 0),
        ("horizon", 2.5),
        ("hist_len", True),
        ("rbf_var", 0.0),
        ("beta", math.inf),
        ("w_coll", -1.0),
        ("u_lower", (1.0, -5.0)),
        ("u_upper", (0.7,)),
        ("ilqr_iters", 0),
        ("line_search_decay", 1.0),
        ("pred_modes", 0),
        ("batch_size", 0),
        ("lr", 0.0),
        ("plan_accels", ()),
        ("pred_lr_decay", 1.5),
        ("alpha_rl", (1.0, -1.0, 1.0)),
        ("pred_scales", (1.0, 1.0, 1.0, 0.0)),
        ("batch_size", 10**9),
        ("pred_modes", 10**6),
        ("dt", 1e-300),
        ("horizon", 10**4),
        ("lr", 1e9),
    ],
)
def test_config_refuses_values_that_would_fail_later(field, value):
    with pytest.raises(ValueError, match=field):
        ds.Config(**{field: value})


def test_config_accepts_its_defaults_and_the_tests_small_models():
    ds.Config(), ds.Config(**TINY), ds.Config(pred_pos_std_min=0.0)


def test_every_number_of_the_config_has_a_range_named_in_its_refusal():
    for f in dataclasses.fields(ds.Config):
        if f.type in ("int", "float"):
            with pytest.raises(
                ValueError,
                match=rf"^Config\.{f.name}: must be a (whole|finite) number from \S+ to \S+, got",
            ):
                ds.Config(**{f.name: 10**12})
        if f.type == "int":  # a flag or a fraction is no count, though Python calls True 1
            for v in (True, 2.5):
                with pytest.raises(ValueError, match=rf"^Config\.{f.name}: must be a whole number"):
                    ds.Config(**{f.name: v})


@pytest.mark.parametrize(
    "kw, culprit",
    [
        (dict(predictor="Learned"), "predictor"),
        (dict(predictor="oracle"), "predictor"),
        (dict(losses=(1, 1)), "losses"),
        (dict(losses=(1, math.nan, 1)), "losses"),
        (dict(losses=(1, -1, 1)), "losses"),
        (dict(weighting="grad-cost"), "weighting"),
    ],
)
def test_method_refuses_unknown_names(kw, culprit):
    with pytest.raises(ValueError, match=culprit):
        tr.Method("m", **kw)


def test_unknown_setting_is_refused(batch):
    cfg = ds.Config()
    for call in (
        lambda: ds.run_stack(batch, None, tr.Method("GT", "gt"), cfg, "xx"),
        lambda: tr.alphas(tr.Method("DiffStack", losses=(1, 1, 1)), "RL", cfg),
        lambda: tr.evaluate_stack(None, batch, tr.Method("GT", "gt"), cfg, "Il"),
    ):
        with pytest.raises(ValueError, match="setting"):
            call()


# ---------------------------------------------------------------------------------------------
# Data is checked where it enters a run: never a silent NaN
# ---------------------------------------------------------------------------------------------


def test_batches_with_inf_or_no_scenarios_are_refused(batch):
    cfg = ds.Config(**TINY)
    model = (
        ds.Predictor(cfg).double() if batch.agent_hist.dtype == torch.float64 else ds.Predictor(cfg)
    )
    import dataclasses

    method = tr.Method("DiffStack", losses=(1, 1, 1))
    for field in ("agent_hist", "others_hist", "ego_fut", "others_fut", "goal", "lanes"):
        bad = getattr(batch, field).clone()
        bad.view(-1)[0] = math.inf
        with pytest.raises(ValueError, match=field):
            tr.evaluate_stack(model, dataclasses.replace(batch, **{field: bad}), method, cfg)
        with pytest.raises(ValueError, match=field):
            tr.train_stack(
                model, dataclasses.replace(batch, **{field: bad}), method, cfg, epochs=0.1
            )
    with pytest.raises(ValueError, match="batch"):
        checks.check_batch(batch[:0], cfg, need_future=False)
    with pytest.raises(ValueError, match="batch"):
        checks.check_batch(batch[:0], cfg, need_future=True, stack=True)
    # the valid batch runs
    ds.run_stack(batch, model, method, cfg, train=True, step=0)


# ---------------------------------------------------------------------------------------------
# The closed loop says how long a scene it needs and what the data has
# ---------------------------------------------------------------------------------------------


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


def test_pretrain_refuses_to_replace_shipped_predictors_and_quick_names_a_broken_provenance(
    tmp_path, monkeypatch, capsys
):
    """--pretrain never replaces pretrained/ without --overwrite (a one-line error before any data
    is made); a provenance file that is not one is an error naming it, not a traceback from inside
    json or torch."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "pretrained").mkdir()
    (tmp_path / "pretrained" / "provenance.json").write_text("{}")
    monkeypatch.setattr(lab_data, "load_data", lambda *a, **k: pytest.fail("no data may be made"))
    err = cli_error(lq.main, ["--pretrain"], capsys)
    assert "--overwrite" in err and "pretrained" in err
    with pytest.raises(ValueError, match="provenance.json: not a provenance file"):
        lq.load_pretrained(tr.Method("Standard"), ds.Config(), tmp_path / "pretrained")
    assert "--quick or --pretrain" in cli_error(lq.main, ["--quick", "--pretrain"], capsys)


@pytest.mark.slow
def test_the_command_lines_answer_a_broken_file_in_one_line(tmp_path, monkeypatch, capsys, batch):
    """--render of a truncated results file, and --quick over a broken shipped predictor: one line
    naming the file, exit code 2, no traceback."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "rl.json").write_text('{"meta": {"command"')  # cut off mid-write
    err = cli_error(ex.main, ["--experiment", "rl", "--render", "--out", str(out)], capsys)
    assert (
        f"{out / 'rl.json'}: not a results file" in err.splitlines()[-1] and "Traceback" not in err
    )
    monkeypatch.chdir(tmp_path)
    (tmp_path / "pretrained").mkdir()
    entry = {"method": "Standard", "seed": 0, "sha256": "0", "cpu_seconds": 1}
    prov = {
        "files": {"standard-seed0.pt": entry},
        "config": dataclasses.asdict(ds.Config()),  # the defaults: the file listed, but missing
        **dict(command="c", date="d", commit="x", epochs=1, seeds=[0], threads=1),
    }
    (tmp_path / "pretrained" / "provenance.json").write_text(json.dumps(prov))
    monkeypatch.setattr(lab_data, "load_data", lambda *a, **k: data_synth.make_dataset(120, seed=5))
    # (the rows before the shipped ones)
    monkeypatch.setattr(lq, "evaluate_stack", lambda *a, **k: {})
    monkeypatch.setattr(lq, "add_relative", lambda res, setting: res)
    monkeypatch.setattr(lq, "open_loop_table", lambda *a, **k: "")
    err = cli_error(lq.main, ["--quick"], capsys)
    assert "standard-seed0.pt: missing" in err.splitlines()[-1] and "Traceback" not in err


def test_a_corrupt_piece_of_the_resume_store_is_named_and_computed_again(tmp_path, capsys):
    store = runs.RunStore(tmp_path, "k")
    piece = lt.Piece("Standard", 0, None)
    store.save("rl", piece, {"ade": 1.0})
    assert store.has("rl", piece)
    store.path("rl", piece).write_text('{"table": "rl", "res')  # a disk error cut it
    assert not store.has("rl", piece)  # computed again
    assert f"{store.path('rl', piece)}: not a finished piece" in capsys.readouterr().err
    assert store.path("rl", piece).with_suffix(".corrupt").exists()


def test_an_evaluation_with_no_plannable_scenario_is_an_error_not_a_table_of_zeros(batch):
    import dataclasses

    # no goal lane anywhere
    no_lanes = dataclasses.replace(batch, lanes_mask=torch.zeros_like(batch.lanes_mask))
    with pytest.raises(ValueError, match=r"GT: none of the 8 scenarios is plannable"):
        tr.evaluate_stack(None, no_lanes, tr.Method("GT", "gt"), ds.Config())
    assert tr.evaluate_stack(None, batch, tr.Method("GT", "gt"), ds.Config())["n"] > 0


# ---------------------------------------------------------------------------------------------
# The distributed entry points, misused
# ---------------------------------------------------------------------------------------------


def _launcher_env(monkeypatch, **env):
    for k in ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT"):
        monkeypatch.delenv(k, raising=False)
    monkeypatch.delenv("TORCHELASTIC_RUN_ID", raising=False)
    for k, v in env.items():
        monkeypatch.setenv(k, v)


@pytest.mark.parametrize("rank", ["0", "1"])
def test_rank_variables_without_a_launcher_are_refused_in_one_line(rank, monkeypatch, capsys):
    _launcher_env(monkeypatch, RANK=rank, WORLD_SIZE="2")
    monkeypatch.setattr(lab_data, "load_data", lambda *a, **k: pytest.fail("work started"))
    for main in (ex.main, lq.main):
        err = cli_error(main, ["--experiment", "rl"] if main is ex.main else ["--quick"], capsys)
        lines = err.strip().splitlines()
        assert (
            f"RANK={rank} WORLD_SIZE=2 are set, but no launcher started this process" in (lines[-1])
        )
        assert "Traceback" not in err


def test_quick_and_pretrain_under_torchrun_are_refused_by_rank_0_alone(monkeypatch, capsys):
    monkeypatch.setattr(lq, "quick", lambda *a, **k: pytest.fail("work started"))
    monkeypatch.setattr(lq, "pretrain", lambda *a, **k: pytest.fail("work started"))
    for argv in (["--quick"], ["--pretrain"]):
        _launcher_env(monkeypatch, RANK="0", WORLD_SIZE="2", TORCHELASTIC_RUN_ID="x")
        err = cli_error(lq.main, argv, capsys)
        assert "not under torchrun (it would run them 2 times)" in err.strip().splitlines()[-1]
        _launcher_env(monkeypatch, RANK="1", WORLD_SIZE="2", TORCHELASTIC_RUN_ID="x")
        assert cli_error(lq.main, argv, capsys) == ""  # rank 1 exits alike, silently


# ---------------------------------------------------------------------------------------------
# Files of the right syntax and the wrong schema: one line naming the file and the field
# ---------------------------------------------------------------------------------------------

META = dict(command="python experiments.py --experiment rl", date="d", machine="m", seconds=1.0)


@pytest.mark.parametrize(
    "text, why",
    [
        ('{"meta": {}, "results": {}}', "meta.command is missing or not text"),
        (
            json.dumps(dict(meta=META, results={"Standard": [{"ade": None}]})),
            "results.Standard[0].ade is null",
        ),
        ('{"meta": {"command": "c"}, "results": {"Standard": [{"ade": NaN}]}}', "it holds NaN"),
        ("[" * 5000 + "]" * 5000, "nested too deeply"),
        ("\xff\xfe not text", "not a results file"),
        (
            json.dumps(dict(meta=dict(META, config={"no_such_field": 1}), results={})),
            "no_such_field",
        ),
    ],
)
def test_render_of_a_file_of_the_wrong_schema_is_one_line(text, why, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "rl.json").write_text(text, errors="surrogateescape")
    (out / "rl.md").write_text("kept")
    if "no_such_field" in text:  # the committed Table 1, its Config from a later version
        saved = json.loads(pathlib.Path("results/rl.json").read_text())
        saved["meta"]["config"]["no_such_field"] = 1
        (out / "rl.json").write_text(json.dumps(saved))
    err = cli_error(ex.main, ["--experiment", "rl", "--render", "--out", str(out)], capsys)
    last = err.strip().splitlines()[-1]
    assert str(out / "rl.json") in last and why in last, err
    assert "Traceback" not in err and (out / "rl.md").read_text() == "kept"


def test_render_all_checks_every_file_before_writing_any(tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    for name in specs.EXPERIMENTS:  # the committed results, the last one damaged
        (out / f"{name}.json").write_text((pathlib.Path("results") / f"{name}.json").read_text())
        (out / f"{name}.md").write_text("kept")
    (out / f"{specs.EXPERIMENTS[-1]}.json").write_text('{"meta": {}, "results": {}}')
    err = cli_error(ex.main, ["--experiment", "all", "--render", "--out", str(out)], capsys)
    assert f"{specs.EXPERIMENTS[-1]}.json: meta.command" in err.strip().splitlines()[-1]
    assert all((out / f"{n}.md").read_text() == "kept" for n in specs.EXPERIMENTS)


def test_damaged_pieces_models_and_provenance_are_named_and_set_aside(tmp_path, capsys):
    store = runs.RunStore(tmp_path, "k")
    piece = lt.Piece("Standard", 0)
    path = store.path("rl", piece)
    path.parent.mkdir(parents=True)
    path.write_text("[" * 100 + "]" * 100)
    assert not store.has("rl", piece) and path.with_suffix(".corrupt").exists()
    assert f"{path}: not a finished piece" in capsys.readouterr().err
    # a model file of the run store that is not a model: set aside, trained again
    model = tmp_path / "m.pt"
    model.write_bytes(b"not a model")
    assert ex.stored_predictor(model, ds.Config(**TINY), "cpu") is None
    assert (tmp_path / "m.pt.corrupt").exists() and not model.exists()
    assert "m.pt: not a stored predictor" in capsys.readouterr().err
    # a provenance entry without its sha256
    folder = tmp_path / "pretrained"
    folder.mkdir()
    prov = dict(
        files={"s0.pt": dict(method="Standard", seed=0)},
        config={},
        command="c",
        date="d",
        commit="x",
        epochs=1,
        seeds=[0],
        threads=1,
    )
    (folder / "provenance.json").write_text(json.dumps(prov))
    with pytest.raises(ValueError, match=r"provenance.json: not a provenance file .*sha256"):
        lq.load_pretrained(tr.Method("Standard"), ds.Config(), folder)


def test_the_default_thread_count_is_said_and_threads_overrides_it(monkeypatch, capsys):
    # fixed (2): a busy machine is told to pass --threads 1 (docs/reproducibility.md)
    monkeypatch.setattr(lq, "quick", lambda threads, **k: print(f"quick at {threads}"))
    lq.main(["--quick"])
    lq.main(["--quick", "--threads", "1"])
    out = capsys.readouterr().out.splitlines()
    assert out == [
        "torch threads: 2 (the default; --threads N to choose)",
        "quick at 2",
        "torch threads: 1 (--threads; --threads N to choose)",
        "quick at 1",
    ]
