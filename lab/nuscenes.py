"""Synthetic scenes (data_synth.py) written as a nuScenes v1.0 dataset folder, the on-disk format
data_real.py reads real nuScenes from: the same tensors come back (test_data_synth.py).

The nuScenes v1.0 format (Caesar et al. 2020; the devkit's schema): <version>/ with 13 JSON
tables, maps/expansion/<location>.json (map expansion 1.3: lanes and lane connectors as arcline
paths, with polygons and connectivity), the map PNGs named by map.json,
maps/prediction/prediction_scenes.json. The ego is the ego_pose of the key-frame sample_data
(CAM_FRONT, LIDAR_TOP) at the sample's timestamp: simultaneous with the annotations.
"""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import numpy as np

from data_synth import (
    _SHAPE_SIGNS,
    BEHAVIOURS,
    Scenes,
    SynthConfig,
    _segment_pose,
    arcline_segments,
    pose_along,
    wrap_angle,
)
from lab.runs import write_folder


NUSC_VERSIONS = ("v1.0-mini", "v1.0-trainval", "v1.0-test")


NUSC_TABLES = (
    "category",
    "attribute",
    "visibility",
    "instance",
    "sensor",
    "calibrated_sensor",
    "ego_pose",
    "log",
    "scene",
    "sample",
    "sample_data",
    "sample_annotation",
    "map",
)


NUSC_LOCATIONS = (
    "singapore-onenorth",
    "singapore-hollandvillage",
    "singapore-queenstown",
    "boston-seaport",
)


MAP_LAYERS = (
    "polygon",
    "line",
    "node",
    "drivable_area",
    "road_segment",
    "road_block",
    "lane",
    "ped_crossing",
    "walkway",
    "stop_line",
    "carpark_area",
    "road_divider",
    "lane_divider",
    "traffic_light",
    "lane_connector",
)


MINI_SCENES = (
    "scene-0061",
    "scene-0103",
    "scene-0553",
    "scene-0655",
    "scene-0757",
    "scene-0796",
    "scene-0916",
    "scene-1077",
    "scene-1094",
    "scene-1100",
)
"""The first 10 written scenes take the v1.0-mini names (the devkit's prediction split knows only
those); later ones are scene-9xxx."""


_SIGNS_SHAPE = {v: k for k, v in _SHAPE_SIGNS.items()}


_T0_US = 1_600_000_000_000_000  # timestamp of the first written frame (microseconds)


def _token(*parts) -> str:
    """A deterministic 32-hex token (the format of nuScenes tokens)."""
    return hashlib.md5("/".join(map(str, parts)).encode()).hexdigest()


def _quat(yaw: float) -> list:
    """Planar yaw -> quaternion [w, x, y, z]."""
    return [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]


def _dump(obj, path: Path):
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as f:
        json.dump(obj, f)


def write_nuscenes(
    scenes: Scenes,
    root,
    version: str = "v1.0-mini",
    cfg: SynthConfig | None = None,
    overwrite: bool = False,
) -> Path:
    """Write scenes as a nuScenes v1.0 dataset folder under root; returns root. Scenes go
    round-robin to the four map locations and sit side by side (300 m apart) in their map's canvas.
    The folder is written whole: into a temporary sibling, renamed into place when complete, under
    a lock on the target (a second writer is refused); an interrupted or killed write leaves the
    old folder (or none). Refuses to replace existing files unless overwrite=True, and a folder
    holding files it does not make at all."""
    cfg = cfg or SynthConfig()
    if version not in NUSC_VERSIONS:
        raise ValueError(f"write_nuscenes: version must be one of {NUSC_VERSIONS}, got {version!r}")
    root = Path(root)
    outputs = (
        [root / version / f"{t}.json" for t in NUSC_TABLES]
        + [root / "maps" / "expansion" / f"{loc}.json" for loc in NUSC_LOCATIONS]
        + [root / "maps" / "prediction" / "prediction_scenes.json"]
    )

    write_folder(
        root,
        lambda tmp: _write_nuscenes(scenes, tmp, version, cfg),
        "write_nuscenes",
        outputs,
        overwrite,
        also=root / "maps",  # (the maps' PNGs)
    )
    return root


