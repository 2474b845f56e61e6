"""prop's Adam is torch.optim.Adam (fused) with LambdaLR's cosine, bit for bit, without torch._dynamo."""

from __future__ import annotations

import math
import subprocess
import sys

import pytest
import torch

from prop_cli.train.optim import Adam, cosine_lr

CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device (scripts/gpu-smoke.sh)")


def _params(seed: int, device: str = "cpu") -> list[torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    w, b = torch.randn(7, 5, generator=g), torch.randn(5, generator=g)
    return [w.to(device).requires_grad_(), b.to(device).requires_grad_()]


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=CUDA)])
def test_same_weights_as_torch_adam_with_groups_and_a_cosine_schedule(device):
    steps, floor = 25, 0.05
    ours_a, ours_b = _params(0, device), _params(1, device)
    ref_a, ref_b = ([p.detach().clone().requires_grad_() for p in ps] for ps in (ours_a, ours_b))
    ours = Adam([{"params": ours_a}, {"params": ours_b, "lr": 3e-3}], lr=1e-2)
    ref = torch.optim.Adam([{"params": ref_a}, {"params": ref_b, "lr": 3e-3}], lr=1e-2, fused=True)
    sched = torch.optim.lr_scheduler.LambdaLR(
        ref, lambda t: floor + (1 - floor) * 0.5 * (1 + math.cos(math.pi * t / steps))
    )
    g = torch.Generator().manual_seed(2)
    for step in range(steps):
        x = torch.randn(4, 7, generator=g).to(device)
        for (w, b), (w2, b2), opt in ((ours_a, ours_b, ours), (ref_a, ref_b, ref)):
            ((x @ w + b).pow(2).sum() + (x @ w2 + b2).tanh().sum()).backward()
            opt.step()
            opt.zero_grad()
        ours.set_lr_factor(cosine_lr(1.0, step + 1, steps, floor))
        sched.step()
    for a, b in zip(ours_a + ours_b, ref_a + ref_b):
        assert torch.equal(a, b)
    assert not torch.equal(ours_a[0], _params(0, device)[0])  # it did train


def test_a_parameter_without_grad_is_left_alone():
    p, q = _params(0)
    q0 = q.detach().clone()
    opt = Adam([p, q], lr=0.1)
    p.sum().backward()
    opt.step()
    assert torch.equal(q, q0) and opt.t == 1


def test_cosine_lr_ends_at_the_floor():
    assert cosine_lr(2.0, 0, 10, 0.1) == 2.0
    assert math.isclose(cosine_lr(2.0, 10, 10, 0.1), 0.2)
    assert math.isclose(cosine_lr(2.0, 50, 10, 0.1), 0.2)  # past the end: stays at the floor


def test_training_does_not_import_torch_dynamo():
    code = (
        "import sys, torch\n"
        "from prop_cli.train.optim import Adam\n"
        "w = torch.ones(3, requires_grad=True); opt = Adam([w], lr=0.1)\n"
        "(w * w).sum().backward(); opt.step()\n"
        "print('torch._dynamo' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
