"""Rig descriptions: cameras, lenses, mounts, lights. Data in ``hardware/rigs/*.json``.

Units: millimetres for focal lengths and sensor sizes, metres for positions, pixels for
resolution, hertz / milliseconds for the strobe. World frame: the stage frame, z up, origin at the
stage centre on the floor.

Roles (paper, "Hardware Setup of the Scene Rig"):

- ``static``: wide field-of-view cameras (14-42 mm on the Scene Rig) that never move during a take;
- ``tracking-landscape``: pan/tilt/zoom heads (45-175 mm) framing faces, lens encoders report focal;
- ``tracking-portrait``: portrait-oriented tracking cameras framing full/upper/lower body.

Lens calibrations (optional): a static camera's ``intrinsics`` (:class:`MeasuredIntrinsics`, or its
``lens_group``'s), a tracking camera's ``zoom_intrinsics`` (:class:`ZoomIntrinsics`: its distortion,
and optionally its principal point, sampled over its focal in mm, linear in the focal in between);
either also read as calibration tools write lenses (OpenCV's distCoeffs vectors, COLMAP cameras:
``hardware.lens_models``)."""

from __future__ import annotations

import bisect
import json
import math
from enum import Enum
from importlib import resources
from pathlib import Path
from typing import Iterable, Literal

from pydantic import (BaseModel, ConfigDict, Field, SerializerFunctionWrapHandler, ValidationError, model_serializer,
                      model_validator)

from hardware.lens_models import DISTORTION_MODELS, colmap_intrinsics, opencv_distortion
from hardware.serialization import omit_unset
from hardware.validation_errors import format_loc, format_validation_error


class CameraRole(str, Enum):
    static = "static"
    tracking_landscape = "tracking-landscape"
    tracking_portrait = "tracking-portrait"

    @property
    def tracks(self) -> bool:
        return self is not CameraRole.static


class Lens(BaseModel):
    """A lens: fixed focal when ``focal_min_mm == focal_max_mm``, a zoom range otherwise."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    focal_min_mm: float = Field(gt=0)
    focal_max_mm: float = Field(gt=0)

    @model_validator(mode="after")
    def _ordered(self) -> "Lens":
        if self.focal_max_mm < self.focal_min_mm:
            raise ValueError(f"lens range {self.focal_min_mm}-{self.focal_max_mm} mm is reversed")
        return self

    def contains(self, focal_mm: float, tol_mm: float = 1e-6) -> bool:
        return self.focal_min_mm - tol_mm <= focal_mm <= self.focal_max_mm + tol_mm


class Sensor(BaseModel):
    """Sensor geometry. ``width_mm``/``height_mm`` are the active area at ``width_px``×``height_px``.

    Portrait cameras are the same sensor rotated: they report width < height in pixels.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)
    width_mm: float = Field(gt=0)
    height_mm: float = Field(gt=0)
    width_px: int = Field(gt=0)
    height_px: int = Field(gt=0)

    def focal_px(self, focal_mm: float) -> float:
        """Focal length in pixels for a focal in millimetres (square pixels assumed)."""
        return focal_mm * self.width_px / self.width_mm


