"""The tiered run's tile flags and stereo windows (geocd run --screen)."""

from __future__ import annotations

import numpy as np

from geocd.screen.tiered import flag_tiles


def test_flagged_tiles_become_windows_with_a_margin():
    changed = np.zeros((300, 260), bool)
    changed[10:12, 10:12] = True        # tile (0, 0)
    changed[70:75, 40:45] = True        # tile (1, 0): touches (0, 0) → one window
    changed[200:210, 200:205] = True    # tile (3, 3): alone
    fl = flag_tiles(changed, 64, margin_cells=8)
    assert fl.tiles.shape == (5, 5)
    assert fl.tiles.sum() == 3 and np.isclose(fl.tile_fraction, 3 / 25)
    assert sorted(fl.windows) == [(0, 0, 136, 72), (184, 184, 80, 76)]
    m = np.zeros(changed.shape, bool)
    for r0, c0, h, w in fl.windows:
        m[r0:r0 + h, c0:c0 + w] = True
    assert m[changed].all()                                  # every changed cell is inside a window
    assert np.isclose(fl.window_fraction(changed.shape), m.mean())
    # a tile needs min_cells changed cells
    assert flag_tiles(changed, 64, 8, min_cells=10).tiles.sum() == 2
    assert flag_tiles(np.zeros((50, 50), bool), 64, 8).windows == []
