"""A large ``--batch-size`` at a large size: ``estimate --pairs`` and ``eval`` run each size's pairs in batches of
at most the pipeline's chunk of pixels, and let each batch's result go before the next runs (an audit: the result
of a whole batch, merged over the pipeline's chunks, was held until every pair was reported: four 3000 x 2000
pairs took 2.9 GB where one took 1.2 GB). The lines printed do not change."""

from __future__ import annotations

import gc
import json
import weakref

import pytest
from real_images import PAIRS

import svs_torch.pipeline
from svs_torch.cli import main
from svs_torch.data import read_pair_sources
from svs_torch.evaluation import runner
from svs_torch.evaluation.runner import EvalSetup, evaluate_pairs
from svs_torch.pipeline import run as pipeline_run

SIZE_WH = (64, 48)


class _Spy:
    """Wraps ``estimate_obstacle_depth``: the pairs of each call, and whether an earlier call's result was still
    alive when a later call began."""

    def __init__(self, real) -> None:
        self.real, self.pairs, self.results, self.held = real, [], [], 0

    def __call__(self, batch, config, *args, **kwargs):
        gc.collect()
        self.held = max(self.held, sum(ref() is not None for ref in self.results))
        self.pairs.append(batch.batch_size)
        result = self.real(batch, config, *args, **kwargs)
        self.results.append(weakref.ref(result))
        return result


def _spy(monkeypatch, *modules) -> _Spy:
    spy = _Spy(svs_torch.pipeline.estimate_obstacle_depth)
    for module in modules:
        monkeypatch.setattr(module, "estimate_obstacle_depth", spy)
    monkeypatch.setattr(pipeline_run, "CHUNK_PIXELS", 2 * SIZE_WH[0] * SIZE_WH[1])  # two pairs a chunk
    return spy


def _estimate_lines(capsys, listing) -> list[dict]:
    code = main(["estimate", "--pairs", str(listing), "--workers", "1", "--batch-size", "5",
                 "--size", f"{SIZE_WH[0]}x{SIZE_WH[1]}", "--json"])
    assert code == 0
    return [{k: v for k, v in json.loads(line).items() if k != "time_s"}
            for line in capsys.readouterr().out.splitlines()]


def test_estimate_pairs_runs_a_large_batch_a_chunk_at_a_time(data_dir, capsys, tmp_path, monkeypatch):
    listing = tmp_path / "pairs.txt"
    listing.write_text("".join(f"{data_dir / left} {data_dir / right}\n" for left, right in PAIRS[:5]))
    want = _estimate_lines(capsys, listing)
    spy = _spy(monkeypatch, svs_torch.pipeline)
    assert _estimate_lines(capsys, listing) == want
    assert spy.pairs == [2, 2, 1] and spy.held == 0


def test_eval_runs_a_large_batch_a_chunk_at_a_time(data_dir, monkeypatch):
    scenes = ["middlebury_eval3_Q/Teddy", "middlebury_eval3_Q/Piano", "middlebury_eval3_Q/ArtL"]
    sources = read_pair_sources([data_dir / scene for scene in scenes])
    setup = EvalSetup(size_wh=SIZE_WH)

    def rows():
        return [{k: v for k, v in vars(e).items() if k != "time_s"} for _, e in evaluate_pairs(sources, setup, 3)]

    want = rows()
    spy = _spy(monkeypatch, runner)
    assert rows() == want
    assert spy.pairs == [2, 1] and spy.held == 0


@pytest.fixture(autouse=True)
def _no_warm_up(monkeypatch):
    """No untimed warm-up run among the calls counted."""
    monkeypatch.setattr(runner, "_WARMED_UP", True)


def test_the_pixel_limit_holds_for_every_listed_pair_and_is_said_once(data_dir, capsys, tmp_path, monkeypatch):
    """The 16-megapixel limit (lowered here to Teddy's size less one pixel) held for estimate's plain listed
    pairs only: a scene folder or a line with its own calibration ran at any size (6000x4000: 3.7 GB), eval ran
    every pair at any size (3.9 GB) and took --size 8192x8192, and estimate --pairs refused an over-size --size
    once per listed pair, after the list's last line (an audit of large frames)."""
    from svs_torch.cli import features

    teddy = data_dir / "middlebury_eval3_Q" / "Teddy"
    listing = tmp_path / "pairs.txt"
    listing.write_text(f"{teddy}\n{teddy / 'im0.png'} {teddy / 'im1.png'} 1000 0.1\n")
    width, height = 450, 375
    monkeypatch.setattr(features, "MAX_PIXELS", width * height - 1)
    monkeypatch.setattr("svs_torch.cli.evaluate.MAX_PIXELS", width * height - 1, raising=False)
    code = main(["estimate", "--pairs", str(listing), "--workers", "1", "--json"])
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    reason = f"left: expected at most 0 megapixels, got {width}x{height} (resample it with --size)"
    assert code == 2 and [line["status"] for line in lines] == ["BAD_INPUT"] * 2
    assert all(line["reason"].startswith(reason) for line in lines)
    code = main(["eval", str(teddy), "--json"])
    row = json.loads(capsys.readouterr().out.splitlines()[0])
    assert code == 0 and (row["status"], row["reason"]) == ("BAD_INPUT", reason)
    for command in (["estimate", "--pairs", str(listing), "--workers", "1"], ["eval", str(teddy)]):
        code = main([*command, "--size", "450x375"])
        out, err = capsys.readouterr()
        assert (code, out) == (2, "") and err.endswith("error: --size: expected at most 0 megapixels, got '450x375'\n")


