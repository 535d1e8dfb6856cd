"""Real footage without a lidar scan, end to end (issue 13): the 40 NeRF-synthetic "lego" views of
``../shared/data/multiview/lego`` (exact poses) written as a studio capture folder and run through
the user's path: ingest -> calibrate (no scan, no tracking cameras: the stage frame and the metric
scale from the rig's surveyed mounts) -> reconstruct with held-out cameras.

The capture (written into tmp_path, never into the repository):

* one static camera per view (``L00``-``L39``), ONE frame (a still: the pipeline takes a one-frame
  take; nothing is repeated), PNG 8-bit sRGB RGBA downscaled from 800x800 to :data:`SIZE` (area
  average of the premultiplied linear pixels);
* the background black: the PNG's alpha is carried as the frames' alpha channel (ingest stores
  R,G,B,A) and the colour is premultiplied by it (composited over black in linear light). Training
  and scoring use R,G,B only: nothing in the pipeline uses the alpha as a performer matte;
* the rig (``rig.json``): each camera's measured intrinsics from ``camera_angle_x`` (``fx = fy``,
  principal point at the image centre, no distortion) on a 36 mm-wide sensor (a 50 mm lens), its
  mount at the true optical centre plus a survey error of :data:`SURVEY_SIGMA_M` per axis, aimed at
  the stage origin (the lego's centre; the design aim, not the true pose) with its roll surveyed to
  1° (:func:`surveyed_roll`), no lidar scan.
* calibrated by ``volcap reconstruct --allow-unregistered --min-pair-inliers 20`` (:data:`CALIBRATION`;
  reconstruct runs the calibration as ``volcap calibrate`` would, the same task and key):
  the views are 5-20° apart and the default 36 matches a pair left them tied by too few pairs (4
  cameras left out, the others turned by up to 7° after step 4: docs/calibration.md).

Units: one lego scene unit is taken as one metre (the cameras orbit at 4.03 m, the model is ~1.3 m
across): a studio-sized stage, and a survey error of 2 cm per axis (3.5 cm in 3-D) is a few cm. The
rig's stage (the performance volume: where each camera's dense points sweep besides the set,
docs/calibration.md) is 3 x 3 x 2 m, inside the dome as a studio's cameras ring its stage; an
8 x 8 m stage put every camera inside it, swept from 0.7 x the camera spacing and took the file
from 10.75 to 14.7 min.
The calibration is compared with the exact poses in the stage frame the calibration itself chose
(from the mounts: no re-alignment to the truth); the similarity-aligned figures are printed for
reference. Skips with a message when ``../shared/data`` is absent. Both tests are slow and share one
reconstruct run, which calibrates the capture (~100 s since step 5's kernels were compiled, 318 s
before: guided matching over all 39 x 38 camera pairs, the bundle adjustments, the stand-in
surface's sweep), matches the frame's dense points at the test preset's half resolution and
trains: 170 s in all on the quiet 2-core machine at one torch thread (2026-11-28; 327 s before).
The contact sheet is written to
``/tmp/h27/lego_contact_sheet.png``.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import cv2  # noqa: F401  (before pycolmap)
import numpy as np
import pytest

from volcap_core.calibration.geometry import camera_centre, look_at_rotation, rotation_angle_deg, umeyama
from volcap_core.calibration.record import Calibration
from volcap_core.colour import srgb_decode, srgb_encode
from volcap_core.store import ArtifactStore

REPO = Path(__file__).resolve().parents[1]
LEGO = REPO.parent / "shared" / "data" / "multiview" / "lego"
SIZE = 300                 # px (from 800x800); at 200 px 7 cameras had too few observations
SENSOR_MM = 36.0           # sensor width, the focal in mm follows from camera_angle_x
SURVEY_SIGMA_M = 0.02      # mount survey error per axis (1 sigma), metres = lego units
HELD_OUT = ["L06", "L28"]  # two views never trained on, each with training views 6-14° away
#: ``volcap calibrate --allow-unregistered --min-pair-inliers 20``: what such a rig needs (docs/calibration.md)
CALIBRATION = {"allow_unregistered": True, "min_pair_inliers": 20}
NAME = "lego-no-lidar"
SHEET_DIR = Path("/tmp/h27")
STEPS = 150
POINTS = 20_000            # dense points kept of the one frame (every camera but the held-out ones)
GAUSSIANS = 20_000


def _cam(i: int) -> str:
    return f"L{i:02d}"


def write_lego_capture(root: Path, size: int = SIZE, seed: int = 0) -> dict:
    """The lego views as a capture folder (module docstring); returns the truth: ``w2c`` (OpenCV
    axes, stage frame = lego world), ``K`` at ``size`` and the surveyed ``mounts``."""
    meta = json.loads((LEGO / "transforms_train.json").read_text())
    f = 0.5 * size / np.tan(0.5 * meta["camera_angle_x"])
    c = (size - 1) / 2.0                       # OpenCV: the centre of the top-left pixel at (0, 0)
    K = np.array([[f, 0, c], [0, f, c], [0, 0, 1.0]])
    rng = np.random.default_rng(seed)
    w2c, mounts, cams, sources = {}, {}, [], []
    for i, fr in enumerate(meta["frames"]):
        cid = _cam(i)
        rgba = cv2.imread(str(LEGO / (fr["file_path"].removeprefix("./") + ".png")), cv2.IMREAD_UNCHANGED)
        rgba = cv2.cvtColor(rgba, cv2.COLOR_BGRA2RGBA).astype(np.float32) / 255.0
        a = rgba[..., 3:4]
        premult = np.concatenate([srgb_decode(rgba[..., :3]) * a, a], axis=2)   # over black, linear
        small = cv2.resize(premult, (size, size), interpolation=cv2.INTER_AREA)
        out = np.concatenate([srgb_encode(np.clip(small[..., :3], 0, 1)), np.clip(small[..., 3:], 0, 1)], axis=2)
        code = np.round(out * 255).astype(np.uint8)
        (root / cid).mkdir(parents=True)
        cv2.imwrite(str(root / cid / "000000.png"), cv2.cvtColor(code, cv2.COLOR_RGBA2BGRA))
        c2w = np.asarray(fr["transform_matrix"], np.float64)
        c2w[:3, 1:3] *= -1                                                # OpenGL -> OpenCV camera axes
        w2c[cid] = np.linalg.inv(c2w)
        mounts[cid] = c2w[:3, 3] + rng.normal(0.0, SURVEY_SIGMA_M, 3)
        roll = surveyed_roll(mounts[cid], w2c[cid][:3, :3])
        focal_mm = f * SENSOR_MM / size
        cams.append({"id": cid, "role": "static",
                     "lens": {"focal_min_mm": round(focal_mm, 3), "focal_max_mm": round(focal_mm, 3)},
                     "sensor": {"width_mm": SENSOR_MM, "height_mm": SENSOR_MM, "width_px": size, "height_px": size},
                     "mount": {"kind": "tripod", "position_m": [round(float(v), 4) for v in mounts[cid]],
                               "look_at_m": [0.0, 0.0, 0.0], "roll_deg": roll},
                     "nominal_focal_mm": round(focal_mm, 3),
                     "intrinsics": {"fx": f, "fy": f, "cx": c, "cy": c}})
        sources.append({"id": cid, "path": cid, "start_timecode": "01:00:00:00", "encoding": "srgb"})
    rig = {"name": "lego-dome", "kind": "scene", "fps": 24.0, "stage_size_m": [3.0, 3.0, 2.0], "cameras": cams,
           "lighting": {"description": "NeRF-synthetic lego renders (Blender)"}}
    (root / "rig.json").write_text(json.dumps(rig, indent=1))
    desc = {"format": "volcap-capture/1", "name": NAME, "rig": "rig.json", "fps": 24,
            "take": {"start_timecode": "01:00:00:00", "frame_count": 1}, "cameras": sources}
    (root / "capture.json").write_text(json.dumps(desc, indent=1))
    return {"w2c": w2c, "K": K, "mounts": mounts, "focal_px": f}


def surveyed_roll(mount: np.ndarray, R_true: np.ndarray) -> float:
    """The mount's roll (degrees, the rig's convention) to the nearest degree, as a survey gives it:
    0 for the cameras around the lego, a few degrees for the one looking almost straight down (L07),
    whose roll the look-at alone leaves to the world axes."""
    rolls = np.arange(-180.0, 180.0, 1.0)
    errs = [rotation_angle_deg(look_at_rotation(mount, np.zeros(3), r), R_true) for r in rolls]
    return float(rolls[int(np.argmin(errs))])


@pytest.fixture(scope="module")
def lego_capture(tmp_path_factory):
    if not (LEGO / "transforms_train.json").is_file():
        pytest.skip(f"real multi-view data absent: {LEGO} (needs ../shared/data next to the repository)")
    root = tmp_path_factory.mktemp("lego") / "cap"
    root.mkdir()
    return root, write_lego_capture(root)


@pytest.fixture(scope="module")
def reconstructed(prefect_api, lego_capture, tmp_path_factory):
    """``volcap ingest`` then ``volcap reconstruct`` (which calibrates the capture itself, as a studio
    without a separate ``volcap calibrate`` would): (store, capture ref, reconstruct result, wall s).
    One run serves both tests: a separate calibrate flow would compute the frame's dense points
    for all 39 cameras once more (measured: 5.5-6.4 min of a 10.5-min file)."""
    from flows.ingest import ingest_flow
    from flows.reconstruct import reconstruct_flow
    from flows.runtime import run_flow

    root, truth = lego_capture
    store = ArtifactStore(str(tmp_path_factory.mktemp("legostore") / "store")).url
    capture = run_flow(ingest_flow, store=store, capture_dir=str(root)).result
    t0 = time.perf_counter()
    res = run_flow(reconstruct_flow, store=store, capture=capture.digest, preset="test", steps=STEPS,
                   points_per_frame=POINTS, max_gaussians=GAUSSIANS, held_out=HELD_OUT, **CALIBRATION)
    return store, capture, res.result, time.perf_counter() - t0


def calibration_errors(calib: Calibration, truth: dict) -> dict:
    """Rotation (deg), centre (m) and focal (%) errors of the calibrated cameras against the exact
    poses: as calibrated (the calibration's own stage frame) and after the best similarity."""
    ids = calib.static_ids
    est = {c: np.asarray(calib.camera(c).world_to_camera, np.float64) for c in ids}
    rot = np.array([rotation_angle_deg(est[c][:3, :3], truth["w2c"][c][:3, :3]) for c in ids])
    ce = np.stack([camera_centre(est[c]) for c in ids])
    ct = np.stack([camera_centre(truth["w2c"][c]) for c in ids])
    T = umeyama(ce, ct)
    rot_sim = np.array([rotation_angle_deg(T.apply_pose(est[c])[:3, :3], truth["w2c"][c][:3, :3]) for c in ids])
    focal = np.array([calib.camera(c).intrinsics[0] / truth["focal_px"] - 1 for c in ids]) * 100
    return {"cameras": len(ids), "rotation_deg_mean": float(rot.mean()), "rotation_deg_max": float(rot.max()),
            "centre_m_mean": float(np.linalg.norm(ce - ct, axis=1).mean()),
            "centre_m_max": float(np.linalg.norm(ce - ct, axis=1).max()),
            "scale_true_over_est": float(T.s),
            "sim_rotation_deg_mean": float(rot_sim.mean()), "sim_rotation_deg_max": float(rot_sim.max()),
            "sim_centre_m_max": float(np.linalg.norm(T.apply(ce) - ct, axis=1).max()),
            "focal_pct_max_abs": float(np.abs(focal).max())}


@pytest.mark.slow
def test_lego_capture_calibrates_without_a_scan(reconstructed, lego_capture):
    store, capture, out, _ = reconstructed
    _, truth = lego_capture
    calib = ArtifactStore(store).get_record(out["calibration"]["digest"], Calibration)
    frame = {k[len("static_frame_"):]: v for k, v in calib.stats.items() if k.startswith("static_frame_")}
    print("unregistered", calib.unregistered)
    print("stage frame", {k: v for k, v in frame.items() if k != "mount_residual"})
    err = calibration_errors(calib, truth)
    print("lego errors", {k: round(v, 5) for k, v in err.items()})
    # every camera calibrated or reported: the ones left out are listed with the reason (measured:
    # L26 alone, 17 observations: its second-nearest view is 34° away), never returned as calibrated
    assert all(why for why in calib.unregistered.values())
    assert sorted(calib.static_ids + list(calib.unregistered)) == [_cam(i) for i in range(40)]
    assert len(calib.unregistered) <= 2 and not set(HELD_OUT) & set(calib.unregistered)
    # the stage frame and the scale from the surveyed mounts (no scan, no known distance)
    assert frame["scale_source"] == 0.0 and frame["mount_inliers"] == len(calib.static_ids), frame
    # measured (2026-11-24): 3.2 cm rms, 7.8 cm max from the mounts (surveyed to 2 cm per axis)
    assert frame["mount_residual_rms_m"] < 0.06, frame
    # measured (2026-11-24, 39 cameras) against the exact poses, in the calibration's own stage frame
    # (no re-alignment): rotation 0.245° mean, 0.503° max; centres 1.9 cm mean, 5.1 cm max; focal
    # within 1.39 % of the measured one (its prior is 3 %). After the best similarity onto the truth
    # (for reference): 0.189° / 0.398°, centres 4.7 cm max; the similarity's scale 1.00061 (the
    # mounts' scale 0.06 % off). With the default --min-pair-inliers (36): 4 cameras left out and
    # 1.06° mean, 4.8° max (before L07's roll was surveyed; docs/calibration.md). Since measured
    # focals need evidence to move (calibrate-static 13, 2026-11-28 at e822efd): 40 cameras, 0.174° mean,
    # 0.395° max, centres 1.7 cm mean, 3.4 cm max, scale 1.00022, focal within 1.14 %. Bounds ~2x
    assert err["rotation_deg_mean"] < 0.5 and err["rotation_deg_max"] < 1.0, err
    assert err["centre_m_max"] < 0.10, err
    assert abs(err["scale_true_over_est"] - 1) < 0.005, err
    assert err["focal_pct_max_abs"] < 3.0, err


@pytest.mark.slow
def test_lego_capture_reconstructs_without_a_scan(reconstructed):
    store, capture, out, wall = reconstructed
    seg = out["segments"][0]
    print("lego reconstruct", f"{wall:.1f} s", {k: seg[k] for k in ("held_out_psnr", "held_out_psnr_raw", "floor_initial_psnr",
                                                    "floor_empty_psnr", "training_psnr", "gaussians", "train_wall_s")})
    # the contact sheet (held-out L06 and L28, then training views: footage | render | error), made by
    # the training task with volcap_core.contact_sheet; look at it before believing the PSNR
    SHEET_DIR.mkdir(parents=True, exist_ok=True)
    ArtifactStore(store).get_file(seg["contact_sheet"]["digest"], SHEET_DIR / "lego_contact_sheet.png")
    # measured (2026-11-26; the test preset stretched to 150 steps, 20 000 Gaussians, 37 training
    # views at 300x300, the one frame's estimated points matched at the preset's dense_scale 0.5,
    # 150x150): held-out 20.93 dB (L06 20.4), untrained 14.03, empty 8.18 (the black background: the
    # empty model is black); training views 23.0 dB; 82 s of training, the file 8 min under load.
    # The render is the lego, in place and soft, with dark holes in the base plate (its low texture
    # finds no match at half resolution, so no point starts there) and blotches in the bucket.
    # Matched at full resolution (before reconstruct followed the preset's dense_scale; the file
    # 10 min 45 s): 23.48 dB, untrained 17.27. Since the room box (train-segment v10, 2026-11-27 at
    # 1a4135a): held-out 20.58 dB, untrained 13.03, empty 8.18, training views 22.12; the sheet shows
    # the lego in place and soft, the base plate's hole, and yellow haze above it. With calibrate-static
    # 13 (2026-11-28 at e822efd): held-out 20.54 dB, untrained 13.07, empty 8.18, training views 22.12.
    # Bounds: about half the margins
    assert seg["held_out_psnr"] >= seg["floor_initial_psnr"] + 3.0
    assert seg["held_out_psnr"] >= seg["floor_empty_psnr"] + 6.0
    assert seg["held_out_psnr"] > 18.5
