"""Shared by every test file: each test runs on one torch thread; `lock_held_elsewhere`; the small
configs, batches and data sets the tests build on (imported as `from conftest import ...`)."""

import contextlib
import dataclasses
import math
import os
import signal
import subprocess
import sys
from dataclasses import dataclass, fields

import pytest
import torch

import data_synth
import diffstack as ds


@pytest.fixture(autouse=True)
def one_thread():
    """Tiny models gain nothing from threads, and two threads on a busy 2-core machine can run
    10x slower."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture
def lock_held_elsewhere():
    """hold(folder, command): a context in which another process holds runs.folder_lock(folder,
    command) (yields that process); leaving it kills the holder (SIGKILL), as a crashed run."""

    @contextlib.contextmanager
    def hold(folder, command):
        holder = subprocess.Popen(
            [
                sys.executable,
                "-c",
                "import sys, time\nfrom lab import runs\n"
                "with runs.folder_lock(sys.argv[1], sys.argv[2]):\n "
                "print('held', flush=True); time.sleep(60)",
                str(folder),
                command,
            ],
            cwd=os.path.dirname(os.path.abspath(__file__)),
            stdout=subprocess.PIPE,
            text=True,
        )
        try:
            assert holder.stdout.readline().strip() == "held"
            yield holder
        finally:
            holder.send_signal(signal.SIGKILL)
            holder.wait()

    return hold


DT = 0.5  # the paper's time step (s)
# a predictor small enough for finite differences and quick trainings
TINY = dict(pred_modes=5, pred_dec_hidden=16, pred_enc_hidden=8, pred_latent_hidden=8)


# ---------------------------------------------------------------------------------------------
# A stand-in for data_synth.Scenarios: the exact field names and shapes of data_synth.Scenarios,
# with plausible agents (unicycle motion whose manoeuvre starts 1 s before t0, so history hints at
# it).
# ---------------------------------------------------------------------------------------------


@dataclass
class FakeScenarios:
    ego_hist: torch.Tensor
    ego_fut: torch.Tensor
    agent_hist: torch.Tensor
    agent_hist_mask: torch.Tensor
    agent_fut: torch.Tensor
    others_hist: torch.Tensor
    others_fut: torch.Tensor
    others_mask: torch.Tensor
    others_is_ped: torch.Tensor
    lanes: torch.Tensor
    lanes_mask: torch.Tensor
    goal: torch.Tensor
    behaviour: torch.Tensor

    def __len__(self):
        return len(self.ego_hist)

    def __getitem__(self, idx):
        return FakeScenarios(*[getattr(self, f.name)[idx] for f in fields(self)])

    def replace(self, **kw):
        d = {f.name: getattr(self, f.name) for f in fields(self)}
        d.update(kw)
        return FakeScenarios(**d)

    @staticmethod
    def cat(items):
        return FakeScenarios(
            *[torch.cat([getattr(b, f.name) for b in items]) for f in fields(FakeScenarios)]
        )


def make_batch(B=32, A=4, seed=0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)

    def rnd(*s):
        return torch.rand(*s, generator=g, dtype=dtype)

    behaviour = torch.randint(0, 4, (B,), generator=g)
    w = torch.tensor([0.0, 0.25, -0.25, 0.0], dtype=dtype)[behaviour]
    a = torch.tensor([0.0, 0.0, 0.0, -1.5], dtype=dtype)[behaviour]
    s = torch.stack(
        [5 + 20 * rnd(B), -10 + 20 * rnd(B), math.pi * (2 * rnd(B) - 1), 3 + 7 * rnd(B)], -1
    )
    states = [s]
    for t in range(14):
        u = torch.stack([w, a], -1) * (t >= 6)
        s = ds.unicycle_step(states[-1], u, DT)
        s = torch.stack([s[:, 0], s[:, 1], s[:, 2], s[:, 3].clamp(min=0)], -1)
        states.append(s)
    traj = torch.stack(states, 1)  # (B, 15, 4), t0 at index 8
    # the ego drives along +x through the origin at t0
    ve = 4 + 6 * rnd(B, 1)
    tt = DT * torch.arange(-8, 7, dtype=dtype)
    ego = torch.stack([ve * tt, 0 * tt.expand(B, -1), 0 * tt.expand(B, -1), ve.expand(-1, 15)], -1)
    # other agents: constant velocity, some padding, some pedestrians
    o0 = torch.stack(
        [60 * rnd(B, A) - 30, 60 * rnd(B, A) - 30, math.pi * (2 * rnd(B, A) - 1), 8 * rnd(B, A)], -1
    )
    vel = torch.stack([o0[..., 3] * torch.cos(o0[..., 2]), o0[..., 3] * torch.sin(o0[..., 2])], -1)
    pos = o0[..., None, :2] + tt[:, None] * vel[..., None, :]  # (B, A, 15, 2)
    others = torch.cat([pos, o0[..., None, 2:].expand(-1, -1, 15, -1)], -1)
    others_mask = rnd(B, A) < 0.7
    others = others * others_mask[..., None, None]
    return FakeScenarios(
        ego_hist=ego[:, :9],
        ego_fut=ego[:, 9:],
        agent_hist=traj[:, :9],
        agent_hist_mask=torch.ones(B, 9, dtype=torch.bool),
        agent_fut=traj[:, 9:],
        others_hist=others[:, :, :9],
        others_fut=others[:, :, 9:],
        others_mask=others_mask,
        others_is_ped=rnd(B, A) < 0.3,
        lanes=torch.zeros(B, 1, 40, 3, dtype=dtype),
        lanes_mask=torch.zeros(B, 1, 40, dtype=torch.bool),
        goal=ego[:, -1],
        behaviour=behaviour,
    )


def small_cfg(**kw):
    return ds.Config(**{"pred_modes": 5, "pred_dec_hidden": 16, "batch_size": 16, **kw})


def make_model(cfg, seed=0):
    torch.manual_seed(seed)
    return ds.Predictor(cfg).double()


# ---------------------------------------------------------------------------------------------
# Synthetic data, shared with test_train.py and test_data_synth.py
# ---------------------------------------------------------------------------------------------

SYNTH_CFG = data_synth.SynthConfig()


def small_dataset():
    """120 synthetic samples: what the fixture `small` of each test file holds."""
    return data_synth.make_dataset(120, SYNTH_CFG, seed=0)


@pytest.fixture(scope="module")
def small():
    return small_dataset()


@pytest.fixture(scope="module")
def batch():
    """8 validation samples of the default generator (seed 5): bad-input tests corrupt them."""
    return data_synth.make_dataset(120, seed=5).val[:8]


def cast(batch, dtype):
    fields = {f.name: getattr(batch, f.name) for f in dataclasses.fields(batch)}
    return dataclasses.replace(
        batch,
        **{
            k: v.to(dtype)
            for k, v in fields.items()
            if torch.is_tensor(v) and v.is_floating_point()
        },
    )


def cli_error(main, argv, capsys) -> str:
    """Run a CLI that must refuse argv: exit code 2, and the message on stderr."""
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2
    return capsys.readouterr().err


def launcher_env(monkeypatch, **env):
    for k in ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT"):
        monkeypatch.delenv(k, raising=False)
    monkeypatch.delenv("TORCHELASTIC_RUN_ID", raising=False)
    for k, v in env.items():
        monkeypatch.setenv(k, v)
