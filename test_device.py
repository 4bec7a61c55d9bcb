"""The stack runs unchanged on any device: every tensor it makes is made on the device (and dtype)
of its inputs. Checked on the CPU, without a GPU, in two ways (1, 2), then the --device argument of
both command lines (3), and the stack on a GPU against the CPU where there is one (4; its body also
runs on the CPU, so that it is tested without one).

1. The meta trick. Inside `with torch.device("meta"):` every factory called WITHOUT device=
   (torch.zeros, tensor, arange, ones, eye, full, linspace, randn, ...) makes a meta tensor (no
   storage), while one called with device=x.device still makes a CPU tensor for CPU inputs. We feed
   CPU inputs: the first time a forgotten factory's meta tensor meets a CPU tensor, torch raises
   "Tensor on device meta is not on the expected device cpu!" -- just as a CPU tensor meeting a
   CUDA one would on a GPU. (Stricter than CUDA, which lets 0-dim CPU tensors mix with CUDA ones:
   good for us.) test_the_meta_trick_catches_a_missing_device shows it on a planted bug.
   One blind spot: indexing a CPU tensor with a meta index tensor does not raise (torch.arange(B)
   used only as an index slips through; on CUDA it works too, with a host-to-device copy).
2. The factory audit, which covers that blind spot and names the line: a TorchFunctionMode (the
   mechanism torch.device("meta") itself uses) records every factory called without device=
   directly from diffstack.py, experiments.py or data_synth.py (the caller's frame), while the
   stack runs normally: none may be left, each named by its file, line and function.
"""

import copy
import pathlib
import sys

import pytest
import torch
from torch.overrides import TorchFunctionMode

from lab import data as lab_data
import data_synth
import diffstack as ds
import experiments as ex
import train as tr
from lab import quick as lq
from lab import tables as lt
from lab import cli

TINY = dict(
    pred_modes=5, pred_dec_hidden=16, pred_enc_hidden=8, pred_latent_hidden=8, batch_size=16
)

# ---------------------------------------------------------------------------------------------
# The factory audit
# ---------------------------------------------------------------------------------------------

FACTORIES = {
    getattr(torch, name)
    for name in (
        "tensor",
        "as_tensor",
        "asarray",
        "scalar_tensor",
        "zeros",
        "ones",
        "empty",
        "full",
        "arange",
        "linspace",
        "logspace",
        "eye",
        "rand",
        "randn",
        "randint",
        "randperm",
        "tril_indices",
        "triu_indices",
    )
    if hasattr(torch, name)
}
HERE = pathlib.Path(__file__).resolve().parent
# data_synth: sample_at
AUDITED = {
    str(HERE / name): name
    for name in ("diffstack.py", "train.py", "experiments.py", "data_synth.py")
    + ("lab/data.py", "lab/nuscenes.py", "lab/waymo.py")
}


class FactoryAudit(TorchFunctionMode):
    """Records (file, line, function, factory) for every tensor factory called without device=
    straight from an audited file. Only the direct caller counts: factories inside torch (an
    optimiser's state) are torch's affair."""

    def __init__(self):
        super().__init__()
        self.calls = set()

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if func in FACTORIES and kwargs.get("device") is None:
            caller = sys._getframe(1)  # the Python frame that called the factory
            name = AUDITED.get(caller.f_code.co_filename)
            if name is not None:
                self.calls.add((name, caller.f_lineno, caller.f_code.co_name, func.__name__))
        return func(*args, **kwargs)


# ---------------------------------------------------------------------------------------------
# What the stack runs: every entry point that makes tensors, on CPU inputs
# ---------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def setup():
    """Real synthetic data (made on the CPU, as always), a tiny config, and the modules (a
    predictor, the cost weights), made here on the CPU: a module built inside torch.device("meta")
    would itself be on meta."""
    scfg = data_synth.SynthConfig()
    data = data_synth.make_dataset(60, scfg, seed=5)
    cfg = ds.Config(**TINY)
    torch.manual_seed(0)
    return data, cfg, ds.Predictor(cfg), scfg, tr.CostWeights(cfg)


