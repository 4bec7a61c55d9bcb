"""Where data enters a run (training, evaluation), it is checked once, here: the method
(diffstack.py) takes it as given. Each check raises one ValueError naming the field."""

from __future__ import annotations

import torch


def check_batch(batch, cfg, need_future: bool, stack: bool = False) -> None:
    """A batch of Scenarios: not empty, of cfg's lengths, one dtype, finite. need_future: the
    agent's GT future is read (training); stack: the ego's, the others', the goal and lanes too."""
    B, H, T = len(batch), cfg.hist_len + 1, cfg.horizon
    if B == 0:
        raise ValueError("batch: no scenarios (a batch of size 0)")
    expect = dict(agent_hist=(B, H, 4), ego_hist=(B, H, 4), others_hist=(B, None, H, 4))
    if need_future or stack:
        expect["agent_fut"] = (B, T, 4)
    if stack:
        expect.update(ego_fut=(B, T, 4), others_fut=(B, None, T, 4), goal=(B, 4))
        expect["lanes"] = (B, None, None, 3)
    for name, shape in expect.items():
        x = getattr(batch, name)
        if x.dim() != len(shape) or any(s not in (None, d) for s, d in zip(shape, x.shape)):
            want = ", ".join("*" if s is None else str(s) for s in shape)
            raise ValueError(f"{name}: expected shape ({want}), got {tuple(x.shape)}")
        if x.dtype != batch.ego_hist.dtype:
            raise ValueError(f"{name}: expected dtype {batch.ego_hist.dtype}, got {x.dtype}")
        if not torch.isfinite(x).all():
            raise ValueError(f"{name} contains NaN or inf")
    m = batch.agent_hist_mask
    if tuple(m.shape) != (B, H):
        raise ValueError(f"agent_hist_mask: expected shape ({B}, {H}), got {tuple(m.shape)}")
    if not m[:, -1].all() or (m[:, 1:].int() < m[:, :-1].int()).any():
        raise ValueError("agent_hist_mask: t0 must be observed and missing steps the earliest")
