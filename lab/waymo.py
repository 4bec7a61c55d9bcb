"""Three real driving scenes, Waymo Open Motion Dataset logs of the metadrive-simulator wheel:
fetched into the git-ignored <cache>/waymo/ (their licence), read by a whitelisting unpickler."""

from __future__ import annotations

import dataclasses
import functools
import math
import pickle
import shutil
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

import data_synth as ds
from data_synth import MAX_LANE_POINTS, Scenarios, Scenes, SynthConfig
from lab.nuscenes import Reading, choose_predicted, routes_through, scene_of, sha256_of
from lab.runs import write_file_atomic

WAYMO_WHEEL = "metadrive-simulator==0.3.0.1"
WAYMO_WHEEL_FILE = "metadrive_simulator-0.3.0.1-py3-none-any.whl"
WAYMO_WHEEL_BYTES = 61_566_390
WAYMO_WHEEL_SHA256 = "04f10b014043a56ffa7780eb82239a65c1cec55887cb98010c86fbf98c0460bc"
_IN_WHEEL = "metadrive/assets/waymo/"
WAYMO_PICKLES = {  # member of the wheel -> its sha256 (also in the wheel's RECORD)
    _IN_WHEEL + "0.pkl": "d11856cdc81285cd8b23566d4363f5f4912bcc7da4760ba0af4613e827e36bf3",
    _IN_WHEEL + "1.pkl": "e0b79e64d0b413317d9d3d17c92de3b1dcef6d15510170a264ba599308d90089",
    _IN_WHEEL + "2.pkl": "505939e3e3bac02b96cca3bde2cd44ba8d567577ea0c8867558187886893d2cf",
}
WAYMO_LICENCE = (
    "Waymo Open Motion Dataset scenes (from the metadrive-simulator 0.3.0.1 wheel), under the "
    "Waymo Open Dataset licence (non-commercial use only): never commit them or anything derived "
    "from them (figures, per-scene numbers that reveal the geometry)"
)
WAYMO_AGENT_TYPES = {1: "vehicle", 2: "pedestrian", 3: "cyclist"}  # (0 unset, 4 other: dropped)
WAYMO_PHASES = 5  # a 10 Hz log gives five 2 Hz clocks: every 5th frame from frame 0, 1, .., 4
WAYMO_CANDIDATE_LANES = 48  # the nearest lanes sample_at hands distinct_lanes per sample
_ENUMS = ("AgentType", "RoadLineType", "RoadEdgeType")
_BUILTINS = "dict list tuple set frozenset int float complex bool str bytes bytearray".split()


class WaymoFormatError(ValueError):
    """A Waymo scenario pickle that cannot be read; the message starts with the offending file."""


class WaymoForbiddenClass(WaymoFormatError, pickle.UnpicklingError):
    """A pickle referenced a global outside the unpickler's whitelist (named); nothing ran."""


class WaymoDownloadError(OSError):
    """The wheel could not be downloaded (no network, no registry): the tests skip on this alone."""


# the stand-in for the writer's enums: the class name ('AgentType', ...) and the value
WaymoEnum = NamedTuple("WaymoEnum", [("kind", str), ("value", int)])


def _enum(kind: str, value) -> WaymoEnum:
    if type(value) is not int:
        raise WaymoFormatError(f"{kind}: an enum value must be an int, got {value!r}")
    return WaymoEnum(kind, value)


class _WaymoUnpickler(pickle.Unpickler):
    """A pickle.Unpickler that resolves the whitelisted globals only (WaymoForbiddenClass)."""

    def find_class(self, module, name):
        if module == "builtins" and name in _BUILTINS:
            return getattr(__import__("builtins"), name)
        if module in ("numpy.core.multiarray", "numpy._core.multiarray") and name == "_reconstruct":
            return (np._core if hasattr(np, "_core") else np.core).multiarray._reconstruct
        if module == "numpy" and name in ("ndarray", "dtype"):
            return getattr(np, name)
        if module == "__main__" and name in _ENUMS:
            return functools.partial(_enum, name)
        why = "which is not on the whitelist (builtins, numpy arrays, the enums); nothing ran"
        raise WaymoForbiddenClass(f"the pickle references {module}.{name}, {why}")


