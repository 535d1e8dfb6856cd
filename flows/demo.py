"""The demo: every stage that exists, run on the built-in synthetic capture.

ingest → calibrate (static cameras, tracking cameras, dense points of the frames reconstructed) →
reconstruct (Poly4DGS, one segment of the first 8 frames to the preset's Gaussian budget, on the
estimated calibration, scored on a held-out camera against the empty- and untrained-model floors) → the segment's contact sheet
(footage | render | error) as ``demo/contact_sheet.png``, a held-out camera's view at the segment's
middle rendered to EXR and the Gaussians there exported as PLY; the calibration's error against the
capture's ground truth is reported. Stages join as they land.
"""

from __future__ import annotations

from pathlib import Path

from prefect import flow, get_run_logger

from flows.ingest import ingest_flow
from flows.reconstruct import reconstruct_flow
from tasks.calibrate import calibration_errors
from tasks.reconstruct import render_views
from volcap_core.segment import ViewSpec, tracking_frames
from volcap_core.calibration.record import Calibration, camera_at
from volcap_core.reconstruction import SegmentModel
from volcap_core.splat import export_ply, load_model
from volcap_core.store import ArtifactStore


@flow(name="demo", persist_result=False)
def demo_flow(store: str, capture_dir: str, out_dir: str, preset: str = "demo") -> dict:
    """Run the pipeline on the demo capture; returns the references a coordinator would look at."""
    log = get_run_logger()
    s = ArtifactStore(store)
    capture = ingest_flow(store=store, capture_dir=capture_dir)
    # The first third of the take, one segment at the preset's budget (the demo preset's 10,000
    # Gaussians a frame): at demo size a whole take spreads the Gaussians too thin per instant (each
    # lives ~1.5 frames), and a reviewer wants a legible view.
    recon = reconstruct_flow(store=store, capture=capture.digest, frames=(0, 8), preset=preset)
    seg_ref = s.resolve(recon["segments"][0]["model"]["digest"])
    seg = s.get_record(seg_ref, SegmentModel)
    calib_ref = s.resolve(recon["calibration"]["digest"])
    points_ref = s.resolve(recon["points"]["digest"])
    errors = s.get_json(calibration_errors(store, capture, calib_ref, points_ref))

    # A held-out camera (never trained on) at mid-take: the view a reviewer looks at first.
    calib = s.get_record(seg.calibration, Calibration)
    camera = seg.held_out_cameras[0] if seg.held_out_cameras else calib.cameras[0].id
    mid = (seg.frames[0] + seg.frames[1]) // 2
    K, w2c, w, h = camera_at(calib, camera, mid, tracking_frames(s.get_bytes, calib))
    [view] = render_views(store, seg_ref, [ViewSpec(K=K.tolist(), world_to_camera=w2c.tolist(), width=w, height=h,
                                                    time_s=mid / seg.fps)])
    out = Path(out_dir)
    s.get_file(view, out / f"render_{camera}_frame{mid:03d}.exr")
    sheet = out / "contact_sheet.png"
    s.get_file(seg.contact_sheet, sheet)
    summary_seg = recon["segments"][0]
    (out / f"gaussians_frame{mid:03d}.ply").write_bytes(export_ply(load_model(s.get_bytes(seg.model)), mid / seg.fps))
    s.set_ref("demo/segment", seg_ref)
    s.set_ref("demo/calibration", calib_ref)
    summary = calibration_summary(errors)
    log.info("calibration: %s", ", ".join(f"{k} {v}" for k, v in summary.items()))
    log.info("held-out PSNR %s dB (empty model %s, untrained %s); contact sheet %s",
             _r(summary_seg["held_out_psnr"]), _r(summary_seg["floor_empty_psnr"]),
             _r(summary_seg["floor_initial_psnr"]), sheet)
    keys = ("held_out_psnr", "held_out_ssim", "held_out_psnr_raw", "held_out_psnr_performers",
            "held_out_ssim_performers", "floor_empty_psnr", "floor_empty_ssim", "floor_initial_psnr",
            "floor_initial_ssim", "training_psnr", "training_ssim")
    return {"capture": capture.model_dump(mode="json"), "calibration": calib_ref.model_dump(mode="json"),
            "points": points_ref.model_dump(mode="json"), "calibration_errors": summary,
            "segment": seg_ref.model_dump(mode="json"),
            **{k: _r(summary_seg[k], 4) for k in keys},
            "contact_sheet": str(sheet),
            "render": str(out / f"render_{camera}_frame{mid:03d}.exr"),
            "ply": str(out / f"gaussians_frame{mid:03d}.ply")}


def _r(x: float | None, digits: int = 2) -> float | None:
    return None if x is None else round(float(x), digits)


def calibration_summary(errors: dict) -> dict:
    """A few headline numbers of the calibration error table (rounded), for the demo's report."""
    out = {}
    st = errors.get("static") or {}
    if st:
        out["static_rotation_deg_mean"] = round(st["rotation_deg_mean"], 3)
        out["static_centre_pct_max"] = round(100 * st["centre_frac_max"], 2)
    tr = (errors.get("tracking") or {}).get("priors")
    if tr:
        out["tracking_focal_pct_max"] = round(tr["focal_pct_max_abs"], 2)
        out["tracking_pose_jitter_px_mean"] = round(tr["pose_jitter_px_mean"], 2)
    pts = errors.get("points") or {}
    if pts.get("median_distance_m") is not None:
        out["points_median_distance_mm"] = round(1000 * pts["median_distance_m"], 1)
    return out
