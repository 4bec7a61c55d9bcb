"""Synthetic data for DiffStack: nuScenes-like driving scenes, and the nuScenes v1.0 format written.

The stack (diffstack.py) trains on *planning samples* (paper §4.1, App. D): 4 s of history and 3 s
of future at 2 Hz in the ego frame at t0, with one predicted vehicle, the other agents, the lanes
near the ego and a goal. Scenes, generated here or read by lab/nuscenes.py and lab/waymo.py, give
Scenarios through sample_at; lab/nuscenes.py writes scenes as a nuScenes folder and reads them back
exactly. The command line is lab/data.py's (python -m lab.data).

Shapes: S scenes, F frames (41 = 20 s at 2 Hz), M agents per scene, B samples, A other agents, L
lanes, P points per lane, Q arcline paths per scene, R paths per lane (a route), N fine simulation
steps; 9 = history with t0, 6 = future steps. A state is (x, y, heading h, speed v). Speeds are
backward differences of positions (central ones would leak the future into the inputs). Everything
random takes a numpy Generator from a seed."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import NamedTuple

import numpy as np
import torch

from lab.runs import save_atomic  # hand-over: files written whole (the lab)

# === 1. Config ==============================================================================

BEHAVIOURS = (
    "cut_in",
    "keep_lane",
    "lead_brake",
    "lead_cruise",
    "turn_across",
    "go_straight",
    "cross_go",
    "cross_yield",
    "far",
    "behind",
)
"""The predicted vehicle's manoeuvre, the label in Scenarios.behaviour. They come in pairs that
share a set-up and differ in what happens at the event time, so the history only partly tells them
apart. The predicted vehicle is
    cut_in / keep_lane        in the next lane, a little ahead: merges in front of the ego, or not
    lead_brake / lead_cruise  ahead in the ego's lane: brakes hard (maybe to a stop), or keeps going
    turn_across / go_straight oncoming: turns left across the ego's lane at an intersection, or not
    cross_go / cross_yield    on the crossing road, from the ego's right: crosses in front, or stops
    far                       35-60 m ahead, next lane: changes lanes or not (errors don't matter)
    behind                    behind, next lane: merges behind the ego or not (errors don't matter)
"""
_B = {name: i for i, name in enumerate(BEHAVIOURS)}
_INTERSECTION_BEHAVIOURS = ("turn_across", "go_straight", "cross_go", "cross_yield")


@dataclass
class SynthConfig:
    """Knobs of the synthetic generator and of cutting planning samples (real nuScenes too)."""

    # --- time (paper App. D.1: nuScenes at 2 Hz, 4 s of history, 3 s of future) ---
    dt: float = 0.5  # frame period (s): nuScenes key frames are 2 Hz
    # frames per scene (20 s): 4 s history + 10 s closed-loop simulation + 3 s horizon fit
    frames: int = 41
    hist: int = 8  # past steps of a sample's history (the current state makes 9)
    fut: int = 6  # future steps of a sample (3 s)
    # step of the generator's simulation (s); frames are every dt / sim_dt steps
    sim_dt: float = 0.25
    # --- behaviour mix ---
    # weight of each behaviour (BEHAVIOURS); normalised, a missing one is 0
    mix: dict = field(
        default_factory=lambda: {
            "cut_in": 0.15,
            "keep_lane": 0.13,
            "lead_brake": 0.12,
            "lead_cruise": 0.10,
            "turn_across": 0.09,
            "go_straight": 0.08,
            "cross_go": 0.09,
            "cross_yield": 0.08,
            "far": 0.08,
            "behind": 0.08,
        }
    )
    # P(an active manoeuvre is announced in the history: a drift to the line, early slowing)
    cue_prob: float = 0.7
    # P(a passive twin shows the same cue, then does not act: keeps lane, resumes speed)
    false_cue_prob: float = 0.3
    # probability of an intersection in scenes whose behaviour does not need one
    intersection_prob: float = 0.25
    # probability that a road without intersection is a constant-curvature arc (else straight)
    curved_prob: float = 0.5
    # smallest road radius (m); curvature uniform in [1/1000, 1/min_radius], random sign
    min_radius: float = 150.0
    # --- agents ---
    # the ego's initial speed (m/s); its desired speed is 0-10 % higher, at most 15
    ego_speed: tuple = (6.0, 14.0)
    # most moving background vehicles per scene (a uniform count from half of it)
    n_vehicles: int = 6
    n_parked: int = 2  # most parked vehicles on the kerb per scene
    n_peds: int = 4  # most pedestrians on the sidewalks per scene
    lane_width: float = 3.5  # lane width W (m)
    # --- tracking noise on the other agents' logged tracks (ego poses are exact, as localised) ---
    # std of the AR(1) position noise (m); applied to history AND future, like real annotations
    pos_noise: float = 0.08
    yaw_noise: float = 0.01  # std of the AR(1) heading noise (rad)
    # AR(1) correlation of the noise from one frame to the next (a tracker's errors are smooth)
    noise_corr: float = 0.9
    # --- cutting samples (synthetic and real) ---
    # samples cut from a synthetic scene, at random frames of event_window
    samples_per_scene: int = 4
    # synthetic t0s: 2.5 s before the event (in the 3 s future) to 0.5 s after (seen)
    event_window: tuple = (-5, 1)
    lane_points: int = 40  # P: points per lane in a sample (2 m apart: 80 m)
    lane_spacing: float = 2.0  # distance between lane points (m)
    # a sample's lane starts this many points behind the point closest to the ego
    lane_behind: int = 2
    max_lanes: int = 12  # L: at most this many lanes per sample, the closest to the ego
    # a lane is near the ego when one of its points is within this distance (m)
    lane_radius: float = 30.0
    max_others: int = 16  # A: at most this many other agents per sample, the closest to the ego
    # other agents farther than this from the ego at t0 are left out (m)
    others_radius: float = 50.0
    # reader: map lanes this near the ego's logged path (m) form the scene's lane graph
    map_radius: float = 60.0
    val_fraction: float = 0.15  # fraction of scenes (not samples) held out for validation


# === 2. Batches: Scenarios (planning samples) and Scenes (world-frame logs) =================


class _Batch:
    """Indexing, length, concatenation, dtype conversion: dataclasses whose tensors share dim 0."""

    def __len__(self):
        return next(iter(self.tensors().values())).shape[0]

    def tensors(self) -> dict:
        return {
            f.name: getattr(self, f.name)
            for f in dataclasses.fields(self)
            if isinstance(getattr(self, f.name), torch.Tensor)
        }

    def _map(self, tensor, other=None):
        """The same class: tensor(v) for each tensor field v, other(v) for the others (lists)."""
        return type(self)(
            **{
                f.name: tensor(v)
                if isinstance(v := getattr(self, f.name), torch.Tensor)
                else other(v)
                if other
                else v
                for f in dataclasses.fields(self)
            }
        )

    def __getitem__(self, idx):
        """idx: a slice, an int64 index tensor or a bool mask -> the same class with those rows."""

        def rows(v):
            return np.arange(len(v))[idx.cpu().numpy() if isinstance(idx, torch.Tensor) else idx]

        return self._map(lambda v: v[idx], lambda v: list(np.asarray(v, dtype=object)[rows(v)]))

    def to(self, dtype=None, device=None):
        """Floating tensors to dtype (bool/int stay), everything to device."""
        return self._map(
            lambda v: v.to(
                device=device, dtype=dtype if dtype is not None and v.is_floating_point() else None
            )
        )

    @classmethod
    def cat(cls, items: list):
        """Concatenate along dim 0, padding other dims to the largest (0 / False; indices: -1)."""
        out = {}
        for f in dataclasses.fields(cls):
            vs = [getattr(b, f.name) for b in items]
            if not isinstance(vs[0], torch.Tensor):
                out[f.name] = [x for v in vs for x in v]
                continue
            shape = [max(v.shape[d] for v in vs) for d in range(1, vs[0].dim())]
            fill = -1 if vs[0].dtype == torch.int64 else 0
            padded = []
            for v in vs:
                p = torch.full((v.shape[0], *shape), fill, dtype=v.dtype)
                p[tuple(slice(0, n) for n in v.shape)] = v
                padded.append(p)
            out[f.name] = torch.cat(padded, 0)
        return cls(**out)


@dataclass
class Scenarios(_Batch):
    """A batch of planning samples, every coordinate in the EGO FRAME AT t0 (ego at the origin,
    heading +x). These are the fields diffstack.py consumes; padding is 0 / False, never NaN."""

    ego_hist: torch.Tensor  # (B, 9, 4)   ego states t-8..t0; ego_hist[:, -1] = (0, 0, 0, v)
    ego_fut: torch.Tensor  # (B, 6, 4)    ego GT future t1..t6 (the expert's plan)
    agent_hist: torch.Tensor  # (B, 9, 4)  the predicted vehicle's history
    # (B, 9) bool  observed steps (missing early ones hold the earliest observed)
    agent_hist_mask: torch.Tensor
    agent_fut: torch.Tensor  # (B, 6, 4)   its GT future (always complete)
    others_hist: torch.Tensor  # (B, A, 9, 4) other vehicles and pedestrians
    # (B, A, 6, 4)  their GT futures (gaps hold the nearest observed state)
    others_fut: torch.Tensor
    others_mask: torch.Tensor  # (B, A) bool  a real agent
    others_is_ped: torch.Tensor  # (B, A) bool
    # (B, L, P, 3)  lane centre lines (x, y, heading) along the driving direction, 2 m apart
    lanes: torch.Tensor
    lanes_mask: torch.Tensor  # (B, L, P) bool  valid points (a prefix of each lane)
    goal: torch.Tensor  # (B, 4)   = ego_fut[:, -1]
    behaviour: torch.Tensor  # (B,) int64  index into BEHAVIOURS; -1 for real data


@dataclass
class Scenes(_Batch):
    """World-frame logs at 2 Hz (float64: global nuScenes coordinates are thousands of metres). The
    map is kept twice: as arcline paths with the lanes' routes through them (what the nuScenes map
    expansion stores; the writer needs it) and as the routes discretised every 2 m (what sample_at
    crops)."""

    ego: torch.Tensor  # (S, F, 4)  ego states (x, y, h, v)
    agents: torch.Tensor  # (S, M, F, 4)  other agents' logged states (tracking noise included)
    agents_mask: torch.Tensor  # (S, M, F) bool  annotated at that frame
    agents_is_ped: torch.Tensor  # (S, M) bool
    agents_size: torch.Tensor  # (S, M, 3)  width, length, height (m)
    # (S, F) int64  the predicted agent for a sample cut at that frame (-1: none)
    pred_idx: torch.Tensor
    # (S,) int64  frame of the predicted agent's manoeuvre (-1 for real data)
    event_frame: torch.Tensor
    behaviour: torch.Tensor  # (S,) int64  index into BEHAVIOURS (-1 for real data)
    # (S, L, P, 3)  routes through the lane graph, discretised every 2 m from their start
    lanes: torch.Tensor
    lanes_mask: torch.Tensor  # (S, L, P) bool
    # (S, Q, 10)  arcline paths [x, y, yaw, radius, l0, l1, l2, sign0, sign1, sign2]
    paths: torch.Tensor
    paths_is_connector: torch.Tensor  # (S, Q) bool  lane connector (inside an intersection) or lane
    # (S, L, R) int64  the paths each lane runs through, in order (-1: padding)
    routes: torch.Tensor
    names: list  # S scene names


# === 3. Geometry: arcline paths, poses along them, discretisation, the road frame ===========
# A nuScenes lane is arcline paths: a start pose and three pieces of curvature sign_k / radius,
# length l_k (shape LSR = left arc, straight, right arc, ...). The generator's roads use them too,
# so a map written and read back gives the same lanes bit for bit. A *segment* is one piece,
# [x0, y0, yaw0, kappa, length]; at arc length u along it:
#     x = x0 + cos(yaw0) A - sin(yaw0) C,   y = y0 + sin(yaw0) A + cos(yaw0) C,
#     yaw = yaw0 + kappa u,   A = sin(kappa u) / kappa,   C = (1 - cos(kappa u)) / kappa.

_SHAPE_SIGNS = {
    "LSL": (1, 0, 1),
    "LSR": (1, 0, -1),
    "RSL": (-1, 0, 1),
    "RSR": (-1, 0, -1),
    "LRL": (1, -1, 1),
    "RLR": (-1, 1, -1),
}  # the devkit's compute_segment_sign


def wrap_angle(a):
    """Angle to (-pi, pi] (numpy or torch), the project's one wrapping function:
    atan2(sin a, cos a), not a modulo, so that it is smooth away from +-pi with gradient 1."""
    if torch.is_tensor(a):
        return torch.atan2(torch.sin(a), torch.cos(a))
    return np.arctan2(np.sin(a), np.cos(a))


def _arc(kappa, u):
    """(A, C) above for curvature kappa and arc length u (broadcast); a Taylor series where
    |kappa u| < 1e-4."""
    ku = kappa * u
    small = np.abs(ku) < 1e-4
    ks = np.where(small, 1.0, kappa)
    a = np.where(small, u * (1 - ku**2 / 6), np.sin(ku) / ks)
    c = np.where(small, u * ku / 2, (1 - np.cos(ku)) / ks)
    return a, c


def _segment_pose(seg, u):
    """Pose (x, y, yaw) at arc length u along segments seg (..., 5); u broadcasts to seg[..., 0]."""
    x0, y0, yaw0, kappa = seg[..., 0], seg[..., 1], seg[..., 2], seg[..., 3]
    a, c = _arc(kappa, u)
    cos, sin = np.cos(yaw0), np.sin(yaw0)
    return np.stack([x0 + cos * a - sin * c, y0 + sin * a + cos * c, yaw0 + kappa * u], -1)


def arcline_segments(paths):
    """Arcline paths (..., 10) -> their three segments (..., 3, 5), each from the last one's end."""
    start, radius, lengths, signs = paths[..., :3], paths[..., 3], paths[..., 4:7], paths[..., 7:10]
    segs = []
    for k in range(3):
        # padding: r = 0
        kappa = np.divide(signs[..., k], radius, out=np.zeros_like(radius), where=radius > 0)
        segs.append(np.concatenate([start, kappa[..., None], lengths[..., k, None]], -1))
        start = _segment_pose(segs[-1], lengths[..., k])
    return np.stack(segs, -2)


def route_segments(paths, routes):
    """The segments of lanes that run through paths (S, Q, 10) in the order routes (S, L, R) gives
    (-1 = none): (S, L, 3R, 5), padded with zero-length segments."""
    segs = arcline_segments(paths)  # (S, Q, 3, 5)
    # (S, L, R, 3, 5)
    gathered = np.take_along_axis(segs[:, None], np.maximum(routes, 0)[..., None, None], 2)
    gathered[..., 4] *= routes[..., None] >= 0  # padding -> length 0
    return gathered.reshape(*routes.shape[:2], -1, 5)


def pose_along(segs, u):
    """Poses (..., N, 3) and curvatures (..., N) at arc lengths u (..., N) along chained segments
    (..., G, 5). Each segment keeps its own start pose (no drift across joints); the first / last
    one extends past the ends."""
    lengths = segs[..., 4]  # (..., G)
    starts = np.cumsum(lengths, -1) - lengths
    G = lengths.shape[-1]
    first = np.argmax(lengths > 0, -1)[..., None]  # (..., 1)
    k = np.broadcast_to(first, u.shape).copy()  # (..., N) the segment each u falls on
    for g in range(G):  # G is small: a loop over segments, vectorised over everything else
        k = np.where((lengths[..., g : g + 1] > 0) & (starts[..., g : g + 1] <= u), g, k)
    seg = np.stack([np.take_along_axis(segs[..., c], k, -1) for c in range(5)], -1)  # (..., N, 5)
    return _segment_pose(seg, u - np.take_along_axis(starts, k, -1)), seg[..., 3]


MAX_LANE_POINTS = 20_000
"""Most points of one discretised lane or route (40 km at 2 m; generated paths are ~430 m, real
lanes under 1 km): it stops a corrupt length (say 1e9 m) from allocating gigabytes."""


def _lane_points(length: float, spacing: float):
    """Number of points discretize gives a polyline of this length (m); math.inf on overflow."""
    q = float(length) / spacing + 1e-9
    return int(np.floor(q)) + 1 if math.isfinite(q) else math.inf


def discretize(segs, spacing: float):
    """Points every `spacing` metres from the start of chained segments (..., G, 5):
    (..., P, 3) poses (yaw wrapped) and (..., P) mask, P from the longest; invalid points are 0.
    A ValueError before allocating if spacing <= 0, a length is not finite, P > MAX_LANE_POINTS."""
    total = segs[..., 4].sum(-1)  # (...)
    if not (spacing > 0 and math.isfinite(spacing)):
        raise ValueError(f"discretize: spacing must be a finite number > 0 (m), got {spacing!r}")
    if total.size and not np.isfinite(total).all():
        raise ValueError("discretize: a segment length is not finite")
    if total.size and _lane_points(total.max(), spacing) > MAX_LANE_POINTS:
        raise ValueError(
            f"discretize: a polyline of {total.max():.6g} m needs "
            f"{_lane_points(total.max(), spacing)} points at {spacing} m spacing, more than "
            f"MAX_LANE_POINTS = {MAX_LANE_POINTS}"
        )
    P = int(np.floor(total.max() / spacing + 1e-9)) + 1 if total.size else 1
    u = np.broadcast_to(np.arange(P) * spacing, (*total.shape, P))
    mask = (u <= total[..., None] + 1e-9) & (total[..., None] > 0)  # an empty route has no points
    pts, _ = pose_along(segs, u)
    pts[..., 2] = wrap_angle(pts[..., 2])
    return np.where(mask[..., None], pts, 0.0), mask


def frenet_to_xy(s, d, kappa):
    """The road frame: a reference arc from the origin heading +x with curvature kappa; (s along,
    d left)."""
    a, c = _arc(kappa, s)
    th = kappa * s
    return a - d * np.sin(th), c + d * np.cos(th), th


def xy_to_frenet(x, y, kappa):
    """Inverse of frenet_to_xy (closed form: d = (2y - kappa (x^2 + y^2)) / (1 + r), no 1/kappa)."""
    r = np.sqrt((kappa * x) ** 2 + (1 - kappa * y) ** 2)
    d = (2 * y - kappa * (x**2 + y**2)) / (1 + r)
    ks = np.where(np.abs(kappa) < 1e-12, 1.0, kappa)
    s = np.where(np.abs(kappa) < 1e-12, x, np.arctan2(kappa * x, 1 - kappa * y) / ks)
    return s, d


def backward_speed(xy, mask, t):
    """Speed by backward differences: |p_t - p_prev| / (t - t_prev), prev = the previous observed
    frame. xy (..., F, 2), mask (..., F), t (..., F) seconds -> (..., F); a track's first frame
    copies its second."""
    F = xy.shape[-2]
    t = np.broadcast_to(t, mask.shape)
    idx = np.where(mask, np.arange(F), -1)
    prev = np.maximum.accumulate(
        np.concatenate([np.full(idx.shape[:-1] + (1,), -1), idx[..., :-1]], -1), -1
    )
    has_prev = mask & (prev >= 0)
    p = np.maximum(prev, 0)
    dp, dt = xy - np.take_along_axis(xy, p[..., None], -2), t - np.take_along_axis(t, p, -1)
    v = np.where(has_prev, np.linalg.norm(dp, axis=-1) / np.where(has_prev, dt, 1.0), 0.0)
    obs = np.where(mask, np.arange(F), F)
    after = np.minimum.accumulate(obs[..., ::-1], -1)[..., ::-1]  # first observed frame >= f
    # first observed frame > f
    nxt = np.concatenate([after[..., 1:], np.full(idx.shape[:-1] + (1,), F)], -1)
    first = mask & ~has_prev & (nxt < F)
    return np.where(first, np.take_along_axis(v, np.minimum(nxt, F - 1), -1), v)


# === 4. Synthetic scenes ====================================================================
# One scene = one road (n_fwd lanes in the ego's direction, n_opp oncoming; straight or an arc),
# sometimes crossed by a two-lane road at an intersection at s = 0. Every agent follows an arcline
# *path* (its lane, or a turn) with a scripted speed program and lateral offset; agents do not react
# to each other and are placed to rarely collide. The ego is simulated last by an expert that sees
# everybody's TRUE future, so its log is a sensible plan to imitate; scenes where anything still
# collides are regenerated. Road frame: s along the centre divider, d to the left; forward lane i
# (0 next to the divider) at d = -(i + 1/2) W, oncoming lane j at +(j + 1/2) W.

_CAR = (1.9, 4.6, 1.6)  # width, length, height (m)
_PED = (0.6, 0.6, 1.75)
_EGO_W, _EGO_L = 1.9, 4.7
_BOX_MARGIN = 3.0  # between the road edges and the intersection box (m)
# paths that approach the intersection start this far before it; u = 300 is the box edge
_FAR = 300.0
_IDM = dict(a_max=1.5, b=2.5, T=1.0, s0=2.0, look=6)  # the ego's IDM, look-ahead in frames (3 s)
_LONG = 1e4  # length of a path's open-ended segment (m)


def _smoothstep(x):
    """Quintic ramp 0 -> 1 on [0, 1] and its derivative (zero speed and acceleration at 0 and 1)."""
    x = np.clip(x, 0.0, 1.0)
    return x**3 * (10 - 15 * x + 6 * x**2), 30 * x**2 * (1 - x) ** 2


def _straight(x, y, yaw, length, ones):
    """A straight arcline path (shape LSR with lengths [0, L, 0]) as (..., 10)."""
    z = 0 * ones
    return np.stack(
        [x * ones, y * ones, yaw * ones, 1000 * ones, z, length * ones, z, ones, z, -ones], -1
    )


def _arc_path(x, y, yaw, radius, sign, l_arc, l_straight, ones):
    """An arc of the given sign (+1 left) followed by a straight: shape LSR/RSL (LSL/RSR without the
    straight), as (..., 10)."""
    cols = [x, y, yaw, radius, l_arc, l_straight, 0, sign, 0, np.where(l_straight > 0, -sign, sign)]
    return np.stack([c * ones for c in cols], -1)


def _lane_d(i, W):
    """Road offset d of forward lane i (0 next to the divider); oncoming lane j: -_lane_d(j, W)."""
    return -(i + 0.5) * W


def _lane_path(d, kappa, forward):
    """The open-ended path of the lane at road offset d, u = 0 at s = 0: segments (..., 3, 5)."""
    one = np.ones_like(d * kappa)
    k_lane = kappa / (1 - kappa * d)
    yaw, k = np.where(forward, 0.0, np.pi), np.where(forward, k_lane, -k_lane)
    seg0 = np.stack([0 * one, d * one, yaw * one, k * one, _LONG * one], -1)
    return np.stack([seg0, 0 * seg0, 0 * seg0], -2)


def _draw_layout(S, cfg, rng):
    """Per-scene road, behaviour, timing and ego speed: a dict of (S,) arrays."""
    if unknown := set(cfg.mix) - set(BEHAVIOURS):
        raise ValueError(
            f"SynthConfig.mix: unknown behaviours {sorted(unknown)}; known: {BEHAVIOURS}"
        )
    w = np.array([float(cfg.mix.get(b, 0.0)) for b in BEHAVIOURS])
    if (w < 0).any() or w.sum() <= 0:
        raise ValueError(
            f"SynthConfig.mix needs non-negative weights with a positive sum, got {cfg.mix}"
        )
    beh = rng.choice(len(BEHAVIOURS), S, p=w / w.sum())
    inter = np.isin(beh, [_B[b] for b in _INTERSECTION_BEHAVIOURS]) | (
        rng.random(S) < cfg.intersection_prob
    )
    n_fwd, n_opp = rng.integers(2, 4, S), rng.integers(1, 3, S)
    curv = rng.uniform(1 / 1000, 1 / cfg.min_radius, S) * rng.choice([-1.0, 1.0], S)
    kappa = np.where(~inter & (rng.random(S) < cfg.curved_prob), curv, 0.0)
    ego_lane = np.floor(rng.random(S) * n_fwd).astype(int)
    side = np.where(rng.random(S) < 0.5, -1, 1)
    side = np.where((ego_lane + side < 0) | (ego_lane + side >= n_fwd), -side, side)
    v_e0 = rng.uniform(*cfg.ego_speed, S)
    v_des = np.minimum(
        np.minimum(v_e0 * rng.uniform(1.0, 1.1, S), 15.0),
        np.sqrt(2.5 / np.maximum(abs(kappa), 1e-9)),
    )
    return dict(
        beh=beh,
        inter=inter,
        n_fwd=n_fwd,
        n_opp=n_opp,
        kappa=kappa,
        ego_lane=ego_lane,
        adj_lane=ego_lane + side,
        t_e=rng.uniform(7.0, 12.5, S),
        v_e0=v_e0,
        v_des=v_des,
    )


def _script_agents(lay, cfg, rng):
    """Programs for every agent slot (slot 0 = the predicted vehicle) and the ego's start s_e0. A
    program: path segments; start u and speed v0; a speed reference v0 -> v1 (from t1) -> v2
    (from t2) tracked with |decel| <= dec1 / dec2; an optional stop at u_stop held until t_go; a
    lateral offset
        d(t) = d0 + D S((t - t_lc)/T_lc) + c (S((t - t_up)/T_up) - S((t - t_dn)/T_dn))
    (S the smoothstep): a lane change D, and a cue c (a drift to the lane line before it, or a drift
    and back). Agents with a finite anchor_t are shifted after simulation so that they are at
    anchor_u at anchor_t. Each step draws from rng in turn; reordering them changes the data."""
    # predicted; ego-lane leader + background; parked; peds
    p = _blank_programs(len(lay["beh"]), 1 + cfg.n_vehicles + cfg.n_parked + cfg.n_peds)
    q = _twin_setup(lay, cfg, rng, p["size"])
    _ego_start(q, rng)
    _place_predicted(p, q)
    _adjacent_event(p, q)
    _lead_event(p, q, rng)
    _oncoming_event(p, q)
    _crossing_event(p, q)
    _leader(p, q, rng)
    _background(p, q, cfg, rng)
    _parked(p, q, cfg, rng)
    _pedestrians(p, q, cfg, rng)
    p["v1"] = np.where(np.isinf(p["t1"]), p["v0"], p["v1"])  # unused phases hold the initial speed
    p["v2"] = np.where(np.isinf(p["t2"]), p["v0"], p["v2"])
    return p, q.s_e0


def _blank_programs(S, M):
    """Every slot (S, M) absent and idle (no phase, stop, lane change or anchor), until scripted."""
    inf = np.inf
    fill = dict(u_start=0.0, v0=0.0, v1=0.0, v2=0.0, d0=0.0, D=0.0, c=0.0, anchor_u=0.0)
    fill |= dict(t1=inf, t2=inf, u_stop=inf, t_lc=inf, t_up=inf, t_dn=inf, anchor_t=inf)
    fill |= dict(dec1=2.0, dec2=2.0, t_go=-inf, b_stop=2.0, T_lc=3.0, T_up=1.5, T_dn=1.5)
    p = {k: np.full((S, M), x) for k, x in fill.items()}
    p.update(exists=np.zeros((S, M), bool), is_ped=np.zeros((S, M), bool))
    p.update(segs=np.zeros((S, M, 3, 5)), size=np.broadcast_to(np.array(_CAR), (S, M, 3)).copy())
    return p


def _twin_setup(lay, cfg, rng, size):
    """lay and the predicted vehicle's set-up, the same for both twins: the history hides which."""
    S, W, t_e, v_e0 = len(lay["beh"]), cfg.lane_width, lay["t_e"], lay["v_e0"]
    q = SimpleNamespace(**lay, W=W)

    def U(lo, hi):
        return rng.uniform(lo, hi, S)

    def is_(*names):
        return np.isin(lay["beh"], [_B[n] for n in names])

    q.de, q.dj = _lane_d(lay["ego_lane"], W), _lane_d(lay["adj_lane"], W)
    q.bx = W + _BOX_MARGIN  # half-length of the intersection box along the main road
    q.y_bot = -(lay["n_fwd"] * W + _BOX_MARGIN)  # the box's edge on the ego's right
    q.R_left = q.bx + W / 2  # radius of the oncoming left turn
    size[:, 0, 0], size[:, 0, 1] = U(1.8, 2.0), U(4.3, 4.9)
    q.cue, q.false_cue = rng.random(S) < cfg.cue_prob, rng.random(S) < cfg.false_cue_prob
    # (a) an agent in the adjacent forward lane: cut_in / keep_lane / far / behind.
    #     Its lane change starts 1 s before the event (the event: it reaches the ego's lane); in
    #     the middle of it (t_ref) it is `gap` ahead of the ego's nominal, constant-speed position.
    q.adj = is_("cut_in", "keep_lane", "far", "behind")
    near, far = is_("cut_in", "keep_lane"), is_("far")
    q.T_lc = U(2.5, 4.0)
    q.t_lc = t_e - 1.0
    q.t_ref = q.t_lc + q.T_lc / 2
    q.gap = np.select([near, far], [U(4, 10), U(35, 60)], U(-25, -10))
    v_adj = np.select([near, far], [v_e0 + U(-4, 0), v_e0 + U(-1, 1)], v_e0 + U(-2, 0.5))
    q.v_adj = v_adj.clip(5.0, 20.0)
    q.changes = is_("cut_in") | (is_("far", "behind") & (rng.random(S) < 0.5))
    q.toward = np.sign(q.de - q.dj)
    # (b) the vehicle ahead in the ego's lane: lead_brake / lead_cruise
    q.lead, q.brake = is_("lead_brake", "lead_cruise"), is_("lead_brake")
    q.v_lead = np.maximum(v_e0 + U(-1, 0.5), 4.0)
    q.g_lead = _CAR[1] + (_IDM["s0"] + _IDM["T"] * v_e0) * U(0.7, 1.3)
    # (c) an oncoming vehicle at the intersection: turn_across / go_straight. The turner reaches the
    #     ego's lane at the event time, the box edge R acos(h / R) / v_turn earlier (h: see below).
    q.turn, q.onc = is_("turn_across"), is_("turn_across", "go_straight")
    q.v_onc, q.v_turn = U(7, 11), U(4.0, 5.5)
    q.h = q.de - (W / 2 - q.R_left)  # the ego lane's offset from the turn's centre
    t_box = t_e - q.R_left * np.arccos(np.clip(q.h / q.R_left, -1, 1)) / q.v_turn
    # (d) a crossing vehicle from the ego's right: cross_go / cross_yield; in the ego's lane at t_e
    q.cross, q.yields = is_("cross_go", "cross_yield"), is_("cross_yield")
    q.v_cross = U(6, 9)
    q.t_box = np.where(q.cross, t_e - (q.de - q.y_bot) / q.v_cross, t_box)
    return q


def _ego_start(q, rng):
    """The ego's start q.s_e0 (road s), which decides whether and when it meets slot 0."""
    # Intersection situations: its front reaches the conflict point delta after the other vehicle's
    # centre (the expert then yields); the same delta for both twins, so nothing leaks. Other
    # scenes: 4-16 s before an intersection if any, else s = 0.
    S = len(q.beh)
    q.delta = rng.uniform(-0.5, 1.0, S)
    x_turn_conflict = q.bx - np.sqrt(np.maximum(q.R_left**2 - q.h**2, 0.0))
    q.s_e0 = np.select(
        [q.onc, q.cross, q.inter],
        [
            x_turn_conflict - _EGO_L / 2 - 1.0 - q.v_e0 * (q.t_e + q.delta),
            q.W / 2 - 1.0 - _EGO_L / 2 - q.v_e0 * (q.t_e + q.delta),
            -q.v_e0 * rng.uniform(4, 16, S),
        ],
        0.0,
    )


def _place_predicted(p, q):
    """Slot 0's path, initial speed and start: the set-up made concrete for the simulation."""
    S = len(q.beh)
    p["exists"][:, 0] = True
    p["segs"][:, 0] = np.select(
        [m[:, None, None] for m in (q.adj, q.lead, q.turn, q.onc)],
        [
            _lane_path(q.dj, q.kappa, True),
            _lane_path(q.de, q.kappa, True),
            _turn_path(S, q.W, q.bx, q.R_left, q.n_fwd),
            _turn_path(S, q.W, q.bx, q.R_left, q.n_fwd, turn=False),
        ],
        _cross_path(S, q.W, q.y_bot),
    )
    p["v0"][:, 0] = np.select([q.adj, q.lead, q.onc], [q.v_adj, q.v_lead, q.v_onc], q.v_cross)
    p["u_start"][:, 0] = np.where(
        q.adj,
        (q.s_e0 + q.v_e0 * q.t_ref + q.gap) * (1 - q.kappa * q.dj) - q.v_adj * q.t_ref,
        np.where(q.lead, (q.s_e0 + q.g_lead) * (1 - q.kappa * q.de), 0.0),
    )


def _set_predicted(p, where, **fields):
    """Slot 0's program fields in the scenes where `where` holds (the others keep theirs)."""
    for k, v in fields.items():
        p[k][:, 0] = np.where(where, v, p[k][:, 0])


def _adjacent_event(p, q):
    """Adjacent: a lane change and its cue (a drift to the line) or false cue (a drift and back)."""
    change, drift = q.adj & q.changes, q.adj & np.where(q.changes, q.cue, q.false_cue)
    t_dn = np.where(q.changes, q.t_lc, q.t_lc + 0.5)  # drift back as the change starts, or after
    _set_predicted(p, change, D=q.de - q.dj, t_lc=q.t_lc)
    _set_predicted(p, drift, c=0.4 * q.toward, t_up=q.t_lc - 1.5, t_dn=t_dn)
    p["T_lc"][:, 0], p["T_dn"][:, 0] = q.T_lc, np.where(q.changes, q.T_lc, 2.0)


def _lead_event(p, q, rng):
    """Lead: brakes 1 s before t_e (to 0-50 % of its speed, a third to a stop), cued by slowing."""
    S, t_brake = len(q.beh), q.t_e - 1.0
    _set_predicted(p, q.lead, t1=t_brake, t2=t_brake)
    _set_predicted(p, q.lead & np.where(q.brake, q.cue, q.false_cue), t1=t_brake - 1.5)
    p["v1"][:, 0], p["dec1"][:, 0] = q.v_lead - 1.5, 1.0  # the cue: slowing gently first
    keep = rng.uniform(0, 0.5, S)
    p["v2"][:, 0] = np.where(q.brake, q.v_lead * keep * (rng.random(S) > 0.33), q.v_lead)
    p["dec2"][:, 0] = np.where(q.brake, rng.uniform(2.5, 4.0, S), 2.0)


def _oncoming_event(p, q):
    """Oncoming: the turner slows to v_turn before the box and turns; a false cue slows alike."""
    turn, onc, t_box = q.turn, q.onc, q.t_box
    gentle = np.where(turn, q.cue, q.false_cue)  # early and gently when cued, else late and harder
    dec = np.where(gentle, 1.5, 3.0)
    slows = turn | (onc & q.false_cue)  # (a go_straight one speeds up again at the box)
    _set_predicted(p, onc & slows, t1=t_box - (q.v_onc - q.v_turn) / dec - 1.0, t2=t_box)
    _set_predicted(p, turn, t2=t_box + 3.0)
    _set_predicted(p, onc, v1=q.v_turn, dec1=dec, v2=q.v_onc, anchor_t=t_box)
    p["anchor_u"][:, 0] = _FAR  # anchored vehicles (oncoming, crossing) are at the box edge


def _crossing_event(p, q):
    """Crossing: cross_go is at the box edge at t_box; cross_yield stops and lets the ego pass."""
    cross, yields, v_cross, t_box = q.cross, q.yields, q.v_cross, q.t_box
    # cross_go with a false cue slows to half speed first
    go_slow = cross & ~yields & q.false_cue
    _set_predicted(p, go_slow, t1=t_box - 3.0, v1=0.5 * v_cross, dec1=1.5, t2=t_box - 1.0)
    _set_predicted(p, cross, v2=v_cross)
    _set_predicted(p, cross & ~yields, anchor_t=t_box)
    # cross_yield stops 1 m before the box at t_box (braking early when cued), goes once the ego
    # has passed
    b_stop = np.where(q.cue, 1.2, 3.0)
    u_stop = _FAR - 1.0 - p["size"][:, 0, 1] / 2
    u_start = u_stop - v_cross**2 / (2 * b_stop) - v_cross * (t_box - v_cross / b_stop)
    t_go = q.t_e + q.delta + (2.0 + _EGO_L) / q.v_e0 + 2.0
    _set_predicted(p, yields, u_stop=u_stop, u_start=u_start, t_go=t_go)
    p["b_stop"][:, 0] = b_stop


def _leader(p, q, rng):
    """Slot 1: a leader far ahead in the ego's lane that drives away (not in lead situations)."""
    S = len(q.beh)
    p["exists"][:, 1] = ~q.lead & (rng.random(S) < 0.5)
    p["segs"][:, 1] = _lane_path(q.de, q.kappa, True)
    p["u_start"][:, 1] = (q.s_e0 + rng.uniform(55, 90, S)) * (1 - q.kappa * q.de)
    p["v0"][:, 1] = np.minimum(q.v_des + rng.uniform(1, 3, S), 20.0)


def _background(p, q, cfg, rng):
    """Traffic on the lanes nobody else uses, each lane at its own speed, 25-45 m apart."""
    S = len(q.beh)
    # forward lanes 0-2, oncoming lanes 0-1: (S, 5)
    lane_d = np.array([-0.5, -1.5, -2.5, 0.5, 1.5]) * q.W * np.ones((S, 1))
    lane_fwd = np.array([True, True, True, False, False])
    free = np.concatenate([q.n_fwd[:, None] > np.arange(3), q.n_opp[:, None] > np.arange(2)], 1)
    free &= np.arange(5) != q.ego_lane[:, None]
    free[:, :3] &= ~(q.adj[:, None] & (np.arange(3) == q.adj_lane[:, None]))
    free[:, 3] &= ~q.onc
    lane_v = rng.uniform(7, 13, (S, 5))
    lane_s0 = np.where(lane_fwd, rng.uniform(-150, -60, (S, 5)), rng.uniform(20, 100, (S, 5)))
    lane_gap = rng.uniform(25, 45, (S, 5))
    nb = cfg.n_vehicles - 1
    if nb > 0:
        bg = slice(2, 2 + nb)
        # (S, nb) a free lane per vehicle
        choice = np.argmax(rng.random((S, nb, 5)) * free[:, None], -1)
        onehot = choice[..., None] == np.arange(5)
        rank = (np.cumsum(onehot, 1) - 1)[onehot].reshape(S, nb)

        def take(a):
            return np.take_along_axis(a, choice, 1)

        s0 = q.s_e0[:, None] + take(lane_s0) + rank * take(lane_gap)
        d, fwd = take(lane_d), lane_fwd[choice]
        p["exists"][:, bg] = np.arange(nb) < rng.integers((nb + 1) // 2, nb + 1, S)[:, None]
        p["segs"][:, bg] = _lane_path(d, q.kappa[:, None], fwd)
        p["u_start"][:, bg], p["v0"][:, bg] = (
            np.where(fwd, s0, -s0) * (1 - q.kappa[:, None] * d),
            take(lane_v),
        )


def _parked(p, q, cfg, rng):
    """Parked cars on the kerb of the outer forward lane (kept off the intersection)."""
    S, n, kappa = len(q.beh), cfg.n_parked, q.kappa[:, None]
    pk = slice(1 + cfg.n_vehicles, 1 + cfg.n_vehicles + n)
    d_out = _lane_d(q.n_fwd - 1, q.W)[:, None]
    first = q.s_e0[:, None] + rng.uniform(-20, 100, (S, 1))
    s_pk = first + np.cumsum(rng.uniform(8, 60, (S, n)), 1)
    s_pk = np.where(q.inter[:, None] & (abs(s_pk) < 25), s_pk + 50, s_pk)
    p["exists"][:, pk] = rng.random((S, n)) < 0.5
    p["segs"][:, pk] = _lane_path(d_out, kappa, True)
    p["u_start"][:, pk] = s_pk * (1 - kappa * d_out)
    p["d0"][:, pk] = -(q.W / 2 + 1.0)  # centre 1 m outside the lane's edge


def _pedestrians(p, q, cfg, rng):
    """Pedestrians on the sidewalks, walking either way (at intersections: away from it)."""
    S, n, W, kappa = len(q.beh), cfg.n_peds, q.W, q.kappa[:, None]
    pd = slice(p["exists"].shape[1] - n, None)
    left = rng.random((S, n)) < 0.5
    # each pedestrian its own line: they never walk into each other
    walkway = 2.5 + 0.7 * np.arange(n)
    d_sw = np.where(left, q.n_opp[:, None] * W + walkway, -q.n_fwd[:, None] * W - walkway)
    s_pd = q.s_e0[:, None] + rng.uniform(-30, 200, (S, n))
    s_pd = np.where(q.inter[:, None] & (abs(s_pd) < 15), s_pd + 30, s_pd)
    fwd = np.where(q.inter[:, None], s_pd > 0, rng.random((S, n)) < 0.5)
    p["exists"][:, pd] = np.arange(n) < rng.integers((n + 1) // 2, n + 1, S)[:, None]
    p["is_ped"][:, pd] = True
    p["size"][:, pd] = _PED
    p["segs"][:, pd] = _lane_path(d_sw, kappa, fwd)
    p["u_start"][:, pd] = np.where(fwd, s_pd, -s_pd) * (1 - kappa * d_sw)
    p["v0"][:, pd] = rng.uniform(0.8, 1.6, (S, n))


def _turn_path(S, W, bx, R, n_fwd, turn=True):
    """The oncoming (westbound) vehicle's left turn into the southbound crossing lane: approach,
    arc, exit; or (turn=False) straight on along its lane. u = _FAR at the box edge either way."""
    one = np.ones(S)
    approach = np.stack(
        [(bx + _FAR) * one, W / 2 * one, np.pi * one, 0 * one, (_FAR if turn else _LONG) * one], -1
    )
    if not turn:
        return np.stack([approach, 0 * approach, 0 * approach], -2)
    arc = np.stack([bx * one, W / 2 * one, np.pi * one, one / R, np.pi / 2 * R * one], -1)
    exit_ = np.stack([-W / 2 * one, (W / 2 - R) * one, 1.5 * np.pi * one, 0 * one, _LONG * one], -1)
    return np.stack([approach, arc, exit_], -2)


def _cross_path(S, W, y_bot):
    """The northbound crossing lane (x = +W/2), u = _FAR at the box edge y_bot: segments
    (S, 3, 5)."""
    one = np.ones(S)
    seg0 = np.stack([W / 2 * one, y_bot - _FAR, np.pi / 2 * one, 0 * one, _LONG * one], -1)
    return np.stack([seg0, 0 * seg0, 0 * seg0], -2)


def _run_programs(p, n_steps, sim_dt):
    """Integrate every agent's speed program: arc position u and speed v along its path,
    (S, M, N) each."""
    u, v = p["u_start"].copy(), p["v0"].copy()
    us, vs = np.empty(u.shape + (n_steps,)), np.empty(u.shape + (n_steps,))
    for k in range(n_steps):  # a loop over time, vectorised over scenes and agents
        us[..., k], vs[..., k] = u, v
        t = k * sim_dt
        v_ref = np.where(t < p["t1"], p["v0"], np.where(t < p["t2"], p["v1"], p["v2"]))
        dec = np.where(t < p["t1"], 2.0, np.where(t < p["t2"], p["dec1"], p["dec2"]))
        a = np.clip(2.0 * (v_ref - v), -dec, 1.5)
        # stopping at u_stop until t_go: brake at constant v^2 / (2 gap) once that exceeds b_stop
        gap = p["u_stop"] - u
        stopping = t < p["t_go"]
        need = v**2 / (2 * np.maximum(gap, 0.05))
        a = np.where(stopping & (need > p["b_stop"]), -np.minimum(need, 4.0), a)
        hold = stopping & (gap < 0.5) & (v < 0.5)
        v_new = np.where(hold, 0.0, np.maximum(v + a * sim_dt, 0.0))
        u, v = u + 0.5 * (v + v_new) * sim_dt, v_new
    # anchored agents: shift along the path so that they are at anchor_u at anchor_t
    k_anchor = np.clip(
        np.where(np.isfinite(p["anchor_t"]), p["anchor_t"], 0) / sim_dt, 0, n_steps - 1
    ).round()
    shift = p["anchor_u"] - np.take_along_axis(us, k_anchor.astype(int)[..., None], -1)[..., 0]
    return us + np.where(np.isfinite(p["anchor_t"]), shift, 0.0)[..., None], vs


def _agent_states(p, us, vs, t):
    """World states (S, M, N, 4) from path positions and the lateral offset program d(t)."""

    def ramp(t0, T):
        return _smoothstep((t - t0[..., None]) / T[..., None])

    s_lc, ds_lc = ramp(p["t_lc"], p["T_lc"])  # the lane change, and the cue's drift up and down
    s_up, ds_up = ramp(p["t_up"], p["T_up"])
    s_dn, ds_dn = ramp(p["t_dn"], p["T_dn"])
    D, c = p["D"][..., None], p["c"][..., None]
    d = p["d0"][..., None] + D * s_lc + c * (s_up - s_dn)  # (S, M, N)
    d_dot = D * ds_lc / p["T_lc"][..., None] + c * (
        ds_up / p["T_up"][..., None] - ds_dn / p["T_dn"][..., None]
    )
    pose, kappa = pose_along(p["segs"], us)  # (S, M, N, 3), (S, M, N)
    along = vs * (1 - kappa * d)
    x, y = pose[..., 0] - d * np.sin(pose[..., 2]), pose[..., 1] + d * np.cos(pose[..., 2])
    return np.stack([x, y, pose[..., 2] + np.arctan2(d_dot, along), np.hypot(along, d_dot)], -1)


def _drive_ego(lay, s_e0, others, exists, sizes, cfg, rng, t):
    """The expert ego: keeps its lane (with a small smooth wander), follows with IDM, and yields. An
    agent that will be in its lane corridor within 3 s (TRUE futures) is an obstacle at its road
    position then, if it drives along the road (a leader, a car merging in) or is still there at
    most 0.6 s before the ego would reach it at its current speed (crossing or turning: the ego
    yields, or passes just after); never if the ego at constant speed would already be past it.
    IDM (Treiber et al. 2000): a = a_max [1 - (v / v_des)^4 - (s*(v, dv) / gap)^2],
    s* = s0 + max(0, v T + v dv / (2 sqrt(a_max b))), a in [-4, a_max]."""
    kappa, de = lay["kappa"], _lane_d(lay["ego_lane"], cfg.lane_width)
    # the others in the road frame: position, speed along the road, half-extents along and across
    s_a, d_a = xy_to_frenet(others[..., 0], others[..., 1], kappa[:, None, None])  # (S, M, N)
    rel = others[..., 2] - kappa[:, None, None] * s_a
    w, length = sizes[..., 0, None] / 2, sizes[..., 1, None] / 2
    ext_long = abs(np.cos(rel)) * length + abs(np.sin(rel)) * w
    ext_lat = abs(np.sin(rel)) * length + abs(np.cos(rel)) * w
    sdot_a = np.gradient(s_a, t, axis=-1)
    in_corr = exists[..., None] & (abs(d_a - de[:, None, None]) < ext_lat + _EGO_W / 2 + 0.3)
    u0 = s_e0 * (1 - kappa * de)  # the ego's arc position along its lane
    us, vs = _follow(lay, u0, de, (s_a, ext_long, sdot_a, in_corr), cfg, len(t))
    return _wander(kappa, de, us, vs, rng), us / (1 - kappa * de)[:, None]


def _follow(lay, u, de, view, cfg, N):
    """The ego's arc position and speed along its lane (S, N) from u: IDM behind what it must."""
    kappa, v_des, dt = lay["kappa"], lay["v_des"], cfg.sim_dt
    stride = int(round(cfg.dt / dt))
    v = lay["v_e0"].copy()
    us, vs = np.empty((len(u), N)), np.empty((len(u), N))
    sqrt_ab = 2 * math.sqrt(_IDM["a_max"] * _IDM["b"])
    for k in range(N):  # time loop, vectorised over scenes
        us[:, k], vs[:, k] = u, v
        idx = np.minimum(k + stride * np.arange(_IDM["look"] + 1), N - 1)
        tau = (idx - k) * dt  # (J,)
        sa, ex, sdot, corr = (x[..., idx] for x in view)  # (S, M, J)
        obstacle, gap = _obstacles(u / (1 - kappa * de), v, tau, sa, ex, sdot, corr)
        vv = v[:, None, None]
        s_star = _IDM["s0"] + np.maximum(0.0, vv * _IDM["T"] + vv * (vv - sdot) / sqrt_ab)
        interaction = np.where(obstacle, (s_star / gap) ** 2, 0.0).max((1, 2))
        a = np.clip(_IDM["a_max"] * (1 - (v / v_des) ** 4 - interaction), -4.0, _IDM["a_max"])
        v_new = np.maximum(v + a * dt, 0.0)
        u, v = u + 0.5 * (v + v_new) * dt, v_new
    return us, vs


def _obstacles(s_e, v, tau, sa, ex, sdot, corr):
    """Whom the ego follows or yields to (_drive_ego's rule), and the gaps to them: (S, M, J)."""
    s_e, vv = s_e[:, None, None], v[:, None, None]
    passed = (tau > 0) & (s_e + vv * tau - _EGO_L / 2 - 1.0 > sa + ex)
    gap = np.maximum(sa - ex - s_e - _EGO_L / 2, 0.1)
    arrival = gap / np.maximum(vv, 1.0)  # when the ego would reach it at its current speed
    along = (sdot > 2.0) | (tau >= arrival - 0.6)
    return corr & (sa > s_e) & ~passed & along, gap


def _wander(kappa, de, us, vs, rng):
    """The ego's world states (S, N, 4): its lane's centre line and a smooth wander (<= 0.2 m)."""
    S = len(us)
    amp, lam, phase = rng.uniform(0, 0.2, S), rng.uniform(60, 150, S), rng.uniform(0, 2 * np.pi, S)
    wave = 2 * np.pi * us / lam[:, None] + phase[:, None]  # (S, N)
    off = amp[:, None] * np.sin(wave)
    doff_du = amp[:, None] * 2 * np.pi / lam[:, None] * np.cos(wave)
    pose, k_lane = pose_along(_lane_path(de, kappa, True), us)  # (S, N, 3)
    x, y = pose[..., 0] - off * np.sin(pose[..., 2]), pose[..., 1] + off * np.cos(pose[..., 2])
    return np.stack([x, y, pose[..., 2] + np.arctan2(doff_du, 1 - k_lane * off), vs], -1)


def _build_map(lay, s_lo, s_hi, cfg):
    """The scene's lane graph as arcline paths (S, 23, 10) and the 9 routes through it (S, 9, 3).
    Path slots: forward lane i -> 3i..3i+2 (before / through / after the intersection; one path
    without it), oncoming lane j -> 9+3j.., southbound crossing lane 15..17, northbound 18..20, the
    ego side's right turn 21, the oncoming left turn 22. Routes: forward 0-2, oncoming 3-4, south 5,
    north 6, right turn 7, left turn 8; they are exactly the maximal chains of the graph, which is
    what the loader rebuilds from the connectivity."""
    S, W, inter, n_fwd = len(s_lo), cfg.lane_width, lay["inter"], lay["n_fwd"]
    bx, one = W + _BOX_MARGIN, np.ones(S)  # bx: half-length of the box along the main road
    paths, valid = np.zeros((S, 23, 10)), np.zeros((S, 23), bool)
    conn, routes = np.zeros((S, 23), bool), np.full((S, 9, 3), -1)
    for i, fwd in [(0, True), (1, True), (2, True), (0, False), (1, False)]:
        base, r = (3 * i, i) if fwd else (9 + 3 * i, 3 + i)
        exists = (n_fwd > i) if fwd else (lay["n_opp"] > i)
        d = _lane_d(i, W) if fwd else -_lane_d(i, W)
        paths[:, base : base + 3] = _road_lane(lay, s_lo, s_hi, d, fwd, bx)
        valid[:, base : base + 3] = exists[:, None] & (inter[:, None] | (np.arange(3) == 0))
        conn[:, base + 1] = inter
        whole = np.where(exists[:, None], [base, -1, -1], -1)
        routes[:, r] = np.where((exists & inter)[:, None], base + np.arange(3), whole)
    paths[:, 15:] = _crossing_road(lay, W, bx)
    valid[:, 15:] = inter[:, None]
    conn[:, [16, 19, 21, 22]] = True  # the crossing lanes' middle pieces and the turns
    conn &= valid
    routes[:, 5] = np.where(inter[:, None], [15, 16, 17], -1)
    routes[:, 6] = np.where(inter[:, None], [18, 19, 20], -1)
    routes[:, 7] = np.where(inter[:, None], np.stack([3 * (n_fwd - 1), 21 * one, 17 * one], 1), -1)
    routes[:, 8] = np.where(inter[:, None], np.stack([9 * one, 22 * one, 17 * one], 1), -1)
    return paths * valid[..., None], conn, routes


def _road_lane(lay, s_lo, s_hi, d, fwd, bx):
    """A main-road lane at offset d (S, 3, 10): one arc over the road, or pieces around the box."""
    kappa, one = lay["kappa"], np.ones(len(s_lo))
    sg, yaw = (1, 0.0) if fwd else (-1, np.pi)  # driving along s, or against it
    x, y, th = frenet_to_xy(np.where(fwd, s_lo, s_hi), d, kappa)
    length = (s_hi - s_lo) * (1 - kappa * d)
    radius = np.where(kappa != 0, abs(1 / np.where(kappa != 0, kappa, 1) - d), 1000.0)
    curved = _arc_path(x, y, th + yaw, radius, np.sign(kappa) * sg, length, 0 * one, one)
    single = np.where((kappa != 0)[:, None], curved, _straight(x, y, th + yaw, length, one))
    # at an intersection (straight roads): before / through / after it
    ends = [s_lo, -bx * one, bx * one, s_hi] if fwd else [s_hi, bx * one, -bx * one, s_lo]
    pieces = [_straight(ends[k], d * one, yaw, sg * (ends[k + 1] - ends[k]), one) for k in range(3)]
    whole = np.stack([single, 0 * single, 0 * single], 1)
    return np.where(lay["inter"][:, None, None], np.stack(pieces, 1), whole)


def _crossing_road(lay, W, bx):
    """Path slots 15-22 (S, 8, 10): the crossing road's two lanes and the turns into it."""
    n_fwd, one = lay["n_fwd"], np.ones(len(lay["n_fwd"]))
    y_top, y_bot = lay["n_opp"] * W + _BOX_MARGIN, -(n_fwd * W + _BOX_MARGIN)
    Y = 60.0  # the crossing road's lanes reach this far from the main road
    out = []  # southbound at x = -W/2, northbound at x = +W/2, in three pieces like the main road
    for x, yaw, ys in [
        (-W / 2, -np.pi / 2, [Y * one, y_top, y_bot, -Y * one]),
        (W / 2, np.pi / 2, [-Y * one, y_bot, y_top, Y * one]),
    ]:
        out += [_straight(x, ys[k], yaw, abs(ys[k + 1] - ys[k]), one) for k in range(3)]
    # turns into the southbound lane: right from the outer forward one, left from the inner oncoming
    r_right, r_left = W / 2 + _BOX_MARGIN, bx + W / 2
    d_out = _lane_d(n_fwd - 1, W)
    out.append(_arc_path(-bx, d_out, 0.0, r_right, -1.0, np.pi / 2 * r_right, 0 * one, one))
    out.append(_arc_path(bx, W / 2, np.pi, r_left, 1.0, np.pi / 2 * r_left, (n_fwd - 1) * W, one))
    return np.stack(out, 1)


def _bodies(states, sizes, is_ped):
    """Three discs along each body (radius half the width; one disc for pedestrians): centres
    (..., 3, 2), radii."""
    # (..., 1) centre to end disc
    half = np.where(is_ped, 0.0, sizes[..., 1] / 2 - sizes[..., 0] / 2)
    off = half[..., None, None] * np.array([-1.0, 0.0, 1.0])[:, None]  # (..., 1, 3, 1)
    # (..., F, 1, 2)
    heading = np.stack([np.cos(states[..., 2]), np.sin(states[..., 2])], -1)[..., None, :]
    centres = states[..., None, :2] + off * heading  # (..., F, 3, 2)
    radius = np.where(is_ped, 0.3, sizes[..., 0] / 2)
    return centres, radius


def _collides(ego, agents, sizes, is_ped, exists):
    """(S,) True where any two bodies (ego included) overlap at any frame. ego (S, F, 4),
    agents (S, M, F, 4)."""
    S, M, F, _ = agents.shape
    states = np.concatenate([ego[:, None], agents], 1)  # (S, 1+M, F, 4)
    sz = np.concatenate([np.broadcast_to(np.array([_EGO_W, _EGO_L, 1.6]), (S, 1, 3)), sizes], 1)
    ped = np.concatenate([np.zeros((S, 1), bool), is_ped], 1)
    ex = np.concatenate([np.ones((S, 1), bool), exists], 1)
    c, r = _bodies(states, sz[:, :, None], ped[:, :, None])  # (S, 1+M, F, 3, 2), (S, 1+M, 1)
    iu, ju = np.triu_indices(M + 1, 1)
    # only pairs whose centres come within reach (two car lengths) need the disc test
    near = (
        (np.linalg.norm(states[:, iu, :, :2] - states[:, ju, :, :2], axis=-1) < 10.0).any(-1)
        & ex[:, iu]
        & ex[:, ju]
    )
    s, k = np.nonzero(near)
    ci, cj = c[s, iu[k]], c[s, ju[k]]  # (n, F, 3, 2)
    dist = np.linalg.norm(ci[:, :, :, None] - cj[:, :, None], axis=-1)  # (n, F, 3, 3)
    hit = (dist < (r[s, iu[k]] + r[s, ju[k]])[:, :, None, None]).any((1, 2, 3))
    return np.bincount(s[hit], minlength=S) > 0


def _ar1_noise(shape, sigma, rho, rng):
    """Stationary AR(1) noise on the last axis: e_f = rho e_(f-1) + sqrt(1 - rho^2) sigma xi_f."""
    xi = rng.standard_normal(shape) * sigma
    e = np.empty(shape)
    e[..., 0] = xi[..., 0]
    for f in range(1, shape[-1]):
        e[..., f] = rho * e[..., f - 1] + math.sqrt(1 - rho**2) * xi[..., f]
    return e


def _simulate_chunk(S, cfg, rng):
    """Simulate S candidate scenes; returns the world-frame arrays of the collision-free ones."""
    stride = int(round(cfg.dt / cfg.sim_dt))
    t = np.arange((cfg.frames - 1) * stride + 1) * cfg.sim_dt  # (N,) fine time grid
    lay = _draw_layout(S, cfg, rng)
    p, s_e0 = _script_agents(lay, cfg, rng)
    us, vs = _run_programs(p, len(t), cfg.sim_dt)
    others = _agent_states(p, us, vs, t)  # (S, M, N, 4)
    # (S, N, 4), (S, N)
    ego, s_ego = _drive_ego(lay, s_e0, others, p["exists"], p["size"], cfg, rng, t)
    ego, others = ego[:, ::stride], others[:, :, ::stride]  # frames: (S, F, 4), (S, M, F, 4)
    ok = ~_collides(ego, others, p["size"], p["is_ped"], p["exists"])
    # the map spans the ego's drive, from 40 m behind it to 90 m past its end (the crop needs 80 m)
    paths, conn, routes = _build_map(lay, s_ego[:, 0] - 40.0, s_ego[:, -1] + 90.0, cfg)
    # tracking noise on the others' logs (history and future alike), then backward-difference speeds
    M, F = others.shape[1], others.shape[2]
    noisy = others.copy()
    for ch, sigma in [(0, cfg.pos_noise), (1, cfg.pos_noise), (2, cfg.yaw_noise)]:
        noisy[..., ch] += _ar1_noise((S, M, F), sigma, cfg.noise_corr, rng)
    noisy[..., 2], ego[..., 2] = wrap_angle(noisy[..., 2]), wrap_angle(ego[..., 2])
    tf = np.arange(F) * cfg.dt
    mask = np.broadcast_to(p["exists"][..., None], (S, M, F))
    noisy[..., 3] = backward_speed(noisy[..., :2], mask, tf) * mask
    ego[..., 3] = backward_speed(ego[..., :2], np.ones((S, F), bool), tf)
    noisy *= mask[..., None]

    def keep(a):
        return a[ok]

    return dict(
        ego=keep(ego),
        agents=keep(noisy),
        agents_mask=keep(mask),
        agents_is_ped=keep(p["is_ped"]),
        agents_size=keep(p["size"]),
        behaviour=keep(lay["beh"]),
        event_frame=keep(np.round(lay["t_e"] / cfg.dt).astype(np.int64)),
        paths=keep(paths),
        paths_is_connector=keep(conn),
        routes=keep(routes),
    )


MAX_SCENES = 500_000
"""Most scenes per generate_scenes call: MAX_SAMPLES at 4 per scene (~35 GB of float64), a bound
against typos."""


def _check_count(where: str, name: str, n, cap: int):
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or not 1 <= n <= cap:
        raise ValueError(f"{where}: {name} must be a whole number from 1 to {cap:,}, got {n!r}")


def _check_seed(where: str, seed):
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"{where}: seed must be a whole number >= 0, got {seed!r}")


def generate_scenes(
    n: int, cfg: SynthConfig | None = None, seed: int = 0, chunk: int = 512
) -> Scenes:
    """n <= MAX_SCENES synthetic scenes, deterministic for (cfg, seed). Candidates where two bodies
    touch are replaced (~4 % by default, mostly crossing vehicles meeting traffic); simulated
    `chunk` scenes at a time."""
    _check_count("generate_scenes", "n (scenes)", n, MAX_SCENES)
    _check_count("generate_scenes", "chunk", chunk, MAX_SCENES)
    _check_seed("generate_scenes", seed)
    cfg = cfg or SynthConfig()
    rng = np.random.default_rng(seed)
    parts = []
    have = 0
    while have < n:
        parts.append(_simulate_chunk(min(chunk, int((n - have) * 1.1) + 4), cfg, rng))
        have += len(parts[-1]["ego"])
    arr = {k: np.concatenate([q[k] for q in parts])[:n] for k in parts[0]}
    segs = route_segments(arr["paths"], arr["routes"])
    lanes, lanes_mask = discretize(segs, cfg.lane_spacing)
    F = cfg.frames
    valid_t0 = (np.arange(F) >= cfg.hist) & (np.arange(F) < F - cfg.fut)
    pred_idx = np.where(valid_t0, 0, -1)[None].repeat(n, 0)

    def T(a):  # (the integer arrays are int64)
        return torch.from_numpy(np.ascontiguousarray(a))

    return Scenes(
        **{k: T(v) for k, v in arr.items()},
        pred_idx=T(pred_idx),
        lanes=T(lanes),
        lanes_mask=T(lanes_mask),
        names=[f"synth-{seed}-{i:06d}" for i in range(n)],
    )


# === 5. Planning samples: cut a batch out of scenes at frame t0 =============================


def _to_frame(states, origin):
    """World states (S, ..., >=3) -> the frame of origin (S, 4): positions rotated by -h0,
    headings - h0."""
    shape = (origin.shape[0],) + (1,) * (states.dim() - 2)
    x0, y0, h0 = (origin[:, i].reshape(shape) for i in range(3))
    c, s = torch.cos(h0), torch.sin(h0)
    dx, dy = states[..., 0] - x0, states[..., 1] - y0
    out = states.clone()
    out[..., 0], out[..., 1] = c * dx + s * dy, -s * dx + c * dy
    out[..., 2] = wrap_angle(states[..., 2] - h0)
    return out


def _fill_gaps(x, mask):
    """Missing steps (mask False) of x (..., T, C) take the last observed step, or else the next."""
    T = mask.shape[-1]
    ar = torch.arange(T, device=mask.device)
    prev = torch.cummax(torch.where(mask, ar, -1), -1).values
    nxt = torch.flip(torch.cummin(torch.flip(torch.where(mask, ar, T), [-1]), -1).values, [-1])
    src = torch.where(prev >= 0, prev, nxt).clamp(max=T - 1)
    return torch.gather(x, -2, src[..., None].expand(x.shape))


def sample_at(
    scenes: Scenes, frame, ego_state=None, cfg: SynthConfig | None = None, dtype=torch.float32
) -> Scenarios:
    """One planning sample per scene at frame t0 (an int, or (S,) frames), in the ego frame at t0:
    the predicted agent scenes.pred_idx, the nearest others and lanes (cfg). ego_state, for
    closed-loop log replay, replaces the logged ego: (S, 4) its current world state, or (S, 9, 4)
    its history; the frame, the history and the others follow it, while the GT future, the goal and
    the lanes stay the logged ego's (paper §4.3)."""
    cfg = cfg or SynthConfig()
    H = cfg.hist
    frame, win, ego = _ego_window(scenes, frame, ego_state, cfg)  # (S,), (S, 15), (S, 15, 4) world
    ar = torch.arange(len(frame), device=frame.device)
    pred = scenes.pred_idx[ar, frame]  # (S,)
    if (pred < 0).any():
        raise ValueError(
            f"sample_at: no predicted agent in scenes {ar[pred < 0].tolist()} at these frames"
        )
    origin = ego[:, H].clone()  # (S, 4)
    ego = _to_frame(ego, origin)
    ag_mask = scenes.agents_mask[ar, pred][ar[:, None], win]  # (S, 15)
    ag = _to_frame(_fill_gaps(scenes.agents[ar, pred][ar[:, None], win], ag_mask), origin)
    # the history the predictor may use: the unbroken run of observed steps that ends at t0 (a real
    # track can be occluded for a frame; differences across the gap would not be velocities, so
    # steps before it count as missing)
    hist_mask = ag_mask[:, : H + 1].flip(-1).int().cumprod(-1).flip(-1).bool()  # (S, 9)
    o, o_mask, o_is_ped = _nearest_others(scenes, frame, win, pred, origin, cfg)
    lanes, lanes_mask = _nearby_lanes(scenes, origin, cfg)
    out = Scenarios(
        ego_hist=ego[:, : H + 1],
        ego_fut=ego[:, H + 1 :],
        agent_hist=ag[:, : H + 1],
        agent_hist_mask=hist_mask,
        agent_fut=ag[:, H + 1 :],
        others_hist=o[:, :, : H + 1],
        others_fut=o[:, :, H + 1 :],
        others_mask=o_mask,
        others_is_ped=o_is_ped,
        lanes=lanes,
        lanes_mask=lanes_mask,
        goal=ego[:, -1].clone(),
        behaviour=scenes.behaviour.clone(),
    )
    return out.to(dtype)


def _ego_window(scenes, frame, ego_state, cfg):
    """The sample's frames (S,), its window t0-8..t0+6 (S, 15) and the ego's world states there
    (S, 15, 4): the logged ones, or in closed loop ego_state for the current state or history."""
    S, F = scenes.ego.shape[:2]
    H, T = cfg.hist, cfg.fut
    # every index made here lives with the scenes (the CPU, for the closed loop)
    dev = scenes.ego.device
    frame = torch.as_tensor(frame, dtype=torch.int64, device=dev).expand(S)
    if ((frame < H) | (frame > F - T - 1)).any():
        raise ValueError(
            f"sample_at: frames must be in [{H}, {F - T - 1}] (history {H}, future {T}), "
            f"got {frame}"
        )
    win = frame[:, None] + torch.arange(-H, T + 1, device=dev)  # (S, 15) the sample's frames
    ego = scenes.ego[torch.arange(S, device=dev)[:, None], win]  # (S, 15, 4) world
    if ego_state is not None:
        es = torch.as_tensor(ego_state, dtype=ego.dtype, device=dev)
        if es.shape == (S, 4):
            ego[:, H] = es
        elif es.shape == (S, H + 1, 4):
            ego[:, : H + 1] = es
        else:
            raise ValueError(
                f"sample_at: ego_state must be ({S}, 4) or ({S}, {H + 1}, 4), got {tuple(es.shape)}"
            )
    return frame, win, ego


def _closest(keep, dist, most):
    """Indices (S, K) of the kept items, closest first: K = the most any scene keeps, <= most."""
    K = int(min(keep.sum(1).max().item() if len(keep) else 0, most))
    return torch.argsort(torch.where(keep, dist, math.inf), 1)[:, :K]


def _nearest_others(scenes, frame, win, pred, origin, cfg):
    """The others the planner sees: present at t0, near, closest first; (S, A, 15, 4) in the ego
    frame at t0 (gaps filled), their mask and is_ped (S, A)."""
    M, dev = scenes.agents.shape[1], frame.device
    ar = torch.arange(len(frame), device=dev)
    now = scenes.agents[ar, :, frame]  # (S, M, 4)
    dist = torch.linalg.norm(now[..., :2] - origin[:, None, :2], dim=-1)  # (S, M)
    other = torch.arange(M, device=dev) != pred[:, None]  # (S, M) not the predicted agent
    cand = scenes.agents_mask[ar, :, frame] & other & (dist < cfg.others_radius)
    order = _closest(cand, dist, cfg.max_others)  # (S, A)
    o_mask = torch.gather(cand, 1, order)  # (S, A)
    pick = (ar[:, None, None], order[..., None], win[:, None, :])  # -> (S, A, 15)
    o, o_obs = scenes.agents[pick], scenes.agents_mask[pick]  # (S, A, 15, 4), (S, A, 15)
    o = _to_frame(_fill_gaps(o, o_obs), origin) * o_mask[..., None, None]
    return o, o_mask, torch.gather(scenes.agents_is_ped, 1, order) & o_mask


def _nearby_lanes(scenes, origin, cfg):
    """The lanes near the ego, closest first, each P points from lane_behind behind its nearest:
    (S, L, P, 3) in the ego frame at t0 (0 where invalid) and their mask (S, L, P)."""
    dev, P, Pw = origin.device, cfg.lane_points, scenes.lanes.shape[2]
    # distances in the world frame; only the crop is transformed
    dx, dy = (scenes.lanes[..., :2] - origin[:, None, None, :2]).unbind(-1)
    d2 = torch.where(scenes.lanes_mask, dx**2 + dy**2, math.inf)  # (S, Lw, Pw)
    dmin, jmin = d2.min(-1)  # (S, Lw)
    near = dmin < cfg.lane_radius**2
    lorder = _closest(near, dmin, cfg.max_lanes)  # (S, L)
    first = (torch.gather(jmin, 1, lorder) - cfg.lane_behind).clamp(min=0)  # (S, L)
    pidx = first[..., None] + torch.arange(P, device=dev)  # (S, L, P)
    inside = pidx < Pw
    pidx = pidx.clamp(max=Pw - 1)
    pick = (torch.arange(len(origin), device=dev)[:, None, None], lorder[..., None], pidx)
    lane_pts = _to_frame(scenes.lanes[pick], origin)  # (S, L, P, 3)
    lane_mask = scenes.lanes_mask[pick] & inside & torch.gather(near, 1, lorder)[..., None]
    return lane_pts * lane_mask[..., None], lane_mask


def cut_samples(
    scenes: Scenes, per_scene: int | None, rng: np.random.Generator, cfg: SynthConfig | None = None
) -> tuple[Scenarios, int]:
    """Planning samples from every scene: per_scene random frames among those with a predicted agent
    (for synthetic scenes: within cfg.event_window of its event), or all such frames when per_scene
    is None. Samples with no lane near the ego are dropped; returns (samples, number dropped)."""
    cfg = cfg or SynthConfig()
    S, F = scenes.pred_idx.shape
    f = torch.arange(F)
    e = scenes.event_frame[:, None]
    lo, hi = cfg.event_window
    cand = (scenes.pred_idx >= 0) & ((e < 0) | ((f >= e + lo) & (f <= e + hi)))  # (S, F)
    k = per_scene if per_scene is not None else int(cand.sum(1).max())
    score = torch.where(
        cand,
        torch.from_numpy(rng.random((S, F))) if per_scene is not None else -f.double(),
        -math.inf,
    )
    frames = torch.argsort(score, 1, descending=True)[:, :k]  # (S, k)
    ok = torch.gather(cand, 1, frames)
    parts = []
    for r in range(k):  # k rounds over all scenes at once
        sel = ok[:, r]
        if sel.any():
            parts.append(sample_at(scenes if sel.all() else scenes[sel], frames[sel, r], cfg=cfg))
    batch = Scenarios.cat(parts)
    has_lane = batch.lanes_mask.flatten(1).any(1)
    return batch[has_lane], int((~has_lane).sum())


# === 6. Dataset: train/val split by scene, disk cache =======================================

_CACHE_FORMAT = 2  # bump when the generator's output changes, so old caches are not reused
MAX_SAMPLES = 2_000_000
"""Most samples make_dataset / load_or_generate make (~20 GB as float32; all of nuScenes has
~40 000 key frames)."""


class Dataset(NamedTuple):
    """Training and validation planning samples, the validation scenes' logs, and maybe a training
    draw per seed."""

    train: Scenarios
    val: Scenarios
    val_scenes: Scenes | None = None  # the validation scenes, for closed-loop log replay
    # Scenarios per training seed 0, 1, ..; None: every seed trains on train
    train_draws: tuple | None = None

    def train_for(self, seed: int) -> Scenarios:
        # the seed's own draw, if any
        return self.train if self.train_draws is None else self.train_draws[seed]


def make_dataset(n: int, cfg: SynthConfig | None = None, seed: int = 0) -> Dataset:
    """n planning samples (train + val) from ceil(n / samples_per_scene) synthetic scenes; the last
    val_fraction of the scenes are validation (no scene gives samples to both); n <= MAX_SAMPLES."""
    _check_count("make_dataset", "n (samples)", n, MAX_SAMPLES)
    _check_seed("make_dataset", seed)
    cfg = cfg or SynthConfig()
    _check_count("make_dataset", "cfg.samples_per_scene", cfg.samples_per_scene, MAX_SAMPLES)
    n_scenes = max(2, math.ceil(n / cfg.samples_per_scene))
    if n_scenes > MAX_SCENES:
        raise ValueError(
            f"make_dataset: n = {n:,} samples at {cfg.samples_per_scene} per scene needs "
            f"{n_scenes:,} scenes, more than MAX_SCENES = {MAX_SCENES:,}"
        )
    scenes = generate_scenes(n_scenes, cfg, seed)
    n_val = min(max(1, round(cfg.val_fraction * n_scenes)), n_scenes - 1)
    rng = np.random.default_rng([seed, 1])  # frame choice: its own stream, derived from the seed
    val, _ = cut_samples(scenes[n_scenes - n_val :], cfg.samples_per_scene, rng, cfg)
    train, _ = cut_samples(scenes[: n_scenes - n_val], cfg.samples_per_scene, rng, cfg)
    return Dataset(train[: max(n - len(val), 0)], val, scenes[n_scenes - n_val :])


def _cache_path(n, seed, cfg, cache_dir):
    key = dict(n=n, seed=seed, cfg=dataclasses.asdict(cfg), format=_CACHE_FORMAT)
    key = json.dumps(key, sort_keys=True)
    digest = hashlib.sha1(key.encode()).hexdigest()[:12]
    return Path(cache_dir) / f"scenarios-n{n}-s{seed}-{digest}.pt", key


def load_or_generate(n: int, seed: int = 0, cache_dir="data_cache", cfg: SynthConfig | None = None):
    """The Dataset for (n, seed, cfg), from cache_dir (its file name hashes all that makes the data)
    else generated and saved; a file of that name that is not such a cache is refused, kept."""
    _check_count("load_or_generate", "n (samples)", n, MAX_SAMPLES)
    _check_seed("load_or_generate", seed)
    n, seed, cfg = int(n), int(seed), cfg or SynthConfig()  # (numpy integers: int, for json)
    path, key = _cache_path(n, seed, cfg, cache_dir)
    if path.exists():
        try:
            blob = torch.load(path, weights_only=True)
            assert blob["key"] == key, "made with other settings"
            return Dataset(
                Scenarios(**blob["train"]), Scenarios(**blob["val"]), Scenes(**blob["val_scenes"])
            )
        except Exception as e:  # any failure means: not our cache (torch's unsafe advice unsaid)
            why = " ".join(f"{e}".split())
            why = "objects other than tensors" if "weights_only" in why else why[:160]
            raise ValueError(
                f"{path}: not a valid data_synth cache ({why}); move it away or use another "
                "cache_dir"
            ) from None
    data = make_dataset(n, cfg, seed)
    path.parent.mkdir(parents=True, exist_ok=True)

    def own(batch):  # (slices share storage)
        return {k: v.clone() for k, v in batch.tensors().items()}

    blob = dict(key=key, train=own(data.train), val=own(data.val))
    blob["val_scenes"] = {**own(data.val_scenes), "names": data.val_scenes.names}
    save_atomic(blob, path)  # atomic: a crash or a full disk leaves no half-written cache
    return data


# === 7. Statistics ==========================================================================

PLAUSIBLE = {"speed_max": 20.5, "accel_p99": 4.0, "yaw_rate_p99": 0.7}
"""Urban driving at 2 Hz: speeds up to 20 m/s, 99 % of |accelerations| below 4 m/s^2 and of vehicle
|yaw rates| below 0.7 rad/s (derived from the states by backward differences, tracking noise
included)."""


def _kinematics(states, mask, dt: float):
    """states (..., T, 4), mask (...,) -> flat arrays of speed, |accel|, |yaw rate| (by backward
    differences; the yaw rate of moving vehicles only: headings of stopped ones mean little)."""
    v, h = states[..., 3], states[..., 2]
    acc, yaw = (v[..., 1:] - v[..., :-1]) / dt, wrap_angle(h[..., 1:] - h[..., :-1]) / dt
    moving = (v[..., 1:] > 2.0) & mask[..., None]
    return v[mask].flatten(), acc[mask].abs().flatten(), yaw[moving].abs().flatten()


def _summary(x) -> dict:
    """Percentiles 1, 50, 99 and the maximum of a flat array ({} when empty)."""
    x = x.double()
    if x.numel() == 0:
        return {}
    q = torch.quantile(x[:100_000], torch.tensor([0.01, 0.5, 0.99], dtype=torch.float64)).tolist()
    return {"p1": q[0], "p50": q[1], "p99": q[2], "max": x.max().item()}


def statistics(batch: Scenarios, dt: float = 0.5) -> dict:
    """Kinematics (from the states, by backward differences), the behaviour mix and how close the
    predicted vehicle comes to the ego's GT future (the collision cost exp(-d^2/4) matters within a
    few metres)."""
    B = len(batch)
    groups = {
        "ego": (torch.cat([batch.ego_hist, batch.ego_fut], 1), torch.ones(B, dtype=torch.bool)),
        "predicted": (
            torch.cat([batch.agent_hist, batch.agent_fut], 1),
            batch.agent_hist_mask.all(1),
        ),
        "other vehicles": (
            torch.cat([batch.others_hist, batch.others_fut], 2),
            batch.others_mask & ~batch.others_is_ped,
        ),
    }
    out = {"samples": B}
    for name, (states, mask) in groups.items():
        v, a, w = _kinematics(states, mask, dt)
        out[name] = {"speed": _summary(v), "|accel|": _summary(a), "|yaw rate|": _summary(w)}
    # (B,)
    d = torch.linalg.norm(batch.ego_fut[..., :2] - batch.agent_fut[..., :2], dim=-1).min(1).values
    rel = (_no_brake_plan(batch, dt) - batch.agent_fut[..., :2]).abs()  # (B, 6, 2), ego frame at t0
    overlap = ((rel[..., 0] < _EGO_L) & (rel[..., 1] < _EGO_W)).any(1)  # the two footprints touch
    mix = {}
    for i, name in enumerate(BEHAVIOURS):
        m = batch.behaviour == i
        if m.any():
            mix[name] = {
                "share": m.float().mean().item(),
                "min_dist_p50": d[m].median().item(),
                "within_5m": (d[m] < 5).float().mean().item(),
                "no_brake_conflict": overlap[m].float().mean().item(),
            }
    out["behaviour"] = mix
    vehicles = [out[g] for g in groups]
    checks = (
        ("speed_max", "speed", "max"),
        ("accel_p99", "|accel|", "p99"),
        ("yaw_rate_p99", "|yaw rate|", "p99"),
    )
    out["plausible"] = {
        k: max(g[q].get(stat, 0) for g in vehicles) <= PLAUSIBLE[k] for k, q, stat in checks
    }
    return out


def _no_brake_plan(batch: Scenarios, dt: float):
    """The ego's positions (B, 6, 2) had it kept its t0 speed along its GT path (extended straight
    past its end): the plan of a planner that ignores the predicted vehicle."""
    path = torch.cat([batch.ego_hist[:, -1:, :2], batch.ego_fut[..., :2]], 1)  # (B, 7, 2)
    seg = path[:, 1:] - path[:, :-1]  # (B, 6, 2)
    seg_len = torch.linalg.norm(seg, dim=-1).clamp(min=1e-6)
    cum = torch.cat([torch.zeros(len(path), 1, dtype=path.dtype), seg_len.cumsum(1)], 1)  # (B, 7)
    want = batch.ego_hist[:, -1, 3:4] * dt * torch.arange(1, 7, dtype=path.dtype)  # (B, 6)
    # segment index (last extends)
    k = (torch.searchsorted(cum.contiguous(), want.contiguous()) - 1).clamp(0, 5)
    frac = (want - cum.gather(1, k)) / seg_len.gather(1, k)
    k2 = k[..., None].expand(-1, -1, 2)
    return path.gather(1, k2) + frac[..., None] * seg.gather(1, k2)


def format_statistics(st: dict) -> str:
    lines = [
        f"{st['samples']} samples   plausible ranges: speed <= {PLAUSIBLE['speed_max']} m/s, "
        f"p99 |accel| <= {PLAUSIBLE['accel_p99']} m/s^2, "
        f"p99 |yaw rate| <= {PLAUSIBLE['yaw_rate_p99']} rad/s"
    ]
    for g in ("ego", "predicted", "other vehicles"):
        for q, unit in (("speed", "m/s"), ("|accel|", "m/s^2"), ("|yaw rate|", "rad/s")):
            if s := st[g][q]:
                lines.append(
                    f"  {g:15s} {q:11s} p1 {s['p1']:6.2f}  p50 {s['p50']:6.2f}  "
                    f"p99 {s['p99']:6.2f}  max {s['max']:6.2f} {unit}"
                )
    lines.append(
        "  behaviour      share | predicted vehicle vs the ego's GT future: "
        "median min distance, share < 5 m | share colliding with a no-braking ego"
    )
    for name, m in st["behaviour"].items():
        lines.append(
            f"  {name:13s} {m['share']:6.1%} | {m['min_dist_p50']:6.1f} m {m['within_5m']:7.1%} | "
            f"{m['no_brake_conflict']:7.1%}"
        )
    verdict = (f"{k} {'ok' if v else 'OUT OF RANGE'}" for k, v in st["plausible"].items())
    lines.append("  plausible: " + ", ".join(verdict))
    return "\n".join(lines)


# === 8. Plot ================================================================================


def _draw_lanes(ax, b) -> None:
    """The lanes of sample b (one sample, on the CPU): grey, arrows along the driving direction."""
    for lane, m in zip(b.lanes[0], b.lanes_mask[0]):
        pts = lane[m].numpy()
        if len(pts):
            ax.plot(pts[:, 0], pts[:, 1], color="0.75", lw=1, zorder=1)
            k = min(len(pts) - 1, 5)
            ax.annotate(
                "",
                pts[k, :2] + 1.5 * np.array([np.cos(pts[k, 2]), np.sin(pts[k, 2])]),
                pts[k, :2],
                arrowprops=dict(arrowstyle="->", color="0.6", lw=0.8),
                zorder=1,
            )


def _draw_box(ax, state, size, color, z) -> None:
    """A vehicle's footprint (width, length) at state (x, y, h, ...)."""
    from matplotlib.patches import Rectangle

    (x, y, h), (w, length) = state[:3].tolist(), size
    back_right = (
        -np.array([np.cos(h), np.sin(h)]) * length / 2 + np.array([np.sin(h), -np.cos(h)]) * w / 2
    )
    corner = np.array([x, y]) + back_right
    ax.add_patch(
        Rectangle(
            corner,
            length,
            w,
            angle=math.degrees(h),
            rotation_point="xy",
            fc=color,
            ec="k",
            lw=0.5,
            alpha=0.8,
            zorder=z,
        )
    )


def _draw_track(ax, hist, fut, color, z, dashed=False) -> None:
    """A history (dotted) and its GT future (solid, or dashed)."""
    ax.plot(hist[:, 0], hist[:, 1], ":", color=color, lw=1.2, zorder=z)
    ax.plot(
        np.r_[hist[-1:, 0], fut[:, 0]],
        np.r_[hist[-1:, 1], fut[:, 1]],
        "--" if dashed else "-",
        color=color,
        lw=1.5,
        zorder=z,
        marker=".",
        ms=3,
    )


def plot_scenario(
    ax, batch: Scenarios, i: int, title: str | None = None, extent: tuple = (-30, 60, -25, 25)
):
    """Draw sample i in the ego frame: lanes (grey, arrows along the driving direction), other
    vehicles and pedestrians (history dotted, GT future solid, box at t0), the predicted vehicle
    (orange), the ego (blue, GT future dashed) and its goal (star). Returns ax; callers overlay
    predictions and plans with ax.plot."""
    # plotted on the CPU, wherever the batch is
    b = batch[torch.tensor([i])].to(torch.float64, device="cpu")
    _draw_lanes(ax, b)
    for oh, of, m, ped in zip(
        b.others_hist[0], b.others_fut[0], b.others_mask[0], b.others_is_ped[0]
    ):
        if m:
            color = "tab:green" if ped else "tab:gray"
            _draw_track(ax, oh.numpy(), of.numpy(), color, 2)
            if ped:
                ax.plot(*oh[-1, :2].tolist(), "o", color=color, ms=4, zorder=3)
            else:
                _draw_box(ax, oh[-1], (1.9, 4.6), "0.6", 3)
    _draw_track(ax, b.agent_hist[0].numpy(), b.agent_fut[0].numpy(), "tab:orange", 4)
    _draw_box(ax, b.agent_hist[0, -1], (1.9, 4.6), "tab:orange", 5)
    _draw_track(ax, b.ego_hist[0].numpy(), b.ego_fut[0].numpy(), "tab:blue", 4, dashed=True)
    _draw_box(ax, b.ego_hist[0, -1], (_EGO_W, _EGO_L), "tab:blue", 5)
    ax.plot(*b.goal[0, :2].tolist(), "*", color="tab:blue", ms=12, mec="k", zorder=6)
    beh = int(b.behaviour[0])
    ax.set_title(
        title if title is not None else (BEHAVIOURS[beh] if beh >= 0 else f"sample {i}"), fontsize=9
    )
    ax.set(xlim=extent[:2], ylim=extent[2:], aspect="equal")
    ax.tick_params(labelsize=7)
    return ax


if __name__ == "__main__":
    # a hand-over: the nuScenes format's command line (write-nuscenes, read-nuscenes) is the lab's,
    # python -m lab.data
    from lab import data

    data.main()
