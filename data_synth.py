"""Scenario data for DiffStack: nuScenes-like synthetic driving, and the real nuScenes format written and read.

The stack (diffstack.py) trains on *planning samples*: 4 s of history and 3 s of future at 2 Hz, in the ego
frame at the current time t0, with one predicted vehicle, other agents, the lanes near the ego and a goal
(paper §4.1, App. E). This module makes them in two ways and writes/reads the real on-disk format:

    synthetic scenes --(sample_at)--> Scenarios  <--(sample_at)-- Scenes <-- load_nuscenes(any v1.0 folder)
           \\------------------- write_nuscenes ------------------------------------^

Map of the module (the order the data flows):
    1. Config            SynthConfig: every knob of the generator and of the sample cutting, documented
    2. Batches           Scenarios (planning samples, INTERFACES.md) and Scenes (20 s world-frame logs)
    3. Geometry          arcline paths (the nuScenes map primitive: arcs and straights), poses along them,
                         2 m discretisation, the road's Frenet frame, backward-difference speeds
    4. Synthetic scenes  map layout -> scripted agents (one predicted vehicle with paired behaviours) ->
                         the expert ego (lane keeping, IDM car following, yielding; it sees the TRUE futures)
                         -> collision filter -> tracking noise
    5. Planning samples  sample_at: cut a batch at frame t0 (optionally with a simulated ego state)
    6. Dataset           train/val split by scene, disk cache, load_or_generate
    7. Statistics        speeds, accelerations, yaw rates, behaviour mix, interaction rate
    8. Plot              plot_scenario(ax, batch, i)
    9. nuScenes writer   13 tables, key frames for CAM_FRONT and LIDAR_TOP, map expansion 1.3, prediction split
   10. nuScenes loader   json + numpy only; the same Scenes/Scenarios from generated or real v1.0 folders
   11. CLI               generate, write-nuscenes, read-nuscenes, render, stats, --bench

Shape letters:  S scenes   F frames (41 = 20 s at 2 Hz)   M agents per scene   B samples   A other agents
                L lanes    P points per lane   Q arcline paths per scene   R paths per lane (a route)
                N fine simulation steps (0.1 s)   9 = history incl. t0   6 = future steps
A state is s = (x, y, heading h, speed v). Speeds are backward differences of positions everywhere (central
differences would leak the future into the inputs); accelerations and yaw rates are left to the consumer.
Everything random takes a numpy Generator made from a seed: no global RNG.
"""
from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import math
import os
import statistics as pystats
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from diffstack import unicycle_rollout  # noqa: F401  (re-exported for notebooks: the same dynamics as the stack)

# ============================================================================================
# 1. Config
# ============================================================================================

BEHAVIOURS = ("cut_in", "keep_lane", "lead_brake", "lead_cruise", "turn_across", "go_straight",
              "cross_go", "cross_yield", "far", "behind")
"""The predicted vehicle's manoeuvre, the label in Scenarios.behaviour. They come in pairs that share a set-up
and differ in what happens at the event time, so the history only partly tells them apart:
    cut_in / keep_lane       a vehicle in the next lane, a little ahead: it merges in front of the ego, or not
    lead_brake / lead_cruise the vehicle ahead in the ego's lane brakes hard (maybe to a stop), or keeps going
    turn_across / go_straight an oncoming vehicle turns left across the ego's lane at an intersection, or not
    cross_go / cross_yield   a vehicle on the crossing road (from the ego's right) crosses in front, or stops
    far                      a vehicle 35-60 m ahead in the next lane that changes lanes or not: errors don't matter
    behind                   a vehicle behind in the next lane that merges behind the ego or not: errors don't matter
"""
_B = {name: i for i, name in enumerate(BEHAVIOURS)}
_INTERSECTION_BEHAVIOURS = ("turn_across", "go_straight", "cross_go", "cross_yield")


@dataclass
class SynthConfig:
    """Knobs of the synthetic generator and of cutting planning samples (used for real nuScenes too)."""

    # --- time (REFERENCE.md §1) ---
    dt: float = 0.5
    """frame period (s): nuScenes key frames are 2 Hz"""
    frames: int = 41
    """frames per scene (20 s): 4 s history + 10 s closed-loop simulation + 3 s horizon fit"""
    hist: int = 8
    """past steps of a sample's history (the current state makes 9)"""
    fut: int = 6
    """future steps of a sample (3 s)"""
    sim_dt: float = 0.1
    """step of the generator's simulation (s); frames are every dt / sim_dt steps"""

    # --- behaviour mix ---
    mix: dict = field(default_factory=lambda: {
        "cut_in": 0.15, "keep_lane": 0.13, "lead_brake": 0.12, "lead_cruise": 0.10, "turn_across": 0.09,
        "go_straight": 0.08, "cross_go": 0.09, "cross_yield": 0.08, "far": 0.08, "behind": 0.08})
    """relative weight of each predicted-agent behaviour (BEHAVIOURS); normalised, missing names are 0"""
    cue_prob: float = 0.7
    """probability that an active manoeuvre is announced in the history (drift to the lane line, early slowing)"""
    false_cue_prob: float = 0.3
    """probability that a passive twin shows the same cue and then does not act (keeps lane, resumes speed)"""
    intersection_prob: float = 0.25
    """probability of an intersection in scenes whose behaviour does not need one"""
    curved_prob: float = 0.5
    """probability that a road without intersection is a constant-curvature arc (else straight)"""
    min_radius: float = 150.0
    """smallest road radius (m); the arc's curvature is uniform in [1/1000, 1/min_radius] with a random sign"""

    # --- agents ---
    ego_speed: tuple = (6.0, 14.0)
    """range of the ego's initial speed (m/s); its desired speed is 0-10 % higher, at most 15 m/s"""
    n_vehicles: int = 6
    """most moving background vehicles per scene (a uniform count from half of it)"""
    n_parked: int = 2
    """most parked vehicles on the kerb per scene"""
    n_peds: int = 4
    """most pedestrians on the sidewalks per scene"""
    lane_width: float = 3.5
    """lane width W (m)"""

    # --- tracking noise on the other agents' logged tracks (ego poses are exact, as from localisation) ---
    pos_noise: float = 0.08
    """std of the AR(1) position noise (m); applied to history AND future, like real annotations"""
    yaw_noise: float = 0.01
    """std of the AR(1) heading noise (rad)"""
    noise_corr: float = 0.9
    """AR(1) correlation of the noise from one frame to the next (a tracker's errors are smooth)"""

    # --- cutting samples (synthetic and real) ---
    samples_per_scene: int = 4
    """samples cut from a synthetic scene, at frames around the predicted agent's event"""
    lane_points: int = 40
    """P: points per lane in a sample (2 m apart: 80 m)"""
    lane_spacing: float = 2.0
    """distance between lane points (m)"""
    lane_behind: int = 2
    """a sample's lane starts this many points behind the point closest to the ego"""
    max_lanes: int = 12
    """L: at most this many lanes per sample, the closest to the ego"""
    lane_radius: float = 30.0
    """a lane is near the ego when one of its points is within this distance (m)"""
    max_others: int = 16
    """A: at most this many other agents per sample, the closest to the ego"""
    others_radius: float = 50.0
    """other agents farther than this from the ego at t0 are left out (m)"""
    map_radius: float = 60.0
    """loader: map lanes within this distance of the ego's logged path form the scene's lane graph (m)"""
    val_fraction: float = 0.15
    """fraction of scenes (not samples) held out for validation"""


# ============================================================================================
# 2. Batches: Scenarios (planning samples) and Scenes (world-frame logs)
# ============================================================================================


class _Batch:
    """Indexing, length, concatenation and dtype conversion for dataclasses whose tensors share dim 0."""

    def __len__(self):
        return next(iter(self.tensors().values())).shape[0]

    def tensors(self) -> dict:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)
                if isinstance(getattr(self, f.name), torch.Tensor)}

    def __getitem__(self, idx):
        """idx: a slice, an int64 index tensor or a bool mask -> the same class with those rows."""
        out = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if isinstance(v, torch.Tensor):
                out[f.name] = v[idx]
            else:  # a list (scene names): index it like the tensors
                out[f.name] = list(np.asarray(v, dtype=object)[np.arange(len(v))[_np_index(idx)]])
        return type(self)(**out)

    def to(self, dtype=None, device=None):
        """Floating tensors to dtype (bool/int stay), everything to device."""
        out = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if isinstance(v, torch.Tensor):
                v = v.to(device=device, dtype=dtype if (dtype is not None and v.is_floating_point()) else None)
            out[f.name] = v
        return type(self)(**out)

    @classmethod
    def cat(cls, items: list):
        """Concatenate along dim 0, padding the other dims to the largest (0 / False; -1 for integer indices)."""
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


def _np_index(idx):
    return idx.numpy() if isinstance(idx, torch.Tensor) else idx


@dataclass
class Scenarios(_Batch):
    """A batch of planning samples, every coordinate in the EGO FRAME AT t0 (ego at the origin, heading +x).
    Exactly the fields of INTERFACES.md; padding is 0 / False, never NaN."""

    ego_hist: torch.Tensor  # (B, 9, 4)   ego states t-8..t0; ego_hist[:, -1] = (0, 0, 0, v)
    ego_fut: torch.Tensor  # (B, 6, 4)    ego GT future t1..t6 (the expert's plan)
    agent_hist: torch.Tensor  # (B, 9, 4)  the predicted vehicle's history
    agent_hist_mask: torch.Tensor  # (B, 9) bool  observed steps (missing ones hold the earliest observed state)
    agent_fut: torch.Tensor  # (B, 6, 4)   its GT future (always complete)
    others_hist: torch.Tensor  # (B, A, 9, 4) other vehicles and pedestrians
    others_fut: torch.Tensor  # (B, A, 6, 4)  their GT futures (gaps hold the nearest observed state)
    others_mask: torch.Tensor  # (B, A) bool  a real agent
    others_is_ped: torch.Tensor  # (B, A) bool
    lanes: torch.Tensor  # (B, L, P, 3)  lane centre lines (x, y, heading) along the driving direction, 2 m apart
    lanes_mask: torch.Tensor  # (B, L, P) bool  valid points (a prefix of each lane)
    goal: torch.Tensor  # (B, 4)   = ego_fut[:, -1]
    behaviour: torch.Tensor  # (B,) int64  index into BEHAVIOURS; -1 for real data