class Mount(BaseModel):
    """Where a camera hangs and where it looks at the rig's nominal set-up (metres, stage frame)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    kind: Literal["ceiling", "floor", "cart", "wall", "tripod"]
    position_m: tuple[float, float, float]
    look_at_m: tuple[float, float, float]
    cart: int | None = None  # cart index for cart mounts
    roll_deg: float = 0.0


class MeasuredIntrinsics(BaseModel):
    """A lens calibration of one camera (or of a lens group): pixels at the camera's
    ``sensor.width_px`` x ``height_px``, OpenCV convention (centre of the top-left pixel at (0, 0));
    ``model`` one of :data:`~hardware.lens_models.DISTORTION_MODELS` with its ``params`` in that
    order (COLMAP's order, also OpenCV's ``distCoeffs`` order).

    Two more forms are read, as calibration tools write them, and held in this one
    (:meth:`_studio_forms`; ``hardware.lens_models`` maps them exactly or refuses them):

    - ``fx, fy, cx, cy`` and ``opencv``: OpenCV's ``distCoeffs`` vector of 4, 5, 8, 12 or 14
      values (thin-prism and tilt terms only as zeros);
    - ``colmap``: ``{"model": ..., "params": [...]}``, a COLMAP camera (a ``cameras.txt`` line's
      model and parameters, COLMAP's order and pixels: principal point +0.5) at the camera's
      resolution; ``fx, fy, cx, cy`` come from it."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    fx: float = Field(gt=0)
    fy: float = Field(gt=0)
    cx: float
    cy: float
    model: str = "PINHOLE"
    params: tuple[float, ...] = ()

    @model_validator(mode="before")
    @classmethod
    def _studio_forms(cls, data):
        # ``opencv`` / ``colmap`` -> model + params (and fx..cy): stored, serialised and applied as
        # the canonical form, so a rig reads the same however its lens was written
        if not isinstance(data, dict) or not ({"opencv", "colmap"} & set(data)):
            return data
        data = dict(data)
        if "opencv" in data and "colmap" in data:
            raise ValueError("give the lens as one of opencv or colmap, not both")
        taken = sorted({"model", "params"} & set(data))
        if "opencv" in data:
            if taken:
                raise ValueError(f"give the distortion as opencv or as model + params, not both (got opencv and "
                                 f"{' and '.join(taken)})")
            data["model"], data["params"] = opencv_distortion(data.pop("opencv"))
            return data
        camera = data.pop("colmap")
        if not isinstance(camera, dict) or set(camera) != {"model", "params"}:
            raise ValueError(f"colmap: a COLMAP camera as {{\"model\": NAME, \"params\": [...]}}, got {camera!r}")
        taken = sorted({"fx", "fy", "cx", "cy", "model", "params"} & set(data))
        if taken:
            raise ValueError(f"a COLMAP camera carries its own focal, principal point and distortion: give colmap "
                             f"without {', '.join(taken)}")
        (fx, fy, cx, cy), model, params = colmap_intrinsics(camera["model"], camera["params"])
        data.update(fx=fx, fy=fy, cx=cx, cy=cy, model=model, params=params)
        return data

    @model_validator(mode="after")
    def _params_fit_model(self) -> "MeasuredIntrinsics":
        names = DISTORTION_MODELS.get(self.model)
        if names is None:
            raise ValueError(f"unknown distortion model {self.model!r}: one of {', '.join(DISTORTION_MODELS)}")
        if len(self.params) != len(names):
            hint = ""
            if self.model in ("OPENCV", "FULL_OPENCV"):
                hint = (": OpenCV's distCoeffs vector (4, 5, 8, 12 or 14 coefficients) goes in as it is in "
                        "opencv, in place of model and params")
            raise ValueError(f"distortion model {self.model} takes {len(names)} parameters "
                             f"({', '.join(names) or 'none'}), got {len(self.params)}{hint}")
        return self

    def check_against(self, cam_id: str, sensor: Sensor, lens: Lens) -> None:
        """Refuse intrinsics that cannot belong to this camera (principal point outside the image,
        a focal that is not the lens's, e.g. given in mm or at another resolution)."""
        if not (0 <= self.cx <= sensor.width_px - 1 and 0 <= self.cy <= sensor.height_px - 1):
            raise ValueError(f"camera {cam_id}: measured principal point ({self.cx}, {self.cy}) px is outside "
                             f"the {sensor.width_px}x{sensor.height_px} image")
        for name, f, px, mm in (("fx", self.fx, sensor.width_px, sensor.width_mm),
                                ("fy", self.fy, sensor.height_px, sensor.height_mm)):
            f_mm = f * mm / px
            if not (0.9 * lens.focal_min_mm <= f_mm <= 1.1 * lens.focal_max_mm):
                raise ValueError(f"camera {cam_id}: measured {name} {f} px is {f_mm:.1f} mm on its sensor, outside "
                                 f"its lens range {lens.focal_min_mm}-{lens.focal_max_mm} mm (pixels must be at "
                                 f"the rig's resolution {sensor.width_px}x{sensor.height_px})")


class ZoomSample(BaseModel):
    """One sample of a zoom lens's calibration: at focal ``focal_mm`` (the focal the lens has at
    that zoom setting, as a checkerboard calibration there measured it: its fx in pixels times the
    sensor's ``width_mm / width_px``; not an encoder count), the distortion ``params`` (in the
    table's ``model``, COLMAP's order, on normalized coordinates) and optionally the principal point
    ``cx``, ``cy`` (pixels at the camera's ``sensor.width_px`` x ``height_px``, OpenCV convention)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    focal_mm: float = Field(gt=0)
    params: tuple[float, ...] = ()
    cx: float | None = None
    cy: float | None = None

    @model_serializer(mode="wrap")
    def _omit_unset(self, handler: SerializerFunctionWrapHandler):
        return omit_unset(handler(self), ("cx", "cy"))


class ZoomIntrinsics(BaseModel):
    """A zoom lens's distortion (and principal point) as a function of its focal length: a table of
    :class:`ZoomSample` in increasing focal, one distortion ``model`` for all of them (one of
    :data:`DISTORTION_MODELS`). Samples may give OpenCV's distCoeffs vectors (``opencv``) in place
    of ``params``: :meth:`_opencv_samples` holds them in one model.

    Between samples every parameter is **linear in the focal** (mm): :meth:`at`. For the OPENCV
    family without a rational term the distorted point is linear in the parameters, so this is the
    linear blend of the two samples' distortion fields. Coefficients on normalized coordinates grow
    about as focal² for a lens whose distortion at the image corner (in %) changes slowly (the
    corner's normalized radius is ``half diagonal / focal``): for k ∝ focal² a line in the focal
    errs a third as much as a line in 1/focal (0.6x on the demo rig's tables). Outside the table the end sample
    holds (**clamped**): readings and estimates stray a little past the zoom's end stops (the
    encoder's noise and gain error), and a table must reach both ends of the lens's range
    (:meth:`check_against`), so the clamp never extrapolates over more than that."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    model: str = "OPENCV"
    samples: tuple[ZoomSample, ...]

    @model_validator(mode="before")
    @classmethod
    def _opencv_samples(cls, data):
        # samples written as OpenCV's distCoeffs (``opencv`` in place of ``params``), as a lens
        # calibrated at each zoom setting gives them: one model for the table (the table's when
        # given, else the smallest that holds every sample) and each sample's params in it
        if not isinstance(data, dict) or not isinstance(data.get("samples"), (list, tuple)):
            return data
        samples = data["samples"]
        vectors = [isinstance(smp, dict) and "opencv" in smp for smp in samples]
        if not any(vectors):
            return data
        if not all(vectors) or any("params" in smp for smp in samples):
            raise ValueError("give every sample's distortion as opencv (OpenCV's distCoeffs), or every sample's as "
                             "params in the table's model, not a mix")

        def read(smp: dict, model: str | None) -> tuple[str, tuple[float, ...]]:
            try:
                return opencv_distortion(smp["opencv"], model)
            except ValueError as exc:
                raise ValueError(f"the sample at {smp.get('focal_mm')} mm: {exc}") from None

        order = list(DISTORTION_MODELS)
        model = data.get("model") or max((read(smp, None)[0] for smp in samples), key=order.index)
        out = [{**{k: v for k, v in smp.items() if k != "opencv"}, "params": read(smp, model)[1]} for smp in samples]
        return {**data, "model": model, "samples": out}

    @model_validator(mode="after")
    def _table_is_consistent(self) -> "ZoomIntrinsics":
        names = DISTORTION_MODELS.get(self.model)
        if names is None:
            raise ValueError(f"unknown distortion model {self.model!r}: one of {', '.join(DISTORTION_MODELS)}")
        if len(self.samples) < 2:
            raise ValueError(f"a zoom lens table needs at least two samples (its zoom's ends), got {len(self.samples)}")
        for s in self.samples:
            if len(s.params) != len(names):
                raise ValueError(f"the sample at {s.focal_mm} mm: distortion model {self.model} takes {len(names)} "
                                 f"parameters ({', '.join(names) or 'none'}), got {len(s.params)}")
            if not all(math.isfinite(v) for v in s.params):
                raise ValueError(f"the sample at {s.focal_mm} mm: non-finite parameters {s.params}")
            if (s.cx is None) != (s.cy is None):
                raise ValueError(f"the sample at {s.focal_mm} mm: give both cx and cy, or neither")
        with_pp = {s.cx is not None for s in self.samples}
        if len(with_pp) > 1:
            raise ValueError("the principal point (cx, cy) is given at some samples and not at others: give it at "
                             "every sample or at none")
        focals = [s.focal_mm for s in self.samples]
        for a, b in zip(focals, focals[1:]):
            if b == a:
                raise ValueError(f"focal {a} mm is sampled twice")
            if b < a:
                raise ValueError(f"samples must be in increasing focal order: {b} mm comes after {a} mm")
        return self

    def check_against(self, cam_id: str, sensor: Sensor, lens: Lens) -> None:
        """Refuse a table that cannot belong to this camera: a sample outside its lens's zoom range
        (e.g. a focal in pixels), a table that does not reach both ends of that range (1 %: beyond
        the ends it would be clamped), a principal point outside the image."""
        lo, hi = self.samples[0].focal_mm, self.samples[-1].focal_mm
        for s in self.samples:
            if not lens.contains(s.focal_mm, tol_mm=1e-6 * lens.focal_max_mm):
                raise ValueError(f"camera {cam_id}: zoom lens sample at {s.focal_mm} mm is outside its lens range "
                                 f"{lens.focal_min_mm}-{lens.focal_max_mm} mm (focals in mm, not pixels)")
        if lo > lens.focal_min_mm * 1.01 or hi < lens.focal_max_mm * 0.99:
            raise ValueError(f"camera {cam_id}: the zoom lens table covers {lo}-{hi} mm of its lens range "
                             f"{lens.focal_min_mm}-{lens.focal_max_mm} mm: sample both ends of the zoom (beyond the "
                             f"table the end sample would hold)")
        for s in self.samples:
            if s.cx is not None and not (0 <= s.cx <= sensor.width_px - 1 and 0 <= s.cy <= sensor.height_px - 1):
                raise ValueError(f"camera {cam_id}: zoom lens sample at {s.focal_mm} mm: principal point "
                                 f"({s.cx}, {s.cy}) px is outside the {sensor.width_px}x{sensor.height_px} image")

    @property
    def focals_mm(self) -> tuple[float, ...]:
        return tuple(s.focal_mm for s in self.samples)

    @property
    def has_principal(self) -> bool:
        return self.samples[0].cx is not None

    def at(self, focal_mm: float) -> ZoomSample:
        """The lens at one focal (mm): a :class:`ZoomSample` of the interpolated parameters (and
        principal point, when the table has one) with ``focal_mm`` the focal asked for. Linear in
        the focal between the samples, the end sample's values outside them."""
        return self.at_each([focal_mm])[0]

    def at_each(self, focals_mm: Iterable[float]) -> list[ZoomSample]:
        """:meth:`at` for each focal of ``focals_mm`` (mm; a list or a numpy array)."""
        focals = self.focals_mm
        out = []
        for f in (float(v) for v in focals_mm):
            if not math.isfinite(f):
                raise ValueError(f"zoom lens at a non-finite focal {f}")
            i = max(0, min(len(focals) - 2, bisect.bisect_right(focals, f) - 1))
            a, b = self.samples[i], self.samples[i + 1]
            w = min(1.0, max(0.0, (f - a.focal_mm) / (b.focal_mm - a.focal_mm)))
            params = tuple((1 - w) * p + w * q for p, q in zip(a.params, b.params))
            pp = {}
            if a.cx is not None:
                pp = {"cx": (1 - w) * a.cx + w * b.cx, "cy": (1 - w) * a.cy + w * b.cy}
            out.append(ZoomSample.model_construct(focal_mm=f, params=params, **pp))
        return out


class RigCamera(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    id: str = Field(pattern=r"^[A-Za-z0-9_.-]+$")
    role: CameraRole
    lens: Lens
    sensor: Sensor
    mount: Mount
    nominal_focal_mm: float = Field(gt=0, description="focal at the nominal set-up (static cameras keep it)")
    intrinsics: MeasuredIntrinsics | None = Field(
        default=None, description="measured intrinsics and distortion (a lens calibration); None: nominal")
    lens_group: str | None = Field(
        default=None, pattern=r"^[A-Za-z0-9_.-]+$",
        description="cameras sharing a body and lens; the rig's lens_groups entry of that name, when there "
                    "is one, is their measured intrinsics")
    zoom_intrinsics: ZoomIntrinsics | None = Field(
        default=None, description="a tracking camera's zoom lens calibration: distortion (and principal point) "
                                  "as a function of its focal; None: a pinhole with its principal point at the "
                                  "image centre")

    @model_serializer(mode="wrap")
    def _omit_unset(self, handler: SerializerFunctionWrapHandler):
        # rigs (and the Capture records holding them) without measured intrinsics serialise as before
        return omit_unset(handler(self), ("intrinsics", "lens_group", "zoom_intrinsics"))

    @model_validator(mode="wrap")
    @classmethod
    def _name_the_camera(cls, data, handler):
        # a lens's own errors (a zoom table's order, parameter counts, an OpenCV term volcap does not
        # apply...) are raised inside the nested model, where the camera is not known: name it
        try:
            return handler(data)
        except ValidationError as exc:
            cam_id = data.get("id") if isinstance(data, dict) else getattr(data, "id", None)
            lines = format_validation_error(exc, describe_loc=lambda loc: ".".join(str(x) for x in loc))
            lens = [line for line in lines if line.startswith(("intrinsics", "zoom_intrinsics"))]
            if cam_id is None or not lens:
                raise
            raise ValueError(f"camera {cam_id}: {lens[0]}") from None

    @model_validator(mode="after")
    def _focal_in_range(self) -> "RigCamera":
        if not self.lens.contains(self.nominal_focal_mm):
            raise ValueError(
                f"camera {self.id}: nominal focal {self.nominal_focal_mm} mm is outside its lens range "
                f"{self.lens.focal_min_mm}-{self.lens.focal_max_mm} mm")
        if self.role is CameraRole.tracking_portrait and self.sensor.width_px > self.sensor.height_px:
            raise ValueError(f"camera {self.id}: a portrait tracking camera must be taller than wide")
        if self.intrinsics is not None:
            if self.role.tracks:
                raise ValueError(f"camera {self.id}: measured intrinsics on a {self.role.value} camera: a zoom "
                                 f"lens's intrinsics change with its focal: give them as a table over its focal "
                                 f"(zoom_intrinsics)")
            self.intrinsics.check_against(self.id, self.sensor, self.lens)
        if self.zoom_intrinsics is not None:
            if not self.role.tracks:
                raise ValueError(f"camera {self.id}: a zoom lens table (zoom_intrinsics) on a static camera: its "
                                 f"focal does not change during a take; give its measured intrinsics instead")
            self.zoom_intrinsics.check_against(self.id, self.sensor, self.lens)
        return self


class Lighting(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    description: str
    strobe_hz: float | None = None       # LED strobe frequency (Scene Rig: 72 Hz)
    flash_ms: float | None = None        # flash length (Scene Rig: 1 ms, in sync with the shutters)
    led_panels: int = 0
    white_lights: int = 0


class Rig(BaseModel):
    """A capture rig. Camera ids are unique; every camera's focal lies in its lens range."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    name: str
    kind: Literal["scene", "face"]
    fps: float = Field(gt=0)
    stage_size_m: tuple[float, float, float] = Field(description="x, y extent and height of the volume")
    cameras: tuple[RigCamera, ...]
    lighting: Lighting
    lens_groups: dict[str, MeasuredIntrinsics] = Field(
        default_factory=dict, description="measured intrinsics shared by the static cameras naming the group")
    zoom_lens_groups: dict[str, ZoomIntrinsics] = Field(
        default_factory=dict, description="a zoom lens table shared by the tracking cameras naming the group "
                                          "(one lens model, calibrated once over its focal)")

    @model_serializer(mode="wrap")
    def _omit_unset(self, handler: SerializerFunctionWrapHandler):
        return omit_unset(handler(self), ("lens_groups", "zoom_lens_groups"))

    @model_validator(mode="after")
    def _unique_ids(self) -> "Rig":
        seen: set[str] = set()
        for cam in self.cameras:
            if cam.id in seen:
                raise ValueError(f"rig {self.name}: duplicate camera id {cam.id!r}")
            seen.add(cam.id)
        if not self.cameras:
            raise ValueError(f"rig {self.name}: no cameras")
        both = sorted(set(self.lens_groups) & set(self.zoom_lens_groups))
        if both:
            raise ValueError(f"rig {self.name}: lens group(s) {both} are given both measured intrinsics and a zoom "
                             f"lens table: one group is one kind of lens")
        groups: dict[str, RigCamera] = {}
        for cam in self.cameras:
            if cam.lens_group is None:
                continue
            first = groups.setdefault(cam.lens_group, cam)
            if (first.sensor, first.lens) != (cam.sensor, cam.lens):
                raise ValueError(f"rig {self.name}: camera {cam.id} is in lens group {cam.lens_group!r} with "
                                 f"camera {first.id} but has another sensor or lens")
            shared = self.lens_groups.get(cam.lens_group)
            if shared is not None:
                if cam.intrinsics is not None:
                    raise ValueError(f"rig {self.name}: camera {cam.id} has its own intrinsics and lens group "
                                     f"{cam.lens_group!r} has measured ones too: give one of them")
                if cam.role.tracks:
                    raise ValueError(f"rig {self.name}: camera {cam.id} is a {cam.role.value} camera in lens "
                                     f"group {cam.lens_group!r} with measured intrinsics: a zoom lens's "
                                     f"intrinsics change with its focal: give the group a table over its "
                                     f"focal (zoom_lens_groups) or the camera one (zoom_intrinsics)")
                shared.check_against(cam.id, cam.sensor, cam.lens)
            table = self.zoom_lens_groups.get(cam.lens_group)
            if table is not None:
                if not cam.role.tracks:
                    raise ValueError(f"rig {self.name}: static camera {cam.id} is in lens group {cam.lens_group!r}, "
                                     f"a zoom lens table: its focal does not change during a take; give the group "
                                     f"measured intrinsics (lens_groups) instead")
                if cam.zoom_intrinsics is not None:
                    raise ValueError(f"rig {self.name}: camera {cam.id} has its own zoom lens table and lens group "
                                     f"{cam.lens_group!r} has one too: give one of them")
                try:
                    table.check_against(cam.id, cam.sensor, cam.lens)
                except ValueError as exc:
                    raise ValueError(f"rig {self.name}: zoom lens group {cam.lens_group!r}: {exc}") from None
        unused = sorted((set(self.lens_groups) | set(self.zoom_lens_groups)) - set(groups))
        if unused:
            raise ValueError(f"rig {self.name}: lens group(s) {unused} are used by no camera")
        return self

    def measured_intrinsics(self, camera_id: str) -> MeasuredIntrinsics | None:
        """A static camera's measured intrinsics: its own, else its lens group's, else None (nominal)."""
        cam = self.camera(camera_id)
        if cam.intrinsics is not None:
            return cam.intrinsics
        if cam.lens_group is not None:
            return self.lens_groups.get(cam.lens_group)
        return None

    def with_finer_pixels(self, scale: int) -> "Rig":
        """This rig with every camera's pixel grid ``scale`` times finer: the same sensors and
        lenses, so the same views, with ``scale``² the pixels (a synthetic capture at higher
        resolution; benchmarks). Measured intrinsics (own and lens groups') and zoom tables'
        principal points move into the finer pixels (focal x ``scale``; OpenCV's pixel centres:
        ``c' = (c + 0.5) scale - 0.5``); distortion acts on normalized coordinates and is kept.
        Named ``<name>_x<scale>``; ``scale`` 1 is the rig itself."""
        if not isinstance(scale, int) or scale < 1:
            raise ValueError(f"rig {self.name}: the pixel scale must be a positive integer, got {scale!r}")
        if scale == 1:
            return self

        def centre(c: float) -> float:
            return (c + 0.5) * scale - 0.5

        def intrinsics(m: MeasuredIntrinsics) -> MeasuredIntrinsics:
            return m.model_copy(update={"fx": m.fx * scale, "fy": m.fy * scale, "cx": centre(m.cx),
                                        "cy": centre(m.cy)})

        def table(z: ZoomIntrinsics) -> ZoomIntrinsics:
            return z.model_copy(update={"samples": tuple(
                s if s.cx is None else s.model_copy(update={"cx": centre(s.cx), "cy": centre(s.cy)})
                for s in z.samples)})

        cams = []
        for c in self.cameras:
            update: dict = {"sensor": c.sensor.model_copy(update={"width_px": c.sensor.width_px * scale,
                                                                  "height_px": c.sensor.height_px * scale})}
            if c.intrinsics is not None:
                update["intrinsics"] = intrinsics(c.intrinsics)
            if c.zoom_intrinsics is not None:
                update["zoom_intrinsics"] = table(c.zoom_intrinsics)
            cams.append(c.model_copy(update=update))
        # validated again: a scaled rig is checked as any other
        return Rig.model_validate(self.model_copy(update={
            "name": f"{self.name}_x{scale}", "cameras": tuple(cams),
            "lens_groups": {k: intrinsics(v) for k, v in self.lens_groups.items()},
            "zoom_lens_groups": {k: table(v) for k, v in self.zoom_lens_groups.items()}}).model_dump())

    def zoom_intrinsics(self, camera_id: str) -> ZoomIntrinsics | None:
        """A tracking camera's zoom lens table: its own, else its lens group's, else None (a pinhole
        with its principal point at the image centre)."""
        cam = self.camera(camera_id)
        if cam.zoom_intrinsics is not None:
            return cam.zoom_intrinsics
        if cam.lens_group is not None:
            return self.zoom_lens_groups.get(cam.lens_group)
        return None

    def camera(self, camera_id: str) -> RigCamera:
        for cam in self.cameras:
            if cam.id == camera_id:
                return cam
        raise KeyError(f"rig {self.name} has no camera {camera_id!r}")

    @property
    def camera_ids(self) -> list[str]:
        return [c.id for c in self.cameras]

    def cameras_with_role(self, *roles: CameraRole) -> list[RigCamera]:
        return [c for c in self.cameras if c.role in roles]

    @property
    def has_tracking_cameras(self) -> bool:
        return any(c.role.tracks for c in self.cameras)


def builtin_rig_names() -> list[str]:
    files = resources.files("hardware") / "rigs"
    return sorted(p.name[:-5] for p in files.iterdir() if p.name.endswith(".json"))


def rig_file(reference: str | Path, base: str | Path = ".") -> Path | None:
    """The rig file a rig reference names, or None when it names a built-in rig.

    The one rule for every rig reference (a capture's ``rig``, a production spec's ``rigs``,
    ``volcap synth --rig``): a reference ending in ``.json`` is a rig file, relative to ``base`` (the
    folder of the document that names it; an absolute path stays as it is); any other is the name
    of a built-in rig (:func:`builtin_rig_names`). A ``.json`` reference never falls back to a
    built-in rig or to a file beside the working directory: a missing file is an error naming it.
    """
    return Path(base) / reference if str(reference).endswith(".json") else None


def load_rig(reference: str | Path, base: str | Path = ".") -> Rig:
    """Load a built-in rig by name (``scene_rig``, ``face_rig``, ``demo_scene``...) or a JSON file
    (relative to ``base``): :func:`rig_file` says which.

    Raises ``ValueError`` naming the rig and the problem when the file is missing or invalid, or the
    name unknown.
    """
    path = rig_file(reference, base)
    if path is not None:
        if not path.is_file():
            raise ValueError(f"rig file {path} does not exist")
        text, where = path.read_text(), str(path)
    else:
        res = resources.files("hardware") / "rigs" / f"{reference}.json"
        if not res.is_file():
            raise ValueError(f"unknown rig {str(reference)!r}: not one of {', '.join(builtin_rig_names())} "
                             "(a rig file's name ends in .json)")
        text, where = res.read_text(), f"built-in rig {reference}"
    try:
        data = json.loads(text)
        return Rig.model_validate(data)
    except ValidationError as exc:
        raise ValueError(f"{where}: invalid rig: {rig_problems(exc, data)}") from exc
    except ValueError as exc:
        raise ValueError(f"{where}: invalid rig: {exc}") from exc


def rig_problems(exc: ValidationError, data, shown: int = 3) -> str:
    """A rig's validation errors on one line: the first ``shown`` of them, each naming its camera
    (by id) or lens group and the field, with pydantic's or the validator's reason; ``; `` between
    them and ``(and N more)`` after. ``data``: the rig as validated (the camera ids are read from it)."""
    cameras = data.get("cameras") if isinstance(data, dict) else None

    def describe(loc: tuple) -> str:
        if loc[:1] == ("cameras",) and len(loc) >= 2 and isinstance(loc[1], int):
            cam = cameras[loc[1]] if isinstance(cameras, list) and loc[1] < len(cameras) else None
            name = f"camera {cam['id']}" if isinstance(cam, dict) and "id" in cam else f"camera #{loc[1]}"
            # a camera's own validators already name it
            return f"{name}: {format_loc(loc[2:])}" if len(loc) > 2 else ""
        if loc[:1] in (("lens_groups",), ("zoom_lens_groups",)) and len(loc) >= 2:
            kind = "lens group" if loc[0] == "lens_groups" else "zoom lens group"
            return f"{kind} {loc[1]!r}" + (f": {format_loc(loc[2:])}" if len(loc) > 2 else "")
        return format_loc(loc) if loc else ""   # the rig's own validators name the rig

    lines = format_validation_error(exc, describe_loc=describe)
    text = "; ".join(lines[:shown])
    return text + (f" (and {len(lines) - shown} more)" if len(lines) > shown else "")
