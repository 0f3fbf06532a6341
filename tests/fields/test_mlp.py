"""The chunked CPU pass of the fields' MLPs against the plain layer sequence and finite differences."""
from __future__ import annotations

import pytest
import torch
from torch import nn

from nerfbake.fields import encoding
from nerfbake.fields.encoding import _ChunkedReLUMLP, cpu_has_bf16, mlp
from nerfbake.fields.hash_sh import HashSHConfig, HashSHField


@pytest.mark.parametrize("layers", [0, 1, 2])
def test_chunked_pass_equals_the_layer_sequence(layers, monkeypatch):
    monkeypatch.setattr(encoding, "CPU_CHUNK_ROWS", 37)  # several chunks and a ragged last one
    torch.manual_seed(0)
    net = mlp(11, 24, layers, 5).double()
    x = torch.randn(200, 11, dtype=torch.float64, requires_grad=True)
    y = net(x)
    y_plain = nn.Sequential.forward(net, x)
    assert y.grad_fn.name().startswith("_ChunkedReLUMLP")
    torch.testing.assert_close(y, y_plain, rtol=0, atol=1e-12)
    g = torch.randn_like(y)
    inputs = [x, *net.parameters()]
    for a, b in zip(torch.autograd.grad(y, inputs, g), torch.autograd.grad(y_plain, inputs, g)):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-10)


def test_chunked_pass_gradient_by_finite_differences():
    torch.manual_seed(1)
    net = mlp(4, 6, 2, 3).double()
    x = torch.randn(9, 4, dtype=torch.float64, requires_grad=True)
    params = [p.detach().clone().requires_grad_() for p in net.parameters()]
    assert torch.autograd.gradcheck(lambda x, *p: _ChunkedReLUMLP.apply(x, 4, torch.float64, *p), (x, *params))


@pytest.mark.skipif(not cpu_has_bf16(), reason="this CPU has no native bfloat16 matmul (the field keeps float32)")
def test_bfloat16_pass_stays_close_to_float32():
    torch.manual_seed(2)
    field = HashSHField(HashSHConfig(levels=4, log2_table=12, max_res=64), [-1.0] * 3, [1.0] * 3)
    field.set_mlp_dtype("bfloat16")
    with torch.no_grad():
        field.grid.table.uniform_(-1, 1)
    x = torch.rand(5000, 3) * 2 - 1
    with torch.no_grad():
        sigma_bf, sh_bf = field(x)
        field.set_mlp_dtype("float32")
        sigma, sh = field(x)
    assert sigma_bf.dtype == torch.float32 and sh_bf.dtype == torch.float32
    # bfloat16 keeps 8 significant bits: relative error ~0.4% per value, never a different function
    assert float((sh_bf - sh).norm() / sh.norm()) < 0.02
    assert float(((sigma_bf.log() - sigma.log()).abs()).max()) < 0.1


def test_unknown_mlp_dtype_is_refused():
    field = HashSHField(HashSHConfig(levels=2, log2_table=8, max_res=32), [0.0] * 3, [1.0] * 3)
    with pytest.raises(ValueError, match="float8"):
        field.set_mlp_dtype("float8")