def _write_nuscenes(scenes: Scenes, root: Path, version: str, cfg: SynthConfig) -> None:
    """write_nuscenes' work: every file of the dataset under root."""
    S, F = scenes.ego.shape[:2]
    ego, agents, amask, paths = (
        x.numpy() for x in (scenes.ego, scenes.agents, scenes.agents_mask, scenes.paths)
    )
    path_valid = paths[..., 4:7].sum(-1) > 0
    names = [MINI_SCENES[i] if i < len(MINI_SCENES) else f"scene-{9000 + i}" for i in range(S)]
    # placement: a translation per scene that puts it, with 300 m around it, next to the last one
    offsets = np.zeros((S, 2))
    cursor, height = dict.fromkeys(NUSC_LOCATIONS, 300.0), dict.fromkeys(NUSC_LOCATIONS, 300.0)
    locs = [NUSC_LOCATIONS[i % 4] for i in range(S)]
    for i in range(S):
        pts = np.concatenate(
            [
                scenes.lanes[i][scenes.lanes_mask[i]][:, :2].numpy(),
                ego[i, :, :2],
                agents[i][amask[i]][:, :2],
            ]
        )
        lo, hi = pts.min(0), pts.max(0)
        offsets[i] = (cursor[locs[i]] - lo[0], 300.0 - lo[1])
        cursor[locs[i]] += hi[0] - lo[0] + 300.0
        height[locs[i]] = max(height[locs[i]], hi[1] - lo[1] + 600.0)
    cat = {
        False: _token("category", "vehicle.car"),
        True: _token("category", "human.pedestrian.adult"),
    }
    tables = {t: [] for t in NUSC_TABLES}
    tables["category"] = [
        {
            "token": cat[False],
            "name": "vehicle.car",
            "description": "Vehicle designed primarily for personal use.",
            "index": 17,
        },
        {
            "token": cat[True],
            "name": "human.pedestrian.adult",
            "description": "Adult subcategory.",
            "index": 2,
        },
    ]
    attr = {
        n: _token("attribute", n)
        for n in ("vehicle.moving", "vehicle.stopped", "pedestrian.moving", "pedestrian.standing")
    }
    tables["attribute"] = [
        {"token": t, "name": n, "description": n.replace(".", " ")} for n, t in attr.items()
    ]
    tables["visibility"] = [
        {"token": str(k + 1), "level": lvl, "description": f"visibility of whole object is {lvl}"}
        for k, lvl in enumerate(("v0-40", "v40-60", "v60-80", "v80-100"))
    ]
    sensors = {
        "CAM_FRONT": (
            "camera",
            [1.70, 0.016, 1.51],
            [0.4998, -0.5031, 0.4998, -0.4972],
            [[1266.4, 0.0, 816.3], [0.0, 1266.4, 491.5], [0.0, 0.0, 1.0]],
            "jpg",
            900,
            1600,
        ),
        "LIDAR_TOP": (
            "lidar",
            [0.943, 0.0, 1.84],
            [0.7071, 0.0, 0.0, -0.7071],
            [],
            "pcd.bin",
            0,
            0,
        ),
    }
    for ch, (modality, trans, rot, intr, *_rest) in sensors.items():
        tables["sensor"].append(
            {"token": _token("sensor", ch), "channel": ch, "modality": modality}
        )
        tables["calibrated_sensor"].append(
            {
                "token": _token("calibrated_sensor", ch),
                "translation": trans,
                "sensor_token": _token("sensor", ch),
                "rotation": rot,
                "camera_intrinsic": intr,
            }
        )
    # scenes: log, samples, key-frame sample_data with their ego poses, instances and annotations
    split = {}
    for i in range(S):
        name, (ox, oy), b = names[i], offsets[i], int(scenes.behaviour[i])
        log_tok, scene_tok = _token(name, "log"), _token(name, "scene")
        tables["log"].append(
            {
                "token": log_tok,
                "logfile": f"synthetic-{scenes.names[i]}",
                "vehicle": "synthetic",
                "date_captured": "2026-01-01",
                "location": locs[i],
            }
        )
        ts = [_T0_US + (i * (F + 20) + f) * int(round(cfg.dt * 1e6)) for f in range(F)]
        sample_tok = [_token(name, "sample", f) for f in range(F)]
        tables["scene"].append(
            {
                "token": scene_tok,
                "log_token": log_tok,
                "nbr_samples": F,
                "first_sample_token": sample_tok[0],
                "last_sample_token": sample_tok[-1],
                "name": name,
                "description": f"synthetic; {BEHAVIOURS[b] if b >= 0 else 'real'}",
            }
        )
        for f in range(F):
            prev, nxt = _links(sample_tok, f)
            tables["sample"].append(
                {
                    "token": sample_tok[f],
                    "timestamp": ts[f],
                    "scene_token": scene_tok,
                    "prev": prev,
                    "next": nxt,
                }
            )
            x, y, h = (float(v) for v in ego[i, f, :3])
            for ch, (_m, _t, _r, _i, fmt, height_px, width_px) in sensors.items():
                sd_toks = [_token(name, ch, "sample_data", g) for g in (f - 1, f, f + 1)]
                pose_tok = _token(name, ch, "ego_pose", f)
                tables["ego_pose"].append(
                    {
                        "token": pose_tok,
                        "timestamp": ts[f],
                        "rotation": _quat(h),
                        "translation": [x + ox, y + oy, 0.0],
                    }
                )
                tables["sample_data"].append(
                    {
                        "token": sd_toks[1],
                        "sample_token": sample_tok[f],
                        "ego_pose_token": pose_tok,
                        "calibrated_sensor_token": _token("calibrated_sensor", ch),
                        "timestamp": ts[f],
                        "fileformat": fmt,
                        "is_key_frame": True,
                        "height": height_px,
                        "width": width_px,
                        "filename": f"samples/{ch}/{name}__{ch}__{ts[f]}.{fmt}",
                        "prev": sd_toks[0] if f else "",
                        "next": sd_toks[2] if f < F - 1 else "",
                    }
                )
        for m in np.nonzero(amask[i].any(-1))[0]:
            frames = np.nonzero(amask[i, m])[0]
            inst = _token(name, "instance", m)
            ann = [_token(name, "annotation", m, f) for f in frames]
            ped = bool(scenes.agents_is_ped[i, m])
            tables["instance"].append(
                {
                    "token": inst,
                    "category_token": cat[ped],
                    "nbr_annotations": len(frames),
                    "first_annotation_token": ann[0],
                    "last_annotation_token": ann[-1],
                }
            )
            w, length, hgt = (float(v) for v in scenes.agents_size[i, m])
            for k, f in enumerate(frames):
                x, y, h, v = (float(q) for q in agents[i, m, f])
                a = (
                    f"pedestrian.{'moving' if v > 0.5 else 'standing'}"
                    if ped
                    else f"vehicle.{'moving' if v > 0.5 else 'stopped'}"
                )
                tables["sample_annotation"].append(
                    {
                        "token": ann[k],
                        "sample_token": sample_tok[f],
                        "instance_token": inst,
                        "visibility_token": "4",
                        "attribute_tokens": [attr[a]],
                        "translation": [x + ox, y + oy, hgt / 2],
                        "size": [w, length, hgt],
                        "rotation": _quat(h),
                        "prev": _links(ann, k)[0],
                        "next": _links(ann, k)[1],
                        "num_lidar_pts": 20,
                        "num_radar_pts": 0,
                    }
                )
        pred = scenes.pred_idx[i].numpy()
        split[name] = [
            f"{_token(name, 'instance', pred[f])}_{sample_tok[f]}"
            for f in range(F)
            if pred[f] >= 0 and amask[i, pred[f], f]
        ]
    # maps: one record per location (with its logs and a tiny PNG), and each one's expansion json
    import matplotlib.image

    for loc in NUSC_LOCATIONS:
        tok = _token("map", loc)
        tables["map"].append(
            {
                "token": tok,
                "category": "semantic_prior",
                "filename": f"maps/{tok}.png",
                "log_tokens": [_token(names[i], "log") for i in range(S) if locs[i] == loc],
            }
        )
        (root / "maps").mkdir(parents=True, exist_ok=True)
        matplotlib.image.imsave(root / "maps" / f"{tok}.png", np.zeros((8, 8)), cmap="gray")
        expansion = {
            "version": "1.3",
            "canvas_edge": [cursor[loc] + 300.0, height[loc]],
            **{layer: [] for layer in MAP_LAYERS},
            "arcline_path_3": {},
            "connectivity": {},
        }
        for i in (i for i in range(S) if locs[i] == loc):
            _write_scene_map(
                expansion,
                names[i],
                paths[i],
                path_valid[i],
                scenes.paths_is_connector[i].numpy(),
                scenes.routes[i].numpy(),
                offsets[i],
                cfg,
            )
        _dump(expansion, root / "maps" / "expansion" / f"{loc}.json")
    for t in NUSC_TABLES:
        _dump(tables[t], root / version / f"{t}.json")
    _dump(split, root / "maps" / "prediction" / "prediction_scenes.json")