def load_waymo_pickle(path) -> dict:
    """One scenario pickle, read by _WaymoUnpickler."""
    try:
        with open(path, "rb") as f:
            return _WaymoUnpickler(f).load()
    except OSError:
        raise
    except WaymoFormatError as e:  # (the unpickler's, naming the file here)
        raise type(e)(f"{path}: {e}") from None
    except Exception as e:  # a truncated or corrupt pickle raises many kinds
        raise WaymoFormatError(f"{path}: not a readable pickle ({type(e).__name__}: {e})") from e


def _pip_download(requirement: str, dest: Path) -> None:
    """`pip download` of one wheel (a wheel only: an sdist would run setup code)."""
    options = "--no-deps --only-binary=:all: --no-cache-dir --disable-pip-version-check --quiet"
    cmd = [sys.executable, "-m", "pip", "download", *options.split(), "--dest", dest, requirement]
    try:
        run = subprocess.run(cmd, capture_output=True, text=True, timeout=900)
    except (OSError, subprocess.TimeoutExpired) as e:
        raise WaymoDownloadError(f"pip download {requirement}: {e}") from e
    if run.returncode != 0:
        tail = " | ".join((run.stderr or run.stdout).strip().splitlines()[-3:])
        raise WaymoDownloadError(f"pip download {requirement} failed ({run.returncode}): {tail}")


def waymo_paths(cache_dir="data_cache") -> list:
    """Where fetch_waymo keeps the three pickles: <cache_dir>/waymo/<k>.pkl."""
    return [Path(cache_dir) / "waymo" / Path(m).name for m in WAYMO_PICKLES]


def _extract(z: zipfile.ZipFile, member: str, out) -> None:
    with z.open(member) as src, open(out, "wb") as dst:
        shutil.copyfileobj(src, dst)
    if (got := sha256_of(out)) != (want := WAYMO_PICKLES[member]):
        raise ValueError(f"{WAYMO_WHEEL_FILE}: {member} has sha256 {got}, expected {want}")


def fetch_waymo(cache_dir="data_cache", log=print) -> list:
    """The three pickles in <cache_dir>/waymo/, sha256 checked; the first call downloads the wheel
    beside them, checks it and extracts them by name: a failure leaves no pickle."""
    paths = waymo_paths(cache_dir)
    if all(p.is_file() for p in paths):
        for p, want in zip(paths, WAYMO_PICKLES.values()):
            if (got := sha256_of(p)) != want:
                raise ValueError(f"{p}: sha256 {got} differs from the expected {want}; delete it")
        return paths
    folder = paths[0].parent
    folder.mkdir(parents=True, exist_ok=True)
    log(f"fetching {WAYMO_WHEEL} ({WAYMO_WHEEL_BYTES / 1e6:.1f} MB) into {folder}: {WAYMO_LICENCE}")
    with tempfile.TemporaryDirectory(prefix=".fetch-", dir=folder) as tmp:
        _pip_download(WAYMO_WHEEL, Path(tmp))
        wheel = Path(tmp) / WAYMO_WHEEL_FILE
        if not wheel.is_file():
            raise WaymoDownloadError(f"pip download {WAYMO_WHEEL} left no {WAYMO_WHEEL_FILE}")
        size, got = wheel.stat().st_size, sha256_of(wheel)
        if (size, got) != (WAYMO_WHEEL_BYTES, WAYMO_WHEEL_SHA256):
            want = f"{WAYMO_WHEEL_BYTES:,} bytes, sha256 {WAYMO_WHEEL_SHA256}"
            raise ValueError(f"{WAYMO_WHEEL_FILE}: {size:,} bytes, sha256 {got}, expected {want}")
        try:
            with zipfile.ZipFile(wheel) as z:
                for member, path in zip(WAYMO_PICKLES, paths):
                    write_file_atomic(path, functools.partial(_extract, z, member))
        except (zipfile.BadZipFile, KeyError) as e:
            raise ValueError(f"{WAYMO_WHEEL_FILE}: cannot extract the Waymo pickles ({e})") from e
    log(f"  {', '.join(p.name for p in paths)} verified (sha256) and kept in {folder}/")
    return paths


