"""The linear RTU layer and its exact RTRL gradients (ermrl.learners._rtu)."""

from __future__ import annotations

import math

import pytest
import torch as th

from ermrl.learners._rtu import RTU, RTUCarry, rtu_coefficients

D_IN, UNITS, BATCH, STEPS = 5, 4, 3, 30


def _params(rtu: RTU) -> list[th.Tensor]:
    return [rtu.nu_log, rtu.theta_log, rtu.w1, rtu.w2]


def _loss(out: th.Tensor, weights: th.Tensor) -> th.Tensor:
    """A loss of one step's output, nonlinear so that every trace matters."""
    return (weights * out).sum() + 0.1 * (out**2).sum()


def _bptt(rtu: RTU, xs: th.Tensor, weights: th.Tensor, h0: th.Tensor) -> list[th.Tensor]:
    """Autograd through the whole unrolled recurrence, written out independently."""
    e = th.exp(rtu.nu_log)
    r = th.exp(-e)
    theta = th.exp(rtu.theta_log)
    g, phi, gamma = r * th.cos(theta), r * th.sin(theta), th.sqrt(1 - r**2)
    c1, c2 = h0[:, 0], h0[:, 1]
    total = th.zeros((), dtype=xs.dtype)
    for x, w in zip(xs, weights):
        c1, c2 = (
            g * c1 - phi * c2 + gamma * (x @ rtu.w1.T),
            g * c2 + phi * c1 + gamma * (x @ rtu.w2.T),
        )
        total = total + _loss(rtu.output(th.stack((c1, c2), dim=1)), w)
    return list(th.autograd.grad(total, _params(rtu)))


def _rtrl(rtu: RTU, xs: th.Tensor, weights: th.Tensor, carry: RTUCarry) -> list[th.Tensor]:
    """Gradients accumulated step by step, each step's loss through one RTRL step only."""
    grads = [th.zeros_like(p) for p in _params(rtu)]
    for x, w in zip(xs, weights):
        out, carry = rtu(x, carry)
        step = th.autograd.grad(_loss(out, w), _params(rtu))
        grads = [a + b for a, b in zip(grads, step)]
    return grads


def _sequence(seed: int, dtype: th.dtype = th.float64) -> tuple[RTU, th.Tensor, th.Tensor]:
    gen = th.Generator().manual_seed(seed)
    th.manual_seed(seed)
    rtu = RTU(D_IN, UNITS).to(dtype)
    xs = th.randn(STEPS, BATCH, D_IN, generator=gen, dtype=dtype)
    weights = th.randn(STEPS, BATCH, 2 * UNITS, generator=gen, dtype=dtype)
    return rtu, xs, weights


@pytest.mark.parametrize("activation", ["relu", "linear", "tanh"])
@pytest.mark.parametrize("start", ["zeros", "state"])
def test_rtrl_gradient_equals_backpropagation_through_time(activation: str, start: str) -> None:
    rtu, xs, weights = _sequence(1)
    rtu.activation = activation
    carry = rtu.initial_carry(BATCH)
    if start == "state":  # a nonzero state with zero traces: BPTT treats h0 as a constant
        carry = carry._replace(h=th.randn(BATCH, 2, UNITS, dtype=th.float64))
    expected = _bptt(rtu, xs, weights, carry.h)
    got = _rtrl(rtu, xs, weights, carry)
    for name, want, have in zip(("nu_log", "theta_log", "w1", "w2"), expected, got):
        assert want.abs().max() > 1e-3, name  # the check is not vacuous
        th.testing.assert_close(have, want, rtol=1e-6, atol=1e-6, msg=name)


def test_the_official_theta_gradient_without_the_chain_rule_factor_fails_bptt() -> None:
    """The official code's theta trace omits theta = exp(theta_log): its gradient is the true
    one / theta, which is not the gradient of the loss (the units' thetas are far from 1)."""
    rtu, xs, weights = _sequence(2)
    expected = _bptt(rtu, xs, weights, th.zeros(BATCH, 2, UNITS, dtype=th.float64))[1]
    # The official recursion: dg/dtheta = -phi, dphi/dtheta = g (no factor theta).
    co = rtu_coefficients(rtu.nu_log, rtu.theta_log)
    g, phi = co.g.detach(), co.phi.detach()
    h = th.zeros(BATCH, 2, UNITS, dtype=th.float64)
    trace = th.zeros(BATCH, 2, UNITS, dtype=th.float64)
    buggy = th.zeros(UNITS, dtype=th.float64)
    for x, w in zip(xs, weights):
        c1p, c2p = h[:, 0], h[:, 1]
        t1 = g * trace[:, 0] - phi * trace[:, 1] - phi * c1p - g * c2p
        t2 = g * trace[:, 1] + phi * trace[:, 0] - phi * c2p + g * c1p
        trace = th.stack((t1, t2), dim=1)
        with th.no_grad():
            _, h = rtu.state_step(x, h)
        # d loss / d c at this step.
        c = h.clone().requires_grad_(True)
        (delta,) = th.autograd.grad(_loss(rtu.output(c), w), c)
        buggy += (delta * trace).sum(dim=(0, 1))
    theta = th.exp(rtu.theta_log.detach())
    assert not th.allclose(theta, th.ones_like(theta), rtol=0.1)
    th.testing.assert_close(buggy, expected / theta, rtol=1e-6, atol=1e-6)
    assert (buggy - expected).abs().max() > 0.1 * expected.abs().max()
    th.testing.assert_close(_rtrl(rtu, xs, weights, rtu.initial_carry(BATCH))[1], expected)


