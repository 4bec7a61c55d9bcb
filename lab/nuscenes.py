"""The nuScenes v1.0 format read (load_nuscenes, no devkit) and written (write_nuscenes: read back
exactly, here and by the devkit); docs/data.md says how a sample is made of a real scene."""

from __future__ import annotations

import contextlib
import dataclasses
import gc
import hashlib
import json
import math
import multiprocessing
import os
import signal
import statistics
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch

import data_synth as ds
from data_synth import MAX_LANE_POINTS, Scenes, SynthConfig
from lab.runs import folder_lock, load_tensors, save_atomic, sha256_of, write_atomic
from lab.runs import write_file_atomic, write_folder

NUSC_VERSIONS = ("v1.0-mini", "v1.0-trainval", "v1.0-test")
NUSC_TABLES = tuple(
    "category attribute visibility instance sensor calibrated_sensor ego_pose log scene sample "
    "sample_data sample_annotation map".split()
)
NUSC_LOCATIONS = tuple(
    "singapore-onenorth singapore-hollandvillage singapore-queenstown boston-seaport".split()
)
QUAT_TOL = 1e-3  # a rotation must be a unit quaternion within this: never a silently wrong heading
MAX_POSITION = 1e6  # m: a translation beyond this is no place on a nuScenes map
MAX_SPEED = 100.0  # m/s between two key frames: faster is a wrong position or timestamp
_BIG = 1e300  # a JSON number beyond this would overflow float64 arithmetic
# scenes per pool task, and per worker at least: a worker takes ~0.1 s to start, a real scene ~30 ms
PARSE_CHUNK = 16


class NuScenesFormatError(ValueError):
    """A nuScenes folder that cannot be read: one line naming the file, the record and the field."""


def _short(v, n: int = 60) -> str:
    return repr(v) if len(repr(v)) <= n else repr(v)[:n] + "..."


class Reading(contextlib.AbstractContextManager):
    """Inside `with Reading(path) as r`, a KeyError, ValueError, ... raised reading r.rec (set, or
    by r.each) is one `error` line "<path>: record <token>: <field>: <what>" (or r.name's)."""

    def __init__(self, path, error=NuScenesFormatError):
        self.path, self.error, self.rec, self.name = path, error, None, ""

    def each(self, records):
        for self.rec in records:
            yield self.rec
        self.rec = None

    def __exit__(self, kind, err, tb):
        bad = (KeyError, TypeError, ValueError, IndexError, AttributeError, OverflowError)
        if kind is None or not issubclass(kind, bad) or isinstance(err, self.error):
            return
        rec = self.rec if isinstance(self.rec, dict) else {}
        token = rec.get("token")
        where = self.name or (f"record {token!r}" if isinstance(token, str) else "")
        why = str(err) if kind is ValueError else f"{kind.__name__}: {err}"
        if kind is KeyError:  # a field missing, or one naming no record (or value)
            key = err.args[0]
            field = next((f for f, v in rec.items() if type(v) is type(key) and v == key), None)
            why = f"{field}: unknown {_short(key)}" if field else f"{_short(key)}: missing"
        raise self.error(f"{self.path}: {where}{': ' if where else ''}{why}") from err


def _read_json(path: Path):
    if not path.is_file():
        raise NuScenesFormatError(f"{path}: missing")
    try:
        with open(path) as f:
            return json.load(f)
    except (ValueError, RecursionError, OSError) as e:  # (an int of > 4300 digits: a ValueError)
        raise NuScenesFormatError(f"{path}: malformed JSON or unreadable ({e})") from e


def _unique(path, tokens: list, what: str = "token") -> None:
    """Tokens are primary keys: a repeated one is an error naming it and its first two records."""
    first = {}
    for j, t in enumerate(tokens):
        if (i := first.setdefault(t, j)) != j:
            raise NuScenesFormatError(f"{path}: {what} {t!r} appears twice (records {i} and {j})")


def _table(path: Path) -> list:
    """A table: a JSON list of records (objects), each with a unique string token."""
    recs = _read_json(path)
    if not isinstance(recs, list):
        raise NuScenesFormatError(f"{path}: a table must be a JSON list, not {type(recs).__name__}")
    for i, r in enumerate(recs):
        if not isinstance(r, dict) or not isinstance(r.get("token"), str):
            raise NuScenesFormatError(f"{path}: record {i} is not an object with a string token")
    _unique(path, [r["token"] for r in recs])
    return recs


def _numbers(rec: dict, key: str, n: int | None = None, lo: float = -_BIG, hi: float = _BIG):
    """rec[key] as n floats (n None: one float), each a JSON number from lo to hi: not a bool, a
    string or null, nor NaN or Infinity (Python's json reads them; JSON does not allow them)."""
    xs = [rec[key]] if n is None else rec[key]
    ok = isinstance(xs, list) and len(xs) == (n or 1)
    if not (ok and all(type(x) in (int, float) and lo <= x <= hi for x in xs)):
        span = f" from {lo:g} to {hi:g}" if (lo, hi) != (-_BIG, _BIG) else ""
        many = f"{n} finite numbers" if n else "a finite number"
        raise ValueError(f"{key}: must be {many}{span}, got {_short(rec[key])}")
    return float(xs[0]) if n is None else [float(x) for x in xs]


def _text(rec: dict, key: str) -> str:
    if not isinstance(rec[key], str):
        raise ValueError(f"{key}: must be a string, got {_short(rec[key])}")
    return rec[key]


