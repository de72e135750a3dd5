"""Our Adam against torch's own."""

from __future__ import annotations

import torch

from pipeline.modelling.checkpoint import ModelConfig
from pipeline.modelling.determinism import exact_sqrt
from pipeline.modelling.kinds import kind_of
from pipeline.modelling.kinds.adam import Adam


def test_adam_matches_torch_optim_bit_for_bit_given_the_same_square_root(monkeypatch) -> None:
    # given: two identical networks and a few batches; torch.optim.Adam taking the exact square root
    # ours takes (torch's own depends on the CPU)
    monkeypatch.setattr(torch.Tensor, "sqrt", exact_sqrt)
    torch.manual_seed(0)
    cfg = ModelConfig("fnn", n_in=3, hidden=(8,), activation="tanh")
    net_a = kind_of("fnn").module(cfg)
    net_b = kind_of("fnn").module(cfg)
    net_b.load_state_dict(net_a.state_dict())
    ours = Adam(net_a.parameters(), lr=0.01, weight_decay=0.001)
    reference = torch.optim.Adam(net_b.parameters(), lr=0.01, weight_decay=0.001, foreach=False)
    x, y = torch.randn(64, 3), torch.randn(64, 3)
    # when: taking the same steps with each optimiser
    for _ in range(20):
        for net, opt in ((net_a, ours), (net_b, reference)):
            opt.zero_grad()
            torch.nn.functional.mse_loss(net(x), y).backward()
            opt.step()
    # then: identical weights
    sa, sb = net_a.state_dict(), net_b.state_dict()
    assert all(torch.equal(sa[k], sb[k]) for k in sa)