def _array(d: dict, key: str, tail: tuple) -> np.ndarray:
    """d[key] as a float64 array (n >= 1, *tail) of finite numbers."""
    a = np.asarray(d[key], dtype=np.float64)
    if a.ndim != 1 + len(tail) or a.shape[1:] != tail or not len(a) or not np.isfinite(a).all():
        raise ValueError(f"{key}: must be finite numbers of shape (n, *{tail}), got {a.shape}")
    return a


def _read_log(path, cfg: SynthConfig) -> tuple:
    """A log's timestamps, frames per 2 Hz step, tracks' states and types, the ego's id, lanes."""
    raw = load_waymo_pickle(path)
    with Reading(path, WaymoFormatError) as r:
        ts = _array(raw, "ts", ())
        if len(ts) < 2 or not (np.diff(ts) > 0).all():
            raise ValueError("ts: must hold at least 2 increasing timestamps (s)")
        stride = cfg.dt / float(np.median(np.diff(ts)))  # 10 Hz logs, 2 Hz samples: 5
        if abs(stride - round(stride)) > 0.05 or round(stride) < 1:
            raise ValueError(f"ts: the log's clock does not divide the samples' dt = {cfg.dt} s")
        states, kinds, ego_id = {}, {}, raw["sdc_index"]
        for tid, tr in raw["tracks"].items():
            r.name, r.rec = f"track {tid!r}", tr
            st = _array(tr, "state", (10,))
            if len(st) != len(ts) or not np.isin(st[:, 9], (0.0, 1.0)).all():
                raise ValueError("state: must have a row per timestamp, its valid column 0 or 1")
            if tid == ego_id or tr["type"].value in WAYMO_AGENT_TYPES:
                states[tid], kinds[tid] = st, tr["type"].value
        lanes = {}
        for fid, feat in raw["map"].items():
            if isinstance(feat, dict) and feat.get("type") == "center_lane":
                r.name, r.rec = f"map feature {fid!r}", feat
                lanes[fid] = (_array(feat, "polyline", (3,))[:, :2], list(feat["exit"]))
        if ego_id not in states:
            raise ValueError(f"sdc_index: {ego_id!r} is not a track id (it names the ego's track)")
    return ts, round(stride), states, kinds, ego_id, lanes


def waymo_scenes(paths, phases=(0,), cfg: SynthConfig | None = None) -> tuple[Scenes, dict]:
    """Waymo pickles -> Scenes at 2 Hz, one per (file, phase p: every 5th frame from frame p); a bad
    file is a WaymoFormatError naming the file, the track or map feature, and the field."""
    cfg = cfg or SynthConfig()
    if not phases or any(type(p) is not int or not 0 <= p < WAYMO_PHASES for p in phases):
        raise ValueError(f"phases: whole numbers in 0..{WAYMO_PHASES - 1}, got {phases!r}")
    out, report = [], dict(files=len(paths), scenes=0, skipped_no_lanes=0, skipped_no_agent=0)
    for path in paths:
        log = _read_log(path, cfg)
        out += [s for p in phases if (s := _waymo_scene(path, log, p, cfg, report)) is not None]
    if not out:
        raise WaymoFormatError(f"{', '.join(map(str, paths))}: no usable scene ({report})")
    report["scenes"] = len(out)
    return Scenes.cat(out), report


