"""Tests of data_synth.py (and lab/nuscenes.py's loader): the synthetic scenes and samples,
their statistics, the nuScenes format written and read back, bad files named, the cache, the plot,
the road geometry. Every test runs on one thread (conftest.py)."""

import json
import math
import os

import numpy as np
import pytest
import torch

import data_synth
from lab import nuscenes
import diffstack as ds
from lab import runs
from conftest import SYNTH_CFG, TINY


# ---------------------------------------------------------------------------------------------
# Data: synthetic scenes, the nuScenes format written and read (data_synth.py)
# ---------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def scenes_mixed():
    """Curved roads, straight roads with intersections, turns and cut-ins: every kind of
    geometry."""
    cfg = data_synth.SynthConfig(
        mix={"turn_across": 1.0, "cut_in": 1.0, "cross_yield": 1.0}, curved_prob=1.0
    )
    return data_synth.generate_scenes(6, cfg, seed=5), cfg


# ---------------------------------------------------------------------------------------------
# shapes and conventions (the fields of data_synth.Scenarios)


def test_scenarios_shapes_and_frame(small):
    b = small.train
    B, A, L = len(b), b.others_hist.shape[1], b.lanes.shape[1]
    expect = {
        "ego_hist": (B, 9, 4),
        "ego_fut": (B, 6, 4),
        "agent_hist": (B, 9, 4),
        "agent_hist_mask": (B, 9),
        "agent_fut": (B, 6, 4),
        "others_hist": (B, A, 9, 4),
        "others_fut": (B, A, 6, 4),
        "others_mask": (B, A),
        "others_is_ped": (B, A),
        "lanes": (B, L, 40, 3),
        "lanes_mask": (B, L, 40),
        "goal": (B, 4),
        "behaviour": (B,),
    }
    assert {k: tuple(v.shape) for k, v in b.tensors().items()} == expect
    assert (
        b.ego_hist.dtype == torch.float32
        and b.behaviour.dtype == torch.int64
        and b.lanes_mask.dtype == torch.bool
    )
    assert all(torch.isfinite(v).all() for v in b.tensors().values() if v.is_floating_point())
    assert torch.equal(b.ego_hist[:, -1, :3], torch.zeros(B, 3))  # ego frame at t0
    assert torch.equal(b.goal, b.ego_fut[:, -1])
    assert b.agent_hist_mask.all() and A > 0 and L > 0
    # padding is 0
    assert (b.others_hist[~b.others_mask] == 0).all() and (b.lanes[~b.lanes_mask] == 0).all()
    m = b.lanes_mask.long()
    assert (m[..., 1:] <= m[..., :-1]).all()  # valid lane points are a prefix
    gaps = torch.linalg.norm(b.lanes[..., 1:, :2] - b.lanes[..., :-1, :2], dim=-1)[
        b.lanes_mask[..., 1:]
    ]
    # 2 m apart along the lane (chords on tight turns)
    assert gaps.min() > 1.95 and gaps.max() < 2.0 + 1e-4
    assert set(b.behaviour.tolist()) <= set(range(len(data_synth.BEHAVIOURS)))
    # the ego's lane: some lane passes within 1 m of the ego, along its heading
    d = (
        torch.where(b.lanes_mask, torch.linalg.norm(b.lanes[..., :2], dim=-1), math.inf)
        .flatten(1)
        .min(1)
        .values
    )
    assert (d < 1.0).float().mean() > 0.95


def test_scenes_fields(scenes_mixed):
    s, cfg = scenes_mixed
    S, F = s.ego.shape[:2]
    assert F == 41 and s.agents.shape[:3] == s.agents_mask.shape and s.pred_idx.shape == (S, F)
    assert (
        (s.pred_idx[:, 8:35] == 0).all()
        and (s.pred_idx[:, :8] == -1).all()
        and (s.pred_idx[:, 35:] == -1).all()
    )
    assert s.ego.dtype == torch.float64 and len(s.names) == S
    # every route has points, padding none
    assert torch.equal(s.lanes_mask.any(-1), (s.routes >= 0).any(-1))
    # the predicted vehicle is present at every frame; the v channel is the backward-difference
    # speed
    assert s.agents_mask[:, 0].all()
    v = torch.linalg.norm(s.ego[:, 1:, :2] - s.ego[:, :-1, :2], dim=-1) / cfg.dt
    assert torch.allclose(s.ego[:, 1:, 3], v) and torch.equal(s.ego[:, 0, 3], s.ego[:, 1, 3])