def _pose(rec: dict) -> list:
    """[x, y, heading] of a record's translation and rotation (a unit quaternion [w, x, y, z])."""
    w, x, y, z = q = _numbers(rec, "rotation", 4)
    norm = math.sqrt(sum(c * c for c in q))
    if not abs(norm - 1.0) <= QUAT_TOL:
        raise ValueError(f"rotation: {_short(q)} is not a unit quaternion (norm {norm:.6g})")
    xy = _numbers(rec, "translation", 3, -MAX_POSITION, MAX_POSITION)[:2]
    return [*xy, math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))]


def _map_path(root: Path, location) -> Path:
    """maps/expansion/<location>.json, confined to <root>/maps: a location is a plain map name."""
    maps = Path(os.path.abspath(root / "maps"))
    seps = {"/", "\\", "..", "\0", os.sep, os.altsep or "/"}
    if isinstance(location, str) and location and not any(s in location for s in seps):
        path = Path(os.path.abspath(maps / "expansion" / f"{location}.json"))
        if maps in path.parents:
            return path
    raise ValueError(f"location: {_short(location)} is not a plain map name inside {root}/maps")


def _read_map(path: Path, cfg: SynthConfig) -> dict:
    """A map expansion's lanes and connectors; one over MAX_LANE_POINTS refused first."""
    js = _read_json(path)
    with Reading(path) as r:
        if not isinstance(js, dict) or str(js.get("version", "1.0")) < "1.3":
            raise ValueError("must be a JSON object, a map expansion of version 1.3 or later")
        records = [(rec["token"], False) for rec in r.each(js["lane"])]
        records += [(rec["token"], True) for rec in r.each(js["lane_connector"])]
        tokens = [t for t, _ in records]
        _unique(path, tokens, "lane / lane_connector token")
        index = {t: k for k, t in enumerate(tokens)}
        arclines, conn, paths, lengths = js["arcline_path_3"], js["connectivity"], [], []
        for t in tokens:
            r.name = f"lane {t!r}"
            rows = []
            for a in r.each(arclines.get(t, [])):
                pose, radius = _numbers(a, "start_pose", 3), _numbers(a, "radius", lo=0.0)
                seg = _numbers(a, "segment_length", 3, lo=0.0)
                rows.append([*pose, radius, *seg, *ds._SHAPE_SIGNS[a["shape"]]])
            paths.append(np.array(rows, dtype=np.float64).reshape(-1, 10))
            lengths.append(float(paths[-1][:, 4:7].sum()))
            if (n_pts := ds._lane_points(lengths[-1], cfg.lane_spacing)) > MAX_LANE_POINTS:
                at = f"{n_pts} points at {cfg.lane_spacing} m spacing"
                raise ValueError(f"{lengths[-1]:.6g} m long: {at}, more than {MAX_LANE_POINTS = }")
        r.name = ""
        links = [conn.get(t, {}) for t in tokens]
        nxt = [[index[o] for o in c.get("outgoing", []) if o in index] for c in links]
        prv = [[index[o] for o in c.get("incoming", []) if o in index] for c in links]
    lanes = dict(tokens=tokens, is_connector=np.array([c for _, c in records], bool), path=path)
    return lanes | dict(paths=paths, length=lengths, next=nxt, prev=prv) | _lane_boxes(paths, cfg)


def _lane_boxes(paths: list, cfg: SynthConfig) -> dict:
    """Every lane's points (n, P, 2), mask, box (n, 4) for _lanes_near; in chunks (~10^4 lanes)."""
    chunks = []
    for c in range(0, len(paths), 1024):
        R = max([len(p) for p in paths[c : c + 1024]] + [1])
        padded = np.zeros((len(paths[c : c + 1024]), R, 10))
        for k, p in enumerate(paths[c : c + 1024]):
            padded[k, : len(p)] = p
        segs = ds.arcline_segments(padded).reshape(len(padded), 3 * R, 5)
        chunks.append(ds.discretize(segs, cfg.lane_spacing))
    P = max([p.shape[1] for p, _ in chunks] + [1])
    pts, mask = np.zeros((len(paths), P, 2)), np.zeros((len(paths), P), bool)
    for c, (p, m) in zip(range(0, len(paths), 1024), chunks):
        pts[c : c + len(p), : p.shape[1]], mask[c : c + len(p), : p.shape[1]] = p[..., :2], m
    lo = np.where(mask[..., None], pts, np.inf).min(1)
    hi = np.where(mask[..., None], pts, -np.inf).max(1)
    return dict(pts=pts, mask=mask, box=np.concatenate([lo, hi], 1))


def routes_through(lmap: dict, near: list, max_routes: int = 256) -> list:
    """Maximal chains of lane indices through lmap's links within `near`, from its sources first."""
    inside = set(near)
    out = {i: [j for j in lmap["next"][i] if j in inside] for i in near}
    sources = [i for i in near if not any(j in inside for j in lmap["prev"][i])]
    routes, covered = [], set()
    for start in sources + near:
        if start in covered or len(routes) >= max_routes:
            continue
        stack = [[start]]
        while stack and len(routes) < max_routes:
            chain = stack.pop()
            succ = [j for j in out[chain[-1]] if j not in chain]
            if succ:
                stack += [chain + [j] for j in reversed(succ)]
            else:
                routes.append(chain)
                covered.update(chain)
    return routes


