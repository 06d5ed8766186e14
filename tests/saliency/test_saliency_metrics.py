"""SOD metrics: PySODMetrics' golden values on its own data, agreement with pysodmetrics, hand-computed cases."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from sgf_plugins.saliency import metrics
from sgf_plugins.saliency.cli_sod_eval import evaluate_prediction_folder
from sgf_plugins.saliency.cli_sod_eval import run as sod_eval_run
from sgf_plugins.saliency.metrics import SodMetrics

from sgf_pipeline.errors import DataError

GOLDEN_KEYS = {
    "maxF": "maxFm",
    "meanF": "meanFm",
    "adpF": "adpFm",
    "mae": "MAE",
    "sm": "Smeasure",
    "maxEm": "maxEm",
    "meanEm": "meanEm",
    "adpEm": "adpEm",
}


def _golden(shared_data: Path) -> dict[str, float]:
    versions = json.loads((shared_data / "pysodmetrics" / "version_performance.json").read_text())
    # v1_4_0 and v1_4_3 hold the same classic values (v1_4_3 is what SOURCE.txt names); v1_2_3 differs
    # in the 7th digit of the S-measure (before a fix), the later keys hold other metrics only.
    for key in ("v1_4_0", "v1_3_0"):
        for ours, theirs in GOLDEN_KEYS.items():
            assert versions[key][theirs] == versions["v1_4_3"][theirs], (key, ours)
    return {ours: versions["v1_4_3"][theirs] for ours, theirs in GOLDEN_KEYS.items()}


def _pairs(shared_data: Path) -> list[tuple[np.ndarray, np.ndarray]]:
    root = shared_data / "pysodmetrics"
    out = []
    for mask in sorted((root / "masks").glob("*.png")):
        gt = cv2.imread(str(mask), cv2.IMREAD_GRAYSCALE)
        pred = cv2.imread(str(root / "preds" / mask.name), cv2.IMREAD_GRAYSCALE)
        out.append((pred, gt))
    return out


def test_golden_values_of_pysodmetrics(shared_data: Path) -> None:
    golden = _golden(shared_data)
    assert golden["maxF"] == pytest.approx(0.588678, abs=1e-6)
    assert golden["mae"] == pytest.approx(0.037056, abs=1e-6)
    result = metrics.evaluate_pairs(_pairs(shared_data))
    for key, value in golden.items():
        assert result[key] == pytest.approx(value, abs=1e-12), key


def test_sod_eval_writes_the_golden_values(shared_data: Path, tmp_path: Path) -> None:
    root = shared_data / "pysodmetrics"
    cfg = {"preds": {"pysod": str(root / "preds")}, "masks": str(root / "masks"), "models": []}
    sod_eval_run(cfg, tmp_path)
    written = json.loads((tmp_path / "sod_metrics.json").read_text())["pysod"]
    golden = _golden(shared_data)
    for key, value in golden.items():
        assert written[key] == pytest.approx(value, abs=1e-6), key
    assert written["em"] == written["meanEm"]
    assert written["fps"] is None
    assert written["images"] == 3


def test_console_script_prints_table_1(shared_data: Path, tmp_path: Path) -> None:
    root = shared_data / "pysodmetrics"
    exe = Path(sys.executable).with_name("sgf-sod-eval")
    proc = subprocess.run(
        [str(exe), f"+preds.golden={root / 'preds'}", f"masks={root / 'masks'}", f"hydra.run.dir={tmp_path}"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    line = next(row for row in proc.stdout.splitlines() if row.startswith("golden"))
    assert line.split()[1:5] == [".589", ".037", ".577", ".903"]  # F_m, M, F_A, S_m
    assert json.loads((tmp_path / "sod_metrics.json").read_text())["golden"]["sm"] == pytest.approx(0.902976, abs=1e-6)


def _random_case(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    h, w = (int(v) for v in rng.integers(5, 60, size=2))
    kind = rng.integers(0, 6)
    gt = np.zeros((h, w), np.uint8)
    if kind == 0:
        pass  # empty mask
    elif kind == 1:
        gt[:] = 255  # all salient
    elif kind == 2:
        gt = rng.choice([0, 64, 128, 129, 200, 255], size=(h, w)).astype(np.uint8)  # soft levels around 128
    else:
        y0, x0 = int(rng.integers(0, h)), int(rng.integers(0, w))
        gt[y0 : y0 + int(rng.integers(1, h)), x0 : x0 + int(rng.integers(1, w))] = 255
    if kind == 4:
        pred = np.full((h, w), int(rng.integers(0, 256)), np.uint8)  # constant: no min-max normalisation
    else:
        noise = rng.normal(0, 60, (h, w))
        pred = np.clip(gt.astype(float) * rng.uniform(0, 1) + noise + rng.uniform(-50, 50), 0, 255).astype(np.uint8)
    return pred, gt


@pytest.mark.filterwarnings("ignore::UserWarning", "ignore::RuntimeWarning")
def test_agrees_with_pysodmetrics_on_random_and_edge_cases() -> None:
    import py_sod_metrics

    rng = np.random.default_rng(7)
    for _ in range(25):
        cases = [_random_case(rng) for _ in range(int(rng.integers(1, 4)))]
        ref_f, ref_s, ref_e, ref_m = (
            py_sod_metrics.Fmeasure(),
            py_sod_metrics.Smeasure(),
            py_sod_metrics.Emeasure(),
            py_sod_metrics.MAE(),
        )
        ours = SodMetrics()
        for pred, gt in cases:
            for ref in (ref_f, ref_s, ref_e, ref_m):
                ref.step(pred=pred, gt=gt)
            ours.add(pred, gt)
        f, e = ref_f.get_results()["fm"], ref_e.get_results()["em"]
        got = ours.results()
        assert got["maxF"] == pytest.approx(f["curve"].max(), abs=1e-12)
        assert got["meanF"] == pytest.approx(f["curve"].mean(), abs=1e-12)
        assert got["adpF"] == pytest.approx(f["adp"], abs=1e-12)
        assert got["mae"] == pytest.approx(ref_m.get_results()["mae"], abs=1e-12)
        if np.isnan(ref_s.get_results()["sm"]):  # an empty S-measure quadrant: skipped here (weight 0)
            assert 0.0 <= got["sm"] <= 1.0
        else:
            assert got["sm"] == pytest.approx(ref_s.get_results()["sm"], abs=1e-12)
        assert got["maxEm"] == pytest.approx(e["curve"].max(), abs=1e-12)
        assert got["meanEm"] == pytest.approx(e["curve"].mean(), abs=1e-12)
        assert got["adpEm"] == pytest.approx(e["adp"], abs=1e-12)


def test_hand_computed_two_by_two() -> None:
    pred = np.array([[255, 0], [0, 0]], np.uint8)
    gt = np.array([[255, 0], [0, 0]], np.uint8)
    r = metrics.evaluate_pairs([(pred, gt)])
    # thresholds 255..1 select the salient pixel only (F = 1); threshold 0 selects all four:
    # P = 1/4, R = 1, F = 1.3 * 0.25 / (0.3 * 0.25 + 1)
    f_all = 1.3 * 0.25 / (0.3 * 0.25 + 1)
    assert r["maxF"] == 1.0
    assert r["meanF"] == pytest.approx((255 + f_all) / 256, abs=1e-15)
    assert r["mae"] == 0.0
    assert r["adpF"] == 1.0  # threshold 2 * mean = 0.5
    assert r["sm"] == pytest.approx(1.0, abs=1e-9)


def test_normalisation_and_conventions() -> None:
    pred = np.array([[100, 150], [200, 200]], np.uint8)
    gt = np.array([[0, 200], [128, 129]], np.uint8)
    p, g = metrics.prepare(pred, gt)
    assert p.min() == 0.0 and p.max() == 1.0  # per-image min-max
    assert g.tolist() == [[False, True], [False, True]]  # > 128
    assert metrics.BETA2 == 0.3 and metrics.THRESHOLDS == 256
    assert metrics.f_curve(p, g).shape == (256,)
    assert metrics.to_uint8(np.array([0.0, 0.5, 1.0])).tolist() == [0, 128, 255]
    with pytest.raises(ValueError, match="shape"):
        metrics.prepare(pred, gt[:1])
    with pytest.raises(TypeError):
        metrics.prepare(pred.astype(np.float32), gt)


def test_s_measure_skips_an_empty_quadrant() -> None:
    gt = np.zeros((5, 7), bool)
    gt[4, 5:7] = True  # centroid (row 4, col 5.5 -> 6): last row, so the lower quadrants are empty
    pred = gt.astype(np.float64)
    assert metrics.s_measure(pred, gt) == pytest.approx(1.0, abs=1e-9)  # a perfect prediction
    pred[0, 0] = 1.0
    assert 0.0 < metrics.s_measure(pred, gt) < 1.0


def test_table_layout() -> None:
    table = metrics.format_table(
        {"selfreformer": {"maxF": 0.953, "mae": 0.032, "meanF": 0.908, "sm": 0.92, "fps": 25.0, "images": 120}}
    )
    assert table.splitlines()[0].split()[-2:] == ["fps", "images"]
    row = table.splitlines()[2].split()
    assert row[:5] == ["selfreformer", ".953", ".032", ".908", ".920"]
    assert row[-2:] == ["25.0", "120"]


def test_prediction_folder_errors(shared_data: Path, tmp_path: Path) -> None:
    root = shared_data / "pysodmetrics"
    (tmp_path / "preds").mkdir()
    cv2.imwrite(str(tmp_path / "preds" / "0001.png"), np.zeros((4, 4), np.uint8))
    with pytest.raises(DataError, match="no prediction for 2 mask"):
        evaluate_prediction_folder(tmp_path / "preds", root / "masks")
    with pytest.raises(DataError, match="not found"):
        evaluate_prediction_folder(tmp_path / "nothing", root / "masks")