def _waymo_scene(path, log: tuple, phase: int, cfg: SynthConfig, report: dict) -> Scenes | None:
    """One (file, phase) as Scenes; None (counted) without lanes or a vehicle to predict."""
    ts, stride, states, kinds, ego_id, lanes = log
    frames = np.arange(phase, len(ts), stride)  # (F,) the 2 Hz frames
    t, F = ts[frames] - ts[frames[0]], len(frames)
    ego_state = states[ego_id][frames]  # (F, 10)
    if not ego_state[:, 9].all():
        raise WaymoFormatError(f"{path}: the ego's track {ego_id!r} is not valid at every frame")
    ego = np.c_[ego_state[:, [0, 1]], ds.wrap_angle(ego_state[:, 6]), np.zeros(F)]  # (F, 4)
    ego[:, 3] = ds.backward_speed(ego[:, :2], np.ones(F, bool), t)
    ids = [tid for tid in states if tid != ego_id and states[tid][frames, 9].any()]
    st = np.stack([states[tid][frames] for tid in ids]) if ids else np.zeros((0, F, 10))
    amask = st[..., 9] > 0.5  # (M, F)
    agents = st[..., [0, 1, 6, 6]]  # x, y, heading, speed (below)
    agents[..., 2] = ds.wrap_angle(agents[..., 2])
    agents[..., 3] = ds.backward_speed(agents[..., :2], amask, t) * amask
    agents *= amask[..., None]  # Waymo fills unobserved steps with placeholders; ours are 0
    is_ped = np.array([WAYMO_AGENT_TYPES[kinds[tid]] == "pedestrian" for tid in ids], bool)
    # the box at each track's first observed frame: width, length, height
    size = st[np.arange(len(ids)), np.argmax(amask, 1)][:, [4, 3, 5]] if ids else np.zeros((0, 3))
    tracks = dict(agents=agents, agents_mask=amask, agents_is_ped=is_ped, agents_size=size)
    lane_pts, lane_mask = _waymo_lanes(path, lanes, ego, cfg)
    if lane_pts is None:
        report["skipped_no_lanes"] += 1
        return None
    pred = choose_predicted(ego, tracks, ids, None, False, set(), cfg)
    if (pred < 0).all():
        report["skipped_no_agent"] += 1
        return None
    no_paths = dict(paths=np.zeros((0, 10), np.float32), paths_is_connector=np.zeros(0, bool))
    lanes = dict(lanes=lane_pts, lanes_mask=lane_mask, routes=np.full((len(lane_pts), 0), -1))
    name = f"waymo-{Path(path).stem}-phase{phase}"
    return scene_of(name, ego=ego, pred_idx=pred, **tracks, **lanes, **no_paths)


def _waymo_lanes(path, lanes: dict, ego, cfg: SynthConfig) -> tuple:
    """The lanes near the ego's path chained into routes, resampled: points (L, P, 3), mask."""
    ids = list(lanes)
    index = {fid: k for k, fid in enumerate(ids)}
    nxt = [[index[e] for e in lanes[fid][1] if e in index] for fid in ids]
    prv = [[k for k, succ in enumerate(nxt) if j in succ] for j in range(len(ids))]
    dist = [np.linalg.norm(lanes[fid][0][:, None] - ego[None, :, :2], axis=-1) for fid in ids]
    near = [k for k, d in enumerate(dist) if (d < cfg.map_radius).any()]
    graph = dict(next=nxt, prev=prv)
    routes = [np.concatenate([lanes[ids[k]][0] for k in r]) for r in routes_through(graph, near)]
    polys = [p for r in routes if (p := _resample(r, cfg.lane_spacing)) is not None]
    if not polys:
        return None, None
    P = max(len(p) for p in polys)
    if P > MAX_LANE_POINTS:
        raise WaymoFormatError(f"{path}: a route of {P} points, more than MAX_LANE_POINTS")
    pts, mask = np.zeros((len(polys), P, 3)), np.zeros((len(polys), P), bool)
    for k, p in enumerate(polys):
        pts[k, : len(p)], mask[k, : len(p)] = p, True
    return pts, mask