def _sample_chain(r: Reading, samples: dict, first: str, name: str) -> tuple[list, list]:
    """(tokens, timestamps) of a scene's samples along `next`, checked: links, no loop, timestamps
    (microseconds) increasing 0.1 to 2 s apart (ms or ns are 1000 times off)."""
    tokens, times, seen, tok = [], [], set(), first
    while tok:
        if tok in seen:
            raise ValueError(f"next: links back to {tok!r}: the next links of scene {name!r} loop")
        rec = r.rec = samples[tok]  # (a KeyError names the `next` of the sample before)
        before = tokens[-1] if tokens else ""
        if rec["prev"] != before:
            raise ValueError(f"prev: {_short(rec['prev'])}, but it follows {before!r}")
        _numbers(rec, "timestamp")  # (kept as written: an int)
        if times and not rec["timestamp"] > times[-1]:
            raise ValueError(f"timestamp: not after {times[-1]}, the sample before's: a step <= 0")
        seen.add(tok)
        tokens.append(tok)
        times.append(rec["timestamp"])
        tok = rec["next"]
    step = statistics.median(b - a for a, b in zip(times, times[1:])) / 1e6 if times[1:] else 0.5
    if not 0.1 <= step <= 2.0:
        r.rec = None
        raise ValueError(f"the samples of scene {name!r} are {step:g} s apart; key frames are 2 Hz")
    return tokens, times


def _index(root: Path, version: str, cfg: SynthConfig):
    """The folder's tables, read and indexed: (what parsing a scene reads, tables, log -> map)."""
    tdir = root / version
    if version not in NUSC_VERSIONS:
        raise NuScenesFormatError(f"{tdir}: unknown version; expected one of {NUSC_VERSIONS}")
    if not tdir.is_dir():
        found = sorted(p.name for p in root.glob("v1.0-*")) if root.is_dir() else []
        raise NuScenesFormatError(f"{tdir}: no such version folder (found: {found or 'none'})")
    tab = {t: _table(tdir / f"{t}.json") for t in NUSC_TABLES}

    def by_token(name, value):  # {token: value(record)} of a table
        with Reading(tdir / f"{name}.json") as r:
            return {rec["token"]: value(rec) for rec in r.each(tab[name])}

    channel = by_token("sensor", lambda s: s["channel"])
    cs_channel = by_token("calibrated_sensor", lambda c: channel[c["sensor_token"]])
    poses = {p["token"]: p for p in tab["ego_pose"]}
    with Reading(tdir / "sample_data.json") as r:
        ego_of = {
            sd["sample_token"]: poses[sd["ego_pose_token"]]
            for sd in r.each(tab["sample_data"])
            if sd["is_key_frame"] and cs_channel[sd["calibrated_sensor_token"]] == "CAM_FRONT"
        }
    cat_name = by_token("category", lambda c: _text(c, "name"))
    inst_cat = by_token("instance", lambda i: cat_name[i["category_token"]])
    anns = {}
    with Reading(tdir / "sample_annotation.json") as r:
        for a in r.each(tab["sample_annotation"]):
            if inst_cat[a["instance_token"]].startswith(("vehicle.", "human.pedestrian.")):
                anns.setdefault(a["sample_token"], []).append(a)
    map_file = by_token("log", lambda lg: _map_path(root, lg["location"]))  # before any work
    split_path = root / "maps" / "prediction" / "prediction_scenes.json"
    split = _read_json(split_path) if split_path.exists() else {}
    with Reading(split_path):
        if not isinstance(split, dict):
            raise ValueError("must be a JSON object: scene name -> ['<instance>_<sample>', ...]")
        listed = {tuple(s.split("_")) for entries in split.values() for s in entries}
    ctx = SimpleNamespace(tdir=tdir, cfg=cfg, ego_of=ego_of, anns=anns, inst_cat=inst_cat)
    ctx.maps, ctx.split_scenes, ctx.listed = {}, frozenset(split), listed
    return ctx, tab, map_file


def load_nuscenes(root, version="v1.0-mini", cfg=None, workers=None) -> tuple[Scenes, dict]:
    """A nuScenes v1.0 folder as Scenes (world frame) and a report naming each scene skipped, why,
    parsed by `workers` processes (default: this process's cores), the same whatever their count."""
    cfg = cfg or SynthConfig()
    ctx, tab, map_file = _index(Path(root), version, cfg)
    samples = {s["token"]: s for s in tab["sample"]}
    report = dict(scenes=len(tab["scene"]), loaded=0, skipped_short=0, skipped_no_lanes=0)
    report |= dict(skipped_no_agent=0, skipped=[])
    jobs = []
    for sc in tab["scene"]:  # here, in order: the sample chains, the maps read once
        with Reading(ctx.tdir / "scene.json") as r:
            r.rec, name = sc, _text(sc, "name")
            first = sc["first_sample_token"]
            first = first and samples[first]["token"]  # (a KeyError: no such sample; "": none)
            mpath = map_file[sc["log_token"]]
        with Reading(ctx.tdir / "sample.json") as r:
            tokens, times = _sample_chain(r, samples, first, name)
        if len(tokens) < cfg.hist + cfg.fut + 1:
            report["skipped_short"] += 1
            need = f"a sample needs {cfg.hist + cfg.fut + 1}"
            report["skipped"].append(f"{name}: {len(tokens)} samples in {r.path}, {need}")
            continue
        if mpath not in ctx.maps:
            ctx.maps[mpath] = _read_map(mpath, cfg)
        jobs.append((name, mpath, tokens, times))
    out = []
    for outcome, got in _map_scenes(jobs, ctx, workers):
        report[outcome] += 1
        if outcome == "loaded":
            out.append(scene_of(got[0], **got[1]))
        else:
            report["skipped"].append(got)  # (its reason)
    if not out:
        raise NuScenesFormatError(f"{ctx.tdir}: no usable scene ({report})")
    return Scenes.cat(out), report


_CONTEXT = None  # the context the pool's workers parse with: inherited when they fork


def _start_worker() -> None:
    torch.set_num_threads(1)  # the pool is the parallelism
    # Ctrl-C is the parent's: it cancels the pool's work, and no worker prints a traceback
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _parse_in_worker(job):
    return _parse_scene(job, _CONTEXT)


