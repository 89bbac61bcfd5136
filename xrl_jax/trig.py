"""``sin(π x)`` and ``cos(π x)`` from vectorisable arithmetic.

The Learned Fourier Features of every Deep Set and the positional encodings of Tracking's MLP agents
take sines of π times their inputs. XLA's CPU backend evaluates ``sin`` and ``cos`` one element at a
time (a libm call with its full range reduction), and on the quick Country Road preset those calls
were about half of a DSAC update's time. Here the argument is reduced exactly in units of π (``x - 2 n``
is exact in floating point) and folded to ``|t| ≤ 1/2``, whose sine is a truncated Taylor series, so
the whole function is additions and multiplications that XLA fuses and vectorises on any backend.
It is also more accurate than ``jnp.sin(jnp.pi * x)``, which first rounds ``π x``.

Accuracy: on the reduced argument ``|t| ≤ 1/2`` the first omitted term of the series is at most
``(π/2)^(2K+1) / (2K+1)!``: 6.9e-10 with the 8 terms used for float32 (degree 15, well below its
rounding of ~6e-8) and 1.2e-18 with the 12 used for float64 (degree 23, below its ~1.1e-16). The
derivatives are the exact ones (``π cos(π x)``, ``-π sin(π x)``), not those of the polynomial.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

# Taylor coefficients of sin(π t) in powers of t: (-1)^k π^(2k+1) / (2k+1)!.
_SIN_PI_SERIES = tuple((-1) ** k * math.pi ** (2 * k + 1) / math.factorial(2 * k + 1) for k in range(12))


def _terms(dtype) -> int:
    return 12 if jnp.finfo(dtype).bits > 32 else 8


def _sin_pi_reduced(t):
    """sin(π t) for |t| ≤ 1/2: the odd series in Horner form over t²."""
    coefficients = _SIN_PI_SERIES[: _terms(t.dtype)]
    t2 = t * t
    acc = jnp.full_like(t, coefficients[-1])
    for c in coefficients[-2::-1]:
        acc = acc * t2 + np.asarray(c, t.dtype)
    return acc * t


def _within_one(x):
    """``x - 2 round(x / 2)``, in [-1, 1]: the same angle in units of π, computed exactly."""
    return x - 2.0 * jnp.round(0.5 * x)


def _as_float(x):
    x = jnp.asarray(x)
    return x if jnp.issubdtype(x.dtype, jnp.floating) else x.astype(jnp.result_type(float))


@jax.custom_jvp
def sin_pi(x):
    """``sin(π x)`` elementwise; NaN for ±inf and NaN, as ``jnp.sin``."""
    x = _as_float(x)
    r = _within_one(x)
    # sin(π r) = sin(π (±1 - r)) folds |r| > 1/2 back to the series' range, again exactly.
    return _sin_pi_reduced(jnp.where(jnp.abs(r) > 0.5, jnp.sign(r) - r, r))


@jax.custom_jvp
def cos_pi(x):
    """``cos(π x)`` elementwise; NaN for ±inf and NaN, as ``jnp.cos``."""
    x = _as_float(x)
    # cos(π r) = sin(π (1/2 - |r|)), and 1/2 - |r| is exact for |r| ≤ 1.
    return _sin_pi_reduced(0.5 - jnp.abs(_within_one(x)))


@sin_pi.defjvp
def _sin_pi_jvp(primals, tangents):
    (x,), (dx,) = primals, tangents
    return sin_pi(x), np.pi * cos_pi(x) * dx


@cos_pi.defjvp
def _cos_pi_jvp(primals, tangents):
    (x,), (dx,) = primals, tangents
    return cos_pi(x), -np.pi * sin_pi(x) * dx
