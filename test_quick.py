"""Tests of lab/quick.py: `python diffstack.py --quick` and `--pretrain`, the shipped predictors and
their provenance, the verdicts, and diffstack.py's command line."""

import pytest
import dataclasses
import json
import pathlib
import torch
import diffstack as ds
import experiments as ex
import train as tr
from lab import quick as lq
from conftest import TINY, cli_error, launcher_env
from lab import data as lab_data


@pytest.mark.slow
def test_quick_runs_and_same_seed_same_table(tmp_path):
    cfg = ds.Config(**TINY)
    lines = []
    first = lq.quick(
        threads=1,
        n=300,
        epochs=1,
        cfg=cfg,
        cache_dir=tmp_path,
        log=lines.append,
        pretrained=tmp_path / "none",
    )
    text = "\n".join(lines)
    assert (
        "| DiffStack (1 epochs) |" in text
        and "| Standard (1 epochs) |" in text
        and "| GT prediction |" in text
    )
    # none shipped here: said, and its row left out
    assert "Standard: no pre-trained predictor" in text
    second = lq.quick(
        threads=1,
        n=300,
        epochs=1,
        cfg=cfg,
        cache_dir=tmp_path,
        log=lambda s: None,
        pretrained=tmp_path / "none",
    )

    def strip(res):  # the results without their wall times
        return {
            k: [{m: v for m, v in r.items() if m != "seconds"} for r in runs]
            for k, runs in res.items()
        }

    assert [strip(r) for r in first] == [strip(r) for r in second]


@pytest.mark.slow
def test_pretrained_predictors_round_trip_and_refuse_what_does_not_fit(tmp_path):
    """--pretrain writes the predictors and their provenance; --quick loads them
    (sha256 checked, weights_only) and shows them beside the baselines; a changed file, or another
    Config, is refused or left out, never misused."""
    cfg = ds.Config(**TINY)
    out = tmp_path / "pre"
    about = lq.pretrain(
        out, n=300, epochs=0.5, seeds=(0, 1), cfg=cfg, cache_dir=tmp_path, log=None, val=200
    )
    assert sorted(about["files"]) == [
        "diffstack-seed0.pt",
        "diffstack-seed1.pt",
        "standard-seed0.pt",
        "standard-seed1.pt",
    ]
    assert about["threads"] == 1 and about["seeds"] == [0, 1]
    with pytest.raises(FileExistsError, match="--overwrite"):
        lq.pretrain(
            out, n=300, epochs=0.5, seeds=(0, 1), cfg=cfg, cache_dir=tmp_path, log=None, val=200
        )
    models, prov = lq.load_pretrained(tr.Method("DiffStack"), cfg, out)
    assert sorted(models) == [0, 1]
    again = tr.train_predictor(
        tr.Method("DiffStack", losses=(1, 1, 1)),  # seed 1 on its draw: the shipped seed 1
        ex.experiment_data(300, (0, 1), 200, tmp_path, log=None),
        cfg,
        "rl",
        0.5,
        1,
        None,
    )
    assert all(
        torch.equal(a, b)
        for a, b in zip(models[1].state_dict().values(), again.state_dict().values())
    )
    assert not all(
        torch.equal(a, b)
        for a, b in zip(models[0].state_dict().values(), again.state_dict().values())
    )
    # two worker processes make the same files, byte for byte
    pooled = lq.pretrain(
        tmp_path / "pooled",
        n=300,
        epochs=0.5,
        seeds=(0, 1),
        jobs=2,
        cfg=cfg,
        cache_dir=tmp_path,
        log=None,
        val=200,
    )
    assert {k: v["sha256"] for k, v in pooled["files"].items()} == {
        k: v["sha256"] for k, v in about["files"].items()
    }
    # another Config
    assert (
        lq.load_pretrained(tr.Method("DiffStack"), dataclasses.replace(cfg, beta=2.0), out)[0]
        is None
    )
    lines = []
    res, _ = lq.quick(
        threads=1, n=300, epochs=0.5, cfg=cfg, cache_dir=tmp_path, log=lines.append, pretrained=out
    )
    # a row per seed
    assert len(res["Standard (0.5 epochs)"]) == 2 and len(res["DiffStack (0.5 epochs)"]) == 2
    assert "\nHindsight cost: " in "\n".join(lines) and "seeds [0, 1], 1 thread each" in "\n".join(
        lines
    )
    with open(out / "standard-seed1.pt", "ab") as f:
        f.write(b"tampered")
    with pytest.raises(ValueError, match="standard-seed1.pt.*sha256"):
        lq.load_pretrained(tr.Method("Standard"), cfg, out)


