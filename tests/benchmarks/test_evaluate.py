"""Smoke test of the evaluation harness (benchmarks/evaluate.py): a tiny run, its outputs, its ranks."""

import csv
import math
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def ev():
    from benchmarks import evaluate

    return evaluate


def test_rank_values_ties_and_nan(ev):
    assert ev.rank_values({"a": 0.3, "b": 0.1, "c": 0.2}) == {"a": 3.0, "b": 1.0, "c": 2.0}
    # ties share the mean of the ranks they span; NaN (undefined) comes last
    assert ev.rank_values({"a": 0.0, "b": 0.0, "c": 0.5, "d": float("nan")}) == {
        "a": 1.5,
        "b": 1.5,
        "c": 3.0,
        "d": 4.0,
    }


def test_rank_filters_orders_like_tables_6_7(ev):
    # Two cells; "apf" best everywhere but on bias, "sir" worst everywhere.
    def row(seq, n, f, rmse, disp, fail, bias):
        return {
            "sequence": seq,
            "N": n,
            "filter": f,
            "rmse": rmse,
            "dispersion": disp,
            "failure_rate": fail,
            "bias": bias,
            "seconds_per_frame": 0.1,
        }

    rows = [
        row("s", 100, "sir", 0.30, 0.10, 0.20, 0.10),
        row("s", 100, "apf", 0.10, 0.02, 0.00, 0.08),
        row("s", 100, "partitioned", 0.20, 0.05, 0.00, 0.02),
        row("s", 500, "sir", 0.25, 0.08, 0.10, 0.09),
        row("s", 500, "apf", 0.08, 0.01, 0.00, 0.06),
        row("s", 500, "partitioned", 0.15, 0.04, 0.05, 0.01),
    ]
    table = ev.rank_filters(rows)
    assert table["apf"]["rmse_rank"] == 1 and table["partitioned"]["rmse_rank"] == 2
    assert table["sir"]["rmse_rank"] == 3 and table["sir"]["overall"] == 3
    assert table["partitioned"]["bias_rank"] == 1 and table["apf"]["bias_rank"] == 2
    # failure: apf ranks 1.5 and 1, partitioned 1.5 and 2 -> apf 1, partitioned 2
    assert table["apf"]["failure_rate_rank"] == 1 and table["partitioned"]["failure_rate_rank"] == 2
    assert table["apf"]["mean_rank"] == pytest.approx((1 + 1 + 1 + 2) / 4)
    assert table["apf"]["rmse"] == pytest.approx(0.09) and table["apf"]["cells"] == 2
    md = ev.ranking_markdown(table, "t")
    lines = [ln for ln in md.splitlines() if ln.startswith("| ") and "Filter" not in ln]
    assert [ln.split("|")[1].strip() for ln in lines] == ["APF", "PARTITIONED", "CONDENSATION"]


def test_tiny_protocol_run_and_outputs(ev, tmp_path):
    cfg = ev.EvalConfig(
        sequences=("generator:wave",),
        filters=("sir", "apf", "partitioned"),
        particles=(30, 60),
        runs=2,
        frames=3,
        mask_size=(40, 30),
        dynamics="table5",
    )
    result = ev.run_benchmark(cfg)
    (name,) = result.sequences
    assert result.sequences[name]["frames"] == 3
    runs = [r for r in result.rows if r["kind"] == "run"]
    agg = result.aggregates()
    assert len(runs) == 3 * 2 * 2 and len(agg) == 3 * 2
    assert len(result.frame_rows) == len(runs) * 3
    for r in agg:
        assert r["evaluations"] <= r["N"] and r["run"] == "all"
        assert 0.0 <= r["failure_rate"] <= 1.0 and r["dispersion"] >= 0.0
        assert 0.0 < r["rmse"] < 1.0 and r["bias"] <= r["rmse"] + 1e-9  # bias <= RMSE (Jensen)
    apf = next(r for r in agg if r["filter"] == "apf" and r["N"] == 60)
    assert apf["particles"] == 20 and apf["evaluations"] == 60  # 3 layers of N/3
    assert all(math.isnan(r["dispersion"]) for r in runs)  # eq. 5 needs several runs

    paths = ev.write_outputs(result, tmp_path / "out", plots=True)
    for key in ("table", "results", "frames", "config", f"fig8_{name}", f"fig15_{name}"):
        assert paths[key].is_file() and paths[key].stat().st_size > 0, key
    with open(paths["results"], newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == len(result.rows)
    assert {"sequence", "filter", "N", "run", "rmse", "bias", "dispersion", "failure_rate"} <= set(rows[0])
    table = paths["table"].read_text()
    assert "| Filter |" in table and "PARTITIONED" in table and "Mean rank" in table


def test_cli_presets_and_errors(ev):
    parser = ev.build_parser()
    cfg = ev.config_from_args(parser.parse_args(["--quick", "--runs", "3"]))
    assert cfg.runs == 3 and cfg.particles == ev.QUICK["particles"]  # explicit values beat the preset
    cfg = ev.config_from_args(parser.parse_args(["--full", "--filters", "sir,apf"]))
    assert cfg.particles == (100, 250, 500, 1000, 1500) and cfg.filters == ("sir", "apf")
    with pytest.raises(ValueError, match="unknown filter"):
        ev.EvalConfig(filters=("kalman",))
    with pytest.raises(ValueError, match="unknown sequence source"):
        ev.sequence_specs(ev.EvalConfig(sequences=("youtube",)))


def test_treadmill_removes_drift(ev):
    from torchpf import Skeleton
    from torchpf.assets import path
    from training.synthetic import generate

    skel = Skeleton.from_urdf(path("human.urdf"))
    angles = generate("walk", 20, 15.0, seed=0).angles
    out = ev.treadmill(skel, angles)
    root = skel.fk(out)[:, 0]
    assert root[:, :2].abs().max() < 0.15  # walked ~1.3 m, now in place
    torch.testing.assert_close(root[:, 2], skel.fk(angles)[:, 0, 2])  # the vertical bob is kept
