"""Colour between the rigs: the ``calibrate-colour`` task's step and its record.

A colour chart seen by the Face Rig and by the Scene Rig (:class:`ChartView`: where, and where its
patches are); :func:`colour_step` fits one rig's linear RGB onto the other's over the patches seen
in both (the library: :mod:`volcap_core.calibration.colour`) into a :class:`ColourMatrixRecord`.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from volcap_core.calibration.colour import (ColourCalibrationOptions, calibrate_colour, chart_grid_px,
                                            chart_patches_in_view, grid_spacing_px, sample_patches)
from volcap_core.calibration.distortion import rectify_frame
from volcap_core.calibration.errors import CalibrationInputError
from volcap_core.calibration.inputs import GetBytes, frame_loader
from volcap_core.calibration.record import (Calibration, Matrix3, camera_at, decode_tracking_frames, float_matrix,
                                            frame_camera)
from volcap_core.capture import Capture
from volcap_core.imageio.read import decode_exr
from volcap_core.records import ArtifactRef, Record

Point2 = tuple[float, float]


class ChartView(BaseModel):
    """Where a colour chart is seen in one rig: the image (a capture's frame: ``capture``,
    ``camera``, ``frame``; or a stored EXR: ``image``) and where its patches are, in exactly one of
    three ways:

    - ``patches_px``: every patch centre (OpenCV px), in the chart's patch order;
    - ``corners_px``: the centres of the four corner patches (first patch, end of the first row,
      last patch, start of the last row) of a ``rows`` x ``cols`` chart (a ColorChecker: 4 x 6);
      the others follow by the chart plane's projective map;
    - ``patches_m`` (stage frame, metres) and ``patch_size_m`` with a ``calibration`` of the capture:
      projected through that camera at that frame.

    ``patch_radius_px``: half the side of the averaged window (default: from the options'
    ``window_fraction`` and the patch spacing). Both rigs' views must list the same patches in the
    same order."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    rig: str = Field(description="which rig this is: 'face' or 'scene' (or any label)")
    capture: ArtifactRef | None = None
    camera: str | None = None
    frame: int = Field(default=0, ge=0, description="take index")
    image: ArtifactRef | None = Field(default=None, description="a stored EXR of the chart instead of a capture frame")
    patches_px: tuple[Point2, ...] | None = None
    corners_px: tuple[Point2, Point2, Point2, Point2] | None = None
    rows: int = Field(default=4, ge=2)
    cols: int = Field(default=6, ge=2)
    patch_radius_px: float | None = Field(default=None, gt=0)
    calibration: ArtifactRef | None = None
    patches_m: tuple[tuple[float, float, float], ...] | None = None
    patch_size_m: float | None = Field(default=None, gt=0)

    def label(self) -> str:
        if self.image is not None:
            return f"{self.rig} rig, image {self.image.digest}"
        return f"{self.rig} rig, camera {self.camera}, frame {self.frame}"


class ColourMatrixRecord(Record):
    """The colour calibration between two rigs: the source rig's linear RGB mapped onto the
    reference rig's, ``ref ≈ matrix @ src + offset`` (Rec.709 linear). ``before`` / ``after``: ΔE76
    and ΔE2000 over the chart patches seen in both views (mean, max), ``delta_e2000`` per patch used
    (after). Applied to an image by :func:`volcap_core.calibration.colour.apply_colour_matrix`."""

    kind: ClassVar[str] = "colour-matrix"
    source_rig: str
    reference_rig: str
    source: ChartView
    reference: ChartView
    matrix: Matrix3
    offset: tuple[float, float, float]
    patches_used: tuple[int, ...]
    before: dict[str, float]
    after: dict[str, float]
    delta_e2000: tuple[float, ...]


def _view_image(view: ChartView, get_bytes: GetBytes) -> np.ndarray:
    if (view.image is None) == (view.capture is None):
        raise CalibrationInputError(f"colour chart ({view.rig} rig): give either a capture (with camera and frame) "
                                    "or an image")
    if view.image is not None:
        try:
            pixels, _ = decode_exr(get_bytes(view.image), name=f"chart image {view.image.digest}")
        except ValueError as exc:
            raise CalibrationInputError(f"colour chart ({view.label()}): not a readable EXR: {exc}") from exc
        return np.ascontiguousarray(pixels[..., :3], np.float32)
    cap = Capture.from_json_bytes(get_bytes(view.capture))
    ids = [c.id for c in cap.cameras]
    if view.camera not in ids:
        raise CalibrationInputError(f"colour chart ({view.rig} rig): capture {cap.name} has no camera "
                                    f"{view.camera!r} (it has {', '.join(ids)})")
    return frame_loader(get_bytes, cap)(view.camera, view.frame)