def _map_scenes(jobs: list, ctx, workers: int | None) -> list:
    """[_parse_scene(job, ctx) for job in jobs] on a pool where the platform forks: the workers
    inherit ctx (hundreds of MB for v1.0-trainval), gc.freeze keeps their gc from copying it."""
    global _CONTEXT
    cores = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else range(os.cpu_count())
    workers = len(cores) if workers is None else workers  # default: the cores this process may use
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValueError(f"load_nuscenes: workers must be a whole number >= 1, got {workers!r}")
    workers = min(workers, math.ceil(len(jobs) / PARSE_CHUNK))
    if workers <= 1 or "fork" not in multiprocessing.get_all_start_methods():
        return [_parse_scene(job, ctx) for job in jobs]
    _CONTEXT = ctx
    gc.freeze()
    try:
        fork = multiprocessing.get_context("fork")
        with ProcessPoolExecutor(workers, fork, initializer=_start_worker) as pool:
            try:  # (SIGINT held while the workers fork: none gets it before _start_worker)
                held = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
                try:
                    results = pool.map(_parse_in_worker, jobs, chunksize=PARSE_CHUNK)
                finally:
                    signal.pthread_sigmask(signal.SIG_SETMASK, held)
                return list(results)
            except KeyboardInterrupt:  # the workers ignore Ctrl-C: they end here, now
                pool.shutdown(wait=False, cancel_futures=True)
                for worker in multiprocessing.active_children():
                    worker.terminate()
                raise
    finally:
        gc.unfreeze()
        _CONTEXT = None


def _parse_scene(job, ctx) -> tuple[str, dict | str]:
    """('loaded', (name, arrays): numpy crosses the pool's pipes, tensors would go as shared memory
    files) or ('skipped_no_lanes' | 'skipped_no_agent', the reason)."""
    name, mpath, tokens, times = job
    cfg, afile = ctx.cfg, ctx.tdir / "sample_annotation.json"
    t = np.array(times, np.float64)
    t = (t - t[0]) * 1e-6  # (F,) seconds
    ego, tracks, inst = _tracks(ctx, name, tokens, t)
    lmap = ctx.maps[mpath]
    routes = routes_through(lmap, _lanes_near(lmap, ego[:, :2], cfg.map_radius))
    if not routes:
        why = f"{name}: no lane of {mpath} within {cfg.map_radius:g} m of the ego's path"
        return "skipped_no_lanes", why
    listed = name in ctx.split_scenes
    pred = choose_predicted(ego, tracks, inst, tokens, listed, ctx.listed, cfg)
    if (pred < 0).all() and listed:  # the split promises a vehicle
        entry = next((f"{i}_{k}" for i, k in sorted(ctx.listed) if k in set(tokens)), None)
        if entry is not None:
            split = ctx.tdir.parent / "maps/prediction/prediction_scenes.json"
            why = f"listed (first entry {_short(entry)}) but {afile} has no vehicle of its entries"
            raise NuScenesFormatError(f"{split}: scene {name!r} is {why}")
    if (pred < 0).all():
        why = f"{name}: no vehicle in {afile} moves >= 1 m with a complete {cfg.fut}-frame future"
        return "skipped_no_agent", why
    arrays = dict(_lanes_of(name, lmap, routes, cfg), ego=ego, pred_idx=pred, **tracks)
    if bad := [k for k, v in arrays.items() if v.dtype.kind == "f" and not np.isfinite(v).all()]:
        # finite inputs can still overflow (coordinates near 1e308): never a silent inf/NaN
        raise NuScenesFormatError(f"{ctx.tdir}: scene {name!r} gives non-finite {', '.join(bad)}")
    return "loaded", (name, arrays)


def _tracks(ctx, name: str, tokens: list, t) -> tuple:
    """The ego (F, 4), the agents (Scenes' fields, by first appearance), their instance tokens."""
    if missing := [k for k in tokens if k not in ctx.ego_of]:
        raise NuScenesFormatError(f"{ctx.tdir}/sample_data.json: no CAM_FRONT for {missing[0]}")
    F, poses = len(tokens), {(f,): ctx.ego_of[k] for f, k in enumerate(tokens)}
    with Reading(ctx.tdir / "ego_pose.json") as r:
        ego = np.array([[*_pose(p), 0.0] for p in r.each(poses.values())])
        ego[:, 2] = ds.wrap_angle(ego[:, 2])
        ego[:, 3] = ds.backward_speed(ego[:, :2], np.ones(F, bool), t)
        _check_speed(r, ego[:, 3], poses, "the ego", tokens, name)
    slot, ann_at, rows = {}, {}, []
    with Reading(ctx.tdir / "sample_annotation.json") as r:
        for f, k in enumerate(tokens):
            for a in r.each(ctx.anns.get(k, [])):
                m = slot.setdefault(a["instance_token"], len(slot))
                if (m, f) in ann_at:
                    raise ValueError(f"instance_token: annotated twice in sample {k!r}")
                ann_at[m, f] = a
                rows.append((m, f, *_pose(a), *_numbers(a, "size", 3)))
        M, inst = len(slot), list(slot)
        rows = np.array(rows, np.float64).reshape(-1, 8)
        mi, fi = rows[:, 0].astype(int), rows[:, 1].astype(int)
        agents, amask, size = np.zeros((M, F, 4)), np.zeros((M, F), bool), np.zeros((M, 3))
        agents[mi, fi, :3], amask[mi, fi], size[mi] = rows[:, 2:5], True, rows[:, 5:8]
        agents[..., 2] = ds.wrap_angle(agents[..., 2])
        agents[..., 3] = ds.backward_speed(agents[..., :2], amask, t) * amask
        _check_speed(r, agents[..., 3], ann_at, "the instance", tokens, name)
    is_ped = np.array([ctx.inst_cat[i].startswith("human.") for i in inst], bool).reshape(M)
    return ego, dict(agents=agents, agents_mask=amask, agents_is_ped=is_ped, agents_size=size), inst


