"""The run's plots: the self-consistency scatter plot (sc_scatter.png), one colour per significance curve and
its legend as drawn; the quick-look (sc_quicklook.png), epoch A | epoch B | the classified buildings with a
legend that counts each class."""

import geopandas as gpd
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.colors import to_hex
from PIL import Image
from shapely.geometry import box

from geocd.change.dsm_buildings import DAMAGE_CLASSES
from geocd.change.plots import (
    QuickLookView,
    change_quicklook_figure,
    curve_colours,
    plot_change_quicklook,
    plot_scatter_curves,
    scatter_curves_figure,
)
from geocd.change.products import quicklook_buildings
from geocd.geodesy import AOIGrid
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
    plt.close(fig)
    assert plot_scatter_curves(model, tmp_path / "sc_scatter.png").stat().st_size > 1000


def test_curve_colours_distinct_for_any_levels():
    keys = ["50", "68.27", "80", "90", "95", "99", "99.9"]
    c = curve_colours(keys)
    assert set(c) == set(keys) and len(set(c.values())) == len(keys)
    assert c["68.27"] != c["90"]


def _scene():
    """A 60 m × 40 m grid, two surfaces (a 9 m block gone, a 6 m block new) and a building layer."""
    grid = AOIGrid.from_bounds(500000, 4000000, 500060, 4000040, 0.5, "EPSG:32631")
    za = np.zeros(grid.shape, np.float32)
    za[10:40, 10:40] = 9.0
    zb = np.zeros(grid.shape, np.float32)
    zb[40:70, 70:100] = 6.0
    zb[:5, :5] = np.nan  # a hole in B's surface
    l, b, r, t = grid.bounds
    classes = ["collapsed", "new", "unchanged", "unchanged", "unobserved"]
    geoms = [
        box(l + 5, t - 20, l + 20, t - 5),
        box(l + 35, t - 35, l + 50, t - 20),
        box(l + 2, b + 2, l + 8, b + 8),
        box(l + 25, b + 2, l + 30, b + 8),
        box(r - 6, b + 2, r - 2, b + 6),
    ]
    bld = gpd.GeoDataFrame({"building_id": range(5), "class": classes}, geometry=geoms, crs=grid.crs)
    return grid, za, zb, bld


def _legend(fig):
    legends = [a.get_legend() for a in fig.axes if a.get_legend() is not None]
    assert len(legends) == 1
    return [t.get_text() for t in legends[0].get_texts()], legends[0]


def _all_text(fig):
    return [t.get_text() for t in fig.findobj(lambda a: hasattr(a, "get_text"))]


def test_quicklook_three_panels_and_legend_counts_equal_the_layer(tmp_path):
    grid, za, zb, bld = _scene()
    fig, counts = change_quicklook_figure(
        grid,
        QuickLookView(surface_m=za),
        QuickLookView(image=np.random.default_rng(0).random(grid.shape), label="ortho of B1"),
        buildings=bld,
        epoch_a="before",
        epoch_b="after",
        confidence=95,
    )
    assert len(fig.axes) == 3  # pre | post | classified objects
    assert (
        counts == bld["class"].value_counts().to_dict() == {"unchanged": 2, "collapsed": 1, "new": 1, "unobserved": 1}
    )
    texts, legend = _legend(fig)
    # one entry per class present, in the damage vocabulary's order, with its count and its colour
    assert texts == ["collapsed: 1", "new: 1", "unchanged: 2", "unobserved: 1"]
    for h, c in zip(legend.legend_handles, ["collapsed", "new", "unchanged", "unobserved"]):
        assert to_hex(h.get_facecolor()) == DAMAGE_CLASSES[c][0]
    titles = [a.get_title() for a in fig.axes]
    assert titles[0].startswith("before: hillshade") and titles[1] == "after: ortho of B1"
    assert "before → after" in fig.get_suptitle() and "95 % confidence" in fig.get_suptitle()
    # plain text only (a "$" would start matplotlib's slow mathtext parser)
    assert not any("$" in t for t in _all_text(fig))
    plt.close(fig)
    png = plot_change_quicklook(
        tmp_path / "sc_quicklook.png", grid, QuickLookView(surface_m=za), QuickLookView(surface_m=zb), buildings=bld
    )
    with Image.open(png) as im:
        assert im.format == "PNG" and im.width > 2 * im.height


def test_quicklook_without_buildings_counts_the_change_regions(tmp_path):
    grid, za, zb, _ = _scene()
    sign = np.sign(np.nan_to_num(zb - za)).astype(np.int8)
    fig, counts = change_quicklook_figure(
        grid, QuickLookView(surface_m=za), QuickLookView(surface_m=zb), dz_m=zb - za, sign=sign
    )
    assert len([a for a in fig.axes if a.get_images()]) == 3  # and the colour bar's axis
    assert counts == {"raised regions": 1, "lowered regions": 1}
    texts, _ = _legend(fig)
    assert texts == ["raised: 1 region, 225 m²", "lowered: 1 region, 225 m²"]
    plt.close(fig)


def test_quicklook_reads_the_buildings_layer_first():
    _, _, _, bld = _scene()
    old = bld.assign(**{"class": ["demolished", "new", "unchanged", "unchanged", "unobserved"]})
    # "buildings" (the merged layer, or a footprint layer of its own classes) first, else "building_damage"
    assert quicklook_buildings({"buildings": bld, "building_damage": old}) is bld
    assert quicklook_buildings({"buildings": old, "building_damage": bld}) is old
    assert quicklook_buildings({"building_damage": bld}) is bld
    assert quicklook_buildings({"changes": bld.drop(columns="class")}) is None
    # a class outside the damage vocabulary keeps a colour of its own
    grid, za, zb, _ = _scene()
    fig, counts = change_quicklook_figure(grid, QuickLookView(surface_m=za), QuickLookView(surface_m=zb), buildings=old)
    texts, legend = _legend(fig)
    assert texts[:2] == ["demolished: 1", "new: 1"]
    colours = [to_hex(h.get_facecolor()) for h in legend.legend_handles]
    assert len(set(colours)) == len(colours)
    plt.close(fig)


def test_quicklook_with_an_empty_building_layer_says_so():
    grid, za, zb, bld = _scene()
    fig, counts = change_quicklook_figure(grid, QuickLookView(surface_m=za), None, buildings=bld.iloc[:0])
    assert counts == {} and "no building" in _all_text(fig)
    assert fig.axes[1].get_title().endswith("nothing to show")
    plt.close(fig)