def run_dynamics():
    """Section 2 (ours): the unicycle and its derivatives, float32 and float64."""
    for dtype in (torch.float32, torch.float64):
        g = torch.Generator().manual_seed(0)
        cpu = dict(dtype=dtype, device="cpu")  # CPU inputs, also under meta
        s = torch.randn(5, 4, generator=g, **cpu)
        u = torch.randn(5, 3, 2, generator=g, **cpu) * torch.tensor([0.5, 1.0], **cpu)
        u[0, 0, 0] = 0.0  # the series branch of the moments
        lam = torch.randn(5, 4, generator=g, **cpu)
        assert ds.unicycle_step(s, u[:, 0], 0.5).device.type == "cpu"
        assert ds.unicycle_rollout(s, u, 0.5).shape == (5, 4, 4)
        A, B = ds.unicycle_jacobians(s, u[:, 0], 0.5)
        H = ds.unicycle_curvature(s, u[:, 0], lam, 0.5)
        assert A.device.type == B.device.type == H.device.type == "cpu"
        up = ds.upsample(s[:, :2], u, 5)
        assert up.shape == (5, 15, 2) and up.device.type == "cpu"


def run_stack_everything(setup):
    """Section 7: the stack with every kind of predictor and option the experiments use."""
    data, cfg, model, *_ = setup
    batch = data.train[:8]
    outs = []
    for method in (
        tr.Method("No prediction", "none"),
        tr.Method("GT prediction", "gt"),
        tr.Method("DiffStack", losses=(1, 1, 1)),
    ):
        out = ds.run_stack(batch, model, method, cfg, "rl", step=0, train=True)
        outs.append(out)
    learned = tr.Method("DiffStack", losses=(1, 1, 1))
    outs.append(ds.run_stack(batch, model, learned, cfg, "il", planner=False, plan_others=False))
    outs.append(ds.run_stack(batch, model, learned, cfg, "rl", controller=False))
    outs.append(ds.run_stack(batch, model, learned, cfg, "rl", plan_dt=0.25))
    # the KKT backward as well
    (outs[-1].l_plan.sum() + outs[2].l_ctr.sum() + outs[2].l_pred.sum()).backward()
    for out in outs:
        assert out.x.device.type == "cpu" and out.hindsight.device.type == "cpu"
    return outs


def run_training(setup):
    """Section 8: two training steps (predictor, and the cost weights), and the evaluation."""
    data, cfg, model, _, weights = setup
    # training changes them (learning the cost freezes the model)
    model, weights = copy.deepcopy(model), copy.deepcopy(weights)
    small = data.train[:32]
    tr.train_stack(
        model, small, tr.Method("DiffStack", losses=(1, 1, 1)), cfg, "rl", epochs=1.0, log=None
    )
    tr.train_stack(
        model,
        small,
        tr.Method("Grad-cost weighted", weighting="grad_cost"),
        cfg,
        "rl",
        epochs=0.5,
        log=None,
    )
    tr.train_stack(
        model,
        small,
        tr.Method("Cost weights", losses=(0, 0, 1)),
        cfg,
        "il",
        epochs=0.5,
        log=None,
        weights=weights,
    )
    for method in (tr.Method("No prediction", "none"), tr.Method("Standard")):
        r = tr.evaluate_stack(
            model if method.predictor == "learned" else None, data.val[:16], method, cfg, "rl"
        )
        assert isinstance(r["hindsight"], float)


def run_closed_loop(setup):
    """experiments.py: one closed-loop step (the simulation on the CPU, the stack on the model's
    device)."""
    data, cfg, model, scfg, _ = setup
    scenes = data.val_scenes[:2]
    roll = ex.simulate(
        scenes, ex.stack_policy(model, tr.Method("Standard"), cfg), cfg, 0.5, scfg=scfg
    )
    assert roll.ego.device.type == "cpu" and roll.ego.shape[1] == 2
    m = ex.closed_loop_metrics(scenes, roll, cfg)
    assert all(v.device.type == "cpu" for v in m.values())


