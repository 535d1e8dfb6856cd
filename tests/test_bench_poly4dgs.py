"""Smoke test of ``bench/bench_poly4dgs.py``: every method runs on a tiny capture and reports its
figures beside the floors, with the library's protocol and production's initial points, and the
region figures per camera role with a held-out tracking camera (~50 s)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "bench"


@pytest.fixture(scope="module")
def bench():
    sys.path.insert(0, str(BENCH))
    try:
        import bench_poly4dgs

        yield bench_poly4dgs
    finally:
        sys.path.remove(str(BENCH))


def test_cap_leaves_room_for_growth(bench):
    from volcap_core.splat.train import TrainConfig, init_budget

    for n in (1, 7, 3000, 30_000, 12_345):
        cap = bench.cap_for(n)
        assert cap > n
        cfg = TrainConfig(mcmc=bench.mcmc_for(360, cap))
        assert init_budget(cfg) == n


@pytest.mark.slow
def test_quick_run_reports_floors(bench, tmp_path, capsys):
    out = tmp_path / "bench.json"
    sheet = tmp_path / "sheet.png"
    rc = bench.main(["--quick", "--steps", "16", "--capture", str(tmp_path / "capture"),
                     "--json", str(out), "--sheet", str(sheet), "--plot", str(tmp_path / "p.png")])
    assert rc == 0
    printed = capsys.readouterr().out
    assert "Floors on the same held-out views" in printed
    assert "floors empty / initial" in printed
    assert sheet.stat().st_size > 1000
    got = json.loads(out.read_text())
    empty = got["floors"]["empty"]
    assert empty["psnr_performers"] is not None          # masks reached the scorer
    assert empty["psnr_raw"] < empty["psnr"]             # black render: the offset fit helps
    res = got["results"]
    assert set(res) == set(bench.METHODS)
    for name, r in res.items():
        curve = r["curve"]
        assert curve[0]["step"] == 0 and curve[-1]["step"] > 0
        assert got["floors"]["initial"][name] == curve[0]
        for c in curve:
            for k in ("psnr", "ssim", "psnr_raw", "psnr_performers", "ssim_performers"):
                assert c[k] is not None
    # production's initialisation: a static pool (scan + persistent points) shared by the segment
    assert res["full"]["init_static"] > res["full"]["init_gaussians"] // 2
    assert res["full"]["cap"] > res["full"]["init_gaussians"]
    # w/o dense points: 2 % of the frames' points and no scan
    assert res["sparse"]["init_gaussians"] < 0.05 * res["full"]["init_gaussians"]
    assert res["full"]["training"]["views"] > 0
    # issue 28: a tracking camera held out too, and score_segment's region figures per camera role
    # for every run and both floors on the same pixels (the bench warns when they differ from it)
    assert "S010 tracking" in printed and "WARNING: score_segment" not in printed
    assert "Region figures per camera role" in printed
    for name, r in res.items():
        held, training = r["regions"]["held_out"], r["regions"]["training"]
        assert held["static"]["cameras"] == ["S002", "S005"]
        assert held["tracking"]["cameras"] == ["S010"]
        assert "S010" not in training["tracking"]["cameras"] and training["tracking"]["cameras"]
        for per_role in (held, training):
            for role in ("static", "tracking"):
                for model in ("trained", "initial", "empty"):
                    for region in ("performers", "face"):
                        fig = per_role[role][model][region]
                        assert fig["views"] > 0 and fig["psnr"] is not None, (name, role, model, region)
                assert per_role[role]["empty"]["performers"]["detail"] == 0.0   # draws no edge
    # trained on the zoom cameras' footage: more detail on their performers than the untrained model
    zoom = res["full"]["regions"]["training"]["tracking"]
    assert zoom["trained"]["performers"]["detail"] > zoom["initial"]["performers"]["detail"]
