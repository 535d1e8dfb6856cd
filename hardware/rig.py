"""Rig descriptions: cameras, lenses, mounts, lights. Data in ``hardware/rigs/*.json``.

Units: millimetres for focal lengths and sensor sizes, metres for positions, pixels for
resolution, hertz / milliseconds for the strobe. World frame: the stage frame, z up, origin at the
stage centre on the floor.

Roles (paper, "Hardware Setup of the Scene Rig"):

- ``static``: wide field-of-view cameras (14-42 mm on the Scene Rig) that never move during a take;
- ``tracking-landscape``: pan/tilt/zoom heads (45-175 mm) framing faces, lens encoders report focal;
- ``tracking-portrait``: portrait-oriented tracking cameras framing full/upper/lower body.
"""

from __future__ import annotations

import json
from enum import Enum
from importlib import resources
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, SerializerFunctionWrapHandler, model_serializer, model_validator


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


#: lens distortion models (COLMAP's names) -> their parameters in order; the same table as
#: ``volcap_core.calibration.distortion.MODELS`` (a test keeps them equal)
DISTORTION_MODELS: dict[str, tuple[str, ...]] = {
    "PINHOLE": (),
    "SIMPLE_RADIAL": ("k",),
    "RADIAL": ("k1", "k2"),
    "OPENCV": ("k1", "k2", "p1", "p2"),
    "FULL_OPENCV": ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
}


class MeasuredIntrinsics(BaseModel):
    """A lens calibration of one camera (or of a lens group): pixels at the camera's
    ``sensor.width_px`` x ``height_px``, OpenCV convention (centre of the top-left pixel at (0, 0));
    ``model`` one of :data:`DISTORTION_MODELS` with its ``params`` in that order (COLMAP's order,
    also OpenCV's ``distCoeffs`` order)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    fx: float = Field(gt=0)
    fy: float = Field(gt=0)
    cx: float
    cy: float
    model: str = "PINHOLE"
    params: tuple[float, ...] = ()

    @model_validator(mode="after")
    def _params_fit_model(self) -> "MeasuredIntrinsics":
        names = DISTORTION_MODELS.get(self.model)
        if names is None:
            raise ValueError(f"unknown distortion model {self.model!r}: one of {', '.join(DISTORTION_MODELS)}")
        if len(self.params) != len(names):
            raise ValueError(f"distortion model {self.model} takes {len(names)} parameters "
                             f"({', '.join(names) or 'none'}), got {len(self.params)}")
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


def _drop_empty(data, keys: tuple[str, ...]):
    if isinstance(data, dict):
        for k in keys:
            if k in data and data[k] in (None, {}, ()):
                del data[k]
    return data


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

    @model_serializer(mode="wrap")
    def _omit_unset(self, handler: SerializerFunctionWrapHandler):
        # rigs (and the Capture records holding them) without measured intrinsics serialise as before
        return _drop_empty(handler(self), ("intrinsics", "lens_group"))

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
                                 f"lens's intrinsics change with its focal, which rigs do not describe yet")
            self.intrinsics.check_against(self.id, self.sensor, self.lens)
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
        default_factory=dict, description="measured intrinsics shared by the cameras naming the group")

    @model_serializer(mode="wrap")
    def _omit_unset(self, handler: SerializerFunctionWrapHandler):
        return _drop_empty(handler(self), ("lens_groups",))

    @model_validator(mode="after")
    def _unique_ids(self) -> "Rig":
        seen: set[str] = set()
        for cam in self.cameras:
            if cam.id in seen:
                raise ValueError(f"rig {self.name}: duplicate camera id {cam.id!r}")
            seen.add(cam.id)
        if not self.cameras:
            raise ValueError(f"rig {self.name}: no cameras")
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
                                     f"intrinsics change with its focal, which rigs do not describe yet")
                shared.check_against(cam.id, cam.sensor, cam.lens)
        unused = sorted(set(self.lens_groups) - set(groups))
        if unused:
            raise ValueError(f"rig {self.name}: lens group(s) {unused} are used by no camera")
        return self

    def measured_intrinsics(self, camera_id: str) -> MeasuredIntrinsics | None:
        """A camera's measured intrinsics: its own, else its lens group's, else None (nominal)."""
        cam = self.camera(camera_id)
        if cam.intrinsics is not None:
            return cam.intrinsics
        if cam.lens_group is not None:
            return self.lens_groups.get(cam.lens_group)
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


def load_rig(name_or_path: str | Path) -> Rig:
    """Load a built-in rig by name (``scene_rig``, ``face_rig``, ``demo_scene``...) or a JSON file.

    Raises ``ValueError`` naming the rig and the problem when the file is invalid.
    """
    path = Path(name_or_path)
    if path.suffix == ".json" and path.exists():
        text, where = path.read_text(), str(path)
    else:
        res = resources.files("hardware") / "rigs" / f"{name_or_path}.json"
        if not res.is_file():
            raise ValueError(f"unknown rig {str(name_or_path)!r}: not a file and not one of "
                             f"{', '.join(builtin_rig_names())}")
        text, where = res.read_text(), f"built-in rig {name_or_path}"
    try:
        return Rig.model_validate(json.loads(text))
    except ValueError as exc:
        raise ValueError(f"{where}: invalid rig: {exc}") from exc
