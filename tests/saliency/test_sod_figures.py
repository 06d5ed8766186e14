"""The SOD examples figure (paper Fig. 8): which samples it shows and where each picture lands."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from sgf_plugins.saliency.figures import GAP, HEADER, Example, example_grid, example_names


def test_examples_are_spread_over_the_samples_that_show_an_object() -> None:
    names = ["a", "b", "c", "d", "e", "f", "g"]
    pixels = {"b": 10, "c": 5, "e": 400, "g": 1}
    assert example_names(names, lambda n: pixels.get(n, 0), 2) == ["b", "e"]
    assert example_names(names, lambda n: pixels.get(n, 0), 9) == ["b", "c", "e", "g"]
    assert example_names(names, lambda n: 0, 3) == ["a", "c", "e"]  # no object anywhere: any sample
    assert example_names(names, lambda n: pixels.get(n, 0), 0) == []
    assert example_names([], lambda n: 1, 3) == []


def test_each_picture_lands_in_its_row_and_column() -> None:
    tile = 32
    image = np.zeros((64, 64, 3), np.uint8)
    image[..., 0] = 200  # red
    mask = np.zeros((64, 64), np.uint8)
    mask[:, 32:] = 255  # right half salient
    rows = [
        Example(
            "one", image, mask, {"net": np.full((64, 64), 100, np.uint8), "classical": np.zeros((64, 64), np.uint8)}
        ),
        Example("two", image[::2, ::2], mask[::2, ::2], {"net": np.full((16, 16), 30, np.uint8), "classical": mask}),
    ]
    grid = example_grid(rows, ["net", "classical"], tile=tile)
    assert grid.shape == (HEADER + 2 * tile + GAP, 4 * tile + 3 * GAP, 3)
    assert (grid[:HEADER] < 100).any() and (grid[:HEADER] == 255).mean() > 0.5  # titles on white

    def cell(r: int, c: int) -> np.ndarray:
        y, x = HEADER + r * (tile + GAP), c * (tile + GAP)
        return grid[y : y + tile, x : x + tile]

    for r in (0, 1):
        assert (cell(r, 0)[..., 0] == 200).all() and (cell(r, 0)[..., 1:] == 0).all()
        truth = cell(r, 1)[..., 0]
        assert (truth[:, :15] == 0).all() and (truth[:, 17:] == 255).all()
    assert (cell(0, 2) == 100).all() and (cell(1, 2) == 30).all()
    assert (cell(0, 3) == 0).all() and (cell(1, 3)[:, 17:] == 255).all()
    assert (grid[HEADER + tile : HEADER + tile + GAP] == 255).all()  # the gap between rows stays white
    with pytest.raises(ValueError, match="no map for u2net"):
        example_grid(rows, ["net", "u2net"], tile=tile)


def test_a_written_figure_reads_back_as_drawn(tmp_path) -> None:  # type: ignore[no-untyped-def]
    from sgf_plugins.saliency.figures import write_examples

    mask = np.zeros((40, 40), np.uint8)
    mask[10:30, 10:30] = 255
    ex = Example("x", np.full((40, 40, 3), (0, 0, 180), np.uint8), mask, {"m": mask})
    write_examples(tmp_path / "fig.png", [ex], ["m"])
    back = cv2.cvtColor(cv2.imread(str(tmp_path / "fig.png")), cv2.COLOR_BGR2RGB)
    np.testing.assert_array_equal(back, example_grid([ex], ["m"]))