def test_quick_verdicts_are_computed_from_its_numbers():
    """The order of the hindsight costs against the paper's, and DiffStack against Standard by the
    paired t-test over the shipped seeds (a shipped method's rows are read by their mean)."""

    def rows(*hs):
        return [dict(rel_hindsight=h) for h in hs]

    res = {
        "No prediction": rows(0.0),
        "Standard (40 epochs)": rows(-0.5, -0.6, -0.4),
        "DiffStack (40 epochs)": rows(-0.9, -1.1, -0.8),
        "GT prediction": rows(-2.0),
    }
    order, test = lq.quick_verdicts(res)
    assert order == (
        "Hindsight cost: GT < DiffStack < Standard < No prediction: the paper's order "
        "(its Table 1)."
    )
    # differences -0.4, -0.5, -0.4: mean -0.43, s.e. 0.033, t = -13, p = 0.006
    assert test == (
        "DiffStack vs Standard, hindsight cost (x1e-2): paired difference -0.43 ± 0.03 (t = "
        "-13.00, p = 0.006, 3 of 3 seeds better): reproduced (the shipped seeds; Table 1's 10: "
        "results/rl.md)"
    )
    # one seed better, two worse: the mean above Standard's, the order and the test say so
    res["DiffStack (40 epochs)"] = rows(-1.0, -0.3, -0.1)
    order, test = lq.quick_verdicts(res)
    assert "GT < Standard < DiffStack < No prediction: NOT the paper's order" in order
    assert "1 of 3 seeds better, 2 worse): not reproduced" in test
    # one seed: no standard error, untested
    one = dict(res, **{"Standard (40 epochs)": rows(-0.5), "DiffStack (40 epochs)": rows(-0.9)})
    assert "untested (one seed" in lq.quick_verdicts(one)[1]
    assert lq.quick_verdicts({k: v for k, v in res.items() if "DiffStack" not in k}) == []


@pytest.mark.parametrize(
    "argv, message",
    [
        ([], "--quick"),
        (["--quick", "--seeds", "0"], "--seeds"),
        (["--quick", "--threads", "0"], "--threads"),
        (["--quick", "--jobs", "2"], "--jobs is an option of --pretrain"),
        (["--pretrain", "--jobs", "0"], "--jobs"),
        (["--quick", "--set", "no_such_field=1"], "no_such_field"),
    ],
)
def test_bad_cli_input_exits_with_a_message(argv, message, capsys):
    with pytest.raises(SystemExit) as e:
        lq.main(argv)
    assert e.value.code != 0 and message in capsys.readouterr().err


@pytest.mark.parametrize(
    "flag", [["--data", "x"], ["--n", "100"], ["--epochs", "2"], ["--out", "x"], ["--seeds", "2"]]
)
def test_quick_rejects_the_flags_it_does_not_take(flag, capsys):
    err = cli_error(lq.main, ["--quick", *flag], capsys)
    assert flag[0] in err


def test_quick_threads_bounds(capsys):
    assert "--threads" in cli_error(lq.main, ["--quick", "--threads", "0"], capsys)
    assert "--threads" in cli_error(lq.main, ["--quick", "--threads", "two"], capsys)


