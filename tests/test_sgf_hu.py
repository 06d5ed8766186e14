"""Hu invariants (eq. 5-7), their distance (eq. 8), the border band and the grouping of views."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from sgf_plugins.sgf.best_view import group_views
from sgf_plugins.sgf.hu import hu_distance, hu_moments, scale_hu
from sgf_plugins.sgf.regions import Region, border_band, majority_instance
from sgf_plugins.sgf.tracking import FeatureView


def pixels_of(mask: np.ndarray) -> np.ndarray:
    v, u = np.nonzero(mask)
    return np.stack([u, v], axis=1)


def rect_mask(shape=(200, 200), centre=(100.0, 100.0), size=(80.0, 30.0), angle=0.0) -> np.ndarray:
    mask = np.zeros(shape, np.uint8)
    box = cv2.boxPoints(((centre[0], centre[1]), size, angle))
    cv2.fillPoly(mask, [np.round(box * 16).astype(np.int32)], 1, shift=4)
    return mask.astype(bool)


def arrow_mask(angle: float, centre=(100.0, 100.0), scale: float = 1.0) -> np.ndarray:
    """A filled arrow polygon rotated by ``angle`` degrees, drawn with sub-pixel precision."""
    poly = np.array([[-50, -8], [15, -8], [15, -25], [50, 0], [15, 25], [15, 8], [-50, 8]], float) * scale
    a = math.radians(angle)
    rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    pts = poly @ rot.T + np.array(centre)
    mask = np.zeros((200, 200), np.uint8)
    cv2.fillPoly(mask, [np.round(pts * 16).astype(np.int32)], 1, shift=4)
    return mask.astype(bool)


def test_hu_moments_match_opencv():
    for mask in (rect_mask(angle=17.0), arrow_mask(33.0)):
        ours = hu_moments(pixels_of(mask))
        ref = cv2.HuMoments(cv2.moments(mask.astype(np.uint8), binaryImage=True)).ravel()
        assert np.allclose(ours, ref, rtol=1e-6, atol=1e-15)


def test_hu_of_a_rectangle_is_analytic():
    # h1 = (a^2 + b^2) / (12 a b) for an a x b rectangle; h2 = ((a^2 - b^2) / (12 a b))^2.
    u, v = np.meshgrid(np.arange(60), np.arange(20))
    hu = hu_moments(np.stack([u.ravel(), v.ravel()], axis=1))
    a, b = 60.0, 20.0
    assert hu[0] == pytest.approx((a * a - 1 + b * b - 1) / (12 * a * b), rel=1e-9)
    assert hu[1] == pytest.approx(((a * a - b * b) / (12 * a * b)) ** 2, rel=1e-9)
    assert np.allclose(hu[2:], 0.0, atol=1e-15)


def test_eq8_is_the_sum_of_absolute_differences():
    a = np.array([0.2, 0.01, 1e-4, 2e-5, 0.0, -1e-6, 3e-9])
    b = np.array([0.21, 0.012, 0.0, 1e-5, 0.0, 1e-6, -3e-9])
    assert hu_distance(a, b, "raw") == pytest.approx(0.01 + 0.002 + 1e-4 + 1e-5 + 2e-6 + 6e-9)
    assert hu_distance(a, a, "raw") == 0.0
    # log scale: sign(h) log10|h|; zeros stay zero instead of -inf.
    logs = scale_hu(a, "log")
    assert logs[0] == pytest.approx(math.log10(0.2))
    assert logs[5] == pytest.approx(6.0)  # sign(-1e-6) * log10(1e-6)
    assert logs[4] == 0.0
    with pytest.raises(ValueError, match="unknown Hu scale"):
        scale_hu(a, "cubic")  # type: ignore[arg-type]


def test_eq8_is_invariant_to_translation_rotation_and_scale():
    base = hu_moments(pixels_of(arrow_mask(0.0)))
    assert hu_distance(base, hu_moments(pixels_of(arrow_mask(0.0, centre=(91.3, 104.7)))), "raw") < 0.005
    assert hu_distance(base, hu_moments(pixels_of(arrow_mask(90.0))), "raw") < 0.005
    # Scale: rasterising a 16-pixel shaft at another size moves the raw invariants by ~1e-2, which
    # is why 0.005 on raw moments is a tight threshold; different shapes are still 5x farther.
    assert hu_distance(base, hu_moments(pixels_of(arrow_mask(180.0, scale=1.4))), "raw") < 0.02
    # A different shape is far above the threshold.
    assert hu_distance(base, hu_moments(pixels_of(rect_mask()))) > 0.05


def test_degenerate_regions_do_not_crash():
    assert np.all(hu_moments(np.zeros((0, 2))) == 0.0)
    one = hu_moments(np.array([[5, 7]]))
    assert np.all(np.isfinite(one)) and np.all(one == 0.0)
    line = hu_moments(np.stack([np.arange(50), np.zeros(50, int)], axis=1))
    assert np.all(np.isfinite(line)) and line[0] > 0.08


def test_border_band_covers_the_image_edge_and_the_field_of_view():
    valid = np.ones((10, 12), bool)
    valid[:, :3] = False  # outside the camera's view
    band = border_band(valid, 1)
    assert band[0].all() and band[-1].all() and band[:, -1].all()
    assert band[:, :4].all()  # the invalid area and one pixel next to it
    assert not band[1:-1, 4:-1].any()
    wider = border_band(valid, 2)
    assert wider[:, :5].all() and not wider[2:-2, 5:-2].any()


def test_majority_instance():
    assert majority_instance(np.array([0, 0, 3, 3, 3, 4]), 0.3) == 3
    assert majority_instance(np.array([0, 0, 0, 0, 0, 4]), 0.3) is None
    assert majority_instance(np.array([], int), 0.3) is None


def view(i: int, hu0: float, border: bool = False, saliency: float = 0.8) -> FeatureView:
    hu = np.array([hu0, 0.01, 0, 0, 0, 0, 0])
    region = Region(np.zeros((5, 2), np.int32), saliency, hu, border, None)
    return FeatureView(i, 0.1 * i, np.eye(4), region)


def test_grouping_follows_eq8_and_border_views_break_groups():
    views = [
        view(0, 0.30, border=True),
        view(1, 0.200),
        view(2, 0.202),
        view(3, 0.204),
        view(4, 0.230),  # a jump in shape: a new group
        view(5, 0.231),
        view(6, 0.232, border=True),
        view(7, 0.232),
    ]
    groups = group_views(views, 0.005, "raw")
    assert [[v.frame_index for v in g] for g in groups] == [[1, 2, 3], [4, 5], [7]]
    assert group_views([view(0, 0.2, border=True)], 0.005, "raw") == []
