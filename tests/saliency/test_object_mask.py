"""The salient-object mask of the synthetic training data: strokes closed into objects, invisible markings left out."""

from __future__ import annotations

import cv2
import numpy as np
from sgf_plugins.saliency.synthetic_data import ObjectMaskParams, object_mask


def scene(paint_value: int) -> tuple[np.ndarray, np.ndarray]:
    """Grey asphalt (value 90) with three 3-px strokes 4 px apart painted at ``paint_value``."""
    rgb = np.full((64, 64, 3), 90, np.uint8)
    paint = np.zeros((64, 64), bool)
    for x in (20, 27, 34):
        paint[20:40, x : x + 3] = True
    rgb[paint] = paint_value
    return rgb, paint


def test_strokes_of_one_marking_become_one_object():
    rgb, paint = scene(230)
    obj = object_mask(rgb, paint, None, ObjectMaskParams())
    count, _ = cv2.connectedComponents(obj.astype(np.uint8))
    assert count - 1 == 1  # one object, not three strokes
    assert obj[30, 24] and obj[30, 31]  # the gaps between the strokes are inside it
    assert not obj[5, 5] and obj.sum() > paint.sum() * 1.5
    assert (obj & paint).sum() == paint.sum()


def test_a_marking_that_cannot_be_seen_is_not_salient():
    rgb, paint = scene(95)  # paint barely differs from the asphalt (night, far away)
    assert not object_mask(rgb, paint, None, ObjectMaskParams()).any()
    rgb, paint = scene(120)  # a contrast of 30 grey levels is seen
    assert object_mask(rgb, paint, None, ObjectMaskParams()).any()


def test_the_mask_stays_inside_the_camera_view():
    rgb, paint = scene(230)
    valid = np.ones((64, 64), bool)
    valid[:, 30:] = False
    obj = object_mask(rgb, paint, valid, ObjectMaskParams())
    assert obj[:, :30].any() and not obj[:, 30:].any()
    assert not object_mask(rgb, np.zeros_like(paint), None, ObjectMaskParams()).any()
