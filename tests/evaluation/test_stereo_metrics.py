"""The Middlebury / KITTI stereo metrics (svs_torch.evaluation.stereo_metrics).

The reference below is written from the data sets' documentation (MiddEval3 SDK ``evaldisp.cpp`` and its README:
bad-t, avgerr, rms, A-quantiles; KITTI 2015 devkit: D1 = error > 3 px and > 5 %; MANIFEST §2 for the files),
one pair at a time in numpy, reading the files with its own PFM parser and OpenCV; the estimates are OpenCV
StereoSGBM's maps of the real pairs, so the errors have a real distribution.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from svs_torch import InputError
from svs_torch.data import collate_stereo_batches, load_stereo_pair, resize_stereo_batch
from svs_torch.evaluation import measure_stereo_metrics
from svs_torch.evaluation.stereo_metrics import metric_values


def _read_pfm(path) -> np.ndarray:
    """MANIFEST §2: 'Pf', 'W H', a negative scale for little-endian float32, rows bottom to top."""
    with open(path, "rb") as handle:
        assert handle.readline().strip() == b"Pf"
        width, height = (int(v) for v in handle.readline().split())
        scale = float(handle.readline())
        data = np.frombuffer(handle.read(), dtype="<f4" if scale < 0 else ">f4", count=width * height)
    return np.flipud(data.reshape(height, width)).copy()


def _reference(d, d_ok, gt, gt_ok, mask, scale=1.0) -> dict:
    """One pair's metrics from the definitions, in numpy (errors in float32 as the maps are)."""
    evaluated = gt_ok & mask
    covered = evaluated & d_ok
    error = (np.abs(d[covered].astype(np.float32) - gt[covered].astype(np.float32)) * np.float32(scale))
    truth = np.abs(gt[covered]).astype(np.float32) * np.float32(scale)
    out = {"num_px": int(evaluated.sum()), "density": covered.sum() / evaluated.sum()}
    for t, key in ((0.5, "bad0_5_pct"), (1, "bad1_pct"), (2, "bad2_pct"), (4, "bad4_pct")):
        out[key] = 100.0 * np.mean(error > t)
    out["avgerr_px"] = float(np.mean(error.astype(np.float64)))
    out["rms_px"] = float(np.sqrt(np.mean(error.astype(np.float64) ** 2)))
    for q in (50, 90, 95, 99):
        out[f"a{q}_px"] = float(np.quantile(error, q / 100, method="inverted_cdf"))
    out["d1_pct"] = 100.0 * np.mean((error > 3) & (error > 0.05 * truth))
    return out


def _sgbm(left_path, right_path) -> tuple[np.ndarray, np.ndarray]:
    left = cv2.imread(str(left_path), cv2.IMREAD_GRAYSCALE)
    right = cv2.imread(str(right_path), cv2.IMREAD_GRAYSCALE)
    matcher = cv2.StereoSGBM_create(minDisparity=0, numDisparities=96, blockSize=5, uniquenessRatio=10)
    raw = matcher.compute(left, right)
    return raw.astype(np.float32) / 16.0, raw >= 0  # OpenCV marks unknown with minDisparity - 1 (x16)


def _real_cases(data_dir):
    """(name, estimate, estimate valid, GT, GT valid, non-occluded or None) of three real pairs."""
    cases = []
    for scene in ("Teddy", "ArtL"):
        folder = data_dir / "middlebury_eval3_Q" / scene
        gt = _read_pfm(folder / "disp0GT.pfm")
        nocc = cv2.imread(str(folder / "mask0nocc.png"), cv2.IMREAD_UNCHANGED) == 255
        cases.append((f"eval3/{scene}", *_sgbm(folder / "im0.png", folder / "im1.png"), np.where(
            np.isfinite(gt), gt, 0), np.isfinite(gt), nocc))
    root = data_dir / "kitti" / "stereo2012_training"
    raw = cv2.imread(str(root / "disp_occ" / "000000_10.png"), cv2.IMREAD_UNCHANGED)
    cases.append(("kitti2012/000000_10", *_sgbm(root / "colored_0" / "000000_10.png",
                                                 root / "colored_1" / "000000_10.png"),
                  raw.astype(np.float32) / 256, raw > 0, None))
    return cases