def _check_speed(r: Reading, speed, records: dict, who: str, tokens: list, name: str) -> None:
    """A track faster than MAX_SPEED: an error naming the record."""
    if (np.abs(speed) > MAX_SPEED).any():
        k = tuple(np.argwhere(np.abs(speed) > MAX_SPEED)[0].tolist())
        r.rec, at = records[k], f"at sample {tokens[k[-1]]!r} of scene {name!r}"
        raise ValueError(f"translation: puts {who} at {abs(speed[k]):.3g} m/s {at}: too fast")


def _lanes_near(lmap: dict, path_xy, radius: float) -> list:
    """The lanes with a point within radius of path_xy (F, 2): by box first, then by point."""
    lo, hi = path_xy.min(0) - radius, path_xy.max(0) + radius
    b = lmap["box"]  # (n, 4): lo, hi
    cand = np.nonzero((b[:, 2:] >= lo).all(1) & (b[:, :2] <= hi).all(1))[0]
    p, m = lmap["pts"][cand], lmap["mask"][cand]
    cand = cand[(m[..., None] & (p >= lo) & (p <= hi)).all(-1).any(-1)]
    d = np.linalg.norm(lmap["pts"][cand][:, :, None] - path_xy[None, None], axis=-1)  # (n, P, F)
    return cand[(np.where(lmap["mask"][cand][..., None], d, np.inf) < radius).any((1, 2))].tolist()


def choose_predicted(ego, tracks: dict, inst, tokens, scene_listed: bool, listed: set, cfg):
    """The predicted vehicle per frame t0 (-1: none), docs/data.md's rule; `listed`: the split's."""
    agents, amask, is_ped = tracks["agents"], tracks["agents_mask"], tracks["agents_is_ped"]
    (M, F), H, T = amask.shape, cfg.hist, cfg.fut
    pred = np.full(F, -1)
    for f in range(H, F - T):
        fut = amask[:, f : f + T + 1].all(1) & ~is_ped  # observed at t0 and the whole future
        if scene_listed:
            ok = fut & np.array([(i, tokens[f]) in listed for i in inst], bool).reshape(M)
        else:
            w, wm = agents[:, f - H : f + T + 1, :2], amask[:, f - H : f + T + 1]
            first = np.take_along_axis(w, np.argmax(wm, 1)[:, None, None], 1)
            ok = fut & (np.where(wm, np.linalg.norm(w - first, axis=-1), 0.0).max(1) >= 1.0)
        if ok.any():
            near = agents[:, f : f + T + 1, :2] - ego[None, f : f + T + 1, :2]
            pred[f] = int(np.argmin(np.where(ok, np.linalg.norm(near, axis=-1).min(1), np.inf)))
    return pred


def _lanes_of(name: str, lmap: dict, routes: list, cfg) -> dict:
    """A scene's map as Scenes' fields; a route of more than MAX_LANE_POINTS points is refused."""
    for r in routes:
        length = sum(lmap["length"][i] for i in r)
        if ds._lane_points(length, cfg.lane_spacing) > MAX_LANE_POINTS:
            ends = f"through lanes {lmap['tokens'][r[0]]!r} .. {lmap['tokens'][r[-1]]!r}"
            why = f"is {length:.6g} m long: more than {MAX_LANE_POINTS = } points"
            raise NuScenesFormatError(f"{lmap['path']}: the route of scene {name!r} {ends} {why}")
    used = sorted({i for r in routes for i in r})
    first = np.cumsum([0] + [len(lmap["paths"][i]) for i in used])  # first path of each used lane
    where = {i: k for k, i in enumerate(used)}
    paths = np.concatenate([lmap["paths"][i] for i in used])  # (Q, 10)
    conn = np.concatenate([np.full(len(lmap["paths"][i]), lmap["is_connector"][i]) for i in used])
    chains = [[q for i in r for q in range(first[where[i]], first[where[i] + 1])] for r in routes]
    R = max(len(c) for c in chains)
    routes = np.array([c + [-1] * (R - len(c)) for c in chains])  # (L, R)
    lanes, mask = ds.discretize(ds.route_segments(paths[None], routes[None]), cfg.lane_spacing)
    out = dict(lanes=lanes[0], lanes_mask=mask[0], paths=paths, paths_is_connector=conn)
    return out | dict(routes=routes)


def scene_of(name: str, **arrays) -> Scenes:
    """A real scene's numpy arrays (Scenes' fields) as a Scenes of length 1: no behaviour, event."""
    t = {k: torch.from_numpy(np.ascontiguousarray(v))[None] for k, v in arrays.items()}
    t["pred_idx"], t["routes"] = t["pred_idx"].long(), t["routes"].long()
    return Scenes(**t, event_frame=torch.tensor([-1]), behaviour=torch.tensor([-1]), names=[name])


# === the parse cache ============================================================================

_NUSC_CACHE_FORMAT = 2  # bump when load_nuscenes's output changes, so old caches are not reused


def nuscenes_cache_path(root, version: str, cache_dir) -> Path:
    """The cache of root/version's parse: one file per folder (by its absolute path)."""
    where = hashlib.sha1(f"{Path(root).resolve()}/{version}".encode()).hexdigest()[:12]
    return Path(cache_dir) / f"nuscenes-{version}-{where}.pt"