# ---------------------------------------------------------------------------------------------
# determinism, statistics


def test_same_seed_same_data_other_seed_other_data():
    a, b, c = (data_synth.make_dataset(40, SYNTH_CFG, seed=s) for s in (1, 1, 2))
    for k, v in a.train.tensors().items():
        assert torch.equal(v, getattr(b.train, k)), k
    assert not torch.equal(a.train.ego_fut, c.train.ego_fut)


def test_statistics_plausible_and_planning_relevant():
    data = data_synth.make_dataset(1200, SYNTH_CFG, seed=0)
    st = data_synth.statistics(data_synth.Scenarios.cat([data.train, data.val]))
    assert all(st["plausible"].values()), data_synth.format_statistics(st)
    assert set(st["behaviour"]) == set(data_synth.BEHAVIOURS)  # the whole mix is there
    assert st["ego"]["speed"]["max"] <= 15.01 and st["ego"]["speed"]["p1"] >= 0
    # the active manoeuvres often hit a no-braking ego; the passive twins, far and behind agents
    # never do
    beh = st["behaviour"]
    assert (
        beh["cut_in"]["no_brake_conflict"] > 0.25 and beh["lead_brake"]["no_brake_conflict"] > 0.1
    )
    assert (
        beh["turn_across"]["no_brake_conflict"] > 0.02
        and beh["cross_go"]["no_brake_conflict"] > 0.02
    )
    for name in ("keep_lane", "lead_cruise", "go_straight", "cross_yield", "far", "behind"):
        assert beh[name]["no_brake_conflict"] == 0.0, name
    assert beh["far"]["min_dist_p50"] > 30 and beh["keep_lane"]["within_5m"] > 0.3


def test_mix_is_configurable():
    data = data_synth.make_dataset(60, data_synth.SynthConfig(mix={"lead_brake": 1.0}), seed=0)
    assert (data.train.behaviour == data_synth.BEHAVIOURS.index("lead_brake")).all()
    with pytest.raises(ValueError, match="unknown behaviours"):
        data_synth.generate_scenes(2, data_synth.SynthConfig(mix={"tailgate": 1.0}))


# ---------------------------------------------------------------------------------------------
# nuScenes round trip, bad input, skipped scenes


def _same_lanes(a, am, b, bm, tol):
    """Every lane of one sample has a twin in the other (the order of equidistant lanes may
    differ)."""
    for x, xm, y, ym in ((a, am, b, bm), (b, bm, a, am)):
        for lane, m in zip(x, xm):
            if m.any():
                assert any(
                    torch.equal(m, m2) and (lane - l2).abs().max() < tol for l2, m2 in zip(y, ym)
                )