@dataclass
class Scenes(_Batch):
    """World-frame logs at 2 Hz (float64: global nuScenes coordinates are thousands of metres).

    The map is kept twice: as arcline paths with the lanes' routes through them (what the nuScenes map
    expansion stores; the writer needs it) and as the routes discretised every 2 m (what sample_at crops)."""

    ego: torch.Tensor  # (S, F, 4)  ego states (x, y, h, v)
    agents: torch.Tensor  # (S, M, F, 4)  other agents' logged states (tracking noise included)
    agents_mask: torch.Tensor  # (S, M, F) bool  annotated at that frame
    agents_is_ped: torch.Tensor  # (S, M) bool
    agents_size: torch.Tensor  # (S, M, 3)  width, length, height (m)
    pred_idx: torch.Tensor  # (S, F) int64  the predicted agent for a sample cut at that frame (-1: none)
    event_frame: torch.Tensor  # (S,) int64  frame of the predicted agent's manoeuvre (-1 for real data)
    behaviour: torch.Tensor  # (S,) int64  index into BEHAVIOURS (-1 for real data)
    lanes: torch.Tensor  # (S, L, P, 3)  routes through the lane graph, discretised every 2 m from their start
    lanes_mask: torch.Tensor  # (S, L, P) bool
    paths: torch.Tensor  # (S, Q, 10)  arcline paths [x, y, yaw, radius, l0, l1, l2, sign0, sign1, sign2]
    paths_is_connector: torch.Tensor  # (S, Q) bool  lane connector (inside an intersection) or lane
    routes: torch.Tensor  # (S, L, R) int64  the paths each lane runs through, in order (-1: padding)
    names: list  # S scene names


# ============================================================================================
# 3. Geometry: arcline paths, poses along them, discretisation, the road frame
# ============================================================================================
#
# The nuScenes map expansion stores a lane as arcline paths. One path = a start pose and three pieces of
# constant curvature sign_k / radius and length l_k (shape LSR = left arc, straight, right arc, ...). We use
# the same primitive for the generator's roads, so that a map written to disk and read back gives back the
# same lanes bit for bit. A *segment* below is one piece with its start pose: [x0, y0, yaw0, kappa, length].
# Along a segment, at arc length u (kappa -> 0 is the straight line; np.sinc keeps it exact there):
#     x = x0 + cos(yaw0) A - sin(yaw0) C,   y = y0 + sin(yaw0) A + cos(yaw0) C,   yaw = yaw0 + kappa u,
#     A = sin(kappa u) / kappa,   C = (1 - cos(kappa u)) / kappa.

_SHAPE_SIGNS = {"LSL": (1, 0, 1), "LSR": (1, 0, -1), "RSL": (-1, 0, 1), "RSR": (-1, 0, -1),
                "LRL": (1, -1, 1), "RLR": (-1, 1, -1)}  # the devkit's compute_segment_sign


def wrap(a):
    """Angle to [-pi, pi)."""
    return (a + np.pi) % (2 * np.pi) - np.pi


def _arc(kappa, u):
    """(A, C) above for curvature kappa and arc length u (broadcast), exact at kappa = 0."""
    ku = kappa * u
    return u * np.sinc(ku / np.pi), u * np.sin(ku / 2) * np.sinc(ku / (2 * np.pi))


def _segment_pose(seg, u):
    """Pose (x, y, yaw) at arc length u along segments seg (..., 5); u broadcasts against seg[..., 0]."""
    x0, y0, yaw0, kappa = seg[..., 0], seg[..., 1], seg[..., 2], seg[..., 3]
    a, c = _arc(kappa, u)
    cos, sin = np.cos(yaw0), np.sin(yaw0)
    return np.stack([x0 + cos * a - sin * c, y0 + sin * a + cos * c, yaw0 + kappa * u], -1)


def arcline_segments(paths):
    """Arcline paths (..., 10) -> their three segments (..., 3, 5), each starting where the previous ends."""
    start, radius, lengths, signs = paths[..., :3], paths[..., 3], paths[..., 4:7], paths[..., 7:10]
    segs = []
    for k in range(3):
        kappa = np.divide(signs[..., k], radius, out=np.zeros_like(radius), where=radius > 0)  # padding: r = 0
        segs.append(np.concatenate([start, kappa[..., None], lengths[..., k, None]], -1))
        start = _segment_pose(segs[-1], lengths[..., k])
    return np.stack(segs, -2)


def route_segments(paths, routes):
    """The segments of lanes that run through paths (S, Q, 10) in the order routes (S, L, R) gives (-1 = none):
    (S, L, 3R, 5), padded with zero-length segments."""
    segs = arcline_segments(paths)  # (S, Q, 3, 5)
    gathered = np.take_along_axis(segs[:, None], np.maximum(routes, 0)[..., None, None], 2)  # (S, L, R, 3, 5)
    gathered[..., 4] *= routes[..., None] >= 0  # padding -> length 0
    return gathered.reshape(*routes.shape[:2], -1, 5)


def pose_along(segs, u):
    """Poses (..., N, 3) and curvatures (..., N) at arc lengths u (..., N) along chained segments (..., G, 5).

    Each segment keeps its own start pose (no drift across joints); before the start and past the end the
    first / last segment is extended, so agents can drive off a path's ends smoothly."""
    lengths = segs[..., 4]  # (..., G)
    starts = np.cumsum(lengths, -1) - lengths
    nonempty = lengths > 0
    ok = nonempty[..., None, :] & (starts[..., None, :] <= u[..., None])  # (..., N, G)
    G = lengths.shape[-1]
    last_ok = G - 1 - np.argmax(ok[..., ::-1], -1)  # (..., N) the last segment that starts before u
    k = np.where(ok.any(-1), last_ok, np.argmax(nonempty, -1)[..., None])
    seg = np.take_along_axis(segs, k[..., None], -2)  # (..., N, 5)
    local = u - np.take_along_axis(starts, k, -1)
    return _segment_pose(seg, local), seg[..., 3]


def discretize(segs, spacing: float):
    """Points every `spacing` metres from the start of chained segments (..., G, 5):
    (..., P, 3) poses (yaw wrapped) and (..., P) mask, P from the longest; invalid points are 0."""
    total = segs[..., 4].sum(-1)  # (...)
    P = int(np.floor(total.max() / spacing + 1e-9)) + 1 if total.size else 1
    u = np.broadcast_to(np.arange(P) * spacing, (*total.shape, P))
    mask = u <= total[..., None] + 1e-9
    pts, _ = pose_along(segs, u)
    pts[..., 2] = wrap(pts[..., 2])
    return np.where(mask[..., None], pts, 0.0), mask


def frenet_to_xy(s, d, kappa):
    """The road frame: a reference arc from the origin heading +x with curvature kappa; (s along, d left)."""
    a, c = _arc(kappa, s)
    th = kappa * s
    return a - d * np.sin(th), c + d * np.cos(th), th


def xy_to_frenet(x, y, kappa):
    """Inverse of frenet_to_xy (closed form; d = (2y - kappa (x^2 + y^2)) / (1 + r) avoids 1/kappa)."""
    r = np.sqrt((kappa * x) ** 2 + (1 - kappa * y) ** 2)
    d = (2 * y - kappa * (x**2 + y**2)) / (1 + r)
    ks = np.where(np.abs(kappa) < 1e-12, 1.0, kappa)
    s = np.where(np.abs(kappa) < 1e-12, x, np.arctan2(kappa * x, 1 - kappa * y) / ks)
    return s, d


def backward_speed(xy, mask, t):
    """Speed by backward differences: |p_t - p_prev| / (t - t_prev), prev = the previous observed frame.
    xy (..., F, 2), mask (..., F), t (..., F) seconds -> (..., F); a track's first frame copies its second."""
    F = xy.shape[-2]
    t = np.broadcast_to(t, mask.shape)
    idx = np.where(mask, np.arange(F), -1)
    prev = np.maximum.accumulate(np.concatenate([np.full(idx.shape[:-1] + (1,), -1), idx[..., :-1]], -1), -1)
    has_prev = mask & (prev >= 0)
    p = np.maximum(prev, 0)
    dp = xy - np.take_along_axis(xy, p[..., None], -2)
    dt = t - np.take_along_axis(t, p, -1)
    v = np.where(has_prev, np.linalg.norm(dp, axis=-1) / np.where(has_prev, dt, 1.0), 0.0)
    # the first observed frame of a track has no past: it copies the speed of the next observed frame
    obs = np.where(mask, np.arange(F), F)
    after = np.minimum.accumulate(obs[..., ::-1], -1)[..., ::-1]  # first observed frame >= f
    nxt = np.concatenate([after[..., 1:], np.full(idx.shape[:-1] + (1,), F)], -1)  # first observed frame > f
    first = mask & ~has_prev & (nxt < F)
    return np.where(first, np.take_along_axis(v, np.minimum(nxt, F - 1), -1), v)


# ============================================================================================
# 4. Synthetic scenes
# ============================================================================================
#
# One scene = one road (main road with n_fwd lanes in the ego's direction and n_opp oncoming lanes,
# straight or a constant-curvature arc), sometimes crossed by a two-lane road at an intersection at road
# position s = 0. Every agent drives along an arcline *path* (its lane, or a turn through the intersection)
# with a scripted speed program and a lateral offset (lane changes); agents do not react to each other and
# are placed so that they rarely collide. The ego is simulated last, with an expert policy that reacts to
# the TRUE futures of everybody, so its logged trajectory is a sensible plan to imitate. Scenes where
# anything still collides are dropped (and regenerated).
#
# Road frame: s along the main road's reference line (its centre divider), d to the left. Forward lane i
# (0 = next to the divider) is at d = -(i + 1/2) W, oncoming lane j at d = +(j + 1/2) W (right-hand traffic).