def load_nuscenes_cached(
    root, version="v1.0-mini", cfg=None, cache_dir="data_cache", workers=None, log=print
) -> tuple[Scenes, dict]:
    """load_nuscenes cached in cache_dir, keyed by the sha256 of the files it reads (a size or time
    can survive an edit), the SynthConfig and the format. A foreign file is refused, kept."""
    cfg, t0, what = cfg or SynthConfig(), time.perf_counter(), f"{root}/{version}"
    files = [Path(root) / version / f"{t}.json" for t in NUSC_TABLES]  # what load_nuscenes reads
    files += sorted((Path(root) / "maps" / "expansion").glob("*.json"))
    files.append(Path(root) / "maps" / "prediction" / "prediction_scenes.json")
    sums = {f.relative_to(root).as_posix(): sha256_of(f) for f in files if f.is_file()}
    key = dict(version=version, files=sums, cfg=dataclasses.asdict(cfg), format=_NUSC_CACHE_FORMAT)
    key, path = json.dumps(key, sort_keys=True), nuscenes_cache_path(root, version, cache_dir)
    if path.exists():
        blob = load_tensors(path, "a readable data_synth nuScenes cache")
        if not isinstance(blob, dict) or "key" not in blob:
            raise ValueError(f"{path}: not a readable data_synth nuScenes cache (no key)")
        stored = blob["key"]
        if stored == key:
            log(f"{what}: parsed scenes read from the cache {path} ({len(sums)} sha256 match)")
            return Scenes(**blob["scenes"]), blob["report"]
        try:  # (a cache of an earlier version of the project may key otherwise)
            before = json.loads(stored)["files"]
            changed = sorted(f for f in set(sums) | set(before) if sums.get(f) != before.get(f))
        except (TypeError, ValueError, KeyError, AttributeError):
            changed = ["the cache's format: an earlier version of the project wrote it"]
        changed = ", ".join(changed[:3] or ["the settings"])
        log(f"{what}: the cache {path} is out of date ({changed} changed); parsing again")
    with folder_lock(path.parent, f"parsing {what} into {path.name}"):
        scenes, report = load_nuscenes(root, version, cfg, workers)
        blob = {"key": key, "scenes": {**scenes.tensors(), "names": scenes.names}, "report": report}
        save_atomic(blob, path)
    log(f"{what}: parsed in {time.perf_counter() - t0:.1f} s, cached in {path}")
    return scenes, report


def load_nuscenes_scenarios(
    root, version="v1.0-mini", cfg=None, workers=None, cache_dir=None, log=print
):
    """A nuScenes folder as planning samples at every usable frame (parse cached in cache_dir)."""
    if cache_dir is None:
        scenes, report = load_nuscenes(root, version, cfg, workers)
    else:
        scenes, report = load_nuscenes_cached(root, version, cfg, cache_dir, workers, log)
    batch, no_lanes = ds.cut_samples(scenes, None, np.random.default_rng(0), cfg)
    report.update(samples=len(batch), samples_skipped_no_lanes=no_lanes)
    return batch, report


# === writing ====================================================================================

MAP_LAYERS = tuple(
    "polygon line node drivable_area road_segment road_block lane ped_crossing walkway stop_line "
    "carpark_area road_divider lane_divider traffic_light lane_connector".split()
)
# the first 10 scenes written take v1.0-mini's names (the devkit's prediction split knows them)
MINI_SCENES = tuple(
    "scene-0061 scene-0103 scene-0553 scene-0655 scene-0757 scene-0796 scene-0916 scene-1077 "
    "scene-1094 scene-1100".split()
)
_FIELDS = {  # the fields of the records written, in the devkit's order
    "log": "token logfile vehicle date_captured location",
    "scene": "token log_token nbr_samples first_sample_token last_sample_token name description",
    "sample": "token timestamp scene_token prev next",
    "ego_pose": "token timestamp rotation translation",
    "sample_data": "token sample_token ego_pose_token calibrated_sensor_token timestamp fileformat "
    "is_key_frame height width filename prev next",
    "instance": "token category_token nbr_annotations first_annotation_token last_annotation_token",
    "sample_annotation": "token sample_token instance_token visibility_token attribute_tokens "
    "translation size rotation prev next num_lidar_pts num_radar_pts",
    "category": "token name description index",
    "attribute": "token name description",
    "visibility": "token level description",
    "sensor": "token channel modality",
    "calibrated_sensor": "token translation sensor_token rotation camera_intrinsic",
    "map": "token category filename log_tokens",
}
# channel: modality, file format, image height, width; translation, rotation, camera intrinsic
_SENSORS = {"CAM_FRONT": ("camera", "jpg", 900, 1600), "LIDAR_TOP": ("lidar", "pcd.bin", 0, 0)}
_CAM_INTRINSIC = [[1266.4, 0.0, 816.3], [0.0, 1266.4, 491.5], [0.0, 0.0, 1.0]]
_CALIBRATION = {
    "CAM_FRONT": ([1.70, 0.016, 1.51], [0.4998, -0.5031, 0.4998, -0.4972], _CAM_INTRINSIC),
    "LIDAR_TOP": ([0.943, 0.0, 1.84], [0.7071, 0.0, 0.0, -0.7071], []),
}
_CAR, _PED = "Vehicle designed primarily for personal use.", "human.pedestrian.adult"
_SIGNS_SHAPE = {v: k for k, v in ds._SHAPE_SIGNS.items()}
_T0_US = 1_600_000_000_000_000  # timestamp of the first written frame (microseconds)


def _token(*parts) -> str:
    """A deterministic 32-hex token (the format of nuScenes tokens)."""
    return hashlib.md5("/".join(map(str, parts)).encode()).hexdigest()


def _add(tables: dict, table: str, *values) -> None:
    """A record appended to a table: its fields (_FIELDS) in order, with these values."""
    tables[table].append(dict(zip(_FIELDS[table].split(), values, strict=True)))


def _quat(yaw: float) -> list:
    return [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]  # planar yaw: [w, x, y, z]


