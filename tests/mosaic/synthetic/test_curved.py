import cv2
import numpy as np
import pytest

from mosaic.eval.datasets import load_fire
from mosaic.preprocess import retina_disc
from mosaic.synthetic.curved import APERTURE, curved_pair, write_fire_folder


@pytest.fixture(scope="module")
def source():
    rng = np.random.default_rng(3)
    h = w = 400
    tex = cv2.GaussianBlur(rng.uniform(40, 220, (h, w)).astype(np.float32), (0, 0), 2)
    yy, xx = np.mgrid[0:h, 0:w]
    img = np.where(np.hypot(xx - 200, yy - 200) <= 190, tex, 0).astype(np.uint8)
    return cv2.merge([img // 2, img, img // 3])


def test_control_points_are_the_exact_mapping_and_the_views_agree_there(source):
    pair = curved_pair(source, seed=0, size=384, turn_deg=12.0)
    cp = pair.control_points
    assert cp.shape == (10, 4)
    np.testing.assert_allclose(pair.moving_to_fixed(cp[:, 2:]), cp[:, :2], atol=1e-9)
    # the two renderings show the same retina at the corresponding points
    f = cv2.GaussianBlur(pair.fixed[..., 1].astype(np.float32), (0, 0), 2)
    m = cv2.GaussianBlur(pair.moving[..., 1].astype(np.float32), (0, 0), 2)
    vf = cv2.remap(f, *cp[:, None, :2].astype(np.float32).transpose(2, 0, 1), cv2.INTER_LINEAR)
    vm = cv2.remap(m, *cp[:, None, 2:].astype(np.float32).transpose(2, 0, 1), cv2.INTER_LINEAR)
    assert np.corrcoef(vf.ravel(), vm.ravel())[0, 1] > 0.8


def test_no_homography_relates_the_views_of_a_curved_retina(source):
    pair = curved_pair(source, seed=1, size=512)
    g = np.stack(np.meshgrid(np.linspace(60, 450, 25), np.linspace(60, 450, 25)), -1)
    g = g.reshape(-1, 2)
    t = pair.moving_to_fixed(g)
    H, _ = cv2.findHomography(g, t, 0)
    residual = np.linalg.norm(cv2.perspectiveTransform(g[None], H)[0] - t, axis=1)
    assert residual.mean() > 0.3  # px at 512: ~2.5 px at FIRE's 2912


def test_fire_folder_loads_as_fire(tmp_path, source):
    path = tmp_path / "src.png"
    cv2.imwrite(str(path), source)
    out = write_fire_folder([path], tmp_path / "fire", n_pairs=2, size=256)
    data = load_fire(out)
    assert len(data) == 2
    pair = next(iter(data))
    assert pair.image1.shape == (256, 256, 3) and pair.control_points.shape == (10, 4)
    assert (out / "pairs.csv").read_text().splitlines()[0] == "fixed,moving"


def test_realistic_pairs_change_the_photographs_not_the_geometry(source):
    """A follow-up pair (`realistic`): the same cameras and control points as the plain pair;
    each photograph differs from its plain rendering (focus, light, gamma, colour, noise) but
    still shows the same retina there, the two differ from each other in brightness, and the
    aperture is filled: each is a whole retina to `retina_disc`."""
    plain = curved_pair(source, seed=4, size=384)
    visit = curved_pair(source, seed=4, size=384, realistic=True)
    np.testing.assert_array_equal(visit.control_points, plain.control_points)
    for a, b in ((plain.fixed, visit.fixed), (plain.moving, visit.moving)):
        inside = a[..., 1] > 20
        assert np.abs(a[..., 1][inside].astype(float) - b[..., 1][inside]).mean() > 5
        r = np.corrcoef(
            cv2.GaussianBlur(a[..., 1], (0, 0), 3)[inside],
            cv2.GaussianBlur(b[..., 1], (0, 0), 3)[inside],
        )[0, 1]
        assert r > 0.5
    level = [
        v[..., 1][v[..., 1] > 20].mean() / p[..., 1][p[..., 1] > 20].mean()
        for v, p in ((visit.fixed, plain.fixed), (visit.moving, plain.moving))
    ]
    assert abs(level[0] - level[1]) > 0.02
    c = (384 - 1) / 2
    for image in (visit.fixed, visit.moving):
        disc = retina_disc(image)
        assert disc is not None
        assert abs(disc[0] - c) < 3 and abs(disc[1] - c) < 3 and abs(disc[2] - APERTURE * c) < 4