_CAR = (1.9, 4.6, 1.6)  # width, length, height (m)
_PED = (0.6, 0.6, 1.75)
_EGO_W, _EGO_L = 1.9, 4.7
_BOX_MARGIN = 3.0  # between the road edges and the intersection box (m)
_FAR = 300.0  # paths that approach the intersection start this far before it; u = 300 is the box edge
_IDM = dict(a_max=1.5, b=2.5, T=1.2, s0=2.5, look=6)  # the ego's IDM, look-ahead in frames (3 s)
_LONG = 1e4  # length of a path's open-ended segment (m)


def _smoothstep(x):
    """Quintic ramp 0 -> 1 on [0, 1] and its derivative (zero velocity and acceleration at both ends)."""
    x = np.clip(x, 0.0, 1.0)
    return x**3 * (10 - 15 * x + 6 * x**2), 30 * x**2 * (1 - x) ** 2


def _straight(x, y, yaw, length, ones):
    """A straight arcline path (shape LSR with lengths [0, L, 0]) as (..., 10)."""
    z = 0 * ones
    return np.stack([x * ones, y * ones, yaw * ones, 1000 * ones, z, length * ones, z, ones, z, -ones], -1)


def _arc_path(x, y, yaw, radius, sign, l_arc, l_straight, ones):
    """An arc of the given sign (+1 left) followed by a straight: shape LSR/RSR (or LSL/RSL), as (..., 10)."""
    z = 0 * ones
    return np.stack([x * ones, y * ones, yaw * ones, radius * ones, l_arc * ones, l_straight * ones, z,
                     sign * ones, z, np.where(l_straight > 0, -sign, sign) * ones], -1)


def _lane_path(d, kappa, forward):
    """The open-ended path of the lane at road offset d, u = 0 at s = 0: segments (..., 3, 5)."""
    one = np.ones_like(d * kappa)
    k_lane = kappa / (1 - kappa * d)
    seg0 = np.stack([0 * one, d * one, np.where(forward, 0.0, np.pi) * one,
                     np.where(forward, k_lane, -k_lane) * one, _LONG * one], -1)
    return np.stack([seg0, 0 * seg0, 0 * seg0], -2)


def _draw_layout(S, cfg, rng):
    """Per-scene road, behaviour, timing and ego speed: a dict of (S,) arrays."""
    unknown = set(cfg.mix) - set(BEHAVIOURS)
    if unknown:
        raise ValueError(f"SynthConfig.mix: unknown behaviours {sorted(unknown)}; known: {BEHAVIOURS}")
    w = np.array([float(cfg.mix.get(b, 0.0)) for b in BEHAVIOURS])
    if (w < 0).any() or w.sum() <= 0:
        raise ValueError(f"SynthConfig.mix needs non-negative weights with a positive sum, got {cfg.mix}")
    beh = rng.choice(len(BEHAVIOURS), S, p=w / w.sum())
    inter = np.isin(beh, [_B[b] for b in _INTERSECTION_BEHAVIOURS]) | (rng.random(S) < cfg.intersection_prob)
    n_fwd, n_opp = rng.integers(2, 4, S), rng.integers(1, 3, S)
    curv = rng.uniform(1 / 1000, 1 / cfg.min_radius, S) * rng.choice([-1.0, 1.0], S)
    kappa = np.where(~inter & (rng.random(S) < cfg.curved_prob), curv, 0.0)
    ego_lane = np.floor(rng.random(S) * n_fwd).astype(int)
    side = np.where(rng.random(S) < 0.5, -1, 1)
    side = np.where((ego_lane + side < 0) | (ego_lane + side >= n_fwd), -side, side)
    v_e0 = rng.uniform(*cfg.ego_speed, S)
    v_des = np.minimum(np.minimum(v_e0 * rng.uniform(1.0, 1.1, S), 15.0), np.sqrt(2.5 / np.maximum(abs(kappa), 1e-9)))
    return dict(beh=beh, inter=inter, n_fwd=n_fwd, n_opp=n_opp, kappa=kappa, ego_lane=ego_lane,
                adj_lane=ego_lane + side, t_e=rng.uniform(7.0, 12.5, S), v_e0=v_e0, v_des=v_des)


