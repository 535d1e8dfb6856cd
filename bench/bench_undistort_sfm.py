"""Real lenses: volcap's static step against undistort-then-SfM, on Pose2Sim's cam01/cam02.

    python bench/bench_undistort_sfm.py [--frames 49 70] [--loose-measured-focal] [--workdir DIR]
                                        [--json out.json]

Why (issue 31): "on real lenses the static step is at least as accurate as undistort-then-SfM".
Pose2Sim's SinglePerson demo (``../shared/data/real/pose2sim``) has a studio calibration (Qualisys,
with lens distortion) to measure against; of its four cameras only cam01 and cam02 share a view
(docs/benchmarks.md, "Real footage: Pose2Sim SinglePerson"), so this is a two-camera comparison.

At each reference frame (a 3-frame take centred on it, the frames decoded as ingest does):

- **static step**: the ``calibrate-static`` task's step (``static_step.calibrate_static_step``,
  default options, ``allow_unregistered``) on a rig written from the imported calibration
  (``rig_from_calibration``: the studio's lens as measured intrinsics, its poses as mounts);
- **undistort-then-SfM**: the reference frame undistorted by the studio's lens into the pinhole of
  the same fx and principal point (``sfm.undistort_views``, Lanczos), then a plain pycolmap SfM on
  it as a user would run one (:func:`plain_sfm`): COLMAP's default SIFT, exhaustive matching and
  verification, its incremental mapper with the intrinsics held (the lens calibration's focal as
  the cameras' prior), ``min_model_size`` 2 and two-view tracks kept (COLMAP's defaults, 10 images
  and two-view tracks ignored, discard any two-image model), in its own arbitrary frame; and the
  same with the static step's SIFT, matching and mapper thresholds ("tuned"). (``sfm.reconstruct_static``
  without seeds is not it: it is volcap's SfM with volcap's matching settings.)

Both are compared with the imported calibration after a similarity (each camera's rotation error
and centre error): the similarity's rotation the mean of the two cameras' (chordal), its scale the
baselines' ratio, its translation the centres' mean; and by the pair's relative rotation (frame
independent). The static step is also given in its own stage frame (no similarity: its mounts,
the studio's poses, are its frame), with each lens calibration's focal as it leaves it and its
decision (held or released, ``focal_prior``); ``--loose-measured-focal`` runs it with every focal
under the loose 3 % prior, as before calibrate-static 13. Prints a table and, with ``--json``, every figure.

The static step is seeded by the mounts (here the very poses it is measured against) and held by
them at 3 cm; the plain SfM knows nothing of them. The relative rotation is the fair figure.
~3-4 min a frame on 2 busy cores (SIFT of 1080x1920 frames, three times).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import cv2  # noqa: F401  (before pycolmap)
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from volcap_core.calibration.geometry import camera_centre, rotation_angle_deg  # noqa: E402
from volcap_core.calibration.importers import calibration_from_qualisys  # noqa: E402
from volcap_core.calibration.rig_from_calibration import rig_from_calibration  # noqa: E402
from volcap_core.calibration.distortion import colmap_camera  # noqa: E402
from volcap_core.calibration.geometry import pose_matrix  # noqa: E402
from volcap_core.calibration.images import to_uint8_gray  # noqa: E402
from volcap_core.calibration.sfm import Intrinsics, rectified_intrinsics, undistort_views  # noqa: E402
from volcap_core.calibration.static import StaticCalibrationOptions  # noqa: E402
from volcap_core.calibration.static_step import calibrate_static_step, reference_frame  # noqa: E402
from volcap_core.capture import CaptureFolder  # noqa: E402
from volcap_core.colour import bt709_oetf_inverse  # noqa: E402

SINGLE = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "pose2sim" / "Demo_SinglePerson"
SIZES = {"cam01": (1080, 1920), "cam02": (1080, 1920), "cam03": (1088, 1920), "cam04": (1088, 1920)}
PAIR = ("cam01", "cam02")


def _capture(workdir: Path, ref: int, imported) -> CaptureFolder:
    """The capture folder of a 3-frame take centred on video frame ``ref`` (60 fps timecodes)."""
    root = workdir / f"take{ref}"
    if not (root / "capture.json").exists():
        (root / "videos").mkdir(parents=True, exist_ok=True)
        for cid in SIZES:
            link = root / "videos" / f"{cid}.mp4"
            if not link.exists():
                link.symlink_to(SINGLE / "videos" / f"{cid}.mp4")
        rig = rig_from_calibration(imported, stage_size_m=(4.0, 4.0, 2.5))
        (root / "rig.json").write_text(json.dumps(rig.model_dump(mode="json")))
        start = ref - 1
        (root / "capture.json").write_text(json.dumps({
            "format": "volcap-capture/1", "name": "pose2sim", "rig": "rig.json", "fps": 60,
            "take": {"start_timecode": f"01:00:{start // 60:02d}:{start % 60:02d}", "frame_count": 3},
            "cameras": [{"id": c, "path": f"videos/{c}.mp4", "start_timecode": "01:00:00:00"} for c in SIZES]}))
    return CaptureFolder.open(root)


def plain_sfm(images: dict[str, np.ndarray], pinholes: dict[str, Intrinsics], work: Path, tuned: bool
              ) -> tuple[dict[str, np.ndarray], int]:
    """COLMAP on ``images`` (camera id -> scene-linear RGB) taken by the square pinholes
    ``pinholes``, intrinsics held: each registered camera's world-to-camera [4, 4] in COLMAP's frame,
    and the number of 3D points. ``tuned``: the static step's SIFT, matching and mapper thresholds
    (``StaticSfmOptions``: more features, guided matching, 30 inliers to start) in place of COLMAP's
    defaults."""
    import pycolmap

    from volcap_core.calibration.sfm import StaticSfmOptions

    sfm = StaticSfmOptions()

    img_dir = work / "images"
    img_dir.mkdir(parents=True, exist_ok=True)
    db = work / "database.db"
    db.unlink(missing_ok=True)
    ids = {}
    with pycolmap.Database.open(str(db)) as d:
        for c, intr in pinholes.items():
            cv2.imwrite(str(img_dir / f"{c}.png"), to_uint8_gray(images[c]))
            model, params = colmap_camera(intr.fx, intr.fy, intr.cx, intr.cy)
            cam = pycolmap.Camera(model=model, width=intr.width, height=intr.height, params=params)
            cam.has_prior_focal_length = True       # the lens calibration's: the pair is verified as calibrated
            ids[c] = int(d.write_camera(cam))
    for c in pinholes:
        ro = pycolmap.ImageReaderOptions()
        ro.existing_camera_id = ids[c]
        pycolmap.extract_features(str(db), str(img_dir), image_names=[f"{c}.png"], reader_options=ro,
                                  device=pycolmap.Device.cpu,
                                  **({"extraction_options": sfm.sift.colmap()} if tuned else {}))
    mo = pycolmap.FeatureMatchingOptions()
    po = pycolmap.IncrementalPipelineOptions()
    if tuned:
        mo.sift.max_ratio, mo.guided_matching = sfm.match_max_ratio, sfm.guided_matching
        po.mapper.init_min_num_inliers = sfm.init_min_num_inliers
        po.mapper.abs_pose_min_num_inliers = sfm.abs_pose_min_num_inliers
    pycolmap.match_exhaustive(str(db), matching_options=mo, device=pycolmap.Device.cpu)
    po.ba_refine_focal_length = po.ba_refine_principal_point = po.ba_refine_extra_params = False
    po.mapper.abs_pose_refine_focal_length = po.mapper.abs_pose_refine_extra_params = False
    # a two-image model: COLMAP drops models under 10 images and ignores two-view tracks (every
    # track of two images is one: the initial pair triangulates nothing and is discarded)
    po.min_model_size = 2
    po.triangulation.ignore_two_view_tracks = False
    (work / "sparse").mkdir(exist_ok=True)
    recs = pycolmap.incremental_mapping(str(db), str(img_dir), str(work / "sparse"), options=po)
    if not recs:
        return {}, 0
    rec = max(recs.values(), key=lambda r: (r.num_reg_images(), r.num_points3D()))
    out = {}
    for iid in rec.reg_image_ids():
        m = rec.images[iid].cam_from_world().matrix()
        out[rec.images[iid].name[:-4]] = pose_matrix(m[:, :3], m[:, 3])
    return out, int(rec.num_points3D())


def errors_after_similarity(w2c: dict[str, np.ndarray], truth: dict[str, np.ndarray]) -> dict:
    """Per camera of ``PAIR``: rotation (degrees) and centre (metres) error against ``truth`` after
    the similarity of the module docstring, and the pair's relative rotation error (degrees)."""
    M = sum(truth[c][:3, :3].T @ w2c[c][:3, :3] for c in PAIR)      # est world -> true world, averaged
    U, _, Vt = np.linalg.svd(M)
    M = U @ np.diag([1, 1, np.linalg.det(U @ Vt)]) @ Vt
    Ce = {c: camera_centre(w2c[c]) for c in PAIR}
    Ct = {c: camera_centre(truth[c]) for c in PAIR}
    s = np.linalg.norm(Ct[PAIR[0]] - Ct[PAIR[1]]) / np.linalg.norm(Ce[PAIR[0]] - Ce[PAIR[1]])
    t = np.mean([Ct[c] for c in PAIR], 0) - s * M @ np.mean([Ce[c] for c in PAIR], 0)
    out = {c: {"rotation_deg": rotation_angle_deg(w2c[c][:3, :3] @ M.T, truth[c][:3, :3]),
               "centre_m": float(np.linalg.norm(s * M @ Ce[c] + t - Ct[c]))} for c in PAIR}
    rel = [w2c[PAIR[1]][:3, :3] @ w2c[PAIR[0]][:3, :3].T, truth[PAIR[1]][:3, :3] @ truth[PAIR[0]][:3, :3].T]
    out["relative_rotation_deg"] = rotation_angle_deg(*rel)
    return out