def _padded(arrays, fill, height, width):
    out = []
    for array in arrays:
        padded = np.full((height, width), fill, dtype=array.dtype)
        padded[:array.shape[0], :array.shape[1]] = array
        out.append(padded)
    return torch.from_numpy(np.stack(out))[:, None]


def _check(metrics, index, expected):
    values = metric_values(metrics, index)
    assert values["num_px"] == expected["num_px"]
    for key, value in expected.items():
        assert values[key] == pytest.approx(value, rel=1e-5, abs=1e-5), key


def test_batched_metrics_equal_a_numpy_reference_on_real_ground_truth(data_dir):
    cases = _real_cases(data_dir)
    height = max(c[1].shape[0] for c in cases)
    width = max(c[1].shape[1] for c in cases)
    d = _padded([c[1] for c in cases], 0.0, height, width)
    d_ok = _padded([c[2] for c in cases], False, height, width)
    gt = _padded([c[3] for c in cases], 0.0, height, width)
    gt_ok = _padded([c[4] for c in cases], False, height, width)
    nocc = _padded([c[5] if c[5] is not None else np.zeros_like(c[4]) for c in cases], False, height, width)
    scale = torch.tensor([1.0, 2.0, 1.0])  # the second pair as if its map had half the GT's resolution
    every = measure_stereo_metrics(d, d_ok, gt, gt_ok, None, scale)
    nonoccluded = measure_stereo_metrics(d, d_ok, gt, gt_ok, nocc, scale)
    for i, (name, est, est_ok, truth, truth_ok, nocc_np) in enumerate(cases):
        _check(every, i, _reference(est, est_ok, truth, truth_ok, np.ones_like(truth_ok), float(scale[i])))
        if nocc_np is not None:
            _check(nonoccluded, i, _reference(est, est_ok, truth, truth_ok, nocc_np, float(scale[i])))
        else:  # KITTI's shared copy has no non-occluded GT: nothing is evaluated there
            assert metric_values(nonoccluded, i) == dict.fromkeys(metric_values(nonoccluded, i))
    # Sanity of the real numbers: SGBM is decent on Teddy (MiddEval3 SGBM bad-2 nocc is about 10-20 %).
    assert 0.5 < float(nonoccluded.density[0]) <= 1 and 2 < float(nonoccluded.bad_pct[0, 2]) < 40


def test_hand_made_case_with_known_answers():
    # GT 20 everywhere but one pixel of 100; the estimate's errors are 0, 0.6, 1, 1.5, 3.5 (at GT 20: a D1
    # outlier, 3.5 > 3 and > 1) and 3.5 at GT 100 (not one: 3.5 < 5); one pixel is unknown and one has no GT.
    gt = torch.tensor([[20.0, 20.0, 20.0, 20.0], [100.0, 20.0, 20.0, 0.0]]).view(1, 1, 2, 4)
    gt_ok = torch.tensor([[True, True, True, True], [True, True, True, False]]).view(1, 1, 2, 4)
    d = torch.tensor([[20.0, 20.6, 21.0, 18.5], [103.5, 23.5, 0.0, 7.0]]).view(1, 1, 2, 4)
    d_ok = torch.tensor([[True, True, True, True], [True, True, False, True]]).view(1, 1, 2, 4)
    m = measure_stereo_metrics(d, d_ok, gt, gt_ok)
    values = metric_values(m, 0)
    assert values["num_px"] == 7 and values["density"] == pytest.approx(6 / 7)
    # errors over the 6 covered pixels: 0, 0.6, 1, 1.5, 3.5, 3.5
    assert values["bad0_5_pct"] == pytest.approx(500 / 6)
    assert values["bad1_pct"] == pytest.approx(300 / 6)  # 1.0 is not > 1
    assert values["bad2_pct"] == pytest.approx(200 / 6)
    assert values["bad4_pct"] == 0
    assert values["avgerr_px"] == pytest.approx(10.1 / 6, rel=1e-6)
    assert values["rms_px"] == pytest.approx(np.sqrt((0.36 + 1 + 2.25 + 12.25 * 2) / 6), rel=1e-6)
    assert (values["a50_px"], values["a90_px"], values["a99_px"]) == pytest.approx((1.0, 3.5, 3.5))
    assert values["d1_pct"] == pytest.approx(100 / 6)
    # At half the GT's resolution errors and true disparities double in native pixels (0, 1.2, 2, 3, 7, 7 at
    # 40 / 200 px): bad-1 gains 1.2 and 2; D1 still only the one at 40 px (7 > 3 and > 2; 7 < 10 at 200 px).
    half = metric_values(measure_stereo_metrics(d, d_ok, gt, gt_ok, px_scale=torch.tensor([2.0])), 0)
    assert half["bad1_pct"] == pytest.approx(500 / 6) and half["avgerr_px"] == pytest.approx(20.2 / 6, rel=1e-6)
    assert half["d1_pct"] == pytest.approx(100 / 6)


