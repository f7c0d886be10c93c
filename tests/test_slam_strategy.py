"""Densification/pruning keeps parameters, Adam state and statistics aligned; new Gaussians."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from evgs.config import load_config
from evgs.data.sequence import Camera
from evgs.slam.gaussians import PARAM_NAMES, Gaussians, make_optimizer
from evgs.slam.strategy import (
    DefaultStrategy,
    duplicate,
    gaussians_from_view,
    remove,
    reset_opacity,
    split,
)

CFG = load_config()
GEN = torch.Generator


def trained(n: int = 12) -> tuple[Gaussians, torch.optim.Adam]:
    """Gaussians with distinct rows and an Adam that has taken two steps (non-zero moments)."""
    g = Gaussians.random(n, 1.0, 0.3, 0.2, GEN().manual_seed(0))
    with torch.no_grad():
        g["means"][:, 0] = torch.arange(n, dtype=torch.float32)  # row id, readable after edits
    opt = make_optimizer(g, CFG.gaussians)
    w = torch.randn(n, generator=GEN().manual_seed(1))
    for _ in range(2):
        opt.zero_grad()
        loss = sum((g[k].reshape(n, -1).sum(1) * w).sum() for k in PARAM_NAMES)
        loss.backward()
        opt.step()
    return g, opt


def row_ids(g: Gaussians) -> torch.Tensor:
    return g["means"].detach()[:, 0].round().long()


def snapshot(g: Gaussians, opt: torch.optim.Adam) -> dict:
    return {
        k: (g[k].detach().clone(), opt.state[g[k]]["exp_avg"].clone(), opt.state[g[k]]["exp_avg_sq"].clone())
        for k in PARAM_NAMES
    }


def assert_aligned(g: Gaussians, opt: torch.optim.Adam, before: dict, src: torch.Tensor, n_zero_state: int):
    """Rows [0, len(src)) come from old rows ``src`` with their moments; the last ``n_zero_state``
    rows have zero moments; every parameter sits in the optimizer's group of its name."""
    n = len(g)
    for grp in opt.param_groups:
        assert grp["params"][0] is g[grp["name"]]
    for k in PARAM_NAMES:
        p, m, v = before[k]
        st = opt.state[g[k]]
        assert g[k].shape[0] == st["exp_avg"].shape[0] == st["exp_avg_sq"].shape[0] == n
        assert torch.equal(st["exp_avg"][: len(src)], m[src]) and torch.equal(
            st["exp_avg_sq"][: len(src)], v[src]
        )
        assert torch.all(st["exp_avg"][n - n_zero_state :] == 0)
        assert torch.all(st["exp_avg_sq"][n - n_zero_state :] == 0)
        if k != "means":
            assert torch.equal(g[k].detach()[: len(src)], p[src])


def test_remove_keeps_rows_and_moments_aligned():
    g, opt = trained()
    before = snapshot(g, opt)
    mask = torch.zeros(12, dtype=torch.bool)
    mask[[0, 5, 11]] = True
    remove(g, opt, mask)
    keep = torch.nonzero(~mask)[:, 0]
    assert torch.equal(row_ids(g), keep)
    assert_aligned(g, opt, before, keep, 0)


def test_duplicate_appends_copies_with_fresh_moments():
    g, opt = trained()
    before = snapshot(g, opt)
    mask = torch.zeros(12, dtype=torch.bool)
    mask[[2, 7]] = True
    duplicate(g, opt, mask)
    assert torch.equal(row_ids(g), torch.cat([torch.arange(12), torch.tensor([2, 7])]))
    assert_aligned(g, opt, before, torch.arange(12), 2)
    for k in PARAM_NAMES:
        assert torch.equal(g[k].detach()[12:], before[k][0][[2, 7]])


