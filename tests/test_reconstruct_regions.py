"""`volcap reconstruct`'s region figures: performers and faces, per camera role, beside the floors."""

from __future__ import annotations

import pytest

from flows.ingest import ingest_flow
from flows.reconstruct import reconstruct_flow
from flows.runtime import run_flow
from volcap_core.store import ArtifactStore
from volcap_core.synth import synthesize_capture

# six static cameras and the two head-framing tracking cameras; S002 and S009 held out
CAMERAS = ["S000", "S001", "S002", "S003", "S004", "S005", "S008", "S009"]


@pytest.mark.slow
def test_reconstruct_reports_face_and_performer_regions_per_role(prefect_api, tmp_path):
    """A 2-frame capture, the test preset (~45 s of CPU on 2 cores)."""
    root = synthesize_capture(tmp_path / "cap", rig="demo_scene", seed=3, frames=2, cameras=CAMERAS,
                              supersample=1, write_depth=True).parent
    store = ArtifactStore(str(tmp_path / "store")).url
    capture = run_flow(ingest_flow, store=store, capture_dir=str(root)).result.digest
    # 4 000 Gaussians: the figures are checked for being there, not for their level (every point
    # kept, ~100 000 Gaussians, the scan's, cost most of the file's time)
    out = run_flow(reconstruct_flow, store=store, capture=capture, preset="test", points_per_frame=2000,
                   held_out=["S002", "S009"], ground_truth=True, max_gaussians=4000).result
    seg = out["segments"][0]
    regions = seg["scores"]["regions"]
    # the figures that were there stay, beside the new key
    assert set(seg["scores"]) == {"held_out", "training", "regions", "alpha"}
    assert set(seg["scores"]["held_out"]) == {"trained", "initial", "empty"}
    held, training = regions["held_out"], regions["training"]
    assert held["static"]["cameras"] == ["S002"] and held["tracking"]["cameras"] == ["S009"]
    assert "tracking" in training or "static" in training
    for per_role in (held, training):
        for role, r in per_role.items():
            for model in ("trained", "initial", "empty"):
                for region in ("performers", "face"):
                    fig = r[model][region]
                    assert set(fig) == {"psnr", "ssim", "detail", "views"}, (role, model, region)
    # the tracking camera frames a head: its face figures exist, the empty model's detail is 0
    face = held["tracking"]
    assert face["trained"]["face"]["views"] == 2 and face["empty"]["face"]["detail"] == 0.0
    assert face["trained"]["face"]["detail"] > 0.0
    print("region figures", regions)
    # the performers' PSNR of a role's region figures is the scores' performer PSNR on the same views
    assert held["static"]["trained"]["performers"]["views"] == 2
    # the performers' alpha on the held-out views, per role, beside the floors: the empty model's
    # is 0 (its error the masks' mean), the trained model's nearer the masks than the untrained one's
    alpha = seg["scores"]["alpha"]
    print("performers' alpha", alpha)
    assert alpha["static"]["cameras"] == ["S002"] and alpha["tracking"]["cameras"] == ["S009"]
    for role, a in alpha.items():
        assert a["empty"]["on"] == 0.0 and a["empty"]["spill"] == 0.0 and a["trained"]["views"] == 2
        assert a["trained"]["error"] < a["empty"]["error"], role
        assert 0.0 < a["trained"]["on"] <= 1.0