def test_nuscenes_round_trip(tmp_path, scenes_mixed):
    scenes, cfg = scenes_mixed
    nuscenes.write_nuscenes(scenes, tmp_path, "v1.0-mini", cfg)
    loaded, report = nuscenes.load_nuscenes(tmp_path, "v1.0-mini", cfg)
    assert report == dict(
        scenes=6, loaded=6, skipped_short=0, skipped_no_lanes=0, skipped_no_agent=0, skipped=[]
    )
    assert torch.equal(loaded.pred_idx >= 0, scenes.pred_idx >= 0)
    for frame in (8, 21, 34):
        a = data_synth.sample_at(scenes, frame, cfg=cfg, dtype=torch.float64)
        b = data_synth.sample_at(loaded, frame, cfg=cfg, dtype=torch.float64)
        # exact up to float64 rounding
        for k in (
            "ego_hist",
            "ego_fut",
            "agent_hist",
            "agent_fut",
            "goal",
        ):
            assert (getattr(a, k) - getattr(b, k)).abs().max() < 1e-9, k
        A = a.others_mask.shape[1]
        assert torch.equal(a.others_mask, b.others_mask[:, :A]) and not b.others_mask[:, A:].any()
        assert (a.others_hist - b.others_hist[:, :A]).abs().max() < 1e-9
        assert (a.others_fut - b.others_fut[:, :A]).abs().max() < 1e-9
        assert torch.equal(a.others_is_ped, b.others_is_ped[:, :A])
        for i in range(len(scenes)):
            _same_lanes(a.lanes[i], a.lanes_mask[i], b.lanes[i], b.lanes_mask[i], 1e-9)
    # the float32 samples agree to float32 precision
    a32, b32 = data_synth.sample_at(scenes, 20, cfg=cfg), data_synth.sample_at(loaded, 20, cfg=cfg)
    assert (a32.ego_fut - b32.ego_fut).abs().max() < 1e-4 and a32.ego_fut.dtype == torch.float32


def test_writer_refuses_to_overwrite(tmp_path, scenes_mixed):
    scenes, cfg = scenes_mixed
    nuscenes.write_nuscenes(scenes[:2], tmp_path, cfg=cfg)
    with pytest.raises(FileExistsError, match="overwrite"):
        nuscenes.write_nuscenes(scenes[:2], tmp_path, cfg=cfg)
    nuscenes.write_nuscenes(scenes[:2], tmp_path, cfg=cfg, overwrite=True)


@pytest.fixture
def folder(tmp_path, scenes_mixed):
    scenes, cfg = scenes_mixed
    nuscenes.write_nuscenes(scenes[:3], tmp_path, cfg=cfg)
    return tmp_path


def test_bad_input_names_the_file(folder):
    (folder / "v1.0-mini" / "sample.json").unlink()
    with pytest.raises(nuscenes.NuScenesFormatError, match=r"sample\.json: missing"):
        nuscenes.load_nuscenes(folder)


def test_malformed_json_names_the_file(folder):
    (folder / "v1.0-mini" / "scene.json").write_text('[{"token": "x", ')
    with pytest.raises(ValueError, match=r"scene\.json: malformed JSON"):
        nuscenes.load_nuscenes(folder)


def test_missing_key_names_the_file(folder):
    path = folder / "v1.0-mini" / "ego_pose.json"
    poses = json.loads(path.read_text())
    del poses[4]["translation"]  # a CAM_FRONT pose (the writer alternates CAM_FRONT, LIDAR_TOP)
    path.write_text(json.dumps(poses))
    with pytest.raises(nuscenes.NuScenesFormatError, match=r"ego_pose\.json"):
        nuscenes.load_nuscenes(folder)


def test_missing_map_expansion_names_the_file(folder):
    loc = json.loads((folder / "v1.0-mini" / "log.json").read_text())[0]["location"]
    (folder / "maps" / "expansion" / f"{loc}.json").unlink()
    with pytest.raises(nuscenes.NuScenesFormatError, match=rf"expansion/{loc}\.json: missing"):
        nuscenes.load_nuscenes(folder)


def test_unknown_or_missing_version_folder(folder):
    with pytest.raises(nuscenes.NuScenesFormatError, match=r"v2\.0-beta: unknown version"):
        nuscenes.load_nuscenes(folder, "v2.0-beta")
    with pytest.raises(
        nuscenes.NuScenesFormatError,
        match=r"v1\.0-trainval: no such version folder \(found: \['v1\.0-mini",
    ):
        nuscenes.load_nuscenes(folder, "v1.0-trainval")


