"""End to end on tiny two-epoch scenes (affine RPC and frame cameras): detection, illumination, bad inputs."""

import numpy as np
import pytest
from scene import affine_rpc, image_truth, make_scene

from geocd.change.metrics import binary_scores
from geocd.errors import ConfigError, NoOverlapError
from geocd.probchange import ProbChangeParams, detect_keyframe, detect_objectspace, make_view

RANGE = (196.0, 214.0)


def _views(scene, epoch):
    return [make_view(im, c, name=n) for im, c, n in zip(scene.images[epoch], scene.cameras[epoch], scene.names[epoch])]


@pytest.fixture(scope="module")
def rpc_scene():
    return make_scene(kind="rpc")


@pytest.fixture(scope="module")
def rpc_views(rpc_scene):
    return _views(rpc_scene, "A"), _views(rpc_scene, "B")


@pytest.mark.parametrize("robust", [False, True])
@pytest.mark.slow
def test_objectspace_finds_the_changes(rpc_scene, rpc_views, robust):
    va, vb = rpc_views
    kw = {"n_bins": 64, "height_range_m": RANGE}
    p = ProbChangeParams.robust(**kw) if robust else ProbChangeParams(**kw)
    r = detect_objectspace(va, vb, rpc_scene.grid, params=p)
    sc = binary_scores(r.changed(), rpc_scene.truth)
    assert sc["f1"] > 0.7, sc
    assert sc["false_alarm_rate"] < 0.08, sc
    assert 2.0 < r.noise.sigma < 12.0 and 2.0 < r.noise.sigma_prime < 12.0
    # the most probable heights (by-products) sit on the truth DSMs where observed and textured
    err = np.abs(r.height_a_m - rpc_scene.dsm["A"])[r.observed]
    assert np.nanpercentile(err, 75) < 1.0


def test_keyframe_rpc_and_grid(rpc_scene, rpc_views):
    va, vb = rpc_views
    p = ProbChangeParams(n_bins=64, height_range_m=RANGE)
    k = detect_keyframe(va[0], va[1:], vb, params=p)
    assert k.probability.shape == rpc_scene.images["A"][0].shape
    sc = binary_scores(k.changed(), image_truth(rpc_scene, "A", 0))
    assert sc["f1"] > 0.7, sc
    g = k.to_grid(rpc_scene.grid)
    assert binary_scores(g.changed(), rpc_scene.truth)["f1"] > 0.7


def test_prior_moves_the_decision_monotonically(rpc_scene, rpc_views):
    va, vb = rpc_views
    fr = []
    base = ProbChangeParams(n_bins=48, height_range_m=RANGE, sigma=5.0, sigma_prime=5.0, uniform_range=90.0)
    for prior in (0.1, 0.5, 0.9):
        r = detect_objectspace(va, vb, rpc_scene.grid, params=base.replace(prior_change=prior))
        fr.append(r.changed().mean())
    assert fr[0] <= fr[1] <= fr[2]


def test_illumination_change_between_epochs_adds_no_false_alarms(rpc_scene):
    """Epoch B under another 'sun' (gain, offset, gamma, shading) vs the same: same false-alarm rate."""
    same = make_scene(kind="rpc", illumination_b="same")
    out = {}
    for name, sc in (("same", same), ("other", rpc_scene)):
        r = detect_objectspace(
            _views(sc, "A"), _views(sc, "B"), sc.grid, params=ProbChangeParams(n_bins=64, height_range_m=RANGE)
        )
        out[name] = binary_scores(r.changed(), sc.truth)
    assert out["other"]["false_alarm_rate"] <= out["same"]["false_alarm_rate"] + 0.01, out
    assert out["other"]["f1"] >= out["same"]["f1"] - 0.05, out


@pytest.mark.slow
def test_keyframe_frame_cameras_inverse_depth():
    scene = make_scene(kind="frame")
    va, vb = _views(scene, "A"), _views(scene, "B")
    truth = image_truth(scene, "A", 0)
    for p in (
        ProbChangeParams(n_bins=64, height_range_m=RANGE),
        ProbChangeParams.robust(n_bins=64, height_range_m=RANGE, symmetric=True),
    ):
        k = detect_keyframe(va[0], va[1:], vb, params=p)
        sc = binary_scores(k.changed(), truth, valid=k.observed)
        assert sc["f1"] > 0.65, sc


# ---------------------------------------------------------------------------------------------
# bad inputs
# ---------------------------------------------------------------------------------------------
def test_single_image_epoch_is_a_clear_error(rpc_scene, rpc_views):
    va, vb = rpc_views
    with pytest.raises(ConfigError, match="at least two images"):
        detect_objectspace(va, vb[:1], rpc_scene.grid, params=ProbChangeParams(height_range_m=RANGE))
    with pytest.raises(ConfigError, match="epoch 'A' has 1 image"):
        detect_keyframe(va[0], [], vb, params=ProbChangeParams(height_range_m=RANGE))


def test_non_overlapping_camera_is_a_clear_error(rpc_scene, rpc_views):
    va, vb = rpc_views
    far_cam = affine_rpc(0.5, (-0.45, 0.02), vb[1].camera.width, vb[1].camera.height)
    far_cam = far_cam.replace(samp_off=far_cam.samp_off + 3000.0)  # looks 1.5 km away
    far = vb[1].__class__(vb[1].name + "_far", vb[1].chips, far_cam)
    with pytest.raises(NoOverlapError, match="does not overlap the key frame"):
        detect_keyframe(va[0], va[1:], [vb[0], far], params=ProbChangeParams(height_range_m=RANGE))
    with pytest.raises(NoOverlapError, match="does not see the AOI"):
        detect_objectspace(va, [vb[0], far], rpc_scene.grid, params=ProbChangeParams(height_range_m=RANGE))


def test_no_height_range_for_frame_cameras_without_dem(rpc_scene):
    from scene import frame_camera

    cams = [frame_camera(x, 0.0, 100, 100) for x in (0.0, 10.0)]
    imgs = [np.random.default_rng(i).uniform(0, 255, (100, 100)) for i in range(2)]
    va = [make_view(im, c, name=f"a{i}") for i, (im, c) in enumerate(zip(imgs, cams))]
    vb = [make_view(im, c, name=f"b{i}") for i, (im, c) in enumerate(zip(imgs, cams))]
    with pytest.raises(ConfigError, match="height range"):
        detect_keyframe(va[0], va[1:], vb)