def _resample(xy, spacing: float):
    """Points (P, 3: x, y, heading) every `spacing` m along a polyline (N, 2); None if no length."""
    xy = xy[np.r_[True, np.linalg.norm(np.diff(xy, axis=0), axis=1) > 1e-6]]
    if len(xy) < 2:
        return None
    seg = np.diff(xy, axis=0)  # (N-1, 2)
    s = np.r_[0.0, np.cumsum(np.linalg.norm(seg, axis=1))]  # (N,) arc length at each point
    u = np.arange(0.0, s[-1] + 1e-9, spacing)  # (P,)
    k = np.clip(np.searchsorted(s, u, side="right") - 1, 0, len(seg) - 1)  # the segment u lies on
    pts = xy[k] + ((u - s[k]) / (s[k + 1] - s[k]))[:, None] * seg[k]
    return np.c_[pts, np.arctan2(seg[k, 1], seg[k, 0])]


def distinct_lanes(batch: Scenarios, max_lanes: int, tol=1.0, share=0.9) -> Scenarios:
    """At most max_lanes lanes per sample, none with `share` of its points within `tol` m of a
    nearer kept one: where lanes fork and merge, many routes share the ego's lane, and the nearest
    would all be copies of it, crowding out the lane a lane change's goal lies on."""
    lanes, mask = batch.lanes, batch.lanes_mask  # (B, L, P, 3), (B, L, P)
    B, L, P, _ = lanes.shape
    n_pts = mask.sum(-1)  # (B, L)
    dup = n_pts == 0  # (B, L) lanes to drop (empty slots too)
    for i in range(L - 1):  # a loop over lanes (a few dozen), every sample at once
        d = torch.cdist(lanes[:, i + 1 :, :, :2].reshape(B, -1, 2), lanes[:, i, :, :2])
        d = torch.where(mask[:, i, None, :], d, math.inf).min(-1).values.reshape(B, L - i - 1, P)
        covered = ((d <= tol) & mask[:, i + 1 :]).sum(-1)  # (B, L-i-1) points of lane j near lane i
        dup[:, i + 1 :] |= ~dup[:, i, None] & (covered >= share * n_pts[:, i + 1 :])
    order = torch.argsort(dup.int(), dim=1, stable=True)[:, :max_lanes]  # kept first, nearest first
    keep = ~torch.gather(dup, 1, order)  # (B, L')
    Lk = int(keep.sum(1).max()) if B else 0
    order, keep = order[:, :Lk], keep[:, :Lk]
    new_mask = torch.gather(mask, 1, order[..., None].expand(B, Lk, P)) & keep[..., None]
    new_lanes = torch.gather(lanes, 1, order[..., None, None].expand(B, Lk, P, 3))
    return dataclasses.replace(batch, lanes=new_lanes * new_mask[..., None], lanes_mask=new_mask)


def load_waymo_scenarios(cache_dir="data_cache", phases=(0,), cfg=None, log=print):
    """The Waymo scenes (fetched if needed) as planning samples and a report; the distinct lanes."""
    cfg = cfg or SynthConfig()
    scenes, report = waymo_scenes(fetch_waymo(cache_dir, log), phases, cfg)
    wide = dataclasses.replace(cfg, max_lanes=max(cfg.max_lanes, WAYMO_CANDIDATE_LANES))
    one_by_one = [scenes[s : s + 1] for s in range(len(scenes))]
    parts = [ds.cut_samples(s, None, np.random.default_rng(0), wide) for s in one_by_one]
    batch = distinct_lanes(Scenarios.cat([p for p, _ in parts]), cfg.max_lanes)
    report.update(samples=len(batch), samples_skipped_no_lanes=sum(n for _, n in parts))
    report["samples_per_scene"] = {name: len(p) for name, (p, _) in zip(scenes.names, parts)}
    return batch, report