def test_skipped_scenes_are_counted(tmp_path, scenes_mixed):
    scenes, cfg = scenes_mixed
    s = data_synth.Scenes(
        **{k: v.clone() for k, v in scenes[:4].tensors().items()}, names=scenes.names[:4]
    )
    s.ego[1, :, :2] += 5000.0  # the ego drives far from its lanes: no lanes
    s.pred_idx[2] = -1  # nobody to predict
    nuscenes.write_nuscenes(s, tmp_path, cfg=cfg)
    path = tmp_path / "v1.0-mini" / "sample.json"
    samples = json.loads(path.read_text())
    first = json.loads((tmp_path / "v1.0-mini" / "scene.json").read_text())[0]["first_sample_token"]
    rec = next(r for r in samples if r["token"] == first)
    for _ in range(10):  # the first scene ends after 11 frames: too short for a 15-frame sample
        rec = next(r for r in samples if r["token"] == rec["next"])
    rec["next"] = ""
    path.write_text(json.dumps(samples))
    loaded, report = nuscenes.load_nuscenes(tmp_path, cfg=cfg)
    why = report.pop("skipped")
    assert report == dict(
        scenes=4, loaded=1, skipped_short=1, skipped_no_lanes=1, skipped_no_agent=1
    )
    assert loaded.names == [nuscenes.MINI_SCENES[3]]
    # each skipped scene is named with its reason and the file it comes from
    names = nuscenes.MINI_SCENES
    assert (
        why[0].startswith(f"{names[0]}: 11 samples in ")
        and "sample.json, a sample needs 15" in why[0]
    )
    assert why[1].startswith(f"{names[1]}: no lane of ") and "expansion" in why[1]
    assert why[2].startswith(f"{names[2]}: no vehicle in ") and "sample_annotation.json" in why[2]
    batch, report = nuscenes.load_nuscenes_scenarios(tmp_path, cfg=cfg)
    assert report["samples"] == len(batch) == 27 and report["samples_skipped_no_lanes"] == 0


def test_a_listed_scene_without_its_vehicle_is_refused(tmp_path, scenes_mixed):
    """The prediction split promises a vehicle to predict in each scene it lists: a listed scene
    whose entries name no annotated vehicle is refused (file, scene, entry), not skipped as if it
    had nobody to predict."""
    scenes, cfg = scenes_mixed
    nuscenes.write_nuscenes(scenes[:3], tmp_path, cfg=cfg)
    path = tmp_path / "maps" / "prediction" / "prediction_scenes.json"
    split = json.loads(path.read_text())
    name = nuscenes.MINI_SCENES[1]
    assert split[name]  # (the writer lists it)
    split[name] = ["nosuchinstance_" + e.split("_")[1] for e in split[name]]
    path.write_text(json.dumps(split))
    with pytest.raises(
        nuscenes.NuScenesFormatError,
        match=rf"prediction_scenes\.json: scene '{name}' is listed "
        r"\(first entry 'nosuchinstance_\w+'\) but .*sample_annotation\.json has no vehicle",
    ):
        nuscenes.load_nuscenes(tmp_path, cfg=cfg)


def test_loader_without_split_takes_the_closest_moving_vehicle(tmp_path, scenes_mixed):
    scenes, cfg = scenes_mixed
    nuscenes.write_nuscenes(scenes[:2], tmp_path, cfg=cfg)
    (tmp_path / "maps" / "prediction" / "prediction_scenes.json").unlink()
    loaded, _ = nuscenes.load_nuscenes(tmp_path, cfg=cfg)
    for i in range(2):
        for f in range(8, 35):
            p = int(loaded.pred_idx[i, f])
            if p < 0:
                continue
            assert not loaded.agents_is_ped[i, p] and loaded.agents_mask[i, p, f : f + 7].all()
            gap = loaded.agents[i, :, f : f + 7, :2] - loaded.ego[i, None, f : f + 7, :2]
            d = torch.linalg.norm(gap, dim=-1).min(1).values
            window = loaded.agents[i, :, f - 8 : f + 7, :2]
            # all observed here
            moved = torch.linalg.norm(window - window[:, :1], dim=-1).max(1).values
            ok = (
                ~loaded.agents_is_ped[i]
                & loaded.agents_mask[i, :, f - 8 : f + 7].all(1)
                & (moved >= 1.0)
            )
            assert d[p] <= d[ok].min() + 1e-9


# ---------------------------------------------------------------------------------------------
# batches, closed-loop cutting, cache, plot


