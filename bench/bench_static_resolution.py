"""Static calibration through measured-but-imperfect lenses against the footage's resolution.

    python bench/bench_static_resolution.py [--seeds 0 1 2 3] [--scales 1 2] [--exact-lenses]
                                            [--workdir DIR] [--json out.json]

Why: on the distorted demo capture (``demo_scene_distorted``, 320×180) some renders miss the
static rotation target (0.1°) by one camera each (3 of seeds 0-9 since the calibration rectifies
with Lanczos, 5 before), and the cause was measured
(``docs/benchmarks.md``, "Why a static camera misses"): that unit's lens calibration puts its
principal point 0.7 px off, and footage read through that lens at 320×180 knows the principal
point no better than the calibration, so it cannot pull it back. This bench asks whether finer
footage can: the same rig with every pixel grid ``scale`` times finer (``Rig.with_finer_pixels``:
the same lenses, sensors and views) and the same lens-calibration errors in physical size (the
same random draws, the principal point's 0.3 px σ of
:data:`volcap_core.synth.synthesize.LENS_CALIBRATION_ERROR` in the finer pixels times ``scale``,
so that the finer rig is not handed a better calibration: ``synthesize_capture``'s
``lens_calibration_error``).

Each render: ``synthesize_capture(rig, seed, frames=6, cameras=<the 8 static>)`` (with the lidar
scan), then the ``calibrate-static`` task's step (``static_step.calibrate_static_step``, default
options) and the errors against the ground truth (``metrics.static_errors``) at the reference
frame. The scale-1 rows are the floors: the same code on the demo's pixels. ``--exact-lenses``
renders every unit with exactly the lens the rig states (no lens-calibration error): what is left
is the calibration's own error. Each row also gives the cameras' stated rotation σ (their
``support``'s ``rotation_sigma_deg``, step 5's covariance) and the largest error in units of it.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import cv2  # noqa: E402,F401  (before pycolmap)

import volcap_core.synth.synthesize as synthesize  # noqa: E402
from hardware.rig import load_rig  # noqa: E402
from volcap_core.calibration.lidar import LidarScan  # noqa: E402
from volcap_core.calibration.inputs import split_cameras  # noqa: E402
from volcap_core.calibration.metrics import load_ground_truth, static_errors  # noqa: E402
from volcap_core.calibration.static import StaticCalibrationOptions  # noqa: E402
from volcap_core.calibration.static_step import calibrate_static_step, reference_frame  # noqa: E402
from volcap_core.capture import CaptureFolder  # noqa: E402

RIG = "demo_scene_distorted"
FRAMES = 6


def render(workdir: Path, seed: int, scale: int, exact_lenses: bool = False) -> Path:
    """The seed's capture of the static cameras on the rig ``scale`` times finer (reused when present)."""
    rig = load_rig(RIG).with_finer_pixels(scale)
    out = workdir / f"x{scale}_seed{seed}{'_exact' if exact_lenses else ''}"
    if (out / "capture.json").exists():
        return out
    out.mkdir(parents=True, exist_ok=True)
    rig_path = out.parent / f"{rig.name}.json"
    rig_path.write_text(rig.model_dump_json(indent=1))
    statics = [c.id for c in rig.cameras if not c.role.tracks]
    # the lens calibration's principal-point error, the same angle at every scale
    error = {"centre_px": synthesize.LENS_CALIBRATION_ERROR["centre_px"] * scale}
    if exact_lenses:
        error = {k: 0.0 for k in synthesize.LENS_CALIBRATION_ERROR}
    synthesize.synthesize_capture(out, rig=str(rig_path), seed=seed, frames=FRAMES, cameras=statics,
                                  lens_calibration_error=error)
    return out


def calibrate(capture_dir: Path) -> dict:
    cap = CaptureFolder.open(capture_dir)
    statics, trackers = split_cameras(capture_dir.name, cap.rig, cap.camera_ids)
    t0 = time.perf_counter()
    scan = LidarScan.from_ply_bytes(cap.lidar_path.read_bytes())
    static = calibrate_static_step(capture_dir.name, cap.rig, statics, trackers, cap.frame_count, cap.load,
                                   scan).calibration
    seconds = time.perf_counter() - t0
    err = static_errors(static.K, static.world_to_camera, load_ground_truth(capture_dir / "ground_truth"),
                        reference_frame(cap.frame_count, StaticCalibrationOptions()))
    rot = {c: e["rotation_deg"] for c, e in err.items()}
    sigma = {c: static.support[c]["rotation_sigma_deg"] for c in rot}
    worst = max(rot, key=rot.get)
    return {"rotation_deg_mean": float(np.mean(list(rot.values()))), "rotation_deg_max": rot[worst],
            "worst_camera": worst, "centre_pct_max": 100 * max(e["centre_frac"] for e in err.values()),
            "focal_pct_max_abs": max(abs(e["focal_pct"]) for e in err.values()),
            "rotation_deg": rot, "rotation_sigma_deg": sigma,
            "error_in_sigma_max": max(rot[c] / sigma[c] for c in rot), "seconds": seconds}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3])
    ap.add_argument("--scales", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--exact-lenses", action="store_true", help="render the lenses the rig states, without error")
    ap.add_argument("--workdir", type=Path, default=None, help="keep the renders here (default: a temporary folder)")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        work = args.workdir or Path(tmp)
        print("| seed | pixels | rotation mean / max (camera) | stated σ | max error / σ | centre max | focal max "
              "| static step |")
        print("|---|---|---|---|---|---|---|---|")
        for seed in args.seeds:
            for scale in args.scales:
                capture = render(work, seed, scale, args.exact_lenses)
                r = calibrate(capture)
                # the footage's size as rendered (the static cameras share a sensor)
                rig = CaptureFolder.open(capture).rig
                size = next(c for c in rig.cameras if not c.role.tracks).sensor
                w, h = size.width_px, size.height_px
                rows.append({"seed": seed, "scale": scale, "pixels": [w, h], **r})
                s = r["rotation_sigma_deg"].values()
                print(f"| {seed} | {w}×{h} | {r['rotation_deg_mean']:.3f}° / {r['rotation_deg_max']:.3f}° "
                      f"({r['worst_camera']}) | {min(s):.3f}-{max(s):.3f}° | {r['error_in_sigma_max']:.2f} "
                      f"| {r['centre_pct_max']:.2f} % | {r['focal_pct_max_abs']:.2f} % | {r['seconds']:.0f} s |",
                      flush=True)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
