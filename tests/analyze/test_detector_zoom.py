"""tsnav analyze detector-zoom: the enlarged crops against a pixel-by-pixel bilinear reference, and the combination of
the frame's and the crops' logits."""

import numpy as np
import pytest
from script_helpers import load_analysis


@pytest.fixture(scope="module")
def mod():
    return load_analysis("detector_zoom")


def bilinear_2x_reference(crop: np.ndarray) -> np.ndarray:
    """2x enlargement of an ``(h, h, 3)`` crop, one output pixel at a time: output pixel i samples the crop at
    (i + 0.5) / 2 - 0.5, clamped to the edge (the half-pixel convention), weighting its two neighbours per axis."""
    h = crop.shape[0]
    out = np.zeros((2 * h, 2 * h, 3))
    for i in range(2 * h):
        for j in range(2 * h):
            y = min(max((i + 0.5) / 2 - 0.5, 0.0), h - 1)
            x = min(max((j + 0.5) / 2 - 0.5, 0.0), h - 1)
            y0, x0 = int(np.floor(y)), int(np.floor(x))
            y1, x1 = min(y0 + 1, h - 1), min(x0 + 1, h - 1)
            wy, wx = y - y0, x - x0
            out[i, j] = (
                (1 - wy) * (1 - wx) * crop[y0, x0]
                + (1 - wy) * wx * crop[y0, x1]
                + wy * (1 - wx) * crop[y1, x0]
                + wy * wx * crop[y1, x1]
            )
    return np.clip(np.round(out), 0, 255).astype(np.uint8)


def test_crops_are_the_quadrants_and_centre_enlarged(mod):
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (2, 16, 16, 3), dtype=np.uint8)
    z = mod.zoom_crops(img)
    assert z.shape == (2, 5, 16, 16, 3) and z.dtype == np.uint8
    for n in range(2):
        for k, (y0, x0) in enumerate(((0, 0), (0, 8), (8, 0), (8, 8), (4, 4))):
            ref = bilinear_2x_reference(img[n, y0 : y0 + 8, x0 : x0 + 8].astype(np.float64))
            assert np.abs(z[n, k].astype(int) - ref.astype(int)).max() <= 1, (n, k)  # rounding of float32 sums


def test_combination_takes_the_largest_after_the_margin(mod):
    plain = np.array([[0.0, 2.0]], np.float32)
    crops = np.array([[[1.0, 1.0], [3.0, -1.0], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0]]], np.float32)
    assert np.array_equal(mod.combine(plain, crops, None), plain)
    assert np.array_equal(mod.combine(plain, crops, 0.0), [[3.0, 2.0]])
    assert np.array_equal(mod.combine(plain, crops, 2.5), [[0.5, 2.0]])
    assert np.array_equal(mod.combine(plain, crops, 5.0), plain)  # a large margin leaves the frame's logits
