"""Where data enters a run (training, evaluation), it is checked once, here: the method
(diffstack.py) takes it as given. Each check raises one ValueError naming the field."""

from __future__ import annotations

import torch


def _shape_error(t, shape) -> bool:
    """Whether t's shape differs from `shape` (None: any size there; a leading ...: any dims)."""
    tail = shape[0] is ...
    want = shape[1:] if tail else shape
    if t.dim() < len(want) or (not tail and t.dim() != len(want)):
        return True
    dims = t.shape[t.dim() - len(want) :]
    return any(s is not None and s != d for s, d in zip(want, dims))


def check_tensor(name: str, t, shape=None, dtype=None):
    """ValueError naming `name` unless t is a tensor of the given shape (None: any size there) and
    dtype, and finite."""
    if not torch.is_tensor(t):
        raise ValueError(f"{name}: expected a tensor, got {type(t).__name__}")
    if shape is not None and _shape_error(t, shape):
        sizes = ("..." if s is ... else "*" if s is None else str(s) for s in shape)
        raise ValueError(f"{name}: expected shape ({', '.join(sizes)}), got {tuple(t.shape)}")
    if dtype is not None and t.dtype != dtype:
        raise ValueError(f"{name}: expected dtype {dtype}, got {t.dtype}")
    try:
        bad = t.is_floating_point() and not torch.isfinite(t).all()
    except RuntimeError:  # inside torch.func's transforms a value cannot steer Python
        bad = False
    if bad:
        raise ValueError(f"{name}: contains NaN or inf")
    return t


def check_batch(batch, cfg, need_future: bool, stack: bool = False) -> None:
    """What the method takes from data, checked where data enters a run (the method does not check
    it again). A batch of Scenarios: not empty, the history and future lengths of cfg, finite.
    need_future: the agent's GT future is read (training); stack: the ego's future, the other
    agents, the goal and the lanes too."""
    if len(batch) == 0:
        raise ValueError("batch: no scenarios (a batch of size 0)")
    H, T = cfg.hist_len + 1, cfg.horizon
    expect = dict(agent_hist=H, ego_hist=H, others_hist=H)
    if need_future or stack:
        expect["agent_fut"] = T
    if stack:
        expect.update(ego_fut=T, others_fut=T)
    for name, steps in expect.items():
        x = getattr(batch, name)
        if tuple(x.shape[-2:]) != (steps, 4):
            raise ValueError(f"{name}: expected shape (..., {steps}, 4), got {tuple(x.shape)}")
        if not torch.isfinite(x).all():
            raise ValueError(f"{name} contains NaN or inf")
    if stack:
        check_tensor("goal", batch.goal, (len(batch), 4), batch.ego_hist.dtype)
        check_tensor("lanes", batch.lanes, (len(batch), None, None, 3), batch.ego_hist.dtype)
    m = batch.agent_hist_mask
    if tuple(m.shape) != tuple(batch.agent_hist.shape[:2]):
        raise ValueError(
            f"agent_hist_mask: expected shape {tuple(batch.agent_hist.shape[:2])}, "
            f"got {tuple(m.shape)}"
        )
    if not m[:, -1].all() or (m[:, 1:].int() < m[:, :-1].int()).any():
        raise ValueError(
            "agent_hist_mask: the current step must be observed and missing steps must be "
            "the earliest"
        )