def test_a_sweep_keeps_the_pixel_limit_of_eval(data_dir, capsys, tmp_path, monkeypatch):
    """An audit of sweep: the limit above (lowered the same way) did not hold for sweep: its file's size =
    "8192x8192" was taken, and at the native size a pair over the limit ran at any size (3.9 GB a 6000x4000 pair, in
    every worker). Now that size fails before any work, and such a pair is BAD_INPUT, as in eval."""
    import csv
    import io

    from svs_torch.cli import features

    teddy = data_dir / "middlebury_eval3_Q" / "Teddy"
    width, height = 450, 375
    monkeypatch.setattr(features, "MAX_PIXELS", width * height - 1)
    sweep_file, store = tmp_path / "sweep.toml", tmp_path / "s.sqlite"
    sweep_file.write_text(f'paths = ["{teddy}"]\nsize = "450x375"\n')
    assert main(["sweep", str(sweep_file), "--db", str(store), "--workers", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].endswith(f"{sweep_file}: size: expected at most 0 megapixels, got '450x375'")
    assert not store.exists()
    sweep_file.write_text(f'paths = ["{teddy}"]\n')  # its native size
    assert main(["sweep", str(sweep_file), "--db", str(store), "--workers", "0"]) == 0
    capsys.readouterr()
    assert main(["results", str(store), "--csv"]) == 0
    row = next(csv.DictReader(io.StringIO(capsys.readouterr().out)))
    # The sweep's own setting named, not eval's --size, which sweep does not take (an audit).
    assert (row["status"], row["reason"]) == ("BAD_INPUT", f"left: expected at most 0 megapixels, got {width}x{height} "
                                                           "(resample it with the sweep file's size = \"WxH\")")


def test_upsample_past_the_pixel_limit_is_warned_of_once(data_dir, capsys, monkeypatch):
    """--upsample detects on the pair enlarged twice: 3000x2000 took 3.0 GB with it and 1.2 GB without, and a
    16-megapixel pair about 7.7 GB, without a word before the process was killed (an audit). Over the limit (here
    lowered to just under a 64x48 pair enlarged) it is said once, with the way out; not without --upsample."""
    from svs_torch.cli import features

    monkeypatch.setattr(features, "MAX_PIXELS", 4 * SIZE_WH[0] * SIZE_WH[1] - 1)
    monkeypatch.setattr(features, "_UPSAMPLE_WARNED", [], raising=False)
    left, right = (str(data_dir / p) for p in PAIRS[0])
    size = ["--size", f"{SIZE_WH[0]}x{SIZE_WH[1]}"]
    for command in (["features", left, right, "--no-segment", *size, "--json"], ["estimate", left, right, *size]):
        assert main([*command, "--no-upsample"]) == 0
        assert "--upsample" not in capsys.readouterr().err
        assert main([*command, "--upsample"]) == 0
        err = capsys.readouterr().err
        assert err.count("warning: --upsample detects on the 64x48 pair enlarged to 128x96") == 1, err
        assert "--no-upsample or a smaller --size keep it down" in err
        monkeypatch.setattr(features, "_UPSAMPLE_WARNED", [])


def test_eval_lets_each_row_go_once_printed_and_stored(data_dir, capsys, tmp_path, monkeypatch):
    """An audit of bulk runs: eval held every row to its end for the summary, the calibration lines and the note of
    the rows a --db store kept (about 4.4 kB a pair, held whether or not the store had them already). Each row now
    goes once printed and stored: when a block runs, no row of the blocks before the last is alive; the output, the
    second run's note of the rows the store kept included, does not change."""
    scenes = [str(data_dir / "middlebury_eval3_Q" / name) for name in ("Teddy", "ArtL", "Piano", "Pipes")]
    real, rows, held = runner.run_loaded, [], []

    def spy(pairs, config, on_result=None):
        gc.collect()
        held.append(sum(ref() is not None for ref in rows[:-1]))  # all but the last row printed (the loop's name)
        evaluations = real(pairs, config, on_result)
        rows.extend(weakref.ref(e) for e in evaluations)
        return evaluations

    store = tmp_path / "runs.sqlite"
    argv = ["eval", *scenes, "--size", f"{SIZE_WH[0]}x{SIZE_WH[1]}", "--batch-size", "1", "--db", str(store), "--json"]

    def run() -> tuple[list[dict], str]:
        assert main(argv) == 0
        out, err = capsys.readouterr()
        lines = [json.loads(line) for line in out.splitlines()]
        timed = ("time_s", "pairs_per_s", "pipeline_s_per_pair")
        return ([{k: v for k, v in line.items() if k not in timed} for line in lines],
                "".join(line for line in err.splitlines(True) if not line.startswith("eval: ")))  # (progress: timed)

    want, _ = run()
    assert want[-1]["pairs"] == 4 and "db_rows_kept" not in want[-1]
    again, err = run()
    assert again[:-1] == want[:-1] and again[-1] == {**want[-1], "db_rows_kept": 4, "db_rows_kept_differing": 0}
    assert "4 of 4 pairs had rows in" in err
    monkeypatch.setattr(runner, "run_loaded", spy)
    assert run() == (again, err)
    assert len(rows) == 4 and held == [0, 0, 0, 0], held
