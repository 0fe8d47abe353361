"""svorf.optim: the fused Adam of the training loop against per-tensor Adam, the gradient
norm of the NaN guard against clip_grad_norm_, speedbench's --optimizer timing, and the
moving average of the weights against its formula."""

from __future__ import annotations

import copy
import json

import pytest
import torch

from benchmark.tools import speedbench
from svorf.optim import WeightAverage, grad_norm, make_optimizer


def _net(seed: int = 0) -> torch.nn.Module:
    torch.manual_seed(seed)
    return torch.nn.Sequential(torch.nn.Linear(5, 7), torch.nn.ReLU(), torch.nn.Linear(7, 3))


def _backward(net: torch.nn.Module, seed: int) -> None:
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(16, 5, generator=g)
    net.zero_grad(set_to_none=True)
    net(x).square().mean().backward()


def test_fused_adam_on_cpu_matches_per_tensor_adam_over_steps():
    a, b = _net(), _net()
    oa = make_optimizer(a.parameters(), 1e-2, (0.9, 0.999), "cpu", fused=False)
    ob = make_optimizer(b.parameters(), 1e-2, (0.9, 0.999), "cpu")
    assert ob.param_groups[0]["fused"] and not oa.param_groups[0]["fused"]
    for step in range(5):
        for net, opt in ((a, oa), (b, ob)):
            _backward(net, step)
            opt.step()
    moved = max(
        float((p - q).detach().abs().max()) for p, q in zip(_net().parameters(), a.parameters())
    )
    assert moved > 1e-3  # the updates did something
    for p, q in zip(a.parameters(), b.parameters()):
        torch.testing.assert_close(p, q, rtol=1e-5, atol=1e-6)


def test_a_per_tensor_checkpoint_resumes_under_fused_adam():
    """An optimizer state written by per-tensor Adam (checkpoints before the fused kernel)
    loads into the optimizer the training loop builds now and continues the same
    trajectory; the loaded param_groups keep the form the state was written with."""
    a, b = _net(), _net()
    oa = make_optimizer(a.parameters(), 1e-2, (0.9, 0.999), "cpu", fused=False)
    for step in range(3):
        _backward(a, step)
        oa.step()
    b.load_state_dict(a.state_dict())
    ob = make_optimizer(b.parameters(), 1e-2, (0.9, 0.999), "cpu")
    ob.load_state_dict(copy.deepcopy(oa.state_dict()))  # as torch.load gives it: no aliasing
    assert ob.param_groups[0]["fused"] is False
    for step in range(3, 6):
        for net, opt in ((a, oa), (b, ob)):
            _backward(net, step)
            opt.step()
    for p, q in zip(a.parameters(), b.parameters()):
        torch.testing.assert_close(p, q, rtol=1e-5, atol=1e-6)


def test_grad_norm_equals_clip_grad_norm_and_leaves_the_gradients():
    net = _net()
    _backward(net, 0)
    before = [p.grad.clone() for p in net.parameters()]
    got = grad_norm(net.parameters())
    want = torch.sqrt(sum(p.grad.double().square().sum() for p in net.parameters()))
    assert float(got) == pytest.approx(float(want), rel=1e-6)
    assert float(got) == float(torch.nn.utils.clip_grad_norm_(net.parameters(), float("inf")))
    for p, g in zip(net.parameters(), before):
        assert torch.equal(p.grad, g)
    net.zero_grad(set_to_none=True)
    assert float(grad_norm(net.parameters())) == 0.0
    _backward(net, 1)
    next(net.parameters()).grad[0, 0] = float("nan")
    assert not torch.isfinite(grad_norm(net.parameters()))  # what the NaN guard reads


def test_speedbench_optimizer_report(tmp_path):
    rep = speedbench.optimizer_run(
        "smoke", scenes=1, rays=8, repeats=1, warmup=0, threads=1, log=lambda s: None
    )
    assert [f["name"] for f in rep["forms"]] == ["per-tensor", "fused"]
    assert all(f["median_s"] > 0 for f in rep["forms"]) and rep["ratio"] > 0
    assert rep["param_tensors"] > 10
    assert rep["grad_norms"][0] == pytest.approx(rep["grad_norms"][1], rel=1e-6)
    assert 0.0 <= rep["update_max_abs_diff"] < 1e-5
    out = tmp_path / "opt.json"
    small = ["--scale", "smoke", "--scenes", "1", "--rays", "4", "--repeats", "1"]
    rc = speedbench.main([*small, "--warmup", "0", "--threads", "1", "--optimizer", "--recipe"])
    assert rc == 0
    rc = speedbench.main([*small, "--threads", "1", "--optimizer", "--json", str(out)])
    assert rc == 0
    assert json.loads(out.read_text())["forms"][1]["name"] == "fused"


def test_weight_average_follows_its_formula_and_round_trips():
    net = _net()
    net[0].bias.requires_grad_(False)  # frozen weights are not averaged
    avg = WeightAverage(net.named_parameters(), 0.9)
    assert avg.names == ["0.weight", "2.weight", "2.bias"]
    ref = {n: p.detach().clone() for n, p in net.named_parameters() if p.requires_grad}
    for t in (1, 2, 3, 40, 41):
        with torch.no_grad():
            for p in net.parameters():
                p.add_(float(t))
        avg.update(t)
        d = min(0.9, (1 + t) / (10 + t))  # the warm-up: 0.2, 0.27, 0.31, then 0.9
        params = dict(net.named_parameters())
        ref = {n: d * r + (1 - d) * params[n].detach() for n, r in ref.items()}
    state = avg.state_dict(net.state_dict())
    for n, r in ref.items():
        torch.testing.assert_close(state[n], r)
        assert not torch.equal(state[n], net.state_dict()[n])
    assert torch.equal(state["0.bias"], net.state_dict()["0.bias"])
    other = WeightAverage(net.named_parameters(), 0.9)
    other.load(state)
    for a, b in zip(other.averages, avg.averages, strict=True):
        assert torch.equal(a, b)
    with pytest.raises(ValueError, match="decay must be in"):
        WeightAverage(net.named_parameters(), 1.0)