EVERYTHING = (run_stack_everything, run_training, run_closed_loop)


# ---------------------------------------------------------------------------------------------
# 0. The traps work: a planted missing device= is caught by both
# ---------------------------------------------------------------------------------------------


def _buggy_upsample(now, fut, substeps):
    """diffstack.upsample with its device= removed: the bug the tests must catch."""
    knots = torch.cat([now[..., None, :], fut], -2)
    a, b = knots[..., :-1, None, :], knots[..., 1:, None, :]
    f = torch.arange(1, substeps + 1, dtype=fut.dtype)[:, None] / substeps  # the bug: no device=
    return (a + (b - a) * f).flatten(-3, -2)


def test_the_meta_trick_catches_a_missing_device():
    now, fut = torch.zeros(3, 2), torch.ones(3, 4, 2)
    # on the CPU the bug is invisible
    assert torch.equal(_buggy_upsample(now, fut, 2), ds.upsample(now, fut, 2))
    with torch.device("meta"):
        # the real one: device= of its input, a CPU tensor
        assert ds.upsample(now, fut, 2).device.type == "cpu"
        with pytest.raises(RuntimeError, match="meta"):
            # the forgotten factory made a meta tensor, which met a CPU one
            _buggy_upsample(now, fut, 2)


def test_the_audit_names_a_missing_device(monkeypatch):
    monkeypatch.setitem(AUDITED, __file__, "test_device.py")
    now, fut = torch.zeros(3, 2), torch.ones(3, 4, 2)
    with FactoryAudit() as audit:
        ds.upsample(now, fut, 2)
        _buggy_upsample(now, fut, 2)
    assert audit.calls == {
        ("test_device.py", _buggy_upsample.__code__.co_firstlineno + 4, "_buggy_upsample", "arange")
    }


# ---------------------------------------------------------------------------------------------
# 1. The meta trick on the stack
# ---------------------------------------------------------------------------------------------


def test_dynamics_make_every_tensor_on_their_inputs_device():
    with torch.device("meta"):
        run_dynamics()


@pytest.mark.parametrize("run", EVERYTHING, ids=lambda f: f.__name__)
def test_the_stack_makes_every_tensor_on_its_inputs_device(run, setup):
    """Every part of the stack under torch.device("meta"): a tensor made without device= lands on
    meta, which has no values, and the run fails. Torch's own code must pass too: torch 2.11's Adam
    makes its step counter on the default device and fails here (seen where 2.11 was installed), so
    training is checked from 2.13 on (pinned in requirements.txt), whose Adam keeps it on the CPU;
    the factory audit below covers our own code on any version."""
    if run is run_training and tuple(
        int(v) for v in torch.__version__.split("+")[0].split(".")[:2]
    ) < (2, 13):
        pytest.skip(
            f"torch {torch.__version__}'s Adam makes its step counter on the default device "
            "(meta here)"
        )
    with torch.device("meta"):
        run(setup)


# ---------------------------------------------------------------------------------------------
# 2. The factory audit on the stack
# ---------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def audit(setup):
    """Every factory without device= that the stack calls from diffstack.py, experiments.py and
    data_synth.py (the closed loop cuts its samples with data_synth.sample_at; generating the data
    is not audited: it is made on the CPU)."""
    with FactoryAudit() as a:
        run_dynamics()
        for run in EVERYTHING:
            run(setup)
    return a.calls


def test_no_factory_without_device(audit):
    """Anywhere in the audited files: every factory the stack calls is given device=."""
    calls = sorted(audit)
    assert not calls, "tensor factories without device=: " + "; ".join(
        f"{f}:{n} {fn}() torch.{t}" for f, n, fn, t in calls
    )


