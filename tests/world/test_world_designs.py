import numpy as np
import pytest
from sgf_plugins.world.designs import (
    DESIGNS,
    HELD_OUT_FAMILIES,
    allowed_designs,
    families,
    resolve_designs,
)
from sgf_plugins.world.hangul_font import hangul_strokes
from sgf_plugins.world.marking_raster import rasterise

from sgf_pipeline.errors import ConfigError


def test_library_has_a_dozen_standard_and_a_dozen_custom_designs():
    standard = [d for d in DESIGNS.values() if d.category == "standard"]
    custom = [d for d in DESIGNS.values() if d.category == "custom"]
    assert len(standard) >= 12 and len(custom) >= 12
    for name in (
        "solid_line",
        "dashed_line",
        "stop_line",
        "zebra_crossing",
        "arrow_straight",
        "arrow_left",
        "arrow_right",
        "arrow_uturn",
        "diamond",
        "number_30",
        "word_slow",
        "bicycle",
        "wheelchair",
        "speed_bump_chevrons",
    ):
        assert DESIGNS[name].category == "standard", name
    for name in (
        "campus_logo_shield",
        "text_hangul",
        "text_script",
        "direction_sign",
        "parking_number",
        "coloured_zone",
        "tactile_dots",
        "painted_star",
        "delivery_pickup",
        "manhole_round",
        "drain_grate",
    ):
        assert DESIGNS[name].category == "custom", name


@pytest.mark.parametrize("name", sorted(DESIGNS))
def test_every_design_paints_a_plausible_mask(name):
    d = DESIGNS[name]
    r = rasterise(d, d.size[0], d.size[1], 0.01, d.colours[0], content_seed=5)
    box = d.size[0] * d.size[1] / 0.01**2
    fill = r.mask.sum() / box
    assert 0.03 < fill <= 1.02, fill
    assert r.alpha.max() <= 1.0 + 1e-6 and r.alpha.min() >= 0.0
    assert np.isfinite(r.colour).all() and r.colour.max() <= 255.0
    # the mask is centred on the marking (its pose is the centre of its box)
    rows, cols = np.nonzero(r.mask)
    x = r.x_top - (rows + 0.5) * 0.01
    y = r.y_left - (cols + 0.5) * 0.01
    assert abs(x.mean()) < 0.3 * d.size[0] and abs(y.mean()) < 0.3 * d.size[1]


def _best_turn_iou(name: str) -> float:
    """Best overlap of a design's mask with itself turned by 20..340 degrees about its centre."""
    import cv2

    d = DESIGNS[name]
    mask = rasterise(d, d.size[0], d.size[1], 0.01, d.colours[0], content_seed=1).mask
    h, w = mask.shape
    side = max(h, w)
    m = np.zeros((side, side), np.uint8)
    r0, c0 = (side - h) // 2, (side - w) // 2
    m[r0 : r0 + h, c0 : c0 + w] = mask
    centre = (c0 + (w - 1) / 2, r0 + (h - 1) / 2)
    best = 0.0
    for angle in range(20, 341, 4):
        rot = cv2.getRotationMatrix2D(centre, angle, 1.0)
        turned = cv2.warpAffine(m, rot, (side, side), flags=cv2.INTER_NEAREST) > 0
        best = max(best, float((m.astype(bool) & turned).sum() / (m.astype(bool) | turned).sum()))
    return best


@pytest.mark.parametrize("name", sorted(n for n, d in DESIGNS.items() if d.symmetric))
def test_designs_flagged_symmetric_look_the_same_turned(name):
    assert _best_turn_iou(name) > 0.85


@pytest.mark.parametrize(
    "name",
    [
        "arrow_straight",
        "arrow_left",
        "bicycle",
        "word_slow",
        "campus_logo_shield",
        "direction_sign",
        "delivery_pickup",
        "painted_footprints",
        "text_hangul",
        "painted_heart",
        "give_way",
        "speed_bump_chevrons",
    ],
)
def test_asymmetric_designs_change_when_turned(name):
    assert not DESIGNS[name].symmetric
    assert _best_turn_iou(name) < 0.8


