import numpy as np
import pytest

from handanno_core.descriptors import compute_descriptors


def _blob_crop(cx=64.0, cy=64.0, rx=20.0, ry=35.0, size=128, tilt=0.0):
    """A hand-like ellipsoidal bump: depth in [-1, 1] inside, +1 background."""
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32)
    c, s = np.cos(tilt), np.sin(tilt)
    u = ((xx - cx) * c + (yy - cy) * s) / rx
    v = (-(xx - cx) * s + (yy - cy) * c) / ry
    r2 = u * u + v * v
    crop = np.ones((size, size), np.float32)
    inside = r2 < 1
    crop[inside] = -0.6 * np.sqrt(1 - r2[inside])
    return crop


@pytest.fixture(scope="module")
def crops():
    rng = np.random.default_rng(0)
    out = [
        _blob_crop(64 + rng.uniform(-10, 10), 64 + rng.uniform(-10, 10), tilt=rng.uniform(0, 3))
        for _ in range(20)
    ]
    out.append(np.ones((128, 128), np.float32))  # an empty (all-background) frame
    return np.stack(out)


@pytest.mark.parametrize("kind,dim", [("hog", 1764), ("downsampled", 256)])
def test_shape_and_unit_rows(crops, kind, dim):
    d = compute_descriptors(crops, kind)
    assert d.shape == (len(crops), dim) and d.dtype == np.float32
    assert np.all(np.isfinite(d))
    norms = np.linalg.norm(d, axis=1)
    np.testing.assert_allclose(norms[:-1], 1.0, atol=1e-5)
    assert norms[-1] == 0.0  # featureless frame: zero row, not NaN


@pytest.mark.parametrize("kind", ["hog", "downsampled"])
def test_chunking_and_memmap_do_not_change_result(tmp_path, crops, kind):
    full = compute_descriptors(crops, kind, chunk=512)
    small = compute_descriptors(crops, kind, chunk=3)
    np.testing.assert_allclose(full, small, atol=1e-6)
    path = tmp_path / "crops.npy"
    np.save(path, crops.astype(np.float16))
    mm = np.load(path, mmap_mode="r")
    from_mm = compute_descriptors(mm, kind, chunk=4)
    np.testing.assert_allclose(full, from_mm, atol=2e-2)  # float16 storage


def test_hog_orientation_bins():
    """A horizontal edge (gradient along y, 90 deg) fills bin 4; a vertical edge (gradient
    along x, 0 deg) splits between bins 8 and 0."""
    img_h = np.ones((128, 128), np.float32)
    img_h[64:] = -0.5
    img_v = np.ones((128, 128), np.float32)
    img_v[:, 64:] = -0.5
    d = compute_descriptors(np.stack([img_h, img_v]), "hog").reshape(2, -1, 9)
    energy = d.sum(axis=1)
    assert np.argmax(energy[0]) == 4
    assert energy[0, 4] > 0.9 * energy[0].sum()
    np.testing.assert_allclose(energy[1, 0], energy[1, 8], rtol=1e-4)
    assert energy[1, 0] + energy[1, 8] > 0.9 * energy[1].sum()


@pytest.mark.parametrize("kind", ["hog", "downsampled"])
def test_similar_crops_are_closer(kind):
    a = _blob_crop(64, 64, tilt=0.0)
    b = _blob_crop(66, 63, tilt=0.1)  # a small change of a
    c = _blob_crop(64, 64, rx=35, ry=15, tilt=1.2)  # a different shape
    d = compute_descriptors(np.stack([a, b, c]), kind)
    d_ab = 1 - d[0] @ d[1]
    d_ac = 1 - d[0] @ d[2]
    assert d_ab < 0.5 * d_ac


def test_downsampled_background_does_not_dominate():
    """Raw crops of two small blobs in different places have cosine ~ 0 (background +1
    dominates); the mean-subtracted descriptor separates them clearly."""
    a = _blob_crop(40, 40, rx=10, ry=10)
    b = _blob_crop(90, 90, rx=10, ry=10)
    raw = np.stack([a.ravel(), b.ravel()])
    raw /= np.linalg.norm(raw, axis=1, keepdims=True)
    assert 1 - raw[0] @ raw[1] < 0.05
    d = compute_descriptors(np.stack([a, b]), "downsampled")
    assert 1 - d[0] @ d[1] > 0.5


def test_other_crop_sizes_and_errors():
    small = np.stack([_blob_crop(size=64, cx=32, cy=32, rx=10, ry=16)] * 2)
    assert compute_descriptors(small, "hog").shape == (2, 1764)
    assert compute_descriptors(small, "downsampled", size=16).shape == (2, 256)
    with pytest.raises(ValueError, match="unknown descriptor"):
        compute_descriptors(small, "sift")
    with pytest.raises(ValueError, match="N, S, S"):
        compute_descriptors(np.ones((2, 8, 9)), "hog")
