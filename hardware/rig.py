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

from pydantic import BaseModel, ConfigDict, Field, model_validator


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


class RigCamera(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    id: str = Field(pattern=r"^[A-Za-z0-9_.-]+$")
    role: CameraRole
    lens: Lens
    sensor: Sensor
    mount: Mount
    nominal_focal_mm: float = Field(gt=0, description="focal at the nominal set-up (static cameras keep it)")

    @model_validator(mode="after")
    def _focal_in_range(self) -> "RigCamera":
        if not self.lens.contains(self.nominal_focal_mm):
            raise ValueError(
                f"camera {self.id}: nominal focal {self.nominal_focal_mm} mm is outside its lens range "
                f"{self.lens.focal_min_mm}-{self.lens.focal_max_mm} mm")
        if self.role is CameraRole.tracking_portrait and self.sensor.width_px > self.sensor.height_px:
            raise ValueError(f"camera {self.id}: a portrait tracking camera must be taller than wide")
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

    @model_validator(mode="after")
    def _unique_ids(self) -> "Rig":
        seen: set[str] = set()
        for cam in self.cameras:
            if cam.id in seen:
                raise ValueError(f"rig {self.name}: duplicate camera id {cam.id!r}")
            seen.add(cam.id)
        if not self.cameras:
            raise ValueError(f"rig {self.name}: no cameras")
        return self

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