def _script_agents(lay, cfg, rng):
    """Programs for every agent slot (slot 0 = the predicted vehicle) and the ego's start s_e0.

    A program: path segments; start u and speed v0; a speed reference v0 -> v1 (from t1) -> v2 (from t2) tracked
    with |decel| <= dec1 / dec2; an optional stop at u_stop held until t_go; a lateral offset
        d(t) = d0 + D S((t - t_lc)/T_lc) + c (S((t - t_up)/T_up) - S((t - t_dn)/T_dn))
    (S the smoothstep): a lane change D, and a cue c (a drift to the lane line before it, or a drift and back).
    Agents with a finite anchor_t are shifted after simulation so that they are at anchor_u at anchor_t."""
    S, W = len(lay["beh"]), cfg.lane_width
    M = 2 + cfg.n_vehicles - 1 + cfg.n_parked + cfg.n_peds  # predicted, ego-lane leader, background, parked, peds
    beh, kappa, t_e, v_e0 = lay["beh"], lay["kappa"], lay["t_e"], lay["v_e0"]
    inf, one = np.inf, np.ones(S)
    U = lambda lo, hi, n=S: rng.uniform(lo, hi, n)  # noqa: E731
    is_ = lambda *names: np.isin(beh, [_B[n] for n in names])  # noqa: E731
    p = {k: np.zeros((S, M)) for k in ("u_start", "v0", "v1", "v2", "d0", "D", "c")}
    p.update({k: np.full((S, M), inf) for k in ("t1", "t2", "u_stop", "t_lc", "t_up", "t_dn", "anchor_t")})
    p.update(dec1=np.full((S, M), 2.0), dec2=np.full((S, M), 2.0), t_go=np.full((S, M), -inf),
             b_stop=np.full((S, M), 2.0), T_lc=np.full((S, M), 3.0), T_up=np.full((S, M), 1.5),
             T_dn=np.full((S, M), 1.5), anchor_u=np.zeros((S, M)), exists=np.zeros((S, M), bool),
             is_ped=np.zeros((S, M), bool), segs=np.zeros((S, M, 3, 5)))
    p["size"] = np.broadcast_to(np.array(_CAR), (S, M, 3)).copy()

    d_f = lambda i: -(i + 0.5) * W  # noqa: E731  forward lane offsets
    d_o = lambda j: (j + 0.5) * W  # noqa: E731  oncoming lane offsets
    de, dj = d_f(lay["ego_lane"]), d_f(lay["adj_lane"])
    bx = W + _BOX_MARGIN  # half-length of the intersection box along the main road
    y_bot = -(lay["n_fwd"] * W + _BOX_MARGIN)  # the box's edge on the ego's right
    R_left = bx + W / 2  # radius of the oncoming left turn

    # --- the ego's start (road s), for scenes whose situation does not fix it: before any intersection
    s_e0 = np.where(lay["inter"], -v_e0 * U(4, 16), 0.0)

    # --- slot 0, the predicted vehicle ------------------------------------------------------------------
    p["exists"][:, 0] = True
    p["size"][:, 0, 0], p["size"][:, 0, 1] = U(1.8, 2.0), U(4.3, 4.9)
    cue, false_cue = rng.random(S) < cfg.cue_prob, rng.random(S) < cfg.false_cue_prob

    # (a) an agent in the adjacent forward lane: cut_in / keep_lane / far / behind.
    #     At t_ref (the middle of its lane change) it is `gap` ahead of the ego's nominal, constant-speed position.
    adj = is_("cut_in", "keep_lane", "far", "behind")
    T_lc = U(2.5, 4.0)
    t_ref = t_e + T_lc / 2
    gap = np.select([is_("cut_in", "keep_lane"), is_("far")], [U(6, 14), U(35, 60)], U(-25, -10))
    v_adj = np.select([is_("cut_in", "keep_lane"), is_("far")], [v_e0 + U(-3, 0.5), v_e0 + U(-1, 1)],
                      v_e0 + U(-2, 0.5)).clip(5.0, 20.0)
    changes = is_("cut_in") | (is_("far", "behind") & (rng.random(S) < 0.5))
    toward = np.sign(de - dj)
    # (b) the vehicle ahead in the ego's lane: lead_brake / lead_cruise
    lead = is_("lead_brake", "lead_cruise")
    v_lead = np.maximum(v_e0 + U(-1, 0.5), 4.0)
    g_lead = _CAR[1] + (_IDM["s0"] + _IDM["T"] * v_e0) * U(0.9, 1.6)
    # (c) an oncoming vehicle at the intersection: turn_across / go_straight; at the box edge at t_e + 1
    turn, onc = is_("turn_across"), is_("turn_across", "go_straight")
    v_onc, v_turn = U(7, 11), U(4.0, 5.5)
    t_box = t_e  # at the box edge at the event time; it reaches the ego's lane 1-2 s later
    # (d) a vehicle on the crossing road from the ego's right: cross_go / cross_yield
    cross, yields = is_("cross_go", "cross_yield"), is_("cross_yield")
    v_cross = U(6, 9)

    p["segs"][:, 0] = np.select(
        [adj[:, None, None], lead[:, None, None], turn[:, None, None], onc[:, None, None]],
        [_lane_path(dj, kappa, True), _lane_path(de, kappa, True), _turn_path(S, W, bx, R_left, lay["n_fwd"]),
         _turn_path(S, W, bx, R_left, lay["n_fwd"], turn=False)],
        _cross_path(S, W, y_bot))
    p["v0"][:, 0] = np.select([adj, lead, onc], [v_adj, v_lead, v_onc], v_cross)
    # adjacent: placement, lane change at t_e, the cue (drift to the line) or the false cue (drift and back)
    u_adj = (s_e0 + v_e0 * t_ref + gap) * (1 - kappa * dj) - v_adj * t_ref
    p["u_start"][:, 0] = np.where(adj, u_adj, np.where(lead, (s_e0 + g_lead) * (1 - kappa * de), 0.0))
    p["D"][:, 0] = np.where(adj & changes, de - dj, 0.0)
    p["t_lc"][:, 0], p["T_lc"][:, 0] = np.where(adj & changes, t_e, inf), T_lc
    drift = adj & np.where(changes, cue, false_cue)
    p["c"][:, 0] = np.where(drift, 0.4 * toward, 0.0)
    p["t_up"][:, 0] = np.where(drift, t_e - 1.5, inf)
    p["t_dn"][:, 0] = np.where(drift, np.where(changes, t_e, t_e + 0.5), inf)
    p["T_dn"][:, 0] = np.where(changes, T_lc, 2.0)
    # lead: brake at t_e (to 0-50 % of its speed, a third to a stop), announced by a gentle slow-down before
    brake = is_("lead_brake")
    slow_first = lead & np.where(brake, cue, false_cue)
    p["t1"][:, 0] = np.where(slow_first, t_e - 1.5, np.where(lead, t_e, inf))
    p["v1"][:, 0], p["dec1"][:, 0] = v_lead - 1.5, 1.0
    p["t2"][:, 0] = np.where(lead, t_e, p["t2"][:, 0])
    p["v2"][:, 0] = np.where(brake, v_lead * U(0, 0.5) * (rng.random(S) > 0.33), v_lead)
    p["dec2"][:, 0] = np.where(brake, U(2.5, 4.0), 2.0)
    # oncoming: the turner slows to v_turn before the box (early and gently when cued, else late and harder);
    # a go_straight vehicle with the false cue slows the same way, then speeds up again at the box
    gentle = np.where(turn, cue, false_cue)
    dec = np.where(gentle, 1.5, 3.0)
    slows = turn | (onc & false_cue)
    p["t1"][:, 0] = np.where(onc & slows, t_box - (v_onc - v_turn) / dec - 1.0, p["t1"][:, 0])
    p["v1"][:, 0] = np.where(onc, v_turn, p["v1"][:, 0])
    p["dec1"][:, 0] = np.where(onc, dec, p["dec1"][:, 0])
    p["t2"][:, 0] = np.where(turn, t_box + 3.0, np.where(onc & slows, t_box, p["t2"][:, 0]))
    p["v2"][:, 0] = np.where(onc, v_onc, p["v2"][:, 0])
    # crossing: cross_go is at the box edge at t_box (a false cue: it slows to half speed first);
    # cross_yield stops 1 m before the box at t_box (braking early when cued) and waits until the ego has passed
    go_slow = cross & ~yields & false_cue
    p["t1"][:, 0] = np.where(go_slow, t_box - 3.0, p["t1"][:, 0])
    p["v1"][:, 0] = np.where(go_slow, 0.5 * v_cross, p["v1"][:, 0])
    p["dec1"][:, 0] = np.where(go_slow, 1.5, p["dec1"][:, 0])
    p["t2"][:, 0] = np.where(go_slow, t_box - 1.0, p["t2"][:, 0])
    p["v2"][:, 0] = np.where(cross, v_cross, p["v2"][:, 0])
    b_stop = np.where(cue, 1.2, 3.0)
    u_stop = _FAR - 1.0 - p["size"][:, 0, 1] / 2
    p["u_stop"][:, 0] = np.where(yields, u_stop, inf)
    p["b_stop"][:, 0] = b_stop
    p["u_start"][:, 0] = np.where(yields, u_stop - v_cross**2 / (2 * b_stop) - v_cross * (t_box - v_cross / b_stop),
                                  p["u_start"][:, 0])
    p["anchor_t"][:, 0] = np.where(onc | (cross & ~yields), t_box, inf)
    p["anchor_u"][:, 0] = _FAR

    # the ego's start for the intersection situations: its front reaches the conflict point delta s after
    # the other vehicle does (the expert then yields); the same delta for both twins, so nothing leaks
    h = de - (W / 2 - R_left)
    x_turn_conflict = bx - np.sqrt(np.maximum(R_left**2 - h**2, 0.0))
    delta = U(-0.5, 1.0)  # the ego's front at the conflict point this long after the other's centre
    t_turn_in = t_box + R_left * np.arccos(np.clip(h / R_left, -1, 1)) / v_turn  # the turner in the ego's lane
    s_e0 = np.where(onc, x_turn_conflict - _EGO_L / 2 - 1.0 - v_e0 * (t_turn_in + delta), s_e0)
    t_pass = t_box + (de - y_bot) / v_cross + delta  # the crossing car in the ego's lane, plus delta
    s_e0 = np.where(cross, W / 2 - 1.0 - _EGO_L / 2 - v_e0 * t_pass, s_e0)
    p["t_go"][:, 0] = np.where(yields, t_pass + (2.0 + _EGO_L) / v_e0 + 2.0, -inf)
    # adjacent and lead placements were relative to s_e0 before the intersection override; redo them
    p["u_start"][:, 0] = np.where(adj, (s_e0 + v_e0 * t_ref + gap) * (1 - kappa * dj) - v_adj * t_ref,
                                  np.where(lead, (s_e0 + g_lead) * (1 - kappa * de), p["u_start"][:, 0]))

    # --- slot 1: a leader far ahead in the ego's lane that drives away (not in lead situations) -----------
    p["exists"][:, 1] = ~lead & (rng.random(S) < 0.5)
    p["segs"][:, 1] = _lane_path(de, kappa, True)
    p["u_start"][:, 1] = (s_e0 + U(55, 90)) * (1 - kappa * de)
    p["v0"][:, 1] = np.minimum(lay["v_des"] + U(1, 3), 20.0)

    # --- background traffic on the lanes nobody else uses, each lane at its own speed, spaced 25-45 m ------
    lane_d = np.stack([d_f(0) * one, d_f(1) * one, d_f(2) * one, d_o(0) * one, d_o(1) * one], 1)  # (S, 5)
    lane_fwd = np.array([True, True, True, False, False])
    free = np.stack([lay["n_fwd"] > 0, lay["n_fwd"] > 1, lay["n_fwd"] > 2, lay["n_opp"] > 0, lay["n_opp"] > 1], 1)
    free &= np.arange(5) != lay["ego_lane"][:, None]
    free[:, :3] &= ~(adj[:, None] & (np.arange(3) == lay["adj_lane"][:, None]))
    free[:, 3] &= ~onc
    lane_v = rng.uniform(7, 13, (S, 5))
    lane_s0 = np.where(lane_fwd, rng.uniform(-150, -60, (S, 5)), rng.uniform(20, 100, (S, 5)))
    lane_gap = rng.uniform(25, 45, (S, 5))
    nb = cfg.n_vehicles - 1
    if nb > 0:
        bg = slice(2, 2 + nb)
        choice = np.argmax(rng.random((S, nb, 5)) * free[:, None], -1)  # (S, nb) a free lane per vehicle
        onehot = choice[..., None] == np.arange(5)
        rank = (np.cumsum(onehot, 1) - 1)[onehot].reshape(S, nb)
        take = lambda a: np.take_along_axis(a, choice, 1)  # noqa: E731
        s0 = s_e0[:, None] + take(lane_s0) + rank * take(lane_gap)
        d, fwd = take(lane_d), lane_fwd[choice]
        p["exists"][:, bg] = np.arange(nb) < rng.integers((nb + 1) // 2, nb + 1, S)[:, None]
        p["segs"][:, bg] = _lane_path(d, kappa[:, None], fwd)
        p["u_start"][:, bg] = np.where(fwd, s0, -s0) * (1 - kappa[:, None] * d)
        p["v0"][:, bg] = take(lane_v)

    # --- parked cars on the kerb of the outer forward lane (kept off the intersection) ---------------------
    pk = slice(1 + cfg.n_vehicles, 1 + cfg.n_vehicles + cfg.n_parked)
    d_out = d_f(lay["n_fwd"] - 1)[:, None]
    s_pk = s_e0[:, None] + rng.uniform(-20, 100, (S, 1)) + np.cumsum(rng.uniform(8, 60, (S, cfg.n_parked)), 1)
    s_pk = np.where(lay["inter"][:, None] & (abs(s_pk) < 25), s_pk + 50, s_pk)
    p["exists"][:, pk] = rng.random((S, cfg.n_parked)) < 0.5
    p["segs"][:, pk] = _lane_path(d_out, kappa[:, None], True)
    p["u_start"][:, pk] = s_pk * (1 - kappa[:, None] * d_out)
    p["d0"][:, pk] = -(W / 2 + 1.0)  # centre 1 m outside the lane's edge

    # --- pedestrians on the sidewalks, walking either way (at intersections: away from it) -----------------
    pd = slice(M - cfg.n_peds, M)
    left = rng.random((S, cfg.n_peds)) < 0.5
    walkway = 2.5 + 0.7 * np.arange(cfg.n_peds)  # each pedestrian its own line: they never walk into each other
    d_sw = np.where(left, lay["n_opp"][:, None] * W + walkway, -lay["n_fwd"][:, None] * W - walkway)
    s_pd = s_e0[:, None] + rng.uniform(-30, 200, (S, cfg.n_peds))
    s_pd = np.where(lay["inter"][:, None] & (abs(s_pd) < 15), s_pd + 30, s_pd)
    fwd = np.where(lay["inter"][:, None], s_pd > 0, rng.random((S, cfg.n_peds)) < 0.5)
    p["exists"][:, pd] = np.arange(cfg.n_peds) < rng.integers((cfg.n_peds + 1) // 2, cfg.n_peds + 1, S)[:, None]
    p["is_ped"][:, pd] = True
    p["size"][:, pd] = _PED
    p["segs"][:, pd] = _lane_path(d_sw, kappa[:, None], fwd)
    p["u_start"][:, pd] = np.where(fwd, s_pd, -s_pd) * (1 - kappa[:, None] * d_sw)
    p["v0"][:, pd] = rng.uniform(0.8, 1.6, (S, cfg.n_peds))
    p["v1"] = np.where(np.isinf(p["t1"]), p["v0"], p["v1"])  # unused phases hold the initial speed
    p["v2"] = np.where(np.isinf(p["t2"]), p["v0"], p["v2"])
    return p, s_e0


def _turn_path(S, W, bx, R, n_fwd, turn=True):
    """The oncoming (westbound) vehicle's left turn into the southbound crossing lane: approach, arc, exit;
    or (turn=False) straight on along its lane. u = _FAR at the box edge either way."""
    one = np.ones(S)
    approach = np.stack([(bx + _FAR) * one, W / 2 * one, np.pi * one, 0 * one, (_FAR if turn else _LONG) * one], -1)
    if not turn:
        return np.stack([approach, 0 * approach, 0 * approach], -2)
    arc = np.stack([bx * one, W / 2 * one, np.pi * one, one / R, np.pi / 2 * R * one], -1)
    exit_ = np.stack([-W / 2 * one, (W / 2 - R) * one, 1.5 * np.pi * one, 0 * one, _LONG * one], -1)
    return np.stack([approach, arc, exit_], -2)


def _cross_path(S, W, y_bot):
    """The northbound crossing lane (x = +W/2), u = _FAR at the box edge y_bot: segments (S, 3, 5)."""
    one = np.ones(S)
    seg0 = np.stack([W / 2 * one, y_bot - _FAR, np.pi / 2 * one, 0 * one, _LONG * one], -1)
    return np.stack([seg0, 0 * seg0, 0 * seg0], -2)


def _run_programs(p, n_steps, sim_dt):
    """Integrate every agent's speed program: arc position u and speed v along its path, (S, M, N) each."""
    u, v = p["u_start"].copy(), p["v0"].copy()
    us, vs = np.empty(u.shape + (n_steps,)), np.empty(u.shape + (n_steps,))
    for k in range(n_steps):  # a loop over time, vectorised over scenes and agents
        us[..., k], vs[..., k] = u, v
        t = k * sim_dt
        v_ref = np.where(t < p["t1"], p["v0"], np.where(t < p["t2"], p["v1"], p["v2"]))
        dec = np.where(t < p["t1"], 2.0, np.where(t < p["t2"], p["dec1"], p["dec2"]))
        a = np.clip(2.0 * (v_ref - v), -dec, 1.5)
        # stopping at u_stop until t_go: brake at the constant deceleration v^2 / (2 gap) once it exceeds b_stop
        gap = p["u_stop"] - u
        stopping = t < p["t_go"]
        need = v**2 / (2 * np.maximum(gap, 0.05))
        a = np.where(stopping & (need > p["b_stop"]), -np.minimum(need, 4.0), a)
        hold = stopping & (gap < 0.5) & (v < 0.5)
        v_new = np.where(hold, 0.0, np.maximum(v + a * sim_dt, 0.0))
        u, v = u + 0.5 * (v + v_new) * sim_dt, v_new
    # anchored agents: shift along the path so that they are at anchor_u at anchor_t
    k_anchor = np.clip(np.where(np.isfinite(p["anchor_t"]), p["anchor_t"], 0) / sim_dt, 0, n_steps - 1).round()
    shift = p["anchor_u"] - np.take_along_axis(us, k_anchor.astype(int)[..., None], -1)[..., 0]
    return us + np.where(np.isfinite(p["anchor_t"]), shift, 0.0)[..., None], vs


def _agent_states(p, us, vs, t):
    """World states (S, M, N, 4) from path positions and the lateral offset program d(t)."""
    ramp = lambda t0, T: _smoothstep((t - t0[..., None]) / T[..., None])  # noqa: E731
    (s_lc, ds_lc), (s_up, ds_up), (s_dn, ds_dn) = ramp(p["t_lc"], p["T_lc"]), ramp(p["t_up"], p["T_up"]), \
        ramp(p["t_dn"], p["T_dn"])
    D, c = p["D"][..., None], p["c"][..., None]
    d = p["d0"][..., None] + D * s_lc + c * (s_up - s_dn)  # (S, M, N)
    d_dot = D * ds_lc / p["T_lc"][..., None] + c * (ds_up / p["T_up"][..., None] - ds_dn / p["T_dn"][..., None])
    pose, kappa = pose_along(p["segs"], us)  # (S, M, N, 3), (S, M, N)
    along = vs * (1 - kappa * d)
    x = pose[..., 0] - d * np.sin(pose[..., 2])
    y = pose[..., 1] + d * np.cos(pose[..., 2])
    return np.stack([x, y, pose[..., 2] + np.arctan2(d_dot, along), np.hypot(along, d_dot)], -1)


def _drive_ego(lay, s_e0, others, exists, sizes, cfg, rng, t):
    """The expert ego: keeps its lane (with a small smooth wander), follows with IDM, and yields.

    It sees the others' TRUE futures: every agent that will be in its lane corridor within the next 3 s is an
    obstacle at the road position it will have then (a crossing or merging car is a stopped obstacle at the
    conflict point until it has cleared), unless the ego at constant speed would already be past it. IDM
    (Treiber et al. 2000):  a = a_max [1 - (v / v_des)^4 - (s*(v, dv) / gap)^2],
                            s* = s0 + max(0, v T + v dv / (2 sqrt(a_max b))),  a in [-4, a_max]."""
    S, N, W = len(s_e0), len(t), cfg.lane_width
    kappa = lay["kappa"]
    de = -(lay["ego_lane"] + 0.5) * W
    # the others in the road frame: position, longitudinal speed, half-extents along and across the road
    s_a, d_a = xy_to_frenet(others[..., 0], others[..., 1], kappa[:, None, None])  # (S, M, N)
    rel = others[..., 2] - kappa[:, None, None] * s_a
    w, length = sizes[..., 0, None] / 2, sizes[..., 1, None] / 2
    ext_long = abs(np.cos(rel)) * length + abs(np.sin(rel)) * w
    ext_lat = abs(np.sin(rel)) * length + abs(np.cos(rel)) * w
    sdot_a = np.gradient(s_a, t, axis=-1)
    in_corr = exists[..., None] & (abs(d_a - de[:, None, None]) < ext_lat + _EGO_W / 2 + 0.3)
    stride = int(round(cfg.dt / cfg.sim_dt))
    u = s_e0 * (1 - kappa * de)  # ego arc position along its lane
    v = lay["v_e0"].copy()
    us, vs = np.empty((S, N)), np.empty((S, N))
    sqrt_ab = 2 * math.sqrt(_IDM["a_max"] * _IDM["b"])
    for k in range(N):  # time loop, vectorised over scenes
        us[:, k], vs[:, k] = u, v
        idx = np.minimum(k + stride * np.arange(_IDM["look"] + 1), N - 1)
        tau = (idx - k) * cfg.sim_dt  # (J,)
        s_e = u / (1 - kappa * de)
        sa, ex = s_a[..., idx], ext_long[..., idx]  # (S, M, J)
        passed = (tau > 0) & (s_e[:, None, None] + v[:, None, None] * tau - _EGO_L / 2 - 1.0 > sa + ex)
        obstacle = in_corr[..., idx] & (sa > s_e[:, None, None]) & ~passed
        gap = np.maximum(sa - ex - s_e[:, None, None] - _EGO_L / 2, 0.1)
        vv = v[:, None, None]
        s_star = _IDM["s0"] + np.maximum(0.0, vv * _IDM["T"] + vv * (vv - sdot_a[..., idx]) / sqrt_ab)
        interaction = np.where(obstacle, (s_star / gap) ** 2, 0.0).max((1, 2))
        a = np.clip(_IDM["a_max"] * (1 - (v / lay["v_des"]) ** 4 - interaction), -4.0, _IDM["a_max"])
        v_new = np.maximum(v + a * cfg.sim_dt, 0.0)
        u, v = u + 0.5 * (v + v_new) * cfg.sim_dt, v_new
    # lane keeping with a smooth wander of the lateral offset along the lane (amplitude <= 0.2 m)
    amp, lam, phase = rng.uniform(0, 0.2, S), rng.uniform(60, 150, S), rng.uniform(0, 2 * np.pi, S)
    off = amp[:, None] * np.sin(2 * np.pi * us / lam[:, None] + phase[:, None])  # (S, N)
    doff_du = amp[:, None] * 2 * np.pi / lam[:, None] * np.cos(2 * np.pi * us / lam[:, None] + phase[:, None])
    pose, k_lane = pose_along(_lane_path(de, kappa, True), us)  # (S, N, 3)
    x = pose[..., 0] - off * np.sin(pose[..., 2])
    y = pose[..., 1] + off * np.cos(pose[..., 2])
    return np.stack([x, y, pose[..., 2] + np.arctan2(doff_du, 1 - k_lane * off), vs], -1), us / (1 - kappa * de)[:, None]


def _build_map(lay, s_lo, s_hi, cfg):
    """The scene's lane graph as arcline paths (S, 23, 10) and the 9 routes through it (S, 9, 3).

    Path slots: forward lane i -> 3i..3i+2 (before / through / after the intersection; one path without it),
    oncoming lane j -> 9+3j.., southbound crossing lane 15..17, northbound 18..20, the ego side's right turn 21,
    the oncoming left turn 22. Routes: forward 0-2, oncoming 3-4, south 5, north 6, right turn 7, left turn 8;
    they are exactly the maximal chains of the graph, which is what the loader rebuilds from the connectivity."""
    S, W, kappa, inter = len(s_lo), cfg.lane_width, lay["kappa"], lay["inter"]
    n_fwd, n_opp = lay["n_fwd"], lay["n_opp"]
    one = np.ones(S)
    bx, y_top, y_bot = W + _BOX_MARGIN, n_opp * W + _BOX_MARGIN, -(n_fwd * W + _BOX_MARGIN)
    Y = 60.0  # the crossing road's lanes reach this far from the main road
    paths = np.zeros((S, 23, 10))
    valid = np.zeros((S, 23), bool)
    conn = np.zeros((S, 23), bool)
    routes = np.full((S, 9, 3), -1)
    for i in range(3):
        for j, (d, fwd) in enumerate([(-(i + 0.5) * W, True), (+(i + 0.5) * W, False)]):
            if not fwd and i > 1:
                continue
            base, r = (3 * i, i) if fwd else (9 + 3 * i, 3 + i)
            exists = (n_fwd > i) if fwd else (n_opp > i)
            # one arc (or straight) over the whole road
            s0 = np.where(fwd, s_lo, s_hi)
            x, y, th = frenet_to_xy(s0, d, kappa)
            length = (s_hi - s_lo) * (1 - kappa * d)
            radius = np.where(kappa != 0, abs(1 / np.where(kappa != 0, kappa, 1) - d), 1000.0)
            sign = np.sign(kappa) * (1 if fwd else -1)
            curved = _arc_path(x, y, th + (0 if fwd else np.pi), radius, sign, length, 0 * one, one)
            single = np.where((kappa != 0)[:, None], curved, _straight(x, y, th + (0 if fwd else np.pi), length, one))
            # before / through / after the intersection (straight road)
            sg = 1 if fwd else -1
            ends = [s_lo, -bx * one, bx * one, s_hi] if fwd else [s_hi, bx * one, -bx * one, s_lo]
            yaw = 0.0 if fwd else np.pi
            for k in range(3):
                piece = _straight(ends[k], d * one, yaw, sg * (ends[k + 1] - ends[k]), one)
                paths[:, base + k] = np.where(inter[:, None], piece, single if k == 0 else 0 * single)
                valid[:, base + k] = exists & (inter | (k == 0))
            conn[:, base + 1] = inter
            routes[:, r] = np.where((exists & inter)[:, None], base + np.arange(3),
                                    np.where(exists[:, None], [base, -1, -1], -1))
    # the crossing road: southbound at x = -W/2, northbound at x = +W/2
    for base, x, yaw, ys in [(15, -W / 2, -np.pi / 2, [Y * one, y_top, y_bot, -Y * one]),
                             (18, W / 2, np.pi / 2, [-Y * one, y_bot, y_top, Y * one])]:
        for k in range(3):
            paths[:, base + k] = _straight(x, ys[k], yaw, abs(ys[k + 1] - ys[k]), one)
        conn[:, base + 1] = True
    # turns: the outer forward lane right into the southbound lane; the inner oncoming lane left into it
    paths[:, 21] = _arc_path(-bx, -(n_fwd - 0.5) * W, 0.0, W / 2 + _BOX_MARGIN, -1.0,
                             np.pi / 2 * (W / 2 + _BOX_MARGIN), 0 * one, one)
    paths[:, 22] = _arc_path(bx, W / 2, np.pi, bx + W / 2, 1.0, np.pi / 2 * (bx + W / 2), (n_fwd - 1) * W, one)
    valid[:, 15:] = inter[:, None]
    conn[:, 21:] = True
    conn &= valid
    routes[:, 5] = np.where(inter[:, None], [15, 16, 17], -1)
    routes[:, 6] = np.where(inter[:, None], [18, 19, 20], -1)
    routes[:, 7] = np.where(inter[:, None], np.stack([3 * (n_fwd - 1), 21 * one, 17 * one], 1), -1)
    routes[:, 8] = np.where(inter[:, None], np.stack([9 * one, 22 * one, 17 * one], 1), -1)
    return paths * valid[..., None], conn, routes


def _bodies(states, sizes, is_ped):
    """Three discs along each body (radius half the width; one disc for pedestrians): centres (..., 3, 2), radii."""
    half = np.where(is_ped, 0.0, sizes[..., 1] / 2 - sizes[..., 0] / 2)  # (..., 1) centre to end disc
    off = half[..., None, None] * np.array([-1.0, 0.0, 1.0])[:, None]  # (..., 1, 3, 1)
    heading = np.stack([np.cos(states[..., 2]), np.sin(states[..., 2])], -1)[..., None, :]  # (..., F, 1, 2)
    centres = states[..., None, :2] + off * heading  # (..., F, 3, 2)
    radius = np.where(is_ped, 0.3, sizes[..., 0] / 2)
    return centres, radius


def _collides(ego, agents, sizes, is_ped, exists):
    """(S,) True where any two bodies (ego included) overlap at any frame. ego (S, F, 4), agents (S, M, F, 4)."""
    S, M, F, _ = agents.shape
    states = np.concatenate([ego[:, None], agents], 1)  # (S, 1+M, F, 4)
    sz = np.concatenate([np.broadcast_to(np.array([_EGO_W, _EGO_L, 1.6]), (S, 1, 3)), sizes], 1)
    ped = np.concatenate([np.zeros((S, 1), bool), is_ped], 1)
    ex = np.concatenate([np.ones((S, 1), bool), exists], 1)
    c, r = _bodies(states, sz[:, :, None], ped[:, :, None])  # (S, 1+M, F, 3, 2), (S, 1+M, 1)
    iu, ju = np.triu_indices(M + 1, 1)
    hit = np.zeros((S, len(iu)), bool)
    for a in range(3):
        for b in range(3):
            dist = np.linalg.norm(c[:, iu][..., a, :] - c[:, ju][..., b, :], axis=-1)  # (S, pairs, F)
            hit |= (dist < (r[:, iu] + r[:, ju])).any(-1)
    return (hit & ex[:, iu] & ex[:, ju]).any(-1)


def _ar1_noise(shape, sigma, rho, rng):
    """Stationary AR(1) noise along the last axis: e_f = rho e_(f-1) + sqrt(1 - rho^2) sigma xi_f."""
    xi = rng.standard_normal(shape) * sigma
    e = np.empty(shape)
    e[..., 0] = xi[..., 0]
    for f in range(1, shape[-1]):
        e[..., f] = rho * e[..., f - 1] + math.sqrt(1 - rho**2) * xi[..., f]
    return e


def _simulate_chunk(S, cfg, rng):
    """Simulate S candidate scenes; returns the world-frame arrays of the ones that are collision-free."""
    stride = int(round(cfg.dt / cfg.sim_dt))
    t = np.arange((cfg.frames - 1) * stride + 1) * cfg.sim_dt  # (N,) fine time grid
    lay = _draw_layout(S, cfg, rng)
    p, s_e0 = _script_agents(lay, cfg, rng)
    us, vs = _run_programs(p, len(t), cfg.sim_dt)
    others = _agent_states(p, us, vs, t)  # (S, M, N, 4)
    ego, s_ego = _drive_ego(lay, s_e0, others, p["exists"], p["size"], cfg, rng, t)  # (S, N, 4), (S, N)
    ego, others = ego[:, ::stride], others[:, :, ::stride]  # frames: (S, F, 4), (S, M, F, 4)
    ok = ~_collides(ego, others, p["size"], p["is_ped"], p["exists"])
    # the map spans the ego's drive: 40 m behind its start, 90 m past its end (the crop needs 80 m ahead)
    paths, conn, routes = _build_map(lay, s_ego[:, 0] - 40.0, s_ego[:, -1] + 90.0, cfg)
    # tracking noise on the others' logs (history and future alike), then speeds by backward differences
    M, F = others.shape[1], others.shape[2]
    noisy = others.copy()
    for ch, sigma in [(0, cfg.pos_noise), (1, cfg.pos_noise), (2, cfg.yaw_noise)]:
        noisy[..., ch] += _ar1_noise((S, M, F), sigma, cfg.noise_corr, rng)
    noisy[..., 2] = wrap(noisy[..., 2])
    ego[..., 2] = wrap(ego[..., 2])
    tf = np.arange(F) * cfg.dt
    mask = np.broadcast_to(p["exists"][..., None], (S, M, F))
    noisy[..., 3] = backward_speed(noisy[..., :2], mask, tf) * mask
    ego[..., 3] = backward_speed(ego[..., :2], np.ones((S, F), bool), tf)
    noisy *= mask[..., None]
    keep = lambda a: a[ok]  # noqa: E731
    return dict(ego=keep(ego), agents=keep(noisy), agents_mask=keep(mask), agents_is_ped=keep(p["is_ped"]),
                agents_size=keep(p["size"]), behaviour=keep(lay["beh"]),
                event_frame=keep(np.round(lay["t_e"] / cfg.dt).astype(np.int64)),
                paths=keep(paths), paths_is_connector=keep(conn), routes=keep(routes)), int((~ok).sum())


def generate_scenes(n: int, cfg: SynthConfig | None = None, seed: int = 0, chunk: int = 512) -> Scenes:
    """n synthetic scenes of cfg.frames frames, deterministic for (cfg, seed). Colliding candidates are
    dropped and replaced; the count is in Scenes.names' companion attribute `dropped` of the last call."""
    cfg = cfg or SynthConfig()
    rng = np.random.default_rng(seed)
    parts, have, dropped = [], 0, 0
    while have < n:
        want = min(chunk, int((n - have) * 1.15) + 4)
        part, d = _simulate_chunk(want, cfg, rng)
        parts.append(part)
        have += len(part["ego"])
        dropped += d
    arr = {k: np.concatenate([q[k] for q in parts])[:n] for k in parts[0]}
    segs = route_segments(arr["paths"], arr["routes"])
    lanes, lanes_mask = discretize(segs, cfg.lane_spacing)
    F = cfg.frames
    valid_t0 = (np.arange(F) >= cfg.hist) & (np.arange(F) < F - cfg.fut)
    pred_idx = np.where(valid_t0, 0, -1)[None].repeat(n, 0)
    T = lambda a: torch.from_numpy(np.ascontiguousarray(a))  # noqa: E731
    scenes = Scenes(ego=T(arr["ego"]), agents=T(arr["agents"]), agents_mask=T(arr["agents_mask"]),
                    agents_is_ped=T(arr["agents_is_ped"]), agents_size=T(arr["agents_size"]),
                    pred_idx=T(pred_idx).long(), event_frame=T(arr["event_frame"]).long(),
                    behaviour=T(arr["behaviour"]).long(), lanes=T(lanes), lanes_mask=T(lanes_mask),
                    paths=T(arr["paths"]), paths_is_connector=T(arr["paths_is_connector"]),
                    routes=T(arr["routes"]).long(), names=[f"synth-{seed}-{i:06d}" for i in range(n)])
    generate_scenes.dropped = dropped
    return scenes


# ============================================================================================
# 5. Planning samples: cut a batch out of scenes at frame t0
# ============================================================================================


def _twrap(a):
    return torch.remainder(a + math.pi, 2 * math.pi) - math.pi


def _to_frame(states, origin):
    """World states (S, ..., >=3) -> the frame of origin (S, 4): positions rotated by -h0, headings - h0."""
    shape = (origin.shape[0],) + (1,) * (states.dim() - 2)
    x0, y0, h0 = (origin[:, i].reshape(shape) for i in range(3))
    c, s = torch.cos(h0), torch.sin(h0)
    dx, dy = states[..., 0] - x0, states[..., 1] - y0
    out = states.clone()
    out[..., 0], out[..., 1], out[..., 2] = c * dx + s * dy, -s * dx + c * dy, _twrap(states[..., 2] - h0)
    return out


def _fill_gaps(x, mask):
    """Missing steps (mask False) of x (..., T, C) take the previous observed step, or else the next one."""
    T = mask.shape[-1]
    ar = torch.arange(T)
    prev = torch.cummax(torch.where(mask, ar, -1), -1).values
    nxt = torch.flip(torch.cummin(torch.flip(torch.where(mask, ar, T), [-1]), -1).values, [-1])
    src = torch.where(prev >= 0, prev, nxt).clamp(max=T - 1)
    return torch.gather(x, -2, src[..., None].expand(x.shape))


def sample_at(scenes: Scenes, frame, ego_state=None, cfg: SynthConfig | None = None,
              dtype=torch.float32) -> Scenarios:
    """One planning sample per scene at frame t0 (an int, or (S,) frames), in the ego frame at t0.

    ego_state replaces the logged ego for closed-loop log replay: (S, 4) the current world state only, or
    (S, 9, 4) the whole history. The frame, the history and the others follow it; the ego's GT future, the
    goal and the lanes stay those of the logged ego (paper §4.3). The predicted agent is scenes.pred_idx;
    the others are the agents present at t0 within cfg.others_radius (closest first, at most max_others);
    the lanes are the cfg.max_lanes routes that come within cfg.lane_radius, cropped to P points from
    cfg.lane_behind points behind the one closest to the ego."""
    cfg = cfg or SynthConfig()
    S, F = scenes.ego.shape[:2]
    H, T, P = cfg.hist, cfg.fut, cfg.lane_points
    frame = torch.as_tensor(frame, dtype=torch.int64).expand(S)
    if ((frame < H) | (frame > F - T - 1)).any():
        raise ValueError(f"sample_at: frames must be in [{H}, {F - T - 1}] (history {H}, future {T}), got {frame}")
    ar = torch.arange(S)
    win = frame[:, None] + torch.arange(-H, T + 1)  # (S, 15) the sample's frames
    ego = scenes.ego[ar[:, None], win]  # (S, 15, 4) world
    if ego_state is not None:
        es = torch.as_tensor(ego_state, dtype=ego.dtype)
        if es.shape == (S, 4):
            ego[:, H] = es
        elif es.shape == (S, H + 1, 4):
            ego[:, : H + 1] = es
        else:
            raise ValueError(f"sample_at: ego_state must be ({S}, 4) or ({S}, {H + 1}, 4), got {tuple(es.shape)}")
    pred = scenes.pred_idx[ar, frame]  # (S,)
    if (pred < 0).any():
        raise ValueError(f"sample_at: no predicted agent in scenes {ar[pred < 0].tolist()} at these frames")
    origin = ego[:, H].clone()  # (S, 4)
    ego = _to_frame(ego, origin)

    # the predicted vehicle
    ag = scenes.agents[ar, pred][ar[:, None], win]  # (S, 15, 4)
    ag_mask = scenes.agents_mask[ar, pred][ar[:, None], win]  # (S, 15)
    ag = _to_frame(_fill_gaps(ag, ag_mask), origin)

    # the others: present at t0, near, closest first
    M = scenes.agents.shape[1]
    now = scenes.agents[ar, :, frame]  # (S, M, 4)
    dist = torch.linalg.norm(now[..., :2] - origin[:, None, :2], dim=-1)  # (S, M)
    cand = scenes.agents_mask[ar, :, frame] & (torch.arange(M) != pred[:, None]) & (dist < cfg.others_radius)
    A = int(min(cand.sum(1).max().item() if S else 0, cfg.max_others))
    order = torch.argsort(torch.where(cand, dist, math.inf), 1)[:, :A]  # (S, A)
    o_mask = torch.gather(cand, 1, order)  # (S, A)
    idx = win[:, None, :, None]
    o_all = scenes.agents[ar[:, None], order]  # (S, A, F, 4)
    o = torch.gather(o_all, 2, idx.expand(S, A, T + H + 1, 4))  # (S, A, 15, 4)
    o_obs = torch.gather(scenes.agents_mask[ar[:, None], order], 2, win[:, None].expand(S, A, T + H + 1))
    o = _to_frame(_fill_gaps(o, o_obs), origin) * o_mask[..., None, None]

    # the lanes near the ego
    lanes = _to_frame(scenes.lanes, origin)  # (S, Lw, Pw, 3)
    d2 = torch.where(scenes.lanes_mask, lanes[..., 0] ** 2 + lanes[..., 1] ** 2, math.inf)  # (S, Lw, Pw)
    dmin, jmin = d2.min(-1)  # (S, Lw)
    near = dmin < cfg.lane_radius**2
    L = int(min(near.sum(1).max().item() if S else 0, cfg.max_lanes))
    lorder = torch.argsort(torch.where(near, dmin, math.inf), 1)[:, :L]  # (S, L)
    Pw = scenes.lanes.shape[2]
    pidx = (torch.gather(jmin, 1, lorder) - cfg.lane_behind).clamp(min=0)[..., None] + torch.arange(P)  # (S, L, P)
    inside = pidx < Pw
    pidx = pidx.clamp(max=Pw - 1)
    sel = lanes[ar[:, None], lorder]  # (S, L, Pw, 3)
    lane_pts = torch.gather(sel, 2, pidx[..., None].expand(S, L, P, 3))  # (S, L, P, 3)
    lane_mask = torch.gather(scenes.lanes_mask[ar[:, None], lorder], 2, pidx) & inside & torch.gather(near, 1, lorder)[..., None]

    out = Scenarios(ego_hist=ego[:, : H + 1], ego_fut=ego[:, H + 1:], agent_hist=ag[:, : H + 1],
                    agent_hist_mask=ag_mask[:, : H + 1], agent_fut=ag[:, H + 1:],
                    others_hist=o[:, :, : H + 1], others_fut=o[:, :, H + 1:], others_mask=o_mask,
                    others_is_ped=torch.gather(scenes.agents_is_ped, 1, order) & o_mask,
                    lanes=lane_pts * lane_mask[..., None], lanes_mask=lane_mask, goal=ego[:, -1].clone(),
                    behaviour=scenes.behaviour.clone())
    return out.to(dtype)


def cut_samples(scenes: Scenes, per_scene: int | None, rng: np.random.Generator,
                cfg: SynthConfig | None = None) -> tuple[Scenarios, int]:
    """Planning samples from every scene: per_scene random frames among those with a predicted agent (for
    synthetic scenes: from 5 frames before its event to 1 after, so the manoeuvre falls in the 3 s future or
    has just begun), or all such frames when per_scene is None. Samples with no lane near the ego are
    dropped; returns (samples, number dropped)."""
    cfg = cfg or SynthConfig()
    S, F = scenes.pred_idx.shape
    f = torch.arange(F)
    e = scenes.event_frame[:, None]
    cand = (scenes.pred_idx >= 0) & ((e < 0) | ((f >= e - 5) & (f <= e + 1)))  # (S, F)
    k = per_scene if per_scene is not None else int(cand.sum(1).max())
    score = torch.where(cand, torch.from_numpy(rng.random((S, F))) if per_scene else -f.double(), -math.inf)
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


# ============================================================================================
# 6. Dataset: train/val split by scene, disk cache
# ============================================================================================

_CACHE_FORMAT = 1  # bump when the generator's output changes, so old caches are not reused


class Dataset(NamedTuple):
    train: Scenarios
    val: Scenarios
    val_scenes: Scenes  # the validation scenes, for closed-loop log replay


def make_dataset(n: int, cfg: SynthConfig | None = None, seed: int = 0) -> Dataset:
    """n planning samples (train + val) from ceil(n / samples_per_scene) synthetic scenes; the last
    val_fraction of the scenes are validation, so no scene gives samples to both."""
    cfg = cfg or SynthConfig()
    n_scenes = max(2, math.ceil(n / cfg.samples_per_scene))
    scenes = generate_scenes(n_scenes, cfg, seed)
    n_val = min(max(1, round(cfg.val_fraction * n_scenes)), n_scenes - 1)
    rng = np.random.default_rng([seed, 1])  # frame choice: its own stream, derived from the seed
    val, _ = cut_samples(scenes[n_scenes - n_val:], cfg.samples_per_scene, rng, cfg)
    train, _ = cut_samples(scenes[: n_scenes - n_val], cfg.samples_per_scene, rng, cfg)
    return Dataset(train[: max(n - len(val), 0)], val, scenes[n_scenes - n_val:])


def _cache_path(n, seed, cfg, cache_dir):
    key = json.dumps({"n": n, "seed": seed, "cfg": dataclasses.asdict(cfg), "format": _CACHE_FORMAT}, sort_keys=True)
    return Path(cache_dir) / f"scenarios-n{n}-s{seed}-{hashlib.sha1(key.encode()).hexdigest()[:12]}.pt", key


def load_or_generate(n: int, seed: int = 0, cache_dir: str | os.PathLike = ".cache/data_synth",
                     cfg: SynthConfig | None = None) -> Dataset:
    """The Dataset for (n, seed, cfg): loaded from cache_dir if it is there, else generated and saved.

    The file name carries a hash of everything that determines the data; a file of that name that is not
    a cache of this module is an error (it is never overwritten)."""
    cfg = cfg or SynthConfig()
    path, key = _cache_path(n, seed, cfg, cache_dir)
    if path.exists():
        try:
            blob = torch.load(path, weights_only=True)
            assert blob["key"] == key, "made with other settings"
            return Dataset(Scenarios(**blob["train"]), Scenarios(**blob["val"]), Scenes(**blob["val_scenes"]))
        except Exception as e:  # noqa: BLE001  (any failure means: not our cache)
            raise ValueError(f"{path}: not a readable data_synth cache ({e}); move it away or use another "
                             f"cache_dir") from e
    data = make_dataset(n, cfg, seed)
    path.parent.mkdir(parents=True, exist_ok=True)
    blob = {"key": key, "train": data.train.tensors(), "val": data.val.tensors(),
            "val_scenes": {**data.val_scenes.tensors(), "names": data.val_scenes.names}}
    tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
    torch.save(blob, tmp)
    os.replace(tmp, path)  # atomic: a crash leaves no half-written cache under the real name
    return data


# ============================================================================================
# 7. Statistics
# ============================================================================================

PLAUSIBLE = {"speed_max": 20.5, "accel_p99": 4.0, "yaw_rate_p99": 0.7}
"""Urban driving at 2 Hz: speeds up to 20 m/s, 99 % of |accelerations| below 4 m/s^2 and of vehicle |yaw rates|
below 0.7 rad/s (derived from the states by backward differences, tracking noise included)."""


def statistics(batch: Scenarios, dt: float = 0.5) -> dict:
    """Kinematics (from the states, by backward differences), the behaviour mix and how close the predicted
    vehicle comes to the ego's GT future (the collision cost exp(-d^2/4) matters within a few metres)."""
    def kin(states, mask):  # states (..., T, 4), mask (...,) -> flat arrays of speed, |accel|, |yaw rate|
        v, h = states[..., 3], states[..., 2]
        acc = (v[..., 1:] - v[..., :-1]) / dt
        yaw = _twrap(h[..., 1:] - h[..., :-1]) / dt
        moving = (v[..., 1:] > 2.0) & mask[..., None]  # headings of (near) stopped vehicles mean little
        return v[mask].flatten(), acc[mask].abs().flatten(), yaw[moving].abs().flatten()

    def summary(x):
        x = x.double()
        if x.numel() == 0:
            return {}
        q = torch.quantile(x[:100_000], torch.tensor([0.01, 0.5, 0.99], dtype=torch.float64)).tolist()
        return {"p1": q[0], "p50": q[1], "p99": q[2], "max": x.max().item()}

    B = len(batch)
    groups = {"ego": (torch.cat([batch.ego_hist, batch.ego_fut], 1), torch.ones(B, dtype=torch.bool)),
              "predicted": (torch.cat([batch.agent_hist, batch.agent_fut], 1), batch.agent_hist_mask.all(1)),
              "other vehicles": (torch.cat([batch.others_hist, batch.others_fut], 2),
                                 batch.others_mask & ~batch.others_is_ped)}
    out = {"samples": B}
    for name, (states, mask) in groups.items():
        v, a, w = kin(states, mask)
        out[name] = {"speed": summary(v), "|accel|": summary(a), "|yaw rate|": summary(w)}
    d = torch.linalg.norm(batch.ego_fut[..., :2] - batch.agent_fut[..., :2], dim=-1).min(1).values  # (B,)
    mix = {}
    for i, name in enumerate(BEHAVIOURS):
        m = batch.behaviour == i
        if m.any():
            mix[name] = {"share": m.float().mean().item(), "min_dist_p50": d[m].median().item(),
                         "within_5m": (d[m] < 5).float().mean().item()}
    out["behaviour"] = mix
    vehicles = [out[g] for g in groups]
    out["plausible"] = {
        "speed_max": max(g["speed"].get("max", 0) for g in vehicles) <= PLAUSIBLE["speed_max"],
        "accel_p99": max(g["|accel|"].get("p99", 0) for g in vehicles) <= PLAUSIBLE["accel_p99"],
        "yaw_rate_p99": max(g["|yaw rate|"].get("p99", 0) for g in vehicles) <= PLAUSIBLE["yaw_rate_p99"]}
    return out


def format_statistics(st: dict) -> str:
    lines = [f"{st['samples']} samples   plausible ranges: speed <= {PLAUSIBLE['speed_max']} m/s, "
             f"p99 |accel| <= {PLAUSIBLE['accel_p99']} m/s^2, p99 |yaw rate| <= {PLAUSIBLE['yaw_rate_p99']} rad/s"]
    for g in ("ego", "predicted", "other vehicles"):
        for q, unit in (("speed", "m/s"), ("|accel|", "m/s^2"), ("|yaw rate|", "rad/s")):
            s = st[g][q]
            if s:
                lines.append(f"  {g:15s} {q:11s} p1 {s['p1']:6.2f}  p50 {s['p50']:6.2f}  p99 {s['p99']:6.2f}  "
                             f"max {s['max']:6.2f} {unit}")
    lines.append("  behaviour      share   min ego-agent distance over the future: median, share < 5 m")
    for name, m in st["behaviour"].items():
        lines.append(f"  {name:13s} {m['share']:6.1%}   {m['min_dist_p50']:6.1f} m   {m['within_5m']:6.1%}")
    lines.append("  plausible: " + ", ".join(f"{k} {'ok' if v else 'OUT OF RANGE'}" for k, v in st["plausible"].items()))
    return "\n".join(lines)


# ============================================================================================
# 8. Plot
# ============================================================================================


def plot_scenario(ax, batch: Scenarios, i: int, title: str | None = None, extent: tuple = (-30, 60, -25, 25)):
    """Draw sample i in the ego frame: lanes (grey, arrows along the driving direction), other vehicles and
    pedestrians (history dotted, GT future solid, box at t0), the predicted vehicle (orange), the ego (blue,
    GT future dashed) and its goal (star). Returns ax; callers overlay predictions and plans with ax.plot."""
    from matplotlib.patches import Rectangle
    b = batch[torch.tensor([i])].to(torch.float64)
    for lane, m in zip(b.lanes[0], b.lanes_mask[0]):
        pts = lane[m].numpy()
        if len(pts):
            ax.plot(pts[:, 0], pts[:, 1], color="0.75", lw=1, zorder=1)
            k = min(len(pts) - 1, 5)
            ax.annotate("", pts[k, :2] + 1.5 * np.array([np.cos(pts[k, 2]), np.sin(pts[k, 2])]), pts[k, :2],
                        arrowprops=dict(arrowstyle="->", color="0.6", lw=0.8), zorder=1)

    def box(state, size, color, z):
        x, y, h = state[:3].tolist()
        w, length = size
        corner = np.array([x, y]) - np.array([np.cos(h), np.sin(h)]) * length / 2 + np.array([np.sin(h), -np.cos(h)]) * w / 2
        ax.add_patch(Rectangle(corner, length, w, angle=math.degrees(h), rotation_point="xy", fc=color, ec="k",
                               lw=0.5, alpha=0.8, zorder=z))

    def track(hist, fut, color, z, dashed=False):
        ax.plot(hist[:, 0], hist[:, 1], ":", color=color, lw=1.2, zorder=z)
        ax.plot(np.r_[hist[-1:, 0], fut[:, 0]], np.r_[hist[-1:, 1], fut[:, 1]], "--" if dashed else "-",
                color=color, lw=1.5, zorder=z, marker=".", ms=3)

    for oh, of, m, ped in zip(b.others_hist[0], b.others_fut[0], b.others_mask[0], b.others_is_ped[0]):
        if m:
            color = "tab:green" if ped else "tab:gray"
            track(oh.numpy(), of.numpy(), color, 2)
            if ped:
                ax.plot(*oh[-1, :2].tolist(), "o", color=color, ms=4, zorder=3)
            else:
                box(oh[-1], (1.9, 4.6), "0.6", 3)
    track(b.agent_hist[0].numpy(), b.agent_fut[0].numpy(), "tab:orange", 4)
    box(b.agent_hist[0, -1], (1.9, 4.6), "tab:orange", 5)
    track(b.ego_hist[0].numpy(), b.ego_fut[0].numpy(), "tab:blue", 4, dashed=True)
    box(b.ego_hist[0, -1], (_EGO_W, _EGO_L), "tab:blue", 5)
    ax.plot(*b.goal[0, :2].tolist(), "*", color="tab:blue", ms=12, mec="k", zorder=6)
    beh = int(b.behaviour[0])
    ax.set_title(title if title is not None else (BEHAVIOURS[beh] if beh >= 0 else f"sample {i}"), fontsize=9)
    ax.set_xlim(*extent[:2])
    ax.set_ylim(*extent[2:])
    ax.set_aspect("equal")
    ax.tick_params(labelsize=7)
    return ax


def render_grid(batch: Scenarios, path, n: int = 12, cols: int = 4):
    """Save the first n samples of batch as a grid of plot_scenario panels (PNG)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    n = min(n, len(batch))
    rows = math.ceil(n / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 2.6 * rows), squeeze=False)
    for k, ax in enumerate(axes.flat):
        if k < n:
            plot_scenario(ax, batch, k)
        else:
            ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