def test_nothing_covered_and_nothing_evaluated():
    gt = torch.full((2, 1, 3, 3), 10.0)
    gt_ok = torch.tensor([True, False]).view(2, 1, 1, 1).expand(2, 1, 3, 3)
    m = measure_stereo_metrics(gt.clone(), torch.zeros_like(gt_ok), gt, gt_ok)
    assert metric_values(m, 0) == dict(dict.fromkeys(metric_values(m, 0)), num_px=9, density=0.0)
    assert metric_values(m, 1) == dict.fromkeys(metric_values(m, 1))


def test_gradients_of_the_mean_and_rms_are_finite_where_a_pair_is_exact():
    """Found by the gradient docstring audit: a pair whose RMS is 0 (an exact map, or nothing covered) put NaN into
    the whole batch's gradient (sqrt's infinite derivative at 0 times a zero upstream), even when only another
    pair's RMS was differentiated. Its subgradient is 0; elsewhere the gradient is the analytic one."""
    generator = torch.Generator().manual_seed(0)
    truth = torch.rand(3, 1, 6, 7, generator=generator, dtype=torch.float64) * 20
    noise = torch.rand(3, 1, 6, 7, generator=generator, dtype=torch.float64) - 0.5
    noise[0] = 0.0  # pair 0 exact
    estimate = (truth + noise).requires_grad_(True)
    known = torch.ones_like(truth, dtype=torch.bool)
    covered = known.clone()
    covered[2] = False  # pair 2 covers nothing
    metrics = measure_stereo_metrics(estimate, covered, truth, known)
    assert metrics.rms_px[0] == 0 and metrics.rms_px[2] == 0
    (metrics.rms_px[1] + metrics.avgerr_px.sum()).backward()
    assert torch.isfinite(estimate.grad).all()
    n = truth[1].numel()
    expected_rms = noise[1] / (n * noise[1].square().mean().sqrt())  # d sqrt(mean e²) / d e
    torch.testing.assert_close(estimate.grad[1], expected_rms + noise[1].sign() / n)
    torch.testing.assert_close(estimate.grad[0], torch.zeros_like(truth[0]))  # |e|' at 0 is 0 in torch, and rms 0
    torch.testing.assert_close(estimate.grad[2], torch.zeros_like(truth[2]))


def test_padding_and_other_pairs_change_nothing(data_dir):
    teddy = load_stereo_pair(data_dir / "middlebury_eval3_Q" / "Teddy")
    kitti = load_stereo_pair(data_dir / "kitti" / "stereo2012_training")
    generator = torch.Generator().manual_seed(3)

    def noisy(batch):
        noise = torch.randn(batch.disparity_px.shape, generator=generator) * 1.5
        return batch.disparity_px + noise, batch.disparity_valid

    est, ok = noisy(teddy)
    alone = measure_stereo_metrics(est, ok, teddy.disparity_px, teddy.disparity_valid,
                                   teddy.disparity_nonoccluded)
    both = collate_stereo_batches([teddy, kitti], mode="pad")
    h, w = teddy.size_hw
    padded_est = torch.zeros_like(both.disparity_px)
    padded_est[0, :, :h, :w] = est[0]
    padded_est[1] = noisy(both.select([1]))[0][0]
    # Padding is marked valid in the estimate on purpose: the GT's padding (False) must keep it out.
    together = measure_stereo_metrics(padded_est, torch.ones_like(both.disparity_valid), both.disparity_px,
                                      both.disparity_valid, both.disparity_nonoccluded)
    assert metric_values(together, 0) == metric_values(alone, 0)
    assert metric_values(together, 1)["num_px"] is None  # no non-occluded GT for the KITTI copy


