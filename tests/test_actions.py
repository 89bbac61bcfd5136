"""Action mappings (docs/carenv-single-agent.md §4): pedal map, the paper's 12-way discrete table, the
reduced 2-D action."""

from pathlib import Path

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from envs.actions import (
    DISCRETE_ACTIONS,
    DISCRETE_CONTROLS,
    NUM_DISCRETE_ACTIONS,
    continuous_to_control,
    discrete_to_action,
    discrete_to_control,
    pedal_to_position,
    reduced_to_action,
    reduced_to_control,
)

DATA = Path(__file__).parent / "data"

# §4.2 table, in index order: (steer command, throttle a, brake b).
SPEC_TABLE = [
    (-1, 0, 0),
    (-1, 0, 1),
    (-1, 1, 0),
    (-1, 1, 1),
    (0, 0, 0),
    (0, 0, 1),
    (0, 1, 0),
    (0, 1, 1),
    (1, 0, 0),
    (1, 0, 1),
    (1, 1, 0),
    (1, 1, 1),
]


def test_pedal_map_dead_zones_and_linear_part():
    pedal = jnp.array([-1.0, -0.95, -0.9, 0.0, 0.45, 0.9, 0.95, 1.0])
    expected = [0.0, 0.0, 0.0, 0.5, 0.75, 1.0, 1.0, 1.0]
    np.testing.assert_allclose(pedal_to_position(pedal), expected, atol=1e-7)


def test_continuous_mapping():
    action = jnp.array([[0.3, -1.0, 1.0], [-2.0, 0.0, -0.45], [1.5, 0.9, -0.9]])
    expected = [[0.3, 0.0, 1.0], [-1.0, 0.5, 0.25], [1.0, 1.0, 0.0]]
    np.testing.assert_allclose(continuous_to_control(action), expected, atol=1e-7)
    assert continuous_to_control(action).dtype == jnp.float32
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        continuous_to_control(jnp.zeros(2))


@pytest.mark.parametrize("name", ["vehicle_public", "episode_tracking_public", "episode_country_road_public"])
def test_continuous_mapping_is_bit_exact_on_golden_actions(name):
    """The original divides by 1.8 in float64; the port keeps a true division under jit and vmap."""
    path = DATA / f"{name}.npz"
    if not path.exists():
        pytest.skip(f"{path.name} not in tests/data")
    with np.load(path) as data:
        raw, controls = data["actions_raw"], data["controls"]
    with jax.enable_x64(True):
        eager = np.asarray(continuous_to_control(raw))
        flat = raw.reshape(-1, 3)
        mapped = np.asarray(jax.jit(jax.vmap(continuous_to_control))(flat)).reshape(raw.shape)
    np.testing.assert_array_equal(eager, controls)
    np.testing.assert_array_equal(mapped, controls)


def test_discrete_table_order_and_values():
    assert NUM_DISCRETE_ACTIONS == 12
    assert DISCRETE_ACTIONS.shape == (12, 3)
    # Raw actions: steer slowest, brake fastest; pedals -1 / +1.
    for i, (steer, throttle, brake) in enumerate(DISCRETE_ACTIONS):
        i_steer, i_throttle, i_brake = i // 4, (i // 2) % 2, i % 2
        assert (steer, throttle, brake) == ((-1, 0, 1)[i_steer], (-1, 1)[i_throttle], (-1, 1)[i_brake])
    np.testing.assert_array_equal(DISCRETE_CONTROLS, SPEC_TABLE)
    np.testing.assert_array_equal(discrete_to_control(jnp.arange(12)), SPEC_TABLE)
    np.testing.assert_array_equal(continuous_to_control(DISCRETE_ACTIONS), SPEC_TABLE)
    np.testing.assert_array_equal(discrete_to_action(jnp.arange(12)), DISCRETE_ACTIONS)
    assert not DISCRETE_ACTIONS.flags.writeable


def test_discrete_mapping_jit_vmap_and_validation():
    index = jnp.array([[0, 5], [11, 6]])
    controls = jax.jit(discrete_to_control)(index)
    assert controls.shape == (2, 2, 3)
    np.testing.assert_array_equal(controls, np.asarray(SPEC_TABLE)[np.asarray(index)])
    np.testing.assert_array_equal(jax.vmap(discrete_to_control)(jnp.arange(12)), SPEC_TABLE)
    with jax.enable_x64(True):
        assert discrete_to_control(3).dtype == jnp.float64
    # Eager: clear errors; traced: out-of-range rows become NaN instead of silently wrapping.
    with pytest.raises(ValueError, match=r"\[0, 12\)"):
        discrete_to_control(12)
    with pytest.raises(ValueError, match=r"\[0, 12\)"):
        discrete_to_control(jnp.array([0, -1]))
    with pytest.raises(TypeError, match="integer"):
        discrete_to_control(1.0)
    traced = jax.jit(discrete_to_control)(jnp.array([12, -1, 4]))
    assert np.isnan(traced[:2]).all()
    np.testing.assert_array_equal(traced[2], [0, 0, 0])


def test_reduced_action():
    action = jnp.array([[0.2, 1.0], [0.2, 0.5], [-0.4, 0.0], [0.0, -0.25], [0.0, -1.0]])
    expected_raw = [
        [0.2, 1.0, -1.0],
        [0.2, 0.0, -1.0],
        [-0.4, -1.0, -1.0],
        [0.0, -1.0, -0.5],
        [0.0, -1.0, 1.0],
    ]
    np.testing.assert_allclose(reduced_to_action(action), expected_raw, atol=1e-7)
    expected_control = [
        [0.2, 1.0, 0.0],
        [0.2, 0.5, 0.0],
        [-0.4, 0.0, 0.0],
        [0.0, 0.0, 0.5 - 0.5 / 1.8],
        [0.0, 0.0, 1.0],
    ]
    np.testing.assert_allclose(reduced_to_control(action), expected_control, atol=1e-7)
    with pytest.raises(ValueError, match=r"\(\.\.\., 2\)"):
        reduced_to_action(jnp.zeros(3))


class MappingsJitAndEager(chex.TestCase):
    """The action mappings give the same controls jitted and not (chex variants)."""

    @chex.variants(with_jit=True, without_jit=True)
    def test_continuous_and_discrete(self):
        continuous = self.variant(continuous_to_control)
        discrete = self.variant(discrete_to_control)
        table = jnp.asarray(SPEC_TABLE, jnp.float32)
        chex.assert_trees_all_close(continuous(DISCRETE_ACTIONS), table, atol=1e-7)
        chex.assert_trees_all_equal(discrete(jnp.arange(12)), table)
        chex.assert_shape(continuous(jnp.zeros((4, 2, 3))), (4, 2, 3))
