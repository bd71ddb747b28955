import math

import numpy as np
import pytest
from affine import Affine

from geocd.change.regions import COLUMNS, change_regions, empty_regions
from geocd.geodesy import AOIGrid


@pytest.fixture
def grid():
    return AOIGrid("EPSG:32631", Affine(2.0, 0, 500000, 0, -2.0, 4000000), 30, 20)


def test_regions_schema_area_volume(grid):
    sign = np.zeros(grid.shape, np.int8)
    dz = np.zeros(grid.shape)
    sign[2:6, 3:8] = 1
    dz[2:6, 3:8] = 2.0
    dz[3, 4] = 5.0
    sign[10:13, 10:12] = -1
    dz[10:13, 10:12] = -1.5
    dz[11, 11] = -4.0
    reg = change_regions(sign, dz, grid, method="m", epoch_a="A", epoch_b="B")
    assert tuple(reg.columns[:-1]) == COLUMNS and reg.geometry.name == "geometry"
    assert reg.crs.to_epsg() == 32631 and len(reg) == 2
    up = reg[reg.sign == 1].iloc[0]
    assert up.n_cells == 20 and up.area_m2 == pytest.approx(80.0)
    assert up.volume_m3 == pytest.approx((19 * 2 + 5) * 4.0)
    assert up.max_dz_m == 5.0 and up.geometry.area == pytest.approx(80.0)
    down = reg[reg.sign == -1].iloc[0]
    assert down.max_dz_m == -4.0 and down.mean_dz_m == pytest.approx((5 * -1.5 - 4) / 6)
    assert math.isnan(up.volume_sigma_m3) and math.isnan(up.confidence)
    assert list(reg.region_id) == [1, 2]


def test_eight_connectivity_and_min_cells(grid):
    sign = np.zeros(grid.shape, np.int8)
    for k in range(5):
        sign[k, k] = 1  # a diagonal line: one 8-connected region
    sign[15, 25] = 1  # single cell
    reg = change_regions(sign, sign.astype(float), grid, min_cells=4)
    assert len(reg) == 1 and reg.iloc[0].n_cells == 5
    assert reg.iloc[0].geometry.is_valid
    assert len(change_regions(sign, sign.astype(float), grid, min_cells=1)) == 2


def test_nodata_value_is_not_change_and_empty_schema(grid):
    sign = np.full(grid.shape, -128, np.int8)
    reg = change_regions(sign, np.zeros(grid.shape), grid)
    assert len(reg) == 0 and tuple(reg.columns[:-1]) == COLUMNS and reg.crs.to_epsg() == 32631
    e = empty_regions("EPSG:4326")
    assert len(e) == 0 and "volume_sigma_m3" in e.columns


def test_confidence_and_sigma_sources(grid):
    sign = np.zeros(grid.shape, np.int8)
    sign[2:6, 2:6] = 1
    dz = np.where(sign == 1, 1.0, 0.0)
    r1 = change_regions(sign, dz, grid, confidence=95.0)
    assert r1.iloc[0].confidence == 95.0
    conf = np.where(sign == 1, 97.0, np.nan)
    r2 = change_regions(sign, dz, grid, confidence=conf)
    assert r2.iloc[0].confidence == pytest.approx(97.0)
    # per-cell σ without correlation info → fully correlated (conservative) volume σ
    r3 = change_regions(sign, dz, grid, dz_sigma_m=0.5)
    assert r3.iloc[0].volume_sigma_m3 == pytest.approx(16 * 0.5 * 4.0)
    assert r3.iloc[0].confidence == pytest.approx(100 * math.erf(64 / 32 / math.sqrt(2)))  # percent
    seen = []

    def fn(mask):
        seen.append(mask.sum())
        return 10.0

    r4 = change_regions(sign, dz, grid, volume_sigma_fn=fn)
    assert seen == [16] and r4.iloc[0].volume_sigma_m3 == 10.0
    assert r4.iloc[0].confidence == pytest.approx(100 * math.erf(6.4 / math.sqrt(2)))
    # the method's own (region-level) confidence kept, σ_V still reported
    r5 = change_regions(sign, dz, grid, confidence=conf, volume_sigma_fn=fn, volume_confidence=False)
    assert r5.iloc[0].confidence == pytest.approx(97.0) and r5.iloc[0].volume_sigma_m3 == 10.0


def test_geographic_grid_cell_area():
    g = AOIGrid("EPSG:4326", Affine(1 / 1200, 0, 40.0, 0, -1 / 1200, 40.5), 10, 10)
    sign = np.zeros(g.shape, np.int8)
    sign[2:4, 2:4] = 1
    reg = change_regions(sign, sign.astype(float), g)
    # 3" cells at 40.5°N: about 70.6 m × 92.6 m
    assert reg.iloc[0].area_m2 == pytest.approx(4 * 70.6 * 92.6, rel=0.01)
