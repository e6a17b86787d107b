"""The stage optimiser: weight decay on matrices only, a faster learning rate for named parts."""

from __future__ import annotations

import pytest
from torch import nn

from physgm.train.optim import OptimConfig, build_optimizer


def _net() -> nn.Module:
    return nn.Sequential(nn.Linear(3, 4), nn.Sequential(nn.Linear(4, 2)))


def test_scaled_parts_take_lr_scale_times_the_rate_through_warmup_and_decay():
    net = _net()
    cfg = OptimConfig(lr=1e-3, weight_decay=0.1, warmup_steps=2, scaled=("1",), lr_scale=10.0)
    opt, sched = build_optimizer(net.named_parameters(), cfg, total_steps=10)
    rate = {id(p): (g["lr"], g["weight_decay"]) for g in opt.param_groups for p in g["params"]}
    assert rate[id(net[0].weight)] == (pytest.approx(5e-4), 0.1)  # warm-up step 0: half the peak
    assert rate[id(net[0].bias)] == (pytest.approx(5e-4), 0.0)
    assert rate[id(net[1][0].weight)] == (pytest.approx(5e-3), 0.1)
    assert rate[id(net[1][0].bias)] == (pytest.approx(5e-3), 0.0)
    for _ in range(6):
        opt.step(), sched.step()
    by_param = {id(p): g["lr"] for g in opt.param_groups for p in g["params"]}
    assert by_param[id(net[1][0].weight)] == pytest.approx(10 * by_param[id(net[0].weight)])


def test_a_scaled_prefix_that_matches_nothing_is_an_error():
    with pytest.raises(ValueError, match=r"optim.scaled names \['head'\], which match no trainable"):
        build_optimizer(_net().named_parameters(), OptimConfig(scaled=("head",)), total_steps=10)
    frozen = _net()
    frozen[1].requires_grad_(False)
    with pytest.raises(ValueError, match="match no trainable"):
        build_optimizer(frozen.named_parameters(), OptimConfig(scaled=("1",)), total_steps=10)
