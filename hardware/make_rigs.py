"""Generate the built-in rig files ``hardware/rigs/*.json`` (run ``python -m hardware.make_rigs``).

Deterministic: no randomness, positions rounded to 0.1 mm, so rerunning rewrites identical files.
The JSON files are committed; this script is how they were made and how to change them.

Choices not fixed by the paper (documented here and in ``docs/synthetic-capture.md``):

- **Sensor.** The Z-CAM E2 is a Micro-Four-Thirds-mount camera with a 4/3" sensor of 3.76 µm pixels
  (Sony IMX299 class). The UHD 3840x2160 read-out therefore covers 14.44 mm x 8.12 mm. The paper's
  14-42 mm and 45-175 mm zooms are MFT lenses, which fits. Low-resolution demo rigs keep the same
  sensor millimetres with fewer, larger pixels, so their fields of view are the real ones.
- **Portrait tracking lenses.** The paper gives no range; we use 14-140 mm (an MFT superzoom): from
  the carts (about 6.5 m from the centre, 3-10 m from an actor) that frames a whole body (2.3 m on the
  14.44 mm long side: 18-63 mm) down to a lower body or upper body (1 m: 43-145 mm).
- **Scene Rig layout.** Stage 6 m (x) x 8 m (y), origin at its centre on the floor, z up. 30 ceiling
  cameras in a 5 x 6 grid at 5.0 m, 25 floor cameras on an ellipse 0.8 m outside the stage edge,
  12 carts evenly on a circle of radius 6.5 m, each carrying 10 or 11 cameras in three rows
  (0.8 / 1.6 / 2.4 m) with a zig-zag of +-7 cm between neighbours. Ceiling and floor cameras are all
  static (55); the carts carry the other 35 static, the 40 landscape and the 50 portrait trackers.
- **Face Rig layout.** A cylinder 2.76 m across and 2.5 m tall; 64 wall cameras in the 16 gaps between
  panel columns at 4 heights, 11 ceiling cameras (one central, ten on a 0.75 m ring), all looking at a
  head at 1.7 m in the centre. Wall cameras carry a 25 mm prime, ceiling cameras a 14 mm prime.
- **Demo rigs** (``demo_scene``, ``demo_face``) are small, low-resolution (320x180) versions for the
  demo and tests; same sensor millimetres, so the same fields of view. ``demo_scene``: 8 static
  cameras (14 mm) 25 degrees apart on an arc of 175 degrees in front of the stage (+x side), 5.5 m from
  the centre, alternating 1.3 m / 2.5 m high, all looking at (0, 0, 1.3); 2 landscape trackers at
  +-25 degrees and 2 portrait trackers at +-75 degrees, between the static ones. Static neighbours
  <= 30 degrees apart is what classic SfM needs (45 degrees failed with COLMAP); at 320x180 COLMAP's
  default incremental mapper registered all 8 static views of ``volcap synth`` frames for seeds 0-2
  at 25 degrees but only 7 of 8 at 30. The backs of actors are seen only when they turn.
  ``demo_face``: 7 wall cameras 30 degrees apart (-90..90) alternating 1.55 / 1.95 m, one ceiling.
- **Distorted demo rig** (``demo_scene_distorted``): ``demo_scene`` whose static cameras carry
  measured intrinsics (a lens calibration): OPENCV distortion, k1 -0.1 ... 0.1, principal points
  2-6 px off centre, two cameras sharing a lens group (values in ``DISTORTED_STATIC``); its tracking
  cameras carry zoom lens tables (``zoom_intrinsics``: OPENCV over the focal, ``ZOOM_LENSES``):
  barrel at the wide end, pincushion at the long end, as zooms are.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from hardware.rig import Rig

RIGS_DIR = Path(__file__).resolve().parent / "rigs"

# Z-CAM E2 UHD read-out of its 4/3" sensor (3.76 µm pixels).
SENSOR_W_MM = 14.44
SENSOR_H_MM = 8.12
UHD = (3840, 2160)
DEMO_PX = (320, 180)

STATIC_LENS = (14.0, 42.0)
LANDSCAPE_LENS = (45.0, 175.0)
PORTRAIT_LENS = (14.0, 140.0)


def _r(x: float) -> float:
    return round(float(x), 4)


def _sensor(px: tuple[int, int], portrait: bool = False) -> dict:
    w, h = px
    if portrait:
        return {"width_mm": SENSOR_H_MM, "height_mm": SENSOR_W_MM, "width_px": h, "height_px": w}
    return {"width_mm": SENSOR_W_MM, "height_mm": SENSOR_H_MM, "width_px": w, "height_px": h}


def _camera(cid: str, role: str, lens: tuple[float, float], focal: float, px: tuple[int, int],
            kind: str, pos, look, cart: int | None = None) -> dict:
    mount = {"kind": kind, "position_m": [_r(v) for v in pos], "look_at_m": [_r(v) for v in look]}
    if cart is not None:
        mount["cart"] = cart
    return {"id": cid, "role": role,
            "lens": {"focal_min_mm": lens[0], "focal_max_mm": lens[1]},
            "sensor": _sensor(px, portrait=role == "tracking-portrait"),
            "mount": mount, "nominal_focal_mm": _r(focal)}


def scene_rig() -> dict:
    cams: list[dict] = []

    def add(role, lens, focal, kind, pos, look, cart=None):
        cams.append(_camera(f"S{len(cams):03d}", role, lens, focal, UHD, kind, pos, look, cart))

    # 30 ceiling cameras: 5 (x) x 6 (y) grid at 5 m, looking down and slightly inwards.
    for iy in range(6):
        for ix in range(5):
            x, y = -4.0 + 2.0 * ix, -5.0 + 2.0 * iy
            add("static", STATIC_LENS, 14.0, "ceiling", (x, y, 5.0), (0.45 * x, 0.45 * y, 0.0))
    # 25 floor cameras on an ellipse 0.8 m outside the stage edge, looking up at the actors.
    for k in range(25):
        a = 2 * math.pi * k / 25
        x, y = 3.8 * math.cos(a), 4.8 * math.sin(a)
        add("static", STATIC_LENS, 14.0, "floor", (x, y, 0.15), (-0.2 * x, -0.2 * y, 1.7))
    # 125 cameras on 12 carts; per-cart role counts sum to 35 static, 40 landscape, 50 portrait.
    sizes = [11] * 5 + [10] * 7
    n_static = [3] * 11 + [2]
    n_land = [4] * 4 + [3] * 8
    rows_z = (2.4, 1.6, 0.8)
    for c in range(12):
        n = sizes[c]
        roles = (["tracking-landscape"] * n_land[c] + ["static"] * n_static[c]
                 + ["tracking-portrait"] * (n - n_land[c] - n_static[c]))
        theta = 2 * math.pi * (c + 0.5) / 12
        radial = (math.cos(theta), math.sin(theta))
        tangent = (-math.sin(theta), math.cos(theta))
        centre = (6.5 * radial[0], 6.5 * radial[1])
        per_row = math.ceil(n / 3)
        for k, role in enumerate(roles):
            row, col = divmod(k, per_row)
            in_row = min(per_row, n - row * per_row)
            s = (col - (in_row - 1) / 2) * 0.42 + (0.1 if row % 2 else -0.1)
            z = rows_z[row] + (0.07 if (k % 2) else -0.07)   # zig-zag between neighbours
            pos = (centre[0] + s * tangent[0], centre[1] + s * tangent[1], z)
            if role == "static":
                # spread the static views over the stage: aim left/centre/right of the centre
                off = (col - (in_row - 1) / 2) * 1.5
                look = (off * tangent[0], off * tangent[1], 1.0)
                focal = 20.0
                lens = STATIC_LENS
            elif role == "tracking-landscape":
                look, focal, lens = (0.0, 0.0, 1.6), 90.0, LANDSCAPE_LENS
            else:
                look, focal, lens = (0.0, 0.0, 1.0), 35.0, PORTRAIT_LENS
            add(role, lens, focal, "cart", pos, look, cart=c)
    return {
        "name": "scene_rig", "kind": "scene", "fps": 24.0, "stage_size_m": [6.0, 8.0, 5.0],
        "cameras": cams,
        "lighting": {
            "description": "white LED strips on the carts and the ceiling, uniform over the stage; "
                           "1 ms flashes at 72 Hz, in sync with the 24 fps shutters (one flash per "
                           "exposure, two more between exposures for actor comfort)",
            "strobe_hz": 72.0, "flash_ms": 1.0, "led_panels": 0, "white_lights": 0},
    }


def face_rig() -> dict:
    cams: list[dict] = []
    head = (0.0, 0.0, 1.7)
    radius = 1.38
    for row, z in enumerate((1.1, 1.5, 1.9, 2.3)):
        for col in range(16):
            a = 2 * math.pi * (col + 0.5) / 16
            pos = (radius * math.cos(a), radius * math.sin(a), z)
            cams.append(_camera(f"F{len(cams):03d}", "static", (25.0, 25.0), 25.0, UHD, "wall",
                                pos, head))
    ceiling_z = 2.48
    cams.append(_camera(f"F{len(cams):03d}", "static", (14.0, 14.0), 14.0, UHD, "ceiling",
                        (0.0, 0.0, ceiling_z), head))
    for k in range(10):
        a = 2 * math.pi * k / 10
        cams.append(_camera(f"F{len(cams):03d}", "static", (14.0, 14.0), 14.0, UHD, "ceiling",
                            (0.75 * math.cos(a), 0.75 * math.sin(a), ceiling_z), head))
    return {
        "name": "face_rig", "kind": "face", "fps": 24.0, "stage_size_m": [2.76, 2.76, 2.5],
        "cameras": cams,
        "lighting": {
            "description": "capped cylinder of black LED panels (16 columns of 5 on the wall, 30 on "
                           "the ceiling, 10 on the floor) with 110 white LED lights evenly "
                           "distributed for flat facial lighting",
            "strobe_hz": None, "flash_ms": None, "led_panels": 80, "white_lights": 110},
    }


def demo_scene() -> dict:
    """12 cameras at 320x180: 8 static, 2 landscape and 2 portrait trackers, in front of the stage."""
    cams: list[dict] = []
    radius = 5.5

    def at(az_deg: float, z: float):
        a = math.radians(az_deg)
        return (radius * math.cos(a), radius * math.sin(a), z)

    for k, az in enumerate(np.arange(-87.5, 88, 25.0)):      # 8 static, 25 degrees apart
        z = 1.3 if k % 2 == 0 else 2.5
        cams.append(_camera(f"S{len(cams):03d}", "static", STATIC_LENS, 14.0, DEMO_PX, "tripod",
                            at(az, z), (0.0, 0.0, 1.3)))
    for az in (-25, 25):
        cams.append(_camera(f"S{len(cams):03d}", "tracking-landscape", LANDSCAPE_LENS, 70.0, DEMO_PX,
                            "tripod", at(az, 1.9), (0.0, 0.0, 1.6)))
    for az in (-75, 75):
        cams.append(_camera(f"S{len(cams):03d}", "tracking-portrait", PORTRAIT_LENS, 30.0, DEMO_PX,
                            "tripod", at(az, 1.6), (0.0, 0.0, 1.0)))
    return {
        "name": "demo_scene", "kind": "scene", "fps": 24.0, "stage_size_m": [4.0, 4.0, 3.5],
        "cameras": cams,
        "lighting": {"description": "white LED strips, 1 ms flashes at 72 Hz in sync with the shutters",
                     "strobe_hz": 72.0, "flash_ms": 1.0, "led_panels": 0, "white_lights": 0},
    }


def demo_face() -> dict:
    """8 cameras at 320x180: 7 on the wall 30 degrees apart in front of the face, 1 in the ceiling."""
    cams: list[dict] = []
    head = (0.0, 0.0, 1.7)
    for k, az in enumerate(range(-90, 91, 30)):
        a = math.radians(az)
        z = 1.55 if k % 2 == 0 else 1.95
        cams.append(_camera(f"F{len(cams):03d}", "static", (25.0, 25.0), 25.0, DEMO_PX, "wall",
                            (1.38 * math.cos(a), 1.38 * math.sin(a), z), head))
    cams.append(_camera(f"F{len(cams):03d}", "static", (14.0, 14.0), 14.0, DEMO_PX, "ceiling",
                        (0.55, 0.0, 2.48), head))
    return {
        "name": "demo_face", "kind": "face", "fps": 24.0, "stage_size_m": [2.76, 2.76, 2.5],
        "cameras": cams,
        "lighting": {"description": "black LED panels with white LED lights, flat facial lighting",
                     "strobe_hz": None, "flash_ms": None, "led_panels": 80, "white_lights": 110},
    }


#: ``demo_scene_distorted``: per static camera (S000-S005) its lens calibration: focal offset from
#: the nominal 14 mm (relative), fy/fx - 1, principal point offset from the image centre (px at
#: 320x180), OPENCV (k1, k2, p1, p2). S006 and S007 share lens group ``zoom14-b`` (one body/lens
#: model calibrated once).
DISTORTED_STATIC = {
    "S000": (0.006, 0.0008, (4.1, -3.2), (-0.10, 0.021, 0.0006, -0.0004)),
    "S001": (-0.004, -0.0005, (-5.3, 2.4), (-0.06, 0.008, -0.0003, 0.0005)),
    "S002": (0.009, 0.0012, (2.7, 4.6), (-0.02, -0.004, 0.0004, 0.0002)),
    "S003": (-0.008, 0.0003, (-3.6, -4.1), (0.03, -0.006, -0.0005, -0.0003)),
    "S004": (0.002, -0.0010, (6.2, 1.9), (0.07, -0.012, 0.0002, 0.0006)),
    "S005": (-0.011, 0.0006, (-2.4, 3.8), (0.10, -0.018, -0.0006, 0.0001)),
}
DISTORTED_GROUPS = {"zoom14-b": (0.004, 0.0004, (3.3, -2.7), (-0.08, 0.015, 0.0003, -0.0002))}
DISTORTED_GROUP_OF = {"S006": "zoom14-b", "S007": "zoom14-b"}


def _measured(nominal_mm: float, px: tuple[int, int], spec) -> dict:
    rel, aspect, (dx, dy), params = spec
    f = nominal_mm * px[0] / SENSOR_W_MM * (1 + rel)
    return {"fx": _r(f), "fy": _r(f * (1 + aspect)), "cx": _r((px[0] - 1) / 2 + dx),
            "cy": _r((px[1] - 1) / 2 + dy), "model": "OPENCV", "params": [float(v) for v in params]}


#: ``demo_scene_distorted``'s tracking cameras: per camera, its zoom lens's distortion at the image
#: corner (radial, a fraction of the corner's radius) at the two ends of its zoom, ``(wide, long)``,
#: linear in log focal in between (so it crosses zero, barrel -> pincushion, 70-75 % of the way
#: along the zoom in log focal: ~125 mm of 45-175 mm, ~80 mm of 14-140 mm), the sample focals, and its
#: decentering ``(t1, t2)`` (the tangential terms' shift of the corner, a share of its radius). Each camera is its
#: own unit (its own table). Converted to OPENCV (k1, 0, p1, p2) on normalized coordinates: the
#: corner's normalized radius is ``half diagonal / focal``, so k1 = D f² / h² grows with the focal
#: (+0.5 % at 175 mm is k1 = 2.2): see :func:`_zoom_table`.
ZOOM_LENSES = {
    "S008": ((-0.015, 0.005), (45.0, 55.0, 70.0, 90.0, 115.0, 145.0, 175.0), (1.0e-4, -0.6e-4)),
    "S009": ((-0.014, 0.006), (45.0, 55.0, 70.0, 90.0, 115.0, 145.0, 175.0), (-0.8e-4, 0.5e-4)),
    "S010": ((-0.030, 0.010), (14.0, 18.0, 24.0, 35.0, 50.0, 75.0, 105.0, 140.0), (0.7e-4, 0.9e-4)),
    "S011": ((-0.028, 0.011), (14.0, 18.0, 24.0, 35.0, 50.0, 75.0, 105.0, 140.0), (-1.1e-4, -0.4e-4)),
}


def _zoom_table(corner: tuple[float, float], focals: tuple[float, ...], tangential: tuple[float, float],
                sensor_mm: tuple[float, float]) -> dict:
    """A zoom lens table (``ZoomIntrinsics``): at each focal f the radial distortion D(f) at the
    image corner (linear in log f from ``corner[0]`` at the first focal to ``corner[1]`` at the
    last) as k1 = D / r² with r = h / f the corner's normalized radius (h the half diagonal, mm),
    k2 = 0 (a narrow field: r ≤ 0.6), and p1, p2 = t / r (the tangential terms, ~p r², then move
    the corner by a constant share t of its radius)."""
    h2 = (sensor_mm[0] / 2) ** 2 + (sensor_mm[1] / 2) ** 2
    lo, hi = focals[0], focals[-1]
    samples = []
    for f in focals:
        d = corner[0] + (corner[1] - corner[0]) * math.log(f / lo) / math.log(hi / lo)
        r2 = h2 / f ** 2
        samples.append({"focal_mm": float(f), "params": [float(f"{d / r2:.6g}"), 0.0,
                                                         float(f"{tangential[0] / math.sqrt(r2):.4g}"),
                                                         float(f"{tangential[1] / math.sqrt(r2):.4g}")]})
    return {"model": "OPENCV", "samples": samples}


def demo_scene_distorted() -> dict:
    """``demo_scene`` with measured intrinsics on its static cameras: OPENCV distortion with k1 from
    -0.1 to 0.1, principal points 2-6 px off the centre, focals within 1.1 % of the nominal, fy/fx
    within 0.12 %; and zoom lens tables on its tracking cameras (``ZOOM_LENSES``: -1.4 ... -3 % at
    the corner at the wide end, +0.5 ... +1.1 % at the long end); the synthetic capture renders
    these lenses (``docs/synthetic-capture.md``)."""
    rig = demo_scene()
    rig["name"] = "demo_scene_distorted"
    for cam in rig["cameras"]:
        if cam["id"] in DISTORTED_STATIC:
            cam["intrinsics"] = _measured(cam["nominal_focal_mm"], DEMO_PX, DISTORTED_STATIC[cam["id"]])
        elif cam["id"] in DISTORTED_GROUP_OF:
            cam["lens_group"] = DISTORTED_GROUP_OF[cam["id"]]
        elif cam["id"] in ZOOM_LENSES:
            s = cam["sensor"]
            cam["zoom_intrinsics"] = _zoom_table(*ZOOM_LENSES[cam["id"]], (s["width_mm"], s["height_mm"]))
    rig["lens_groups"] = {g: _measured(14.0, DEMO_PX, spec) for g, spec in DISTORTED_GROUPS.items()}
    return rig


BUILDERS = {"scene_rig": scene_rig, "face_rig": face_rig, "demo_scene": demo_scene,
            "demo_face": demo_face, "demo_scene_distorted": demo_scene_distorted}


def main(out_dir: Path = RIGS_DIR) -> list[Path]:
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for name, build in BUILDERS.items():
        data = build()
        Rig.model_validate(data)                # fail here, not at load time
        path = out_dir / f"{name}.json"
        path.write_text(json.dumps(data, indent=1) + "\n")
        written.append(path)
    return written


if __name__ == "__main__":
    for p in main():
        print(p)