def test_split_replaces_by_two_smaller_samples():
    g, opt = trained()
    before = snapshot(g, opt)
    mask = torch.zeros(12, dtype=torch.bool)
    mask[[3, 4]] = True
    split(g, opt, mask, GEN().manual_seed(0))
    keep = torch.nonzero(~mask)[:, 0]
    assert len(g) == 14
    assert_aligned(g, opt, before, keep, 4)
    old_log_scales = before["log_scales"][0]
    new = g["log_scales"].detach()[10:]
    assert torch.allclose(new, torch.log(torch.exp(old_log_scales[[3, 4, 3, 4]]) / 1.6))
    for k in ("quats", "opacity_logits", "colors"):
        assert torch.equal(g[k].detach()[10:], before[k][0][[3, 4, 3, 4]])
    offsets = g["means"].detach()[10:] - before["means"][0][[3, 4, 3, 4]]
    assert offsets.norm(dim=1).max() < 6 * torch.exp(old_log_scales[[3, 4]]).max()
    assert not torch.equal(offsets[:2], offsets[2:])  # two different samples per parent


def test_optimizer_keeps_working_after_edits():
    g, opt = trained()
    remove(g, opt, torch.arange(12) % 3 == 0)
    duplicate(g, opt, torch.arange(8) < 2)
    opt.zero_grad()
    g["colors"].sum().backward()
    before = g["colors"].detach().clone()
    opt.step()
    assert not torch.equal(before, g["colors"].detach())


def test_reset_opacity_clamps_and_clears_moments():
    g, opt = trained()
    with torch.no_grad():
        g["opacity_logits"][:3] = 5.0
    reset_opacity(g, opt, 0.2)
    assert g.opacities().max() <= 0.2 + 1e-6
    assert torch.all(opt.state[g["opacity_logits"]]["exp_avg"] == 0)


def strategy(**kw) -> DefaultStrategy:
    return DefaultStrategy(dataclasses.replace(CFG.strategy, **kw), scene_scale=1.0)


def test_refine_grows_clones_small_splits_large_and_prunes():
    g, opt = trained(6)
    with torch.no_grad():
        g["log_scales"][:] = torch.log(torch.tensor([0.001, 0.5, 0.001, 0.001, 0.001, 0.001]))[:, None]
        g["opacity_logits"][:] = 2.0
        g["opacity_logits"][5] = -5.0  # transparent: pruned
    s = strategy(grow_grad2d=1e-3, grow_scale3d=0.01, prune_opa=0.05, refine_start=0, refine_every=10)
    norm = torch.tensor([[1e-4, 1e-4, 0.0, 1e-8, 1e-4, 1e-4]])  # per-view pixel gradients
    radii = torch.tensor([[3, 3, 3, 3, 0, 3]], dtype=torch.int32)  # row 4 invisible: not counted
    for _ in range(2):
        s.accumulate(norm, radii, width=40, height=40)
    assert torch.allclose(s.grad2d[:2], torch.full((2,), 2 * 1e-4 * 20))  # ×½√(WH)·B
    assert s.count.tolist() == [2, 2, 2, 2, 0, 2]
    report = s.step(g, opt, step=5, generator=GEN().manual_seed(0))
    assert report.cloned == 0 and len(g) == 6  # not a refine step
    report = s.step(g, opt, step=10, generator=GEN().manual_seed(0))
    # row 0: high & small → cloned; row 1: high & large → split in two; row 5 high but pruned.
    assert (report.cloned, report.split) == (2, 1)  # rows 0 and 5 cloned, row 1 split
    assert report.pruned == 2  # row 5 and its clone
    # Order: clones appended, then split children appended (their means are resampled), then pruning.
    assert len(g) == 7 and row_ids(g)[:5].tolist() == [0, 2, 3, 4, 0]
    assert torch.allclose(
        g["log_scales"].detach()[5:], torch.full((2, 3), float(torch.log(torch.tensor(0.5 / 1.6))))
    )
    assert len(s.grad2d) == len(g) and torch.all(s.grad2d == 0) and torch.all(s.count == 0)
    for k in PARAM_NAMES:
        assert opt.state[g[k]]["exp_avg"].shape[0] == len(g)