def test_standard_markings_repeat_identically_custom_ones_vary():
    arrow = DESIGNS["arrow_left"]
    a = rasterise(arrow, *arrow.size, 0.01, arrow.colours[0], content_seed=1).mask
    b = rasterise(arrow, *arrow.size, 0.01, arrow.colours[0], content_seed=99).mask
    assert np.array_equal(a, b)
    text = DESIGNS["text_serif"]
    masks = [rasterise(text, *text.size, 0.01, text.colours[0], content_seed=s).mask for s in range(6)]
    assert len({m.tobytes() for m in masks}) > 1


def test_wear_fades_paint_but_not_the_instance_mask():
    d = DESIGNS["word_stop"]
    clean = rasterise(d, *d.size, 0.01, d.colours[0], content_seed=1)
    worn = rasterise(d, *d.size, 0.01, d.colours[0], content_seed=1, wear=0.5, wear_seed=3)
    assert np.array_equal(clean.mask, worn.mask)
    assert worn.alpha[clean.mask].mean() < 0.85 * clean.alpha[clean.mask].mean()


def test_held_out_selection_by_family_and_name():
    held = resolve_designs(HELD_OUT_FAMILIES)
    assert held and all(DESIGNS[n].family in HELD_OUT_FAMILIES for n in held)
    train = {d.name for d in allowed_designs(exclude=HELD_OUT_FAMILIES)}
    test = {d.name for d in allowed_designs(only=HELD_OUT_FAMILIES)}
    assert train.isdisjoint(test) and test == held and train | test == set(DESIGNS)
    assert {d.name for d in allowed_designs(only=["arrow"], exclude=["arrow_uturn"])} == {
        "arrow_straight",
        "arrow_left",
        "arrow_right",
    }
    assert set(families()["utility"]) == {"manhole_round", "drain_grate"}


def test_unknown_design_names_are_a_clear_error():
    with pytest.raises(ConfigError, match=r"unknown marking design or family .arow.*arrow_left"):
        allowed_designs(exclude=["arow"])
    with pytest.raises(ConfigError, match="no marking design is left"):
        allowed_designs(only=["arrow"], exclude=["arrow"])


def test_random_shapes_are_painted_only_when_a_world_asks():
    from sgf_plugins.world.layout_generator import LayoutOptions, build_layout
    from sgf_plugins.world.params import WorldParams

    assert DESIGNS["random_shape"].weight == 0.0
    default = build_layout(3, 0.3, LayoutOptions(designs=tuple(allowed_designs())))
    assert not [m for m in default.markings if m.design.name == "random_shape"]
    weights = {"random_shape": 8.0}
    designs = allowed_designs(exclude=HELD_OUT_FAMILIES, weights=weights)
    assert {d.name: d.weight for d in designs}["random_shape"] == 8.0
    asked = build_layout(3, 0.3, LayoutOptions(designs=tuple(designs)))
    shapes = [m for m in asked.markings if m.design.name == "random_shape"]
    custom = [m for m in asked.markings if m.design.category == "custom"]
    assert len(shapes) >= 0.3 * len(custom) > 0
    assert not [m for m in asked.markings if m.design.family in HELD_OUT_FAMILIES]
    with pytest.raises(ConfigError, match=r"design_weights: unknown marking design.*randomshape"):
        allowed_designs(weights={"randomshape": 1.0})
    with pytest.raises(ValueError, match="design_weights must be >= 0"):
        WorldParams(design_weights={"random_shape": -1.0})


def test_random_shapes_differ_from_instance_to_instance():
    d = DESIGNS["random_shape"]
    masks = [rasterise(d, 1.0, 1.0, 0.01, d.colours[0], content_seed=s).mask for s in range(12)]
    fills = np.array([m.mean() for m in masks])
    assert fills.min() > 0.03 and fills.max() < 0.9
    ious = [(a & b).sum() / (a | b).sum() for i, a in enumerate(masks) for b in masks[i + 1 :]]
    assert max(ious) < 0.7  # no two instances are the same shape


def test_hangul_words_are_composed_from_jamo_strokes():
    strokes = hangul_strokes("천천히")
    assert len(strokes) == 2 * (4 + 2 + 1) + (3 + 1)  # ㅊ(4) ㅓ(2) ㄴ(1) twice, ㅎ(3) ㅣ(1)
    xs = np.concatenate([np.asarray(s)[:, 0] for s in strokes])
    assert xs.min() >= 0.0 and xs.max() <= 3.0
    with pytest.raises(ValueError, match="not a Hangul syllable"):
        hangul_strokes("abc")