def _links(tokens: list, k: int) -> tuple:
    """(prev, next) tokens of item k of a chain ("" at the ends)."""
    return tokens[k - 1] if k else "", tokens[k + 1] if k < len(tokens) - 1 else ""


def _dump(obj, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, json.dumps(obj, allow_nan=False))


def write_nuscenes(scenes: Scenes, root, version="v1.0-mini", cfg=None, overwrite=False) -> Path:
    """Scenes as a nuScenes v1.0 folder, written whole (runs.write_folder); returns root."""
    cfg = cfg or SynthConfig()
    if version not in NUSC_VERSIONS:
        raise ValueError(f"write_nuscenes: version must be one of {NUSC_VERSIONS}, got {version!r}")
    root = Path(root)
    files = [root / version / f"{t}.json" for t in NUSC_TABLES]
    files += [root / "maps" / "expansion" / f"{loc}.json" for loc in NUSC_LOCATIONS]
    files.append(root / "maps" / "prediction" / "prediction_scenes.json")
    write = lambda tmp: _write_nuscenes(scenes, tmp, version, cfg)  # noqa: E731
    write_folder(root, write, "write_nuscenes", files, overwrite, also=root / "maps")  # (PNGs)
    return root


def _write_nuscenes(scenes: Scenes, root: Path, version: str, cfg: SynthConfig) -> None:
    """Every file: scenes go round-robin to the four maps, 300 m apart in their map's canvas."""
    S = len(scenes)
    names = [MINI_SCENES[i] if i < len(MINI_SCENES) else f"scene-{9000 + i}" for i in range(S)]
    locs = [NUSC_LOCATIONS[i % 4] for i in range(S)]
    offsets, canvas = np.zeros((S, 2)), {loc: [300.0, 300.0] for loc in NUSC_LOCATIONS}
    for i, loc in enumerate(locs):  # a translation that puts the scene beside the one before
        lanes = scenes.lanes[i][scenes.lanes_mask[i]][:, :2].numpy()
        agents = scenes.agents[i][scenes.agents_mask[i]][:, :2].numpy()
        pts = np.concatenate([lanes, scenes.ego[i, :, :2].numpy(), agents])
        lo, hi = pts.min(0), pts.max(0)
        offsets[i] = (canvas[loc][0] - lo[0], 300.0 - lo[1])
        canvas[loc][0] += hi[0] - lo[0] + 300.0
        canvas[loc][1] = max(canvas[loc][1], hi[1] - lo[1] + 600.0)
    tables, split = _fixed_tables(), {}
    for i in range(S):
        split[names[i]] = _write_scene(tables, scenes, i, names[i], locs[i], offsets[i], cfg)
    import matplotlib.image

    for loc in NUSC_LOCATIONS:
        tok, mine = _token("map", loc), [i for i in range(S) if locs[i] == loc]
        logs = [_token(names[i], "log") for i in mine]
        _add(tables, "map", tok, "semantic_prior", f"maps/{tok}.png", logs)
        exp = {"version": "1.3", "canvas_edge": [canvas[loc][0] + 300.0, canvas[loc][1]]}
        exp |= {layer: [] for layer in MAP_LAYERS} | {"arcline_path_3": {}, "connectivity": {}}
        for i in mine:
            _write_scene_map(exp, scenes, i, names[i], offsets[i], cfg)
        _dump(exp, root / "maps" / "expansion" / f"{loc}.json")  # (makes maps/)
        png = lambda tmp: matplotlib.image.imsave(tmp, np.zeros((8, 8)), cmap="gray")  # noqa: E731
        write_file_atomic(root / "maps" / f"{tok}.png", png)
    for t in NUSC_TABLES:
        _dump(tables[t], root / version / f"{t}.json")
    _dump(split, root / "maps" / "prediction" / "prediction_scenes.json")


def _fixed_tables() -> dict:
    """The 13 tables, those every folder shares filled (categories, attributes, sensors...)."""
    tables = {t: [] for t in NUSC_TABLES}
    _add(tables, "category", _token("category", "vehicle.car"), "vehicle.car", _CAR, 17)
    _add(tables, "category", _token("category", _PED), _PED, "Adult subcategory.", 2)
    for n in ("vehicle.moving", "vehicle.stopped", "pedestrian.moving", "pedestrian.standing"):
        _add(tables, "attribute", _token("attribute", n), n, n.replace(".", " "))
    for k, lvl in enumerate(("v0-40", "v40-60", "v60-80", "v80-100")):
        _add(tables, "visibility", str(k + 1), lvl, f"visibility of whole object is {lvl}")
    for ch, (modality, *_) in _SENSORS.items():
        trans, rot, intrinsic = _CALIBRATION[ch]
        _add(tables, "sensor", _token("sensor", ch), ch, modality)
        cs = (_token("calibrated_sensor", ch), trans, _token("sensor", ch), rot, intrinsic)
        _add(tables, "calibrated_sensor", *cs)
    return tables


