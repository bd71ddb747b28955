"""A tiny two-epoch scene for the probabilistic change tests.

A textured height field with boxes ("buildings") seen by affine RPC cameras
(parallel projections with known parallax, like a pushbroom over a small area)
or by nadir frame cameras. Epoch B demolishes one box, raises another and adds a
third. Images are rendered by marching each pixel's ray down through the DSM
with ``camera.localize`` (any camera kind), so occlusions are real. Epoch B can
be rendered under a different "illumination" (gain, offset, gamma and shading).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from geocd.camera import RPCModel
from geocd.geodesy import AOIGrid, from_lonlat, utm_crs_for

LON0, LAT0, H0 = 5.30, 44.10, 200.0
M_PER_DEG_LAT = 111_132.0
M_PER_DEG_LON = 111_320.0 * np.cos(np.radians(LAT0))
H_LO, H_HI = H0 - 4.0, H0 + 14.0


def affine_rpc(gsd_m: float, parallax_px_per_m: tuple[float, float], width: int, height: int) -> RPCModel:
    """``col = cx + Δlon/dlon + pc·(h − H0)``, ``row = cy − Δlat/dlat + pr·(h − H0)`` as an RPC00B."""
    cx, cy = width / 2.0, height / 2.0
    s_lon = s_lat = 0.01
    s_h = 500.0
    z = np.zeros(20)
    samp = z.copy()
    samp[1] = s_lon / (gsd_m / M_PER_DEG_LON)
    samp[3] = parallax_px_per_m[0] * s_h
    line = z.copy()
    line[2] = -s_lat / (gsd_m / M_PER_DEG_LAT)
    line[3] = parallax_px_per_m[1] * s_h
    den = z.copy()
    den[0] = 1.0
    return RPCModel(
        line_num=line,
        line_den=den,
        samp_num=samp,
        samp_den=den.copy(),
        line_off=cy - 0.5,
        samp_off=cx - 0.5,
        lat_off=LAT0,
        lon_off=LON0,
        height_off=H0,
        line_scale=1.0,
        samp_scale=1.0,
        lat_scale=s_lat,
        lon_scale=s_lon,
        height_scale=s_h,
        width=width,
        height=height,
        source="probchange test affine RPC",
    )


def local_xy(lon, lat):
    return (np.asarray(lon) - LON0) * M_PER_DEG_LON, (np.asarray(lat) - LAT0) * M_PER_DEG_LAT


# boxes: (x0, x1, y0, y1, height above ground) in local metres
BOXES_A = {
    "demolished": (-16.0, -6.0, 4.0, 14.0, 8.0),
    "raised": (4.0, 14.0, -14.0, -4.0, 5.0),
    "unchanged": (-17.0, -9.0, -17.0, -9.0, 6.0),
}
BOXES_B = {
    "raised": (4.0, 14.0, -14.0, -4.0, 10.0),
    "new": (6.0, 15.0, 6.0, 15.0, 7.0),
    "unchanged": (-17.0, -9.0, -17.0, -9.0, 6.0),
}


def ground(x, y):
    return H0 + 0.03 * x - 0.02 * y + 0.8 * np.sin(x / 7.0) * np.cos(y / 9.0)


def dsm(x, y, epoch: str):
    z = ground(x, y)
    for x0, x1, y0, y1, hb in (BOXES_A if epoch == "A" else BOXES_B).values():
        inside = (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
        z = np.where(inside, H0 + hb, z)
    return z


class Texture:
    def __init__(self, seed: int = 0, extent_m: float = 80.0, step_m: float = 0.25):
        rng = np.random.default_rng(seed)
        n = int(2 * extent_m / step_m)
        a = ndimage.gaussian_filter(rng.normal(size=(n, n)), 1.5)
        a += 0.5 * ndimage.gaussian_filter(rng.normal(size=(n, n)), 5.0)
        self.a = (a - a.mean()) / a.std()
        self.step, self.extent = step_m, extent_m

    def __call__(self, x, y):
        c = (np.asarray(x) + self.extent) / self.step
        r = (np.asarray(y) + self.extent) / self.step
        return ndimage.map_coordinates(self.a, [r, c], order=1, mode="reflect")


def _ray_ends(cam):
    H, W = cam.height, cam.width
    cols, rows = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    lo = cam.localize(cols, rows, np.full(cols.shape, H_LO))
    hi = cam.localize(cols, rows, np.full(cols.shape, H_HI))
    return lo, hi


def march(cam, epoch: str, dh: float = 0.05):
    """First surface along every pixel's ray: (hit height, x, y) images (local metres).

    Rays are localized at the top and bottom of the scene and followed linearly
    in between (exact for affine RPCs, < 1 mm off for the frame cameras here).
    """
    (lo_lon, lo_lat), (hi_lon, hi_lat) = _ray_ends(cam)
    found = np.zeros(lo_lon.shape, bool)
    hit = np.full(lo_lon.shape, np.nan)
    hx, hy = hit.copy(), hit.copy()
    for h in np.arange(H_HI, H_LO, -dh):
        t = (h - H_LO) / (H_HI - H_LO)
        x, y = local_xy(lo_lon + t * (hi_lon - lo_lon), lo_lat + t * (hi_lat - lo_lat))
        new = ~found & (h <= dsm(x, y, epoch))
        found |= new
        hit[new], hx[new], hy[new] = h, x[new], y[new]
    return hit, hx, hy


def render(cam, epoch: str, tex: Texture):
    """(albedo image, hit height image) of a camera in an epoch."""
    hit, hx, hy = march(cam, epoch)
    return tex(hx, hy) + 0.03 * (hit - H0), hit


def frame_camera(
    x_m: float, y_m: float, width: int, height: int, altitude_m: float = 150.0, gsd_m: float = 0.5, opk=(0.0, 0.0, 0.0)
):
    from geocd.camera.frame import FrameCamera

    crs = utm_crs_for(LON0, LAT0)
    lon, lat = LON0 + x_m / M_PER_DEG_LON, LAT0 + y_m / M_PER_DEG_LAT
    e, n = from_lonlat(lon, lat, crs)
    return FrameCamera(
        width=width,
        height=height,
        focal_px=altitude_m / gsd_m,
        position=(float(e), float(n), H0 + altitude_m),
        opk_deg=opk,
        crs=crs,
        vertical_datum="ellipsoid",
        source="probchange test",
    )


@dataclass
class Scene:
    grid: AOIGrid
    images: dict  # epoch → list of raw image arrays
    cameras: dict  # epoch → list of cameras
    names: dict  # epoch → list of names
    dsm: dict  # epoch → DSM on the grid
    truth: np.ndarray  # |ΔDSM| > 1 m on the grid
    hits: dict  # epoch → list of hit-height images (truth in image geometry)


def make_scene(
    *,
    kind: str = "rpc",
    size_m: float = 44.0,
    gsd_m: float = 0.5,
    seed: int = 0,
    illumination_b: str = "other",
    noise: float = 0.03,
    n_a: int = 3,
    n_b: int = 3,
) -> Scene:
    """Build the scene.

    kind : "rpc" (affine RPC views) or "frame" (nadir frame cameras along a strip)
    illumination_b : "same" (B rendered with A's radiometry) or "other" (gain, offset, gamma, shading)
    """
    crs = utm_crs_for(LON0, LAT0)
    xc, yc = from_lonlat(LON0, LAT0, crs)
    grid = AOIGrid.from_bounds(
        float(xc) - size_m / 2, float(yc) - size_m / 2, float(xc) + size_m / 2, float(yc) + size_m / 2, 0.5, crs
    )
    lon, lat = grid.lonlat()
    gx, gy = local_xy(lon, lat)
    dsm_g = {e: dsm(gx, gy, e) for e in ("A", "B")}
    truth = np.abs(dsm_g["B"] - dsm_g["A"]) > 1.0
    tex = Texture(seed)
    rng = np.random.default_rng(seed + 1)
    npx = int(size_m / gsd_m) + 40
    if kind == "rpc":
        par = {
            "A": [(0.0, 0.02), (0.55, 0.05), (-0.5, 0.03), (0.3, -0.45)][:n_a],
            "B": [(0.05, -0.1), (-0.45, 0.02), (0.5, 0.1), (-0.2, 0.4)][:n_b],
        }
        cams = {e: [affine_rpc(gsd_m, p, npx, npx) for p in par[e]] for e in ("A", "B")}
    elif kind == "frame":
        npx = int(size_m / gsd_m) + 100
        offs = {
            "A": [(0.0, 0.0), (22.0, 1.0), (-22.0, -1.0), (0.0, 22.0)][:n_a],
            "B": [(2.0, -20.0), (-20.0, 3.0), (20.0, 2.0), (0.0, 20.0)][:n_b],
        }
        cams = {
            e: [
                frame_camera(x, y, npx, npx, gsd_m=gsd_m, opk=(rng.normal(0, 0.3), rng.normal(0, 0.3), 0.0))
                for x, y in offs[e]
            ]
            for e in ("A", "B")
        }
    else:
        raise ValueError(kind)
    images, hits, names = {}, {}, {}
    for e in ("A", "B"):
        images[e], hits[e], names[e] = [], [], []
        for k, cam in enumerate(cams[e]):
            inten, hit = render(cam, e, tex)
            inten = inten + noise * rng.normal(size=inten.shape)
            if e == "B" and illumination_b == "other":
                # another sun and sensor: gain, offset, gamma and a height-dependent shading
                inten = 0.6 * inten - 0.04 * (hit - H0) + 0.3
                img = np.clip(500 + 220 * np.sign(inten) * np.abs(inten) ** 0.8, 0, 2047).astype(np.uint16)
            else:
                img = np.clip(900 + 150 * inten, 0, 2047).astype(np.uint16)
            images[e].append(img)
            hits[e].append(hit)
            names[e].append(f"{e}{k + 1}")
    return Scene(grid, images, cams, names, dsm_g, truth, hits)


def image_truth(scene: Scene, epoch: str, k: int) -> np.ndarray:
    """Per-pixel truth in image k of ``epoch``: the first surface along the ray moves by > 1 m between epochs."""
    other = "B" if epoch == "A" else "A"
    hit2, _, _ = march(scene.cameras[epoch][k], other)
    return np.abs(hit2 - scene.hits[epoch][k]) > 1.0
