"""The fused Adam step (``slam.optimizers.adam``) against torch's plain one."""

import torch

from slam.optimizers import adam
from slam.voxels import grow_adam_state


def _run(make, steps: int = 30) -> list[torch.Tensor]:
    torch.manual_seed(0)
    table = torch.nn.Parameter(torch.randn(500, 16))
    weight = torch.nn.Parameter(torch.randn(8, 16))
    opt = make([{"params": [table], "lr": 5e-3}, {"params": [weight], "lr": 1e-2}])
    for step in range(steps):
        if step == steps // 2:  # the map grows mid-run, as voxel allocation grows it
            grown = torch.nn.Parameter(torch.cat([table.detach(), torch.randn(100, 16)]))
            grow_adam_state(opt, table, grown)
            table = grown
        opt.zero_grad(set_to_none=True)
        x = torch.randn(64, 16)
        loss = (table[torch.randint(0, table.shape[0], (64,))] * x).sum().square() + (weight @ x.t()).abs().mean()
        loss.backward()
        opt.step()
    return [table.detach(), weight.detach()]


def test_fused_adam_matches_the_plain_step():
    fused = _run(lambda groups: adam(groups))
    plain = _run(lambda groups: torch.optim.Adam(groups, fused=False, foreach=False))
    assert isinstance(adam([torch.nn.Parameter(torch.zeros(2))]), torch.optim.Adam)
    assert adam([torch.nn.Parameter(torch.zeros(2))]).defaults["fused"] is True
    for a, b in zip(fused, plain):
        assert a.shape == b.shape
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