def _write_scene(tables: dict, scenes: Scenes, i: int, name: str, loc: str, offset, cfg) -> list:
    """Scene i's records (log, scene, samples, poses, annotations); its split entries."""
    F, b, (ox, oy) = scenes.ego.shape[1], int(scenes.behaviour[i]), offset
    log_tok, scene_tok = _token(name, "log"), _token(name, "scene")
    _add(tables, "log", log_tok, f"synthetic-{scenes.names[i]}", "synthetic", "2026-01-01", loc)
    ts = [_T0_US + (i * (F + 20) + f) * int(round(cfg.dt * 1e6)) for f in range(F)]
    sample_tok = [_token(name, "sample", f) for f in range(F)]
    about = f"synthetic; {ds.BEHAVIOURS[b] if b >= 0 else 'real'}"
    _add(tables, "scene", scene_tok, log_tok, F, sample_tok[0], sample_tok[-1], name, about)
    ego = scenes.ego[i].numpy()
    sd = {ch: [_token(name, ch, "sample_data", f) for f in range(F)] for ch in _SENSORS}
    for f in range(F):
        _add(tables, "sample", sample_tok[f], ts[f], scene_tok, *_links(sample_tok, f))
        x, y, h = (float(v) for v in ego[f, :3])
        for ch, (_, fmt, height, width) in _SENSORS.items():
            pose, sensor = _token(name, ch, "ego_pose", f), _token("calibrated_sensor", ch)
            _add(tables, "ego_pose", pose, ts[f], _quat(h), [x + ox, y + oy, 0.0])
            row = (sd[ch][f], sample_tok[f], pose, sensor, ts[f], fmt, True, height, width)
            file = f"samples/{ch}/{name}__{ch}__{ts[f]}.{fmt}"
            _add(tables, "sample_data", *row, file, *_links(sd[ch], f))
    agents, amask = scenes.agents[i].numpy(), scenes.agents_mask[i].numpy()
    for m in np.nonzero(amask.any(-1))[0]:
        frames, inst = np.nonzero(amask[m])[0], _token(name, "instance", m)
        ann = [_token(name, "annotation", m, f) for f in frames]
        ped = bool(scenes.agents_is_ped[i, m])
        cat = _token("category", _PED if ped else "vehicle.car")
        _add(tables, "instance", inst, cat, len(frames), ann[0], ann[-1])
        w, length, hgt = (float(v) for v in scenes.agents_size[i, m])
        for k, f in enumerate(frames):
            x, y, h, v = (float(q) for q in agents[m, f])
            moving = "moving" if v > 0.5 else "standing" if ped else "stopped"
            attr = _token("attribute", f"{'pedestrian' if ped else 'vehicle'}.{moving}")
            box = ([x + ox, y + oy, hgt / 2], [w, length, hgt], _quat(h))
            ids = (ann[k], sample_tok[f], inst, "4", [attr])
            _add(tables, "sample_annotation", *ids, *box, *_links(ann, k), 20, 0)
    pred = scenes.pred_idx[i].numpy()
    listed = [f for f in range(F) if pred[f] >= 0 and amask[pred[f], f]]
    return [f"{_token(name, 'instance', pred[f])}_{sample_tok[f]}" for f in listed]


def _write_scene_map(exp: dict, scenes: Scenes, i: int, name: str, offset, cfg) -> None:
    """Scene i's arcline paths as lanes (or connectors) of a map expansion, with polygons, links."""
    paths, is_conn = scenes.paths[i].numpy(), scenes.paths_is_connector[i].numpy()
    tok = {q: _token(name, "lane", q) for q in np.nonzero(paths[..., 4:7].sum(-1) > 0)[0]}
    links = {q: {"incoming": [], "outgoing": []} for q in tok}
    for r in scenes.routes[i].numpy():
        r = [q for q in r if q >= 0]
        for a, b in zip(r[:-1], r[1:]):
            if tok[b] not in links[a]["outgoing"]:
                links[a]["outgoing"].append(tok[b])
                links[b]["incoming"].append(tok[a])
    segs = ds.arcline_segments(paths)  # (Q, 3, 5)
    for q, t in tok.items():
        x, y, yaw, radius, *lengths = (float(v) for v in paths[q, :7])
        end = ds._segment_pose(segs[q, 2], lengths[2])
        end = [float(end[0] + offset[0]), float(end[1] + offset[1]), float(ds.wrap_angle(end[2]))]
        arc = dict(start_pose=[x + offset[0], y + offset[1], yaw], end_pose=end)
        arc["shape"] = _SIGNS_SHAPE[tuple(int(s) for s in paths[q, 7:10])]
        exp["arcline_path_3"][t] = [arc | dict(radius=radius, segment_length=lengths)]
        exp["connectivity"][t] = links[q]
        # polygon: the centre line every 2 m (and its end), offset by half a lane to either side
        u = np.append(np.arange(0.0, sum(lengths), cfg.lane_spacing), sum(lengths))
        pose, _ = ds.pose_along(segs[q], u)
        normal = np.stack([-np.sin(pose[:, 2]), np.cos(pose[:, 2])], -1) * cfg.lane_width / 2
        ring = np.concatenate([pose[:, :2] + normal, (pose[:, :2] - normal)[::-1]]) + offset
        nodes = [_token(t, "node", k) for k in range(len(ring))]
        exp["node"] += [dict(token=n, x=float(px), y=float(py)) for n, (px, py) in zip(nodes, ring)]
        poly = _token(t, "polygon")
        exp["polygon"].append(dict(token=poly, exterior_node_tokens=nodes, holes=[]))
        if is_conn[q]:
            exp["lane_connector"].append(dict(token=t, polygon_token=poly))
            continue
        edges = [_token(t, "from_edge"), _token(t, "to_edge")]
        exp["line"].append(dict(token=edges[0], node_tokens=[nodes[0], nodes[-1]]))
        exp["line"].append(dict(token=edges[1], node_tokens=[nodes[len(u) - 1], nodes[len(u)]]))
        lane = dict(token=t, polygon_token=poly, lane_type="CAR", from_edge_line_token=edges[0])
        lane |= dict(to_edge_line_token=edges[1], left_lane_divider_segments=[])
        exp["lane"].append(lane | dict(right_lane_divider_segments=[]))
    polys = [_token(t, "polygon") for t in tok.values()]
    exp["drivable_area"].append(dict(token=_token(name, "drivable_area"), polygon_tokens=polys))
