"""Our Adam against torch.optim.Adam: the same weights after every step, the same state."""

from __future__ import annotations

import subprocess
import sys

import torch

from mpnode_cli.training.optim import Adam


def _nets():
    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Linear(3, 8), torch.nn.Tanh(), torch.nn.Linear(8, 2))
    twin = torch.nn.Sequential(torch.nn.Linear(3, 8), torch.nn.Tanh(), torch.nn.Linear(8, 2))
    twin.load_state_dict(net.state_dict())
    return net, twin


def _loss(net, k):
    x = torch.randn(16, 3, generator=torch.Generator().manual_seed(k))
    return net(x).pow(2).mean()


def test_steps_are_bit_identical_to_torch_adam():
    ours_net, ref_net = _nets()
    ours, ref = Adam(ours_net.parameters(), lr=3e-2), torch.optim.Adam(ref_net.parameters(),
                                                                        lr=3e-2)
    for k in range(6):
        for net, opt in ((ours_net, ours), (ref_net, ref)):
            opt.zero_grad(set_to_none=True)
            _loss(net, k).backward()
            opt.step()
        if k == 3:  # an lr change between steps, as the schedules make
            ours.param_groups[0]["lr"] = ref.param_groups[0]["lr"] = 1e-2
        for a, b in zip(ours_net.parameters(), ref_net.parameters(), strict=True):
            assert torch.equal(a, b)


def test_state_dicts_load_into_each_other():
    ours_net, ref_net = _nets()
    ref = torch.optim.Adam(ref_net.parameters(), lr=1e-2)
    for k in range(3):
        ref.zero_grad()
        _loss(ref_net, k).backward()
        ref.step()
    ours_net.load_state_dict(ref_net.state_dict())
    ours = Adam(ours_net.parameters(), lr=5.0)
    ours.load_state_dict(ref.state_dict())  # torch's state continues in ours
    assert ours.param_groups[0]["lr"] == 1e-2
    for net, opt in ((ours_net, ours), (ref_net, ref)):
        opt.zero_grad()
        _loss(net, 9).backward()
        opt.step()
    for a, b in zip(ours_net.parameters(), ref_net.parameters(), strict=True):
        assert torch.equal(a, b)
    back = torch.optim.Adam(_nets()[0].parameters())
    back.load_state_dict(ours.state_dict())  # and ours loads into torch's
    assert back.state_dict()["state"][0]["step"] == 4


def test_training_imports_no_dynamo():
    """The point of the class: `torch.optim` imports torch._dynamo (seconds) on first use."""
    code = ("import sys, torch\nfrom mpnode_cli.training.optim import Adam\n"
            "net = torch.nn.Linear(2, 2)\nopt = Adam(net.parameters())\n"
            "net(torch.ones(1, 2)).sum().backward()\n"
            "torch.nn.utils.clip_grad_norm_(net.parameters(), 1.0)\nopt.step()\n"
            "opt.load_state_dict(opt.state_dict())\n"
            "print('torch._dynamo' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    assert out.stdout.strip() == "False"
