"""The flow's two evaluation paths (direct and zuko's own) agree on the same weights, both ways."""

from __future__ import annotations

import pytest

torch = pytest.importorskip("torch")


def test_direct_and_zuko_paths_agree_forward_and_inverse(monkeypatch) -> None:
    from invphys.models.nets import FlowNet

    torch.manual_seed(0)
    net = FlowNet(d=5, m=3, k=4, projection=16, n_couplings=4, coupling_hidden=(16,), scale_bound=1.0, head=(8,))
    for p in net.parameters():  # move away from the near-identity initialisation
        torch.nn.init.normal_(p, std=0.3)
    h = torch.randn(32, 4)
    with torch.no_grad():
        monkeypatch.setattr(FlowNet, "evaluation", "direct")
        z_d, ladj_d = net.flow_forward(h)
        back_d = net.flow_inverse(z_d)
        monkeypatch.setattr(FlowNet, "evaluation", "zuko")
        z_z, ladj_z = net.flow_forward(h)
        back_z = net.flow_inverse(z_z)
    assert not torch.allclose(z_d, h, atol=1e-2)  # a real transform, not the identity
    assert torch.allclose(z_d, z_z, atol=1e-5) and torch.allclose(ladj_d, ladj_z, atol=1e-4)
    assert torch.allclose(back_d, h, atol=1e-4) and torch.allclose(back_z, h, atol=1e-4)