def run_frame(workdir: Path, ref: int, imported, options: StaticCalibrationOptions) -> dict:
    cap = _capture(workdir, ref, imported)
    cache: dict = {}

    def load(camera: str, k: int) -> np.ndarray:
        if (camera, k) not in cache:
            cache[camera, k] = bt709_oetf_inverse(cap.load(camera, k)).astype(np.float32)
        return cache[camera, k]

    truth = {c: np.asarray(imported.camera(c).world_to_camera, np.float64) for c in PAIR}
    row = {"frame": ref}
    # the plain pipeline: the static step's reference frame, undistorted by the studio's lens, COLMAP alone
    lens = {c: Intrinsics.from_rig(cap.rig, c) for c in PAIR}
    images = {c: load(c, reference_frame(3, options)) for c in PAIR}
    t2 = time.perf_counter()
    undistorted = undistort_views(images, lens)
    for name, tuned in (("sfm", False), ("sfm_tuned", True)):
        poses, row[f"{name}_points"] = plain_sfm(undistorted, {c: rectified_intrinsics(lens[c]) for c in PAIR},
                                                 workdir / f"{name}{ref}", tuned)
        row[f"{name}_s"] = round(time.perf_counter() - t2, 1)
        row[name] = errors_after_similarity(poses, truth) if set(PAIR) <= set(poses) else None
        row[f"{name}_unregistered"] = sorted(set(PAIR) - set(poses))
        print(ref, name, row[name], flush=True)
    t0 = time.perf_counter()
    step = calibrate_static_step(cap.name, cap.rig, list(PAIR), [], 3, load, None, options)
    static = step.calibration
    t1 = time.perf_counter()
    row["static_s"] = round(t1 - t0, 1)
    row["static"] = errors_after_similarity(static.world_to_camera, truth)
    row["static_stage_frame"] = {c: {"rotation_deg": rotation_angle_deg(static.world_to_camera[c][:3, :3],
                                                                        truth[c][:3, :3]),
                                     "centre_m": float(np.linalg.norm(camera_centre(static.world_to_camera[c])
                                                                      - camera_centre(truth[c]))),
                                     # the lens calibration's focal as the step leaves it
                                     "focal_pct": 100 * (static.raw_intrinsics[c].fx / imported.camera(c).intrinsics[0] - 1),
                                     **{k: v for k, v in static.support[c].items() if k.startswith("focal_")}}
                           for c in PAIR}
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, nargs="+", default=[49, 70],
                    help="reference frames of the videos (1-98; each a 3-frame take centred on it)")
    ap.add_argument("--loose-measured-focal", action="store_true",
                    help="the static step with every focal under the loose 3 %% prior (before calibrate-static 13)")
    ap.add_argument("--workdir", type=Path, default=None)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    if not SINGLE.is_dir():
        sys.exit(f"bench_undistort_sfm: needs {SINGLE} (the shared Pose2Sim data)")
    imported = calibration_from_qualisys((SINGLE / "calibration" / "Calib.qca.txt").read_bytes(), "pose2sim", 100,
                                         60.0, frame_sizes=SIZES)
    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="undistort_sfm_"))
    options = StaticCalibrationOptions(allow_unregistered=True)
    if args.loose_measured_focal:
        options = replace(options, measured_focal_sigma_rel=None)
    rows = []
    print("frame | method | cam01 rot / centre | cam02 rot / centre | relative rotation")
    for ref in args.frames:
        row = run_frame(workdir, ref, imported, options)
        rows.append(row)
        for name in ("static", "sfm", "sfm_tuned"):
            e = row[name]
            if e is None:
                print(f"{ref} | {name} | not registered: {row.get(name + '_unregistered')}")
                continue
            print(f"{ref} | {name} | " + " | ".join(f"{e[c]['rotation_deg']:.3f}° / {100 * e[c]['centre_m']:.1f} cm"
                                                     for c in PAIR) + f" | {e['relative_rotation_deg']:.3f}°")
        sf = row["static_stage_frame"]
        print(f"{ref} | static, stage frame | " + " | ".join(
            f"{sf[c]['rotation_deg']:.3f}° / {100 * sf[c]['centre_m']:.1f} cm, focal {sf[c]['focal_pct']:+.2f} %"
            for c in PAIR), flush=True)
        if args.json:
            args.json.write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
