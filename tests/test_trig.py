"""sin(π x) and cos(π x) from arithmetic (xrl_jax.trig): values, special points, derivatives, and that
XLA gets no transcendental op to evaluate element by element."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from xrl_jax.trig import cos_pi, sin_pi


def _reference(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """sin(π x), cos(π x) in float64 after an exact reduction to [-1, 1], so that the reference does
    not carry the rounding of π·x for large x (~|x|·2⁻⁵² would swamp a float64 comparison)."""
    x = np.asarray(x, np.float64)
    r = x - 2.0 * np.round(0.5 * x)
    return np.sin(np.pi * r), np.cos(np.pi * r)


def _arguments(dtype) -> np.ndarray:
    rng = np.random.default_rng(0)
    parts = [
        rng.uniform(-1, 1, 4000),  # the first period, where LFF inputs mostly lie
        rng.normal(0, 30, 4000),  # LFF projections with scale 30
        rng.uniform(-1e4, 1e4, 2000),
        np.arange(-8, 8.5, 0.25),  # quarter turns: the reduction's and the fold's edges
    ]
    return np.concatenate(parts).astype(dtype)


# Tolerances from the evaluation: the reduction is exact, the truncated series errs by at most
# (π/2)^(2K+1)/(2K+1)! (6.9e-10 for float32's K = 7, 1.2e-18 for float64's K = 11), and each of the K + 1
# Horner steps rounds once at a magnitude below π/2 (for the multiply by t ≤ 1/2 and the final value ≤ 1),
# so the rounding adds at most (K + 1) · π/2 · eps/2 ≈ (K + 1) · eps.
@pytest.mark.parametrize("dtype, terms", [(np.float32, 8), (np.float64, 12)])
def test_sin_pi_and_cos_pi_match_float64_reference(dtype, terms):
    x = _arguments(dtype)
    sin_ref, cos_ref = _reference(x)
    with jax.enable_x64(dtype == np.float64):
        got_sin = np.asarray(jax.jit(sin_pi)(jnp.asarray(x)))
        got_cos = np.asarray(jax.jit(cos_pi)(jnp.asarray(x)))
    assert got_sin.dtype == dtype and got_cos.dtype == dtype
    tolerance = terms * np.finfo(dtype).eps
    np.testing.assert_allclose(got_sin, sin_ref, rtol=0, atol=tolerance)
    np.testing.assert_allclose(got_cos, cos_ref, rtol=0, atol=tolerance)


def test_zeros_are_exact_and_non_finite_inputs_give_nan():
    integers = np.arange(-50, 51, dtype=np.float32)
    assert np.all(np.asarray(sin_pi(integers)) == 0.0)
    assert np.all(np.asarray(cos_pi(integers + 0.5)) == 0.0)
    np.testing.assert_array_equal(np.asarray(cos_pi(integers)), np.where(integers % 2 == 0, 1.0, -1.0))
    special = jnp.array([jnp.inf, -jnp.inf, jnp.nan], jnp.float32)
    assert np.all(np.isnan(np.asarray(sin_pi(special)))) and np.all(np.isnan(np.asarray(cos_pi(special))))


def test_derivatives_are_those_of_the_functions():
    x = jnp.asarray(_arguments(np.float32)[:2000])
    sin_ref, cos_ref = _reference(np.asarray(x))
    first_sin = jax.vmap(jax.grad(sin_pi))(x)
    first_cos = jax.vmap(jax.grad(cos_pi))(x)
    second_sin = jax.vmap(jax.grad(jax.grad(sin_pi)))(x)
    # Each is ±π^k times the other function: its tolerance scaled by π^k.
    tolerance = 8 * np.finfo(np.float32).eps
    np.testing.assert_allclose(first_sin, np.pi * cos_ref, rtol=0, atol=np.pi * tolerance)
    np.testing.assert_allclose(first_cos, -np.pi * sin_ref, rtol=0, atol=np.pi * tolerance)
    np.testing.assert_allclose(second_sin, -(np.pi**2) * sin_ref, rtol=0, atol=np.pi**2 * tolerance)


def test_compiles_without_transcendental_ops():
    """The point of the module: XLA's CPU backend runs sine/cosine one element at a time."""
    x = jnp.zeros((8, 16), jnp.float32)
    for fn in (sin_pi, cos_pi, jax.grad(lambda v: sin_pi(v).sum()), jax.grad(lambda v: cos_pi(v).sum())):
        text = jax.jit(fn).lower(x).as_text()
        assert "sine" not in text and "cosine" not in text