def test_loaders_give_the_non_occluded_mask(data_dir):
    folder = data_dir / "middlebury_eval3_Q" / "Teddy"
    batch = load_stereo_pair(folder)
    mask = cv2.imread(str(folder / "mask0nocc.png"), cv2.IMREAD_UNCHANGED)
    expected = (mask == 255) & np.isfinite(_read_pfm(folder / "disp0GT.pfm"))
    assert np.array_equal(batch.disparity_nonoccluded[0, 0].numpy(), expected)
    assert 0.8 < expected.mean() < 0.95  # 128 (occluded) and 0 (no GT) are the rest
    assert load_stereo_pair(data_dir / "middlebury_2003_quarter" / "Teddy").disparity_nonoccluded is None
    small = resize_stereo_batch(batch, (225, 188))
    assert small.disparity_nonoccluded.shape == small.disparity_valid.shape
    assert bool((small.disparity_nonoccluded <= small.disparity_valid).all())
    assert bool(small.disparity_nonoccluded[0, 0, ::2, ::2].float().mean() > 0.8)


@pytest.mark.parametrize("change, message", [
    (lambda a: dict(a, disparity_px=a["disparity_px"][0]), "disparity_px: expected"),
    (lambda a: dict(a, valid=a["valid"].float()), "valid: expected a bool"),
    (lambda a: dict(a, mask=a["mask"][:, :, :2]), "mask: expected"),
    (lambda a: dict(a, truth_px=a["truth_px"].long()), "truth_px: expected a float"),
    (lambda a: dict(a, disparity_px=a["disparity_px"].index_fill(3, torch.tensor([1]), float("nan"))),
     "disparity_px: expected finite values where valid"),
    (lambda a: dict(a, px_scale=torch.tensor([1.0, -2.0])), "px_scale: expected finite positive"),
    (lambda a: dict(a, px_scale=torch.tensor([1.0])), r"px_scale: expected \(2\)"),
])
def test_bad_input_is_named(change, message):
    arguments = {"disparity_px": torch.ones(2, 1, 3, 4), "valid": torch.ones(2, 1, 3, 4, dtype=torch.bool),
                 "truth_px": torch.ones(2, 1, 3, 4), "truth_valid": torch.ones(2, 1, 3, 4, dtype=torch.bool),
                 "mask": torch.ones(2, 1, 3, 4, dtype=torch.bool), "px_scale": torch.ones(2)}
    with pytest.raises(InputError, match=message):
        measure_stereo_metrics(**change(arguments))


