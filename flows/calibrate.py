"""The calibrate flow: an ingested capture in, a Calibration and per-frame dense points out.

DAG: ``calibrate-static`` once -> ``calibrate-tracking-camera`` per tracking camera (mapped; none for
a capture without tracking cameras) -> ``assemble-calibration`` -> ``dense-points-frame`` per frame
(mapped) -> ``point-cloud-sequence``; for a synthetic capture also ``calibration-errors``; with
colour charts (``colour_charts``) also ``calibrate-colour``, the colour matrix between the Face Rig and
the Scene Rig, which :func:`calibrate_colour_flow` runs on its own (``volcap calibrate-colour``).

:func:`calibrate_capture` and :func:`point_cloud_for_frames` are plain functions, not flows: they
submit their tasks into whatever flow run calls them (this one, reconstruct, production), so their
task runs count, cache and retry as that run's own.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from prefect import flow, get_run_logger, unmapped
from pydantic import ValidationError

from tasks.calibrate import (assemble_calibration, calibrate_colour, calibrate_static, calibrate_tracking_camera,
                             calibration_errors, dense_points_frame, point_cloud_sequence)
from volcap_core.calibration.colour_step import ChartView, ColourMatrixRecord
from volcap_core.calibration.dense_points_step import dense_cameras
from volcap_core.calibration.errors import CalibrationInputError, KnownPointsError
from volcap_core.calibration.inputs import tracking_camera_ids
from volcap_core.calibration.metrics import errors_against
from volcap_core.calibration.record import Calibration
from volcap_core.calibration.scale import KnownPoints
from volcap_core.calibration.sfm import StaticSfmOptions
from volcap_core.calibration.static import StaticCalibrationOptions
from volcap_core.calibration.tracking.options import TrackingOptions
from volcap_core.capture import Capture
from volcap_core.records import ArtifactRef
from volcap_core.store import ArtifactStore


def static_calibration_options(allow_unregistered: bool = False, instants: int = 1,
                               known_distance: tuple[str, str, float] | None = None,
                               min_pair_inliers: int | None = None) -> StaticCalibrationOptions | None:
    """The static calibration's settings from the options of ``volcap calibrate`` / ``volcap
    reconstruct``: only those given differ from the defaults; None when none is given (the
    defaults' cache key). The calibrate and reconstruct flows both build them here, so the same
    options give the same (cached) calibration from either command. ``min_pair_inliers``: the
    verified matches a camera pair needs in the static SfM (``StaticSfmOptions.min_pair_inliers``;
    None: its default, tuned on the 320x180 demo rig's close neighbours)."""
    given = {k: v for k, v in (("allow_unregistered", allow_unregistered), ("instants", instants),
                               ("known_distance", tuple(known_distance) if known_distance else None))
             if v != getattr(StaticCalibrationOptions, k)}
    if min_pair_inliers is not None and min_pair_inliers != StaticSfmOptions.min_pair_inliers:
        if min_pair_inliers < 8:
            raise CalibrationInputError(f"min_pair_inliers must be at least 8 (a two-view geometry's own "
                                        f"minimum), got {min_pair_inliers}")
        given["sfm"] = replace(StaticSfmOptions(), min_pair_inliers=int(min_pair_inliers))
    return StaticCalibrationOptions(**given) if given else None


def tracking_calibration_options(allow_unregistered: bool = False) -> TrackingOptions | None:
    """The tracking cameras' settings a calibrate or reconstruct run asks for: None for the
    defaults (their cache key), else a camera the solve cannot support is left out
    (``TrackingOptions.allow_unsupported``) as ``allow_unregistered`` leaves out a static one."""
    return TrackingOptions(allow_unsupported=True) if allow_unregistered else None


def known_points_spec(doc: dict | KnownPoints | None, known_distance=None) -> KnownPoints | None:
    """Known scene points (``volcap calibrate --known-points``'s JSON, :mod:`volcap_core.calibration.scale`)
    validated; a :class:`CalibrationInputError` naming the field, or when a known distance between
    cameras is given too."""
    if doc is None:
        return None
    if known_distance:
        raise CalibrationInputError("give either a known distance between two cameras (--known-distance) or "
                                    "known scene points (--known-points), not both")
    try:
        return KnownPoints.parse(doc)
    except KnownPointsError as exc:
        raise CalibrationInputError(str(exc)) from None


def calibrate_capture(store: str, capture: ArtifactRef,
                      static_options: StaticCalibrationOptions | None = None,
                      known_points: KnownPoints | None = None,
                      tracking_options: TrackingOptions | None = None) -> ArtifactRef:
    """The capture's Calibration ref: static cameras once, each tracking camera in its own task,
    then the record. Call it inside a flow run (any). Every step is cached by its inputs' digests.
    ``static_options`` / ``tracking_options``: the static and tracking calibrations' settings (None:
    the tasks' defaults, the same key as the defaults spelled out); ``known_points``: distances
    between marked scene points, the scale of a capture without a lidar scan
    (:mod:`volcap_core.calibration.scale`)."""
    s = ArtifactStore(store)
    cap = s.get_record(capture, Capture)
    trackers = tracking_camera_ids(cap)
    extra = {} if known_points is None else {"known_points": known_points}
    static = calibrate_static(store, capture, **extra) if static_options is None else calibrate_static(
        store, capture, static_options, **extra)
    tracking: list[ArtifactRef] = []
    if trackers:
        extra_t = {} if tracking_options is None else {"options": unmapped(tracking_options)}
        futures = calibrate_tracking_camera.map(unmapped(store), unmapped(capture), unmapped(static), trackers,
                                                **extra_t)
        tracking = [f.result() for f in futures]
    return assemble_calibration(store, capture, static, tracking)


#: dense-points frames in flight at once in :func:`point_cloud_for_frames` (each holds its own
#: working set: docs/calibration.md, "Dense points: memory and time")
DENSE_FRAMES_AT_ONCE = 1


def point_cloud_for_frames(store: str, capture: ArtifactRef, calibration: ArtifactRef, frames: list[int],
                           max_points_per_frame: int | None = None, seed: int = 0, scale: float = 1.0,
                           exclude_cameras: list[str] | None = None) -> ArtifactRef:
    """The PointCloudSequence ref of ``frames`` (take indices): one dense-points task per frame
    (mapped), then the sequence record (``max_points_per_frame``: a training budget, see
    :func:`tasks.calibrate.point_cloud_sequence`); ``exclude_cameras``: held-out cameras, which
    take no part. Call it inside a flow run (any). The frames run ``DENSE_FRAMES_AT_ONCE`` at a
    time, so the memory of a run is that of one frame whatever the frames.

    The same points get the same task inputs (:func:`dense_points_inputs`), so ``volcap
    reconstruct`` reuses the frames ``volcap calibrate`` made from the same cameras at the same
    scale."""
    frames = sorted({int(f) for f in frames})
    scale, exclude = dense_points_inputs(store, capture, calibration, scale, exclude_cameras)
    dense = []
    # Prefect's thread pool would run every frame at once, each with its own sweep, images and
    # points (the 11-14 GB for 12 frames at 640x360); a frame's sweep already uses every
    # core through torch, so frames go DENSE_FRAMES_AT_ONCE at a time
    for i in range(0, len(frames), DENSE_FRAMES_AT_ONCE):
        futures = dense_points_frame.map(unmapped(store), unmapped(capture), unmapped(calibration),
                                         frames[i:i + DENSE_FRAMES_AT_ONCE], unmapped(scale), unmapped(exclude))
        dense += [f.result() for f in futures]
    # without a budget the seed picks nothing: the sequence of the same frames is the same
    return point_cloud_sequence(store, calibration, dense, max_points_per_frame,
                                seed if max_points_per_frame is not None else 0)


def dense_points_inputs(store: str, capture: ArtifactRef, calibration: ArtifactRef, scale: float,
                        exclude_cameras: list[str] | None) -> tuple[float, list[str]]:
    """The ``dense-points-frame`` inputs ``(scale, exclude_cameras)`` in one spelling for the same
    points: the scale a float (``1`` and ``1.0`` are the same matching), and only the excluded
    cameras that would take part (:func:`~volcap_core.calibration.dense_points_step.dense_cameras`:
    a held-out tracking camera, or one the calibration left out, changes no point), sorted, an
    empty list for none."""
    s = ArtifactStore(store)
    exclude = set(exclude_cameras or ())
    if exclude:
        used = dense_cameras(s.get_record(capture, Capture), s.get_record(calibration, Calibration))
        exclude &= set(used)
    return float(scale), sorted(exclude)


#: the rigs a colour-charts spec names, and which one is mapped onto which by default
CHART_RIGS = ("face", "scene")


def chart_view(s: ArtifactStore, rig: str, spec: dict, base_dir: str | None = None) -> ChartView:
    """A :class:`ChartView` from its JSON spec (the fields of ChartView but ``rig``), with ``capture``
    and ``calibration`` given as ref names (``captures/NAME``, ``calibrations/NAME``) or digests, and
    ``image`` as a ref/digest or an EXR file (relative paths from ``base_dir``), which is stored."""
    if not isinstance(spec, dict):
        raise CalibrationInputError(f"colour charts: the {rig} rig's view must be a JSON object, got {type(spec).__name__}")
    fields = dict(spec)
    for key in ("capture", "calibration"):
        if isinstance(fields.get(key), str):
            fields[key] = s.resolve(fields[key])
    image = fields.get("image")
    if isinstance(image, str):
        path = Path(base_dir or ".") / image
        if image.startswith("blake3:") or not path.suffix:
            fields["image"] = s.resolve(image)
        elif path.is_file():
            fields["image"] = s.put_file(path, "image/x-exr", check_first=True)
        else:
            raise CalibrationInputError(f"colour charts: the {rig} rig's image {path} does not exist")
    try:
        return ChartView(rig=rig, **fields)
    except ValidationError as exc:
        err = exc.errors()[0]
        loc = ".".join(str(x) for x in err["loc"]) or "view"
        raise CalibrationInputError(f"colour charts: the {rig} rig's view: {loc}: {err['msg']}") from None


def chart_views(s: ArtifactStore, charts: dict, onto: str = "scene",
                base_dir: str | None = None) -> tuple[ChartView, ChartView]:
    """(source, reference) views of a colour-charts spec ``{"face": view, "scene": view}``: the rig
    ``onto`` is the reference, the other one is mapped onto it."""
    if not isinstance(charts, dict) or sorted(charts) != sorted(CHART_RIGS):
        got = ", ".join(sorted(charts)) if isinstance(charts, dict) else type(charts).__name__
        raise CalibrationInputError(f"colour charts: expected a view of each rig ({', '.join(CHART_RIGS)}), got {got}")
    if onto not in CHART_RIGS:
        raise CalibrationInputError(f"colour charts: --onto must be one of {', '.join(CHART_RIGS)}, got {onto!r}")
    source = next(r for r in CHART_RIGS if r != onto)
    return chart_view(s, source, charts[source], base_dir), chart_view(s, onto, charts[onto], base_dir)


def colour_summary(s: ArtifactStore, ref: ArtifactRef) -> dict:
    """JSON of a stored colour-matrix record: ref, rigs, matrix, offset, ΔE before and after."""
    rec = s.get_record(ref, ColourMatrixRecord)
    return {"colour": ref.model_dump(mode="json"), "source_rig": rec.source_rig, "reference_rig": rec.reference_rig,
            "matrix": [list(r) for r in rec.matrix], "offset": list(rec.offset), "patches": len(rec.patches_used),
            "before": rec.before, "after": rec.after}


@flow(name="calibrate-colour", persist_result=False)
def calibrate_colour_flow(store: str, charts: dict, onto: str = "scene", name: str | None = None,
                          base_dir: str | None = None) -> dict:
    """The colour matrix between the Face Rig and the Scene Rig from a chart seen by each
    (``charts``: ``{"face": view, "scene": view}``, see :func:`chart_view`), the other rig mapped
    onto ``onto``. Names the record ``colour/<name>`` (default ``colour/<source>-to-<reference>``)
    and returns :func:`colour_summary`."""
    s = ArtifactStore(store)
    source, reference = chart_views(s, charts, onto, base_dir)
    ref = calibrate_colour(store, source, reference)  # the task's default ColourCalibrationOptions
    s.set_ref(f"colour/{name or f'{source.rig}-to-{reference.rig}'}", ref)
    out = colour_summary(s, ref)
    get_run_logger().info("colour %s -> %s: ΔE2000 mean %.2f (max %.2f) over %d patches; before %.2f (max %.2f)",
                          source.rig, reference.rig, out["after"]["delta_e2000_mean"], out["after"]["delta_e2000_max"],
                          out["patches"], out["before"]["delta_e2000_mean"], out["before"]["delta_e2000_max"])
    return out


def scale_source_text(stage_frame: dict) -> str:
    """Where a capture without a scan took its scale from, in words (``stage_frame``: the
    ``static_frame_*`` stats of the Calibration record)."""
    source = stage_frame.get("scale_source")
    if source == 2.0:
        return "known distance between scene points"
    return "known distance between cameras" if source == 1.0 else "rig's mounts"


def known_points_text(stage_frame: dict, has_scan: bool) -> str:
    """The known scene points' figures of a calibration's ``stage_frame`` in one line."""
    d, t, sg = (stage_frame.get(k) for k in ("known_points_distance_m", "known_points_triangulated_m",
                                              "known_points_sigma_m"))
    n = int(stage_frame.get("known_points_distances", 1))
    text = (f"{d:.3f} m measured, {t:.3f} m ± {1000 * sg:.1f} mm triangulated"
            + (f" (first of {n} distances)" if n > 1 else ""))
    if has_scan:
        off = 1000 * stage_frame["known_points_residual_max_m"]
        return text + f"; with the lidar scan's scale: off by {off:.1f} mm"
    return (text + f"; scaled by {stage_frame['known_points_scale']:.5f}"
            + (f", distances within {1000 * stage_frame['known_points_residual_max_m']:.1f} mm after" if n > 1 else ""))


@flow(name="calibrate", persist_result=False)
def calibrate_flow(store: str, capture: str, frames: tuple[int, int] | None = None,
                   allow_unregistered: bool = False, colour_charts: dict | None = None,
                   colour_base_dir: str | None = None, instants: int = 1,
                   known_distance: tuple[str, str, float] | None = None,
                   known_points: dict | None = None, min_pair_inliers: int | None = None,
                   points: bool = True, against: str | None = None) -> dict:
    """Calibrate ``capture`` (a ref name such as ``captures/demo`` or a digest) and compute dense
    points for ``frames`` [a, b) (all frames when None).

    ``allow_unregistered``: a static or tracking camera the adjustment cannot support is left out
    (listed in ``unregistered`` with the reason) instead of failing the run. ``instants``: take instants pooled
    into the static SfM (``StaticCalibrationOptions.instants``: a sparse background). ``known_distance``:
    (camera, camera, metres) between two static cameras' centres, the scale of a capture without a
    lidar scan (``StaticCalibrationOptions.known_distance``; default: the rig's mounts). ``known_points``:
    the JSON of :class:`~volcap_core.calibration.scale.KnownPoints` (named scene points marked in two or
    more static cameras and the measured distance between them), the scale instead.
    ``min_pair_inliers``: the verified matches a pair of static cameras needs to take part in the
    static SfM (default 36, tuned on the 320x180 demo rig whose neighbours share 50-95; a sparse rig
    of wide baselines, e.g. 40 views around one object, needs ~20, or its cameras fall apart into
    weakly tied groups that the adjustment turns by degrees: docs/calibration.md).

    Returns JSON: ``calibration`` and ``points`` (ref dumps), ``errors`` (the error table of
    ``volcap_core.calibration.metrics`` when the capture carries ground truth, else None),
    ``unregistered`` (camera id -> reason), ``warnings`` (the Calibration's: a step that did not run and
    why, a camera whose sigma cannot be trusted; each also logged as a warning). Also names the results ``calibrations/<capture name>``
    and ``points/<capture name>`` in the store.

    ``stage_frame``: for a capture without a lidar scan, how its stage frame and scale were set
    (``static.frame_without_lidar``: ``scale_source`` 0 mounts / 1 known distance / 2 known points, ``scale``,
    ``mount_residual_rms_m`` / ``_max_m``...; with a scan and a known distance, its check), else None.

    ``points=False``: the calibration alone, no dense points (``points`` None in the result; a
    reconstruction computes them). ``against``: a Calibration ref (``imported-calibrations/NAME``:
    the studio's) to compare the static cameras with: ``against`` in the result holds each camera's
    :func:`~volcap_core.calibration.metrics.errors_against` beside its stated σ.

    ``colour_charts``: ``{"face": view, "scene": view}`` (:func:`chart_view`; relative image paths
    from ``colour_base_dir``) also runs ``calibrate-colour`` (Face Rig onto Scene Rig) and adds
    ``colour`` (:func:`colour_summary`) to the result, the record named ``colour/<capture name>``.
    """
    log = get_run_logger()
    known = known_points_spec(known_points, known_distance)
    s = ArtifactStore(store)
    capture_ref = s.resolve(capture)
    cap = s.get_record(capture_ref, Capture)
    a, b = cap.take_range(frames)
    # the trusted calibration read before the solve: a wrong ref fails at once, not after minutes
    trusted = s.get_record(s.resolve(against), Calibration) if against is not None else None
    trackers = tracking_camera_ids(cap)
    log.info("capture %s: %d static + %d tracking cameras, dense points for frames %d:%d", cap.name,
             len(cap.cameras) - len(trackers), len(trackers), a, b)
    # only the settings given differ from the task's defaults (none given: the defaults' cache key)
    calib_ref = calibrate_capture(store, capture_ref,
                                  static_calibration_options(allow_unregistered, instants, known_distance,
                                                             min_pair_inliers), known,
                                  tracking_calibration_options(allow_unregistered))
    calib = s.get_record(calib_ref, Calibration)
    unregistered = calib.unregistered
    # without a lidar scan: the stage frame from the mounts (or a known distance) and their residual
    stage_frame = {k[len("static_frame_"):]: v for k, v in calib.stats.items() if k.startswith("static_frame_")} or None
    if stage_frame is not None and cap.lidar is None:
        log.info("capture %s has no lidar scan: stage frame and scale from the %s; camera centres %.3f m rms "
                 "(max %.3f m) from their mounts", cap.name,
                 scale_source_text(stage_frame),
                 stage_frame.get("mount_residual_rms_m", float("nan")), stage_frame.get("mount_residual_max_m", float("nan")))
    if stage_frame is not None and "known_points_distance_m" in stage_frame:
        log.info("capture %s: known points: %s", cap.name, known_points_text(stage_frame, cap.lidar is not None))
    for cam, why in unregistered.items():
        log.warning("capture %s: camera %s left out of the calibration: %s", cap.name, cam, why)
    for line in calib.warnings:
        log.warning("capture %s: %s", cap.name, line)
    points_ref = point_cloud_for_frames(store, capture_ref, calib_ref, list(range(a, b))) if points else None
    errors = None
    if cap.ground_truth is not None:
        errors = s.get_json(calibration_errors(store, capture_ref, calib_ref, points_ref))
    compared = None
    if trusted is not None:
        compared = errors_against(calib, trusted)
        for cam, e in compared.items():
            log.info("capture %s: camera %s against %s: rotation %.3f° (stated σ %s°), centre %.1f cm, focal %+.2f %%",
                     cap.name, cam, against, e["rotation_deg"],
                     "none" if e["rotation_sigma_deg"] is None else f"{e['rotation_sigma_deg']:.3f}",
                     100 * e["centre_m"], e["focal_pct"])
    colour = None
    if colour_charts is not None:
        source, reference = chart_views(s, colour_charts, "scene", colour_base_dir)
        colour_ref = calibrate_colour(store, source, reference)
        s.set_ref(f"colour/{cap.name}", colour_ref)
        colour = colour_summary(s, colour_ref)
    s.set_ref(f"calibrations/{cap.name}", calib_ref)
    if points_ref is not None:
        s.set_ref(f"points/{cap.name}", points_ref)
    return {"capture": capture_ref.model_dump(mode="json"), "calibration": calib_ref.model_dump(mode="json"),
            "points": points_ref.model_dump(mode="json") if points_ref is not None else None,
            "frames": [a, b], "tracking_cameras": trackers,
            "errors": errors, "unregistered": dict(unregistered), "warnings": list(calib.warnings), "colour": colour,
            "stage_frame": stage_frame, "against": compared}
