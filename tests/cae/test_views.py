"""The training views (cae/views.py): light that varies across the frame (``shade``)."""

import numpy as np
import torch

from cae.views import _shaded, default_views, photometric


def test_shade_is_a_smooth_field_of_light_across_the_frame():
    """On a flat grey frame a shaded view varies across the frame (tenths of the range) but smoothly (neighbouring
    pixels within a few hundredths); the share of the images shaded follows ``shade``; empty in, empty out."""
    x = torch.full((16, 3, 128, 128), 0.5)
    shaded = _shaded(x, np.random.default_rng(0), 1.0)
    assert shaded.shape == x.shape and 0.0 <= float(shaded.min()) and float(shaded.max()) <= 1.0
    spread = shaded.flatten(1).amax(1) - shaded.flatten(1).amin(1)
    assert float(spread.min()) > 0.05, spread  # every image shaded, none uniformly
    step = (shaded[..., 1:] - shaded[..., :-1]).abs().amax()
    assert float(step) < 0.04, float(step)  # a field drawn on 2-4 cells, not per-pixel noise
    assert torch.equal(shaded[:, 0], shaded[:, 2])  # the same light on every channel
    assert torch.equal(_shaded(x, np.random.default_rng(0), 0.0), x)
    some = _shaded(x, np.random.default_rng(0), 0.5)
    changed = int((some != x).flatten(1).any(1).sum())
    assert 3 <= changed <= 13, changed
    assert _shaded(x[:0], np.random.default_rng(0), 1.0).shape == (0, 3, 128, 128)


def test_photometric_shades_only_where_asked():
    """``photometric`` with every other change off: ``shade`` 0 gives the frame back, ``shade`` 1 a shaded one."""
    off = {**default_views, "colour": 0.0, "grey": 0.0, "night": 0.0, "noise": 0.0, "low_res": 0.0, "blur": 0.0,
           "jpeg": 0.0}
    x = torch.full((4, 3, 32, 32), 0.5)
    assert torch.equal(photometric(x, np.random.default_rng(0), 0.0, {**off, "shade": 0.0}), x)
    assert not torch.equal(photometric(x, np.random.default_rng(0), 0.0, {**off, "shade": 1.0}), x)
