"""The self-consistency scatter plot (sc_scatter.png): one colour per significance curve, legend as drawn."""

import numpy as np
from matplotlib.colors import to_hex

from geocd.change.plots import curve_colours, plot_scatter_curves, scatter_curves_figure
from geocd.consistency import ConsistencyParams, learn_self_consistency
from tests.test_consistency import SHAPE, make_rec


def _model():
    rng = np.random.default_rng(5)
    t = np.zeros(SHAPE, np.float32)
    A = [make_rec(t, rng, f"A{i}", outlier_frac=0.05) for i in range(3)]
    return learn_self_consistency([A], ConsistencyParams(confidences=(68.27, 90.0, 95.0, 99.0)))


def test_each_curve_has_its_own_colour_and_legend_markers_match(tmp_path):
    model = _model()
    assert {"68.27", "90"} <= set(model.curves)
    fig = scatter_curves_figure(model)
    ax = fig.axes[0]
    curves = {ln.get_gid().split()[1]: ln for ln in ax.get_lines() if (ln.get_gid() or "").startswith("curve ")}
    dots = {ln.get_gid().split()[1]: ln for ln in ax.get_lines() if (ln.get_gid() or "").startswith("bins ")}
    assert set(curves) == set(model.curves)
    colours = {k: to_hex(ln.get_color()) for k, ln in curves.items()}
    assert len(set(colours.values())) == len(colours), colours
    for k, ln in dots.items():  # the per-bin values in their curve's colour
        assert to_hex(ln.get_color()) == colours[k]
    legend = {t.get_text(): h for t, h in zip(ax.get_legend().get_texts(), ax.get_legend().legend_handles)}
    for k, c in colours.items():
        h = legend[f"{k}% curve"]
        assert to_hex(h.get_color()) == c and h.get_linestyle() == "-"
        if k in dots:
            assert h.get_marker() == dots[k].get_marker()
    import matplotlib.pyplot as plt

    plt.close(fig)
    assert plot_scatter_curves(model, tmp_path / "sc_scatter.png").stat().st_size > 1000


def test_curve_colours_distinct_for_any_levels():
    keys = ["50", "68.27", "80", "90", "95", "99", "99.9"]
    c = curve_colours(keys)
    assert set(c) == set(keys) and len(set(c.values())) == len(keys)
    assert c["68.27"] != c["90"]