def test_the_input_gets_the_one_step_gradient_and_the_carry_none() -> None:
    rtu, xs, weights = _sequence(3)
    carry = rtu.initial_carry(BATCH)
    for x in xs[:5]:  # a state and traces that are not zero
        _, carry = rtu(x, carry)
    x = xs[5].clone().requires_grad_(True)
    h = carry.h.clone().requires_grad_(True)
    out, new = rtu(x, carry._replace(h=h))
    (grad_x,) = th.autograd.grad(_loss(out, weights[5]), x, allow_unused=True)
    # One plain step with the state held constant: the same gradient of x.
    x2 = xs[5].clone().requires_grad_(True)
    out2, _ = rtu.state_step(x2, carry.h)
    (want,) = th.autograd.grad(_loss(out2, weights[5]), x2)
    th.testing.assert_close(grad_x, want, rtol=1e-10, atol=1e-12)
    th.testing.assert_close(out, out2)
    # gamma (W1^T delta1 + W2^T delta2), written out.
    c = new.h.clone().requires_grad_(True)
    (delta,) = th.autograd.grad(_loss(rtu.output(c), weights[5]), c)
    gamma = rtu_coefficients(rtu.nu_log, rtu.theta_log).gamma.detach()
    formula = (gamma * delta[:, 0]) @ rtu.w1.detach() + (gamma * delta[:, 1]) @ rtu.w2.detach()
    th.testing.assert_close(grad_x, formula)
    # Nothing flows into the stored carry, and the new carry is detached.
    out, new = rtu(xs[6], carry._replace(h=h))
    out.sum().backward()
    assert h.grad is None
    assert not any(t.requires_grad for t in new)


def test_carry_shapes_reset_and_float32() -> None:
    rtu = RTU(D_IN, UNITS)
    carry = rtu.initial_carry(BATCH)
    assert carry.h.shape == carry.nu.shape == carry.theta.shape == (BATCH, 2, UNITS)
    assert carry.w.shape == (BATCH, 2, UNITS, D_IN)
    assert all(t.dtype == th.float32 and not t.any() for t in carry)
    x = th.randn(BATCH, D_IN)
    out, carry = rtu(x, carry)
    out, carry = rtu(x, carry)
    assert out.shape == (BATCH, 2 * UNITS) and out.dtype == th.float32
    assert (out >= 0).all()  # ReLU, the official linear RTU's f
    assert all(t.abs().sum(dim=tuple(range(1, t.dim()))).min() > 0 for t in carry)
    reset = carry.reset(th.tensor([True, False, True]))
    for before, after in zip(carry, reset):
        assert not after[0].any() and not after[2].any()
        assert th.equal(after[1], before[1])
    # A reset row continues exactly as a fresh carry would.
    out_reset, _ = rtu(x, reset)
    out_fresh, _ = rtu(x, rtu.initial_carry(BATCH))
    th.testing.assert_close(out_reset[0], out_fresh[0])
    # float32 and float64 agree to float32 precision.
    rtu64 = RTU(D_IN, UNITS).double()
    rtu64.load_state_dict({k: v.double() for k, v in rtu.state_dict().items()})
    out64, _ = rtu64(x.double(), carry.to(th.float64))
    out32, _ = rtu(x, carry)
    th.testing.assert_close(out32.double(), out64, rtol=1e-4, atol=1e-5)


def test_initialisation_follows_the_official_code() -> None:
    th.manual_seed(0)
    rtu = RTU(64, 2000)
    r = th.exp(-th.exp(rtu.nu_log.detach().double()))
    theta = th.exp(rtu.theta_log.detach().double())
    assert r.min() >= 0 and r.max() < 1
    # r² ~ U(0, 1), theta ~ U(0, 2 pi): means 1/2 and pi.
    assert abs(float((r**2).mean()) - 0.5) < 0.03
    assert 0 < theta.min() and theta.max() <= 2 * math.pi
    assert abs(float(theta.mean()) - math.pi) < 0.15
    std = math.sqrt(1 / 64) / 0.87962566103423978
    for w in (rtu.w1, rtu.w2):
        assert w.abs().max() <= 2 * std + 1e-6
        assert abs(float(w.detach().std()) - math.sqrt(1 / 64)) < 0.01  # lecun_normal's variance
    narrow = RTU(8, 1000, r_min=0.9, r_max=0.99, max_phase=0.5)
    r = th.exp(-th.exp(narrow.nu_log.detach().double()))
    assert r.min() >= 0.9 - 1e-6 and r.max() <= 0.99 + 1e-6
    assert th.exp(narrow.theta_log.detach()).max() <= 0.5 + 1e-6
    with pytest.raises(ValueError, match="activation"):
        RTU(8, 4, activation="sigmoid")


def test_slow_units_stay_finite() -> None:
    """r close to 1: 1 - r² underflows in float32 if computed directly; the gradients stay finite."""
    rtu = RTU(D_IN, UNITS)
    with th.no_grad():
        rtu.nu_log.copy_(th.tensor([-30.0, -60.0, -120.0, 0.0]))
    carry = rtu.initial_carry(2)
    x = th.randn(2, D_IN)
    for _ in range(3):
        out, carry = rtu(x, carry)
    out.sum().backward()
    assert all(th.isfinite(p.grad).all() for p in _params(rtu))  # type: ignore[arg-type]
    assert all(th.isfinite(t).all() for t in carry)


def test_a_step_without_the_next_carry_gives_the_same_output_and_gradients() -> None:
    rtu, xs, weights = _sequence(4)
    carry = rtu.initial_carry(BATCH)
    for x in xs[:6]:
        _, carry = rtu(x, carry)
    out, _ = rtu(xs[6], carry)
    full = th.autograd.grad(_loss(out, weights[6]), _params(rtu))
    only = rtu.step_output(xs[6], carry)
    assert th.equal(only, out)
    for a, b in zip(th.autograd.grad(_loss(only, weights[6]), _params(rtu)), full):
        th.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
