"""The categorical mixture of XDSAC (paper eq. 3-4, docs/algorithms.md §2.4, §3.5), whose components
are the per-object action distributions q_o.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
from flax import struct

from xrl_jax.distributions.weights import (
    Mixture,
    as_float,
    as_present,
    clipped_entropy,
    masked_log_softmax,
    require_distrax,
)

if TYPE_CHECKING:
    import distrax

Array = jax.Array


@struct.dataclass
class CategoricalMixture(Mixture):
    """π(a|s) = Σ_o w_o q_o(a) with q_o = softmax(action logits of object o) (paper eq. 3).

    Fields: ``component_logits`` (..., O, N) with absent rows replaced by zeros (uniform, as
    the reference does; they carry no weight), ``log_weights`` (..., O) and ``present`` (..., O)
    as in :class:`SquashedGaussianMixture`.
    """

    component_logits: Array
    log_weights: Array
    present: Array

    @classmethod
    def create(
        cls, component_logits: Array, logits: Array | None = None, mask: Array | None = None
    ) -> CategoricalMixture:
        """component_logits (..., O, N); mixture logits, mask (..., O) (``None``: uniform / all present)."""
        component_logits = as_float(component_logits)
        if component_logits.ndim < 2:
            raise ValueError(f"component_logits must have shape (..., O, N), got {component_logits.shape}")
        object_shape = component_logits.shape[:-1]
        logits = jnp.zeros(object_shape, component_logits.dtype) if logits is None else as_float(logits)
        if logits.shape != object_shape:
            raise ValueError(f"logits must have shape {object_shape}, got {logits.shape}")
        present = as_present(mask, object_shape)
        return cls(
            component_logits=jnp.where(present[..., None], component_logits, 0.0),
            log_weights=masked_log_softmax(logits, present),
            present=present,
        )

    _per_component_field = "component_logits"

    @property
    def num_actions(self) -> int:
        return self.component_logits.shape[-1]

    def component_log_probs(self) -> Array:
        """log q_o(a): (..., O, N)."""
        return jax.nn.log_softmax(self.component_logits, axis=-1)

    def component_probs(self) -> Array:
        """q_o(a): (..., O, N), the per-object explanation distributions."""
        return jax.nn.softmax(self.component_logits, axis=-1)

    def probs(self) -> Array:
        """π(a|s) = Σ_o w_o q_o(a): (..., N), sums to 1."""
        return jnp.sum(self.weights[..., None] * self.component_probs(), axis=-2)

    def log_probs(self) -> Array:
        """log π(a|s) in log space (logsumexp over objects): (..., N), finite at extreme logits."""
        return jax.nn.logsumexp(self.log_weights[..., None] + self.component_log_probs(), axis=-2)

    def log_prob(self, action: Array) -> Array:
        """log π(a|s) of integer actions (...) broadcasting against the batch shape."""
        action = jnp.asarray(action)
        if not jnp.issubdtype(action.dtype, jnp.integer):
            raise ValueError(f"discrete actions must be integers, got dtype {action.dtype}")
        log_probs = self.log_probs()
        shape = jnp.broadcast_shapes(log_probs.shape[:-1], action.shape)
        log_probs = jnp.broadcast_to(log_probs, (*shape, self.num_actions))
        index = jnp.broadcast_to(action, shape)[..., None]
        return jnp.take_along_axis(log_probs, index, axis=-1)[..., 0]

    def entropy(self) -> Array:
        """Entropy of the **mixture** π (not of its components), with the reference's 1e-10 clip."""
        return clipped_entropy(self.probs())

    def sample_with_component(self, key: Array) -> tuple[Array, Array]:
        """Ancestral sample (paper §III-C): o ~ Cat(w), a ~ Cat(q_o). Returns (a, o), int32."""
        object_key, action_key = jax.random.split(key)
        component = jax.random.categorical(object_key, self.log_weights, axis=-1)
        logits = jnp.take_along_axis(self.component_logits, component[..., None, None], axis=-2)[..., 0, :]
        return jax.random.categorical(action_key, logits, axis=-1), component

    def sample(self, key: Array) -> Array:
        """One action (...) from π (training-time acting, §3.7)."""
        return self.sample_with_component(key)[0]

    def mode(self) -> Array:
        """argmax_a π(a|s): the XDSAC evaluation action (§3.8)."""
        return jnp.argmax(self.probs(), axis=-1)

    def components_distrax(self) -> distrax.Categorical:
        """Per-object categoricals q_o as one distrax distribution, batch (..., O)."""
        return require_distrax().Categorical(logits=self.component_logits)

    def to_distrax(self) -> distrax.Categorical:
        """The mixture π as a plain distrax categorical, batch (...)."""
        return require_distrax().Categorical(logits=self.log_probs())