def test_scenarios_indexing_cat_and_to(small):
    b = small.train
    assert (
        len(b[2:5]) == 3
        and len(b[torch.tensor([0, 3])]) == 2
        and len(b[b.behaviour == b.behaviour[0]]) >= 1
    )
    assert torch.equal(b[torch.tensor([3])].goal, b.goal[3:4])
    few = b[:2]
    few = data_synth.Scenarios(
        **{
            **few.tensors(),
            "others_hist": few.others_hist[:, :1],
            "others_fut": few.others_fut[:, :1],
            "others_mask": few.others_mask[:, :1],
            "others_is_ped": few.others_is_ped[:, :1],
            "lanes": few.lanes[:, :1],
            "lanes_mask": few.lanes_mask[:, :1],
        }
    )
    cat = data_synth.Scenarios.cat([few, b[2:4]])
    assert len(cat) == 4 and cat.others_hist.shape[1] == b.others_hist.shape[1]
    assert cat.lanes.shape[1] == b.lanes.shape[1]
    assert not cat.others_mask[:2, 1:].any() and (cat.others_hist[:2, 1:] == 0).all()
    assert not cat.lanes_mask[:2, 1:].any()
    assert torch.equal(cat.others_hist[2:], b.others_hist[2:4])
    b64 = b.to(torch.float64)
    assert b64.lanes.dtype == torch.float64 and b64.lanes_mask.dtype == torch.bool
    assert b64.behaviour.dtype == torch.int64


def test_sample_at_with_a_simulated_ego(scenes_mixed):
    scenes, cfg = scenes_mixed
    logged = data_synth.sample_at(scenes, 20, cfg=cfg, dtype=torch.float64)
    state = scenes.ego[:, 20].clone()
    h = state[:, 2]
    state[:, 0] += torch.cos(h) + 0.5 * -torch.sin(h)  # 1 m ahead and 0.5 m to the left of the log
    state[:, 1] += torch.sin(h) + 0.5 * torch.cos(h)
    sim = data_synth.sample_at(scenes, 20, ego_state=state, cfg=cfg, dtype=torch.float64)
    assert torch.allclose(
        sim.ego_hist[:, -1, :3], torch.zeros(len(scenes), 3, dtype=torch.float64), atol=1e-12
    )
    shift = torch.tensor([1.0, 0.5], dtype=torch.float64)
    # the goal stays the logged ego's
    assert torch.allclose(sim.goal[:, :2], logged.goal[:, :2] - shift)
    assert torch.allclose(sim.agent_fut[..., :2], logged.agent_fut[..., :2] - shift)
    hist = scenes.ego[:, 12:21].clone()
    hist[:, -1] = state
    full = data_synth.sample_at(scenes, 20, ego_state=hist, cfg=cfg, dtype=torch.float64)
    assert torch.allclose(full.ego_hist, sim.ego_hist)
    with pytest.raises(ValueError, match="ego_state"):
        data_synth.sample_at(scenes, 20, ego_state=state[:, :3], cfg=cfg)
    with pytest.raises(ValueError, match="frames must be in"):
        data_synth.sample_at(scenes, 35, cfg=cfg)


def test_an_occluded_history_frame_leaves_a_usable_sample(scenes_mixed):
    """A real track can miss a frame in the middle of the history: the sample keeps the unbroken run
    of observed steps that ends at t0 (a prefix mask, as check_batch requires), and the predictor
    runs on it."""
    scenes, cfg = scenes_mixed
    f0 = 20
    pred = scenes.pred_idx[:, f0]
    mask = scenes.agents_mask.clone()
    ar = torch.arange(len(scenes))
    mask[ar, pred, f0 - 3] = False  # occluded 1.5 s before t0
    gap = data_synth.Scenes(**{**scenes.tensors(), "agents_mask": mask, "names": scenes.names})
    b = data_synth.sample_at(gap, f0, cfg=cfg)
    H = cfg.hist
    want = torch.zeros(len(scenes), H + 1, dtype=torch.bool)
    want[:, H - 2 :] = True  # the 3 steps after the gap (t0 - 1 s .. t0)
    assert torch.equal(b.agent_hist_mask, want & scenes.agents_mask[ar, pred, f0 - H : f0 + 1])
    model = ds.Predictor(ds.Config(**TINY))
    pred_out = model.eval()(b, use_posterior=False)
    assert torch.isfinite(pred_out.states).all()