def test_pretrain_refuses_to_replace_shipped_predictors_and_quick_names_a_broken_provenance(
    tmp_path, monkeypatch, capsys
):
    """--pretrain never replaces pretrained/ without --overwrite (a one-line error before any data
    is made); a provenance file that is not one is an error naming it, not a traceback from inside
    json or torch."""
    monkeypatch.setattr(lq, "PRETRAINED", tmp_path / "pretrained")
    monkeypatch.setattr(lq, "CACHE", tmp_path / "data_cache")
    (tmp_path / "pretrained").mkdir()
    (tmp_path / "pretrained" / "provenance.json").write_text("{}")
    monkeypatch.setattr(lab_data, "load_data", lambda *a, **k: pytest.fail("no data may be made"))
    err = cli_error(lq.main, ["--pretrain"], capsys)
    assert "--overwrite" in err and "pretrained" in err
    with pytest.raises(ValueError, match="provenance.json: not a provenance file"):
        lq.load_pretrained(tr.Method("Standard"), ds.Config(), tmp_path / "pretrained")
    assert "--quick or --pretrain" in cli_error(lq.main, ["--quick", "--pretrain"], capsys)


def test_quick_and_pretrain_under_torchrun_are_refused_by_rank_0_alone(monkeypatch, capsys):
    monkeypatch.setattr(lq, "quick", lambda *a, **k: pytest.fail("work started"))
    monkeypatch.setattr(lq, "pretrain", lambda *a, **k: pytest.fail("work started"))
    for argv in (["--quick"], ["--pretrain"]):
        launcher_env(monkeypatch, RANK="0", WORLD_SIZE="2", TORCHELASTIC_RUN_ID="x")
        err = cli_error(lq.main, argv, capsys)
        assert "not under torchrun (it would run them 2 times)" in err.strip().splitlines()[-1]
        launcher_env(monkeypatch, RANK="1", WORLD_SIZE="2", TORCHELASTIC_RUN_ID="x")
        assert cli_error(lq.main, argv, capsys) == ""  # rank 1 exits alike, silently


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


def test_pretrain_overwrite_replaces_the_folder_whole_or_not_at_all(tmp_path, monkeypatch):
    out, calls = tmp_path / "pre", []
    out.mkdir()
    for name in ("standard-seed0.pt", "diffstack-seed0.pt", "provenance.json"):
        (out / name).write_text("old")

    def one(m, seed, *_):  # the second predictor is interrupted (Ctrl-C)
        calls.append(m.name)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return {"w": torch.ones(1)}, dict(ade=1.0, nll=0.0, hindsight=0.0), 1.0

    monkeypatch.setattr(lq, "_pretrain_one", one)
    monkeypatch.setattr(lq, "experiment_data", lambda *a, **k: None)
    kw = dict(seeds=(0,), cfg=ds.Config(**TINY), cache_dir=tmp_path, log=None, overwrite=True)
    with pytest.raises(KeyboardInterrupt):
        lq.pretrain(out, **kw)
    assert all(f.read_text() == "old" for f in out.iterdir()) and len(list(out.iterdir())) == 3
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".pre.")) == [".pre.lock"]
    about = lq.pretrain(out, **kw)  # the same command, to its end: the new folder whole
    assert sorted(about["files"]) == sorted(p.name for p in out.glob("*.pt"))
    assert json.loads((out / "provenance.json").read_text())["files"] == about["files"]


def test_quick_and_pretrain_find_their_folders_beside_the_module(tmp_path, monkeypatch, capsys):
    root = pathlib.Path(lq.__file__).resolve().parent.parent
    monkeypatch.chdir(tmp_path)  # python /path/to/diffstack.py --quick from another folder
    seen = {}
    monkeypatch.setattr(lq, "quick", lambda *a, **k: seen.update(k))
    lq.main(["--quick"])
    assert seen["pretrained"] == root / "pretrained" and seen["cache_dir"] == root / "data_cache"
    assert not (tmp_path / "data_cache").exists()