# ---------------------------------------------------------------------------------------------
# 3. --device on the command lines
# ---------------------------------------------------------------------------------------------


def cli_error(main, argv, capsys) -> str:
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2
    return capsys.readouterr().err


@pytest.mark.parametrize("name", ["gpu", "cuda", "cuda:0", "meta", ""])
@pytest.mark.parametrize("cli", ["diffstack", "experiments"])
def test_a_device_this_machine_lacks_is_a_one_line_error(cli, name, capsys, monkeypatch, tmp_path):
    # the same on a machine with a GPU
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    work = []
    monkeypatch.setattr(lq, "quick", lambda *a, **k: work.append(1))
    monkeypatch.setattr(lab_data, "load_data", lambda *a, **k: work.append(1))
    monkeypatch.setattr(lt, "experiment_data", lambda *a, **k: work.append(1))
    if cli == "diffstack":
        err = cli_error(lq.main, ["--quick", "--device", name], capsys)
    else:
        err = cli_error(
            ex.main, ["--experiment", "rl", "--out", str(tmp_path), "--device", name], capsys
        )
    last = err.strip().splitlines()[-1]
    assert "argument --device" in last and (name in last if name else "torch device" in last), err
    assert "cuda" in last and not work  # it says what would do, and refused before any work


def test_device_reaches_the_work(capsys, monkeypatch, tmp_path):
    seen = {}
    monkeypatch.setattr(lq, "quick", lambda *a, **k: seen.update(quick=k["device"]))
    lq.main(["--quick"])
    lq.main(["--quick", "--device", "cpu"])
    monkeypatch.setattr(lt, "experiment_data", lambda *a, **k: "data")
    monkeypatch.setattr(lt, "run_experiment", lambda *a, **k: seen.update(experiment=k["device"]))
    ex.main(["--experiment", "rl", "--out", str(tmp_path), "--device", "cpu"])
    assert seen == {"quick": torch.device("cpu"), "experiment": torch.device("cpu")}


def test_device_arg_takes_the_devices_that_are_there(monkeypatch):
    import argparse

    assert cli.device_arg("cpu") == torch.device("cpu")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    assert cli.device_arg("cuda") == torch.device("cuda") and cli.device_arg(
        "cuda:1"
    ) == torch.device("cuda", 1)
    with pytest.raises(argparse.ArgumentTypeError, match="2 CUDA device"):
        cli.device_arg("cuda:2")


# ---------------------------------------------------------------------------------------------
# 4. On a GPU, when there is one: the same numbers as on the CPU
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "device",
    [
        "cpu",
        pytest.param(
            "cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
        ),
    ],
)
def test_the_stack_on_a_device_matches_the_cpu(device, setup):
    """On cuda the real check; on the CPU the same body runs (trivially equal), so that a mistake in
    the test itself (a float32 batch for a float64 model, say) shows on machines without a GPU too.
    """
    data, cfg, model, *_ = setup
    batch = data.val[:16].to(torch.float64)
    cpu_model = ds.Predictor(cfg).double()
    cpu_model.load_state_dict(model.state_dict())
    dev_model = ds.Predictor(cfg).double().to(device)
    dev_model.load_state_dict(model.state_dict())
    for method in (tr.Method("No prediction", "none"), tr.Method("Standard")):
        a = ds.run_stack(batch, cpu_model.eval(), method, cfg)
        b = ds.run_stack(batch.to(device=device), dev_model.eval(), method, cfg)
        assert b.x.device.type == device
        assert torch.allclose(a.hindsight, b.hindsight.cpu(), atol=1e-6)
    # training on the device: the data stays on the CPU (in the model's float64), each batch moved
    # as it is drawn
    history = tr.train_stack(
        dev_model,
        data.train[:32].to(torch.float64),
        tr.Method("DiffStack", losses=(1, 1, 1)),
        cfg,
        epochs=1.0,
        log=None,
    )
    assert history and all(torch.isfinite(torch.tensor(h["loss"])) for h in history)