def test_refine_schedule_large_prune_and_reset():
    g, opt = trained(4)
    with torch.no_grad():
        g["log_scales"][:] = -5.0
        g["log_scales"][0] = 0.0  # scale 1 > prune_scale3d · scene scale
        g["opacity_logits"][:] = 2.0
    s = strategy(
        refine_start=100, refine_stop=400, refine_every=100, prune_scale3d_start=250, reset_every=300
    )
    gen = GEN().manual_seed(0)
    assert s.step(g, opt, 100, gen).pruned == 0 and len(g) == 4  # start is exclusive
    assert s.step(g, opt, 200, gen).pruned == 0  # too early for the size prune
    report = s.step(g, opt, 300, gen)
    assert report.pruned == 1 and report.reset and len(g) == 3
    assert g.opacities().max() <= CFG.strategy.reset_opacity + 1e-6
    assert s.step(g, opt, 400, gen).pruned == 0  # stop is exclusive


def test_strategy_add_and_remove_keep_statistics_aligned():
    g, opt = trained(5)
    s = strategy()
    s.accumulate(torch.arange(1, 6, dtype=torch.float32)[None], torch.ones(1, 5), 2, 2)
    s.remove(g, opt, torch.tensor([True, False, False, True, False]))
    assert s.grad2d.tolist() == [2.0, 3.0, 5.0] and len(g) == 3
    extra = {k: g[k].detach()[:2].clone() for k in PARAM_NAMES}
    s.add(g, opt, extra)
    assert len(g) == 5 and s.grad2d.tolist() == [2.0, 3.0, 5.0, 0.0, 0.0] and len(s.count) == 5
    assert opt.state[g["means"]]["exp_avg"].shape == (5, 3)
    remove(g, opt, torch.tensor([True, False, False, False, False]))  # behind the strategy's back
    with pytest.raises(ValueError, match="statistics cover 5 Gaussians but there are 4"):
        s.accumulate(torch.zeros(1, 4), torch.ones(1, 4), 2, 2)


CAM = Camera(64, 48, 50.0, 50.0, 32.0, 24.0)


def test_gaussians_from_view_back_projects_low_alpha_pixels():
    alpha = torch.ones(48, 64)
    alpha[10:20, 5:25] = 0.1  # 200 low-alpha pixels
    T = torch.eye(4, dtype=torch.float64)
    T[:3, 3] = torch.tensor([1.0, 2.0, 3.0])
    new = gaussians_from_view(
        alpha, T, CAM, 2.0, max_new=50, max_alpha=0.8, opacity=0.1, color=0.05, generator=GEN().manual_seed(0)
    )
    assert new["means"].shape == (50, 3) and len(new["colors"]) == 50
    p = new["means"].double() - T[:3, 3]  # camera frame (identity rotation)
    assert torch.allclose(p[:, 2], torch.full((50,), 2.0, dtype=torch.float64))
    u = CAM.fx * p[:, 0] / p[:, 2] + CAM.cx
    v = CAM.fy * p[:, 1] / p[:, 2] + CAM.cy
    assert torch.allclose(u, u.round(), atol=1e-4)  # pixel centres (OpenCV: at integers)
    assert (u >= 5).all() and (u < 25).all() and (v >= 10).all() and (v < 20).all()
    assert torch.allclose(
        new["log_scales"], torch.full((50, 3), float(torch.log(torch.tensor(2.0 * 2 / 50))))
    )
    assert torch.allclose(torch.sigmoid(new["opacity_logits"]), torch.full((50,), 0.1))
    g = Gaussians.random(8, 1.0, 0.1, 0.1, GEN().manual_seed(0))
    DefaultStrategy(CFG.strategy, 1.0).add(g, None, new)
    assert len(g) == 58


def test_gaussians_from_view_event_threshold_and_few_candidates():
    alpha = torch.zeros(48, 64)
    events = torch.zeros(48, 64)
    events[7, 9] = 0.3
    events[8, 9] = 0.05
    new = gaussians_from_view(
        alpha, torch.eye(4), CAM, 1.0, max_new=1000, max_alpha=0.8, opacity=0.1, color=0.1,
        generator=GEN().manual_seed(0), events=events, event_threshold=0.1,
    )  # fmt: skip
    assert new["means"].shape == (1, 3)
    assert CAM.fx * new["means"][0, 0] + CAM.cx == pytest.approx(9.0)