def _links(tokens: list, k: int) -> tuple:
    """(prev, next) tokens of item k of a chain ("" at the ends)."""
    return tokens[k - 1] if k else "", tokens[k + 1] if k < len(tokens) - 1 else ""


def _write_scene_map(exp: dict, name: str, paths, valid, is_conn, routes, offset, cfg):
    """Add one scene's arcline paths to a map expansion: each path becomes a lane (or lane
    connector) with a polygon (the centre line +- W/2), edge lines and connectivity from consecutive
    paths of the routes."""
    ox, oy = offset
    tok = {q: _token(name, "lane", q) for q in np.nonzero(valid)[0]}
    links = {q: {"incoming": [], "outgoing": []} for q in tok}
    for r in routes:
        r = [q for q in r if q >= 0]
        for a, b in zip(r[:-1], r[1:]):
            if tok[b] not in links[a]["outgoing"]:
                links[a]["outgoing"].append(tok[b])
                links[b]["incoming"].append(tok[a])
    segs = arcline_segments(paths)  # (Q, 3, 5)
    for q, t in tok.items():
        x, y, yaw, radius, *lengths = paths[q, :7]
        end = _segment_pose(segs[q, 2], lengths[2])
        exp["arcline_path_3"][t] = [
            {
                "start_pose": [float(x + ox), float(y + oy), float(yaw)],
                "end_pose": [float(end[0] + ox), float(end[1] + oy), float(wrap_angle(end[2]))],
                "shape": _SIGNS_SHAPE[tuple(int(s) for s in paths[q, 7:10])],
                "radius": float(radius),
                "segment_length": [float(v) for v in lengths],
            }
        ]
        exp["connectivity"][t] = links[q]
        # polygon: the centre line every 2 m (and its end), offset by half a lane to either side
        total = sum(lengths)
        u = np.append(np.arange(0.0, total, cfg.lane_spacing), total)
        pose, _ = pose_along(segs[q], u)
        normal = np.stack([-np.sin(pose[:, 2]), np.cos(pose[:, 2])], -1) * cfg.lane_width / 2
        ring = np.concatenate([pose[:, :2] + normal, (pose[:, :2] - normal)[::-1]]) + offset
        nodes = [_token(t, "node", k) for k in range(len(ring))]
        exp["node"] += [
            {"token": n, "x": float(px), "y": float(py)} for n, (px, py) in zip(nodes, ring)
        ]
        poly = _token(t, "polygon")
        exp["polygon"].append({"token": poly, "exterior_node_tokens": nodes, "holes": []})
        if is_conn[q]:
            exp["lane_connector"].append({"token": t, "polygon_token": poly})
        else:
            n = len(u)
            edges = [_token(t, "from_edge"), _token(t, "to_edge")]
            exp["line"] += [
                {"token": edges[0], "node_tokens": [nodes[0], nodes[-1]]},
                {"token": edges[1], "node_tokens": [nodes[n - 1], nodes[n]]},
            ]
            exp["lane"].append(
                {
                    "token": t,
                    "polygon_token": poly,
                    "lane_type": "CAR",
                    "from_edge_line_token": edges[0],
                    "to_edge_line_token": edges[1],
                    "left_lane_divider_segments": [],
                    "right_lane_divider_segments": [],
                }
            )
    polys = [_token(t, "polygon") for t in tok.values()]
    exp["drivable_area"].append({"token": _token(name, "drivable_area"), "polygon_tokens": polys})