def test_cache_round_trip_and_foreign_file(tmp_path):
    a = data_synth.load_or_generate(30, seed=3, cache_dir=tmp_path)
    (path,) = tmp_path.glob("scenarios-*.pt")
    b = data_synth.load_or_generate(30, seed=3, cache_dir=tmp_path)
    assert torch.equal(a.train.lanes, b.train.lanes) and torch.equal(
        a.val_scenes.ego, b.val_scenes.ego
    )
    assert b.val_scenes.names == a.val_scenes.names and len(a.train) + len(a.val) == 30
    path.write_bytes(b"not a cache")
    with pytest.raises(ValueError, match=path.name):
        data_synth.load_or_generate(30, seed=3, cache_dir=tmp_path)
    assert path.read_bytes() == b"not a cache"  # never overwritten


def test_a_tampered_cache_read_directly_is_refused_in_one_line(tmp_path):
    """load_or_generate itself (not only lab.data) refuses a cache holding objects other than
    tensors: one line naming the file, and neither it nor its traceback repeats torch's advice to
    load it with weights_only=False (which would run the payload)."""
    import pickle
    import traceback

    class Payload:
        def __reduce__(self):
            return (os.getcwd, ())

    path = data_synth._cache_path(30, 3, data_synth.SynthConfig(), tmp_path)[0]
    path.write_bytes(pickle.dumps(Payload()))
    with pytest.raises(ValueError) as e:
        data_synth.load_or_generate(30, seed=3, cache_dir=tmp_path)
    assert str(e.value).startswith(f"{path}: not a valid data_synth cache")
    assert "\n" not in str(e.value)
    assert "weights_only" not in "".join(traceback.format_exception(e.value))


def test_plot_scenario_draws_everything(small):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots()
    data_synth.plot_scenario(ax, small.train, 0)
    n_lanes = int(small.train.lanes_mask[0].any(-1).sum())
    n_others = int(small.train.others_mask[0].sum())
    assert len(ax.lines) >= n_lanes + 2 * n_others + 5 and len(ax.patches) >= 2
    assert ax.get_title() == data_synth.BEHAVIOURS[int(small.train.behaviour[0])]
    plt.close(fig)


# ---------------------------------------------------------------------------------------------
# geometry


def test_arcline_geometry():
    # a left quarter circle of radius 10 from the origin heading +x ends at (10, 10) heading +y,
    # points on the circle
    p = np.array([[0.0, 0.0, 0.0, 10.0, 5 * math.pi, 0.0, 0.0, 1, 0, 1]])
    segs = data_synth.arcline_segments(p)
    pts, mask = data_synth.discretize(segs, 2.0)
    assert mask.sum() == 8  # 15.7 m: points at 0, 2, ..., 14
    assert np.allclose(np.linalg.norm(pts[mask][:, :2] - [0, 10], axis=-1), 10)
    end, _ = data_synth.pose_along(segs[0], np.array([5 * math.pi]))
    assert np.allclose(end[0], [10, 10, math.pi / 2])
    # arc then straight (shape LSR with lengths [arc, 5, 0]): the straight continues north; past the
    # end it extends
    p2 = np.array([[0.0, 0.0, 0.0, 10.0, 5 * math.pi, 5.0, 0.0, 1, 0, -1]])
    ends, _ = data_synth.pose_along(
        data_synth.arcline_segments(p2)[0], np.array([5 * math.pi + 5, 5 * math.pi + 7])
    )
    assert np.allclose(ends, [[10, 15, math.pi / 2], [10, 17, math.pi / 2]])
    # the road frame round trip, straight and curved
    for kappa in (0.0, 1 / 150, -1 / 300):
        s, d = np.array([-40.0, 0.0, 120.0]), np.array([-5.25, 1.75, 8.0])
        x, y, _ = data_synth.frenet_to_xy(s, d, kappa)
        s2, d2 = data_synth.xy_to_frenet(x, y, kappa)
        assert np.allclose(s2, s) and np.allclose(d2, d)


