"""Explanation figures over the bird view (the paper's Fig. 1, 3, 4), PNG / GIF / MP4, and attributions.

Host side only (numpy + matplotlib); the episode itself is rolled out on the device by
:func:`xrl_jax.explain.make_episode_rollout`. How to read a figure:

* Every observed object whose mixture weight w_o is at least ``threshold`` (default 0.05) gets a
  *glyph* next to it, joined to the object by a thin black line. The glyph's **area is
  proportional to w_o** (side = ``max_side`` · √w_o, so w_o = 1 fills the full ``max_side`` box),
  which keeps sizes comparable across frames. Lighter objects are left unmarked.
* Discrete actions (DSAC / XDSAC): the paper's 3 × 4 matrix of the object's 12 probabilities q_o(a).
  Columns are the steering command, ordered so that the left column steers towards the left of
  the screen (steer +1 on the left in the default view; −1, 0, +1 in the ``mirrored`` view, as in
  the paper). Rows from top: throttle only (green), coast (white), throttle and brake (orange),
  brake only (red); the cell colour is the row colour times q / (max q over the frame's glyphs),
  so black means no probability.
* Continuous actions (SAC / XSAC): an image of the probability mass of the object's distribution
  over steering (x, same left/right rule as above, 21 bins) × longitudinal control
  l = throttle position − brake position (y, +1 = full throttle at the top, −1 = full brake at the
  bottom, 21 values), after the pedal map of ``envs.actions`` (raw pedals below −0.9 are released).
  Colours: ``inferno``, normalised per glyph (black = no mass). The mass per cell is exact for
  steering (CDF differences of the squashed Gaussian) and for each pedal; l's distribution is
  the discrete convolution of the two pedal distributions on a 0.1 grid.
* The inset at the top left shows the combined policy π(·|s) = Σ_o w_o π_o, which is exactly the
  weighted sum of the glyphs' distributions. Baselines (SAC / DSAC) have no objects: they show only
  the inset.

The pieces live where their names say: :mod:`~xrl_jax.explain.glyphs` (glyph contents),
:mod:`~xrl_jax.explain.scenes` (where the objects are), :mod:`~xrl_jax.explain.drawing` (glyphs on
the bird view) and :mod:`~xrl_jax.explain.episodes` (recorded episodes: frames and attributions).
This module gathers their public names.
"""

from xrl_jax.explain.drawing import GLYPH_Z, Glyph, draw_explanation, explained_frame, render_base
from xrl_jax.explain.episodes import (
    EpisodeFigures,
    IntersectionEpisodeFigures,
    attribution_items,
    first_alive_slot,
    write_attributions,
)
from xrl_jax.explain.glyphs import (
    StepExplanation,
    component_density_images,
    discrete_matrix,
    mixture_image,
    pedal_masses,
    steer_column_order,
    steering_masses,
    step_explanation,
)
from xrl_jax.explain.scenes import (
    SCENES,
    ObjectSet,
    Scene,
    ego_to_world,
    intersection_objects,
    scene_for,
    scene_objects,
    slot_pose,
)

__all__ = [
    "GLYPH_Z",
    "SCENES",
    "EpisodeFigures",
    "Glyph",
    "IntersectionEpisodeFigures",
    "ObjectSet",
    "Scene",
    "StepExplanation",
    "attribution_items",
    "component_density_images",
    "discrete_matrix",
    "draw_explanation",
    "ego_to_world",
    "explained_frame",
    "first_alive_slot",
    "intersection_objects",
    "mixture_image",
    "pedal_masses",
    "render_base",
    "scene_for",
    "scene_objects",
    "slot_pose",
    "steer_column_order",
    "steering_masses",
    "step_explanation",
    "write_attributions",
]