def test_eval_rows_store_csv_and_export_agree_with_a_reference(data_dir, tmp_path, capsys):
    import csv
    import io
    import json

    from svs_torch.cli import main

    teddy = data_dir / "middlebury_eval3_Q" / "Teddy"
    kitti = data_dir / "kitti" / "stereo2012_training" / "colored_0" / "000000_10.png"
    db = tmp_path / "eval.sqlite"
    code = main(["eval", str(teddy), str(kitti), "--size", "160x120", "--json", "--db", str(db),
                 "--disparity-out", str(tmp_path / "maps")])
    rows = [json.loads(line) for line in capsys.readouterr().out.strip().splitlines()]
    summary, rows = rows[-1], rows[:-1]
    assert code == 0 and [r["status"] for r in rows] == ["OK", "OK"] and not rows[0]["rectified"]
    assert rows[0]["metric_px_scale"] == pytest.approx(450 / 160)
    assert rows[1]["kept_nocc_density"] is None and rows[1]["kept_all_d1_pct"] is not None  # KITTI: no noc GT
    assert summary["kept_nocc_pairs"] == 1 and summary["kept_all_pairs"] == 2
    # Each object's own metrics (all GT over its region): fewer pixels than the kept regions together.
    objects = rows[0]["objects"]
    assert objects and all(0 < o["num_px"] <= rows[0]["kept_all_num_px"] and o["bad2_pct"] is not None
                           for o in objects)
    assert sum(o["num_px"] for o in objects) <= rows[0]["kept_all_num_px"]
    # The exported 160x120 map of Teddy against the native GT sampled as the loader does (nearest pixel
    # centres), errors scaled to native pixels: the row's whole-frame metrics.
    pfm = _read_pfm(tmp_path / "maps" / "Teddy" / "disp0SVSTorch.pfm")
    gt = _read_pfm(teddy / "disp0GT.pfm")
    rows_index = ((np.arange(120) + 0.5) * gt.shape[0] / 120).astype(int)
    cols_index = ((np.arange(160) + 0.5) * gt.shape[1] / 160).astype(int)
    small = gt[rows_index][:, cols_index]
    known = np.isfinite(small)
    small = np.where(known, small, 0).astype(np.float32) * np.float32(160 / 450)
    expected = _reference(np.where(np.isfinite(pfm), pfm, 0), np.isfinite(pfm), small, known,
                          np.ones_like(known), 450 / 160)
    one_pixel = 100.0 / (expected["num_px"] * expected["density"])  # a float tie may flip one pixel
    for key, value in expected.items():
        assert rows[0][f"map_all_{key}"] == pytest.approx(value, rel=1e-4, abs=one_pixel if "pct" in key
                                                           else 1e-4), key
    # The store keeps every value and results --csv exports it.
    assert main(["results", str(db), "--csv"]) == 0
    table = list(csv.DictReader(io.StringIO(capsys.readouterr().out)))
    by_name = {row["name"]: row for row in table}
    for key in ("kept_nocc_bad2_pct", "kept_all_a90_px", "map_all_d1_pct", "map_nocc_density"):
        assert float(by_name["eval3/Teddy"][key]) == pytest.approx(rows[0][key], rel=1e-12)
    assert by_name["kitti2012/000000_10"]["kept_nocc_bad2_pct"] == ""


def test_an_older_results_file_gets_the_new_columns(tmp_path):
    import sqlite3

    from svs_torch.evaluation.store import ResultStore

    with ResultStore(tmp_path / "old.sqlite"):
        pass
    connection = sqlite3.connect(tmp_path / "old.sqlite")
    for name in ("kept_all_d1_pct", "metric_px_scale"):  # as a file written before these columns existed
        connection.execute(f'ALTER TABLE results DROP COLUMN "{name}"')
    connection.commit()
    connection.close()
    def columns() -> set[str]:
        with ResultStore(tmp_path / "old.sqlite", create=False) as store:
            return {row[1] for row in store.connection.execute("PRAGMA table_info(results)")}

    assert "kept_all_d1_pct" not in columns()  # opened to read: left as it is
    with ResultStore(tmp_path / "old.sqlite"):  # opened to write
        pass
    assert {"kept_all_d1_pct", "metric_px_scale"} <= columns()


def test_a_sweep_stores_the_metrics(data_dir, tmp_path, capsys):
    from svs_torch.cli import main
    from svs_torch.evaluation.store import ResultStore

    sweep = tmp_path / "sweep.toml"
    sweep.write_text(f'paths = ["{data_dir / "middlebury_eval3_Q" / "Teddy"}"]\nsize = "160x120"\n'
                     '[grid]\n"dense.window_size" = [7, 9]\n')
    code = main(["sweep", str(sweep), "--db", str(tmp_path / "s.sqlite"), "--workers", "0"])
    capsys.readouterr()
    assert code == 0
    with ResultStore(tmp_path / "s.sqlite", create=False) as store:
        rows = store.results()
    assert len(rows) == 2 and all(0 < row["kept_nocc_density"] <= 1 and row["kept_nocc_bad2_pct"] is not None
                                  and row["metric_px_scale"] == pytest.approx(450 / 160) for row in rows)
    assert rows[0]["kept_all_avgerr_px"] != rows[1]["kept_all_avgerr_px"]  # two windows, two maps