def chart_view_colours(view: ChartView, get_bytes: GetBytes,
                       options: ColourCalibrationOptions = ColourCalibrationOptions()) -> tuple[np.ndarray, np.ndarray]:
    """The chart's patch colours [N, 3] (linear) in ``view`` and which were sampled [N] (window inside
    the image, ≥ 4 px)."""
    given = [k for k in ("patches_px", "corners_px", "patches_m") if getattr(view, k) is not None]
    if len(given) != 1:
        raise CalibrationInputError(f"colour chart ({view.label()}): give exactly one of patches_px, corners_px, "
                                    f"patches_m (got {', '.join(given) or 'none'})")
    image = _view_image(view, get_bytes)
    if view.patches_m is not None:
        if view.calibration is None or view.patch_size_m is None or view.capture is None:
            raise CalibrationInputError(f"colour chart ({view.label()}): patches_m needs the capture, its "
                                        "calibration and patch_size_m")
        calib = Calibration.from_json_bytes(get_bytes(view.calibration))
        tracking = None
        if calib.tracking_frames is not None and view.camera in calib.tracking_ids:
            tracking = decode_tracking_frames(get_bytes(calib.tracking_frames))
        try:
            K, w2c, _, _ = camera_at(calib, view.camera, view.frame, tracking)
        except (KeyError, IndexError) as exc:
            raise CalibrationInputError(f"colour chart ({view.label()}): {exc}") from exc
        # the record's K is the pinhole of the rectified frame (a tracking camera's: of that frame's lens)
        image = rectify_frame(image, frame_camera(calib, view.camera, view.frame, tracking))
        return chart_patches_in_view(image, K, w2c, np.asarray(view.patches_m, np.float64), view.patch_size_m,
                                     options.window_fraction)
    if view.corners_px is not None:
        try:
            centres = chart_grid_px(np.asarray(view.corners_px, np.float64), view.rows, view.cols)
        except ValueError as exc:
            raise CalibrationInputError(f"colour chart ({view.label()}): {exc}") from exc
        spacing = grid_spacing_px(centres, view.rows, view.cols)
    else:
        centres = np.asarray(view.patches_px, np.float64).reshape(-1, 2)
        if len(centres) < 2 and view.patch_radius_px is None:
            raise CalibrationInputError(f"colour chart ({view.label()}): one patch: give patch_radius_px")
        d = np.linalg.norm(centres[:, None] - centres[None], axis=-1)
        np.fill_diagonal(d, np.inf)
        spacing = d.min(1)
    radius = (np.full(len(centres), view.patch_radius_px) if view.patch_radius_px is not None
              else 0.5 * options.window_fraction * spacing)
    cols, ok = np.zeros((len(centres), 3)), np.zeros(len(centres), bool)
    for i, (c, r) in enumerate(zip(centres, radius)):
        v, m = sample_patches(image, c[None], float(r))
        cols[i], ok[i] = v[0], bool(m[0])
    return cols, ok


def colour_step(source: ChartView, reference: ChartView, get_bytes: GetBytes,
                options: ColourCalibrationOptions = ColourCalibrationOptions()) -> ColourMatrixRecord:
    """Fit the source rig's chart colours onto the reference rig's (:func:`colour.calibrate_colour`)
    over the patches sampled in both views; refuses views that disagree on the patch count or
    share fewer than ``options.min_patches`` patches."""
    src, ok_s = chart_view_colours(source, get_bytes, options)
    ref, ok_r = chart_view_colours(reference, get_bytes, options)
    if len(src) != len(ref):
        raise CalibrationInputError(f"colour chart: {len(src)} patches in the {source.label()} but {len(ref)} in the "
                                    f"{reference.label()}: both views must list the same patches")
    both = ok_s & ok_r
    need = max(options.min_patches, 4 if options.offset else 3)
    if both.sum() < need:
        where = [f"{v.label()}: {int(ok.sum())} of {len(ok)}" for v, ok in ((source, ok_s), (reference, ok_r))]
        raise CalibrationInputError(f"colour chart: {int(both.sum())} patches sampled in both views, the fit needs "
                                    f"{need} (patches inside the image: {'; '.join(where)})")
    res = calibrate_colour(src[both], ref[both], offset=options.offset, robust_iterations=options.robust_iterations)
    summary = lambda r: {k: float(v) for k, v in r.items() if k != "delta_e2000"}  # noqa: E731
    return ColourMatrixRecord(source_rig=source.rig, reference_rig=reference.rig, source=source, reference=reference,
                              matrix=float_matrix(res["matrix"]), offset=tuple(float(v) for v in res["offset"]),
                              patches_used=tuple(int(i) for i in np.flatnonzero(both)),
                              before=summary(res["before"]), after=summary(res["after"]),
                              delta_e2000=tuple(round(float(v), 6) for v in res["after"]["delta_e2000"]))