def test_backward_speed_with_gaps():
    xy = np.array([[0, 0], [1, 0], [0, 0], [4, 0], [5, 0]], float)
    mask = np.array([True, True, False, True, True])
    v = data_synth.backward_speed(xy, mask, np.arange(5) * 0.5)
    # first copies the second; the gap spans 1 s
    assert np.allclose(v[[0, 1, 3, 4]], [2.0, 2.0, 3.0, 2.0])


# ---- the nuScenes folder is written whole ----------------------------------------------------


def _tree(root):
    return {
        str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()
    }


def test_an_interrupted_overwrite_leaves_the_old_folder(tmp_path, scenes_mixed, monkeypatch):
    scenes, cfg = scenes_mixed
    root = tmp_path / "nusc"
    nuscenes.write_nuscenes(scenes[:2], root, cfg=cfg)
    before = _tree(root)
    dump = nuscenes._dump
    calls = []

    def interrupted(obj, path):
        calls.append(path)
        if len(calls) == 3:
            raise KeyboardInterrupt  # Ctrl-C, mid-write
        dump(obj, path)

    monkeypatch.setattr(nuscenes, "_dump", interrupted)
    with pytest.raises(KeyboardInterrupt):
        nuscenes.write_nuscenes(scenes[:3], root, cfg=cfg, overwrite=True)
    assert _tree(root) == before  # the old folder, whole
    assert sorted(p.name for p in tmp_path.iterdir()) == [".nusc.lock", "nusc"]  # no temporary


def test_a_killed_writer_leaves_the_old_folder_and_the_next_one_cleans_up(tmp_path, scenes_mixed):
    import signal
    import subprocess
    import sys

    scenes, cfg = scenes_mixed
    root = tmp_path / "nusc"
    nuscenes.write_nuscenes(scenes[:2], root, cfg=cfg)
    before = _tree(root)
    code = (
        "import sys, time, data_synth\nfrom lab import nuscenes\n"
        "dump = nuscenes._dump\n"
        "def slow(obj, path):\n"
        "    dump(obj, path); print('wrote', flush=True); time.sleep(60)\n"
        "nuscenes._dump = slow\n"
        "nuscenes.write_nuscenes(data_synth.generate_scenes(2, seed=1), sys.argv[1], "
        "overwrite=True)\n"
    )
    writer = subprocess.Popen(
        [sys.executable, "-c", code, str(root)],
        cwd=os.path.dirname(data_synth.__file__),
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert writer.stdout.readline().strip() == "wrote"  # one file written, mid-way
        # a second writer meanwhile is refused: the target is locked
        with pytest.raises(runs.OutputRefused, match="another run is writing here"):
            nuscenes.write_nuscenes(scenes[:2], root, cfg=cfg, overwrite=True)
        writer.send_signal(signal.SIGKILL)
    finally:
        writer.kill()
        writer.wait()
    assert _tree(root) == before
    assert [p.name for p in tmp_path.glob(".nusc.writing-*")]  # its temporary folder, left
    nuscenes.write_nuscenes(scenes[:3], root, cfg=cfg, overwrite=True)
    assert not list(tmp_path.glob(".nusc.writing-*")) and _tree(root) != before


def test_a_folder_with_files_of_its_own_is_never_replaced(tmp_path, scenes_mixed):
    scenes, cfg = scenes_mixed
    root = tmp_path / "nusc"
    nuscenes.write_nuscenes(scenes[:2], root, cfg=cfg)
    (root / "notes.txt").write_text("mine")
    with pytest.raises(FileExistsError, match=r"notes.txt is no file of what it writes"):
        nuscenes.write_nuscenes(scenes[:2], root, cfg=cfg, overwrite=True)
    assert (root / "notes.txt").read_text() == "mine"
