"""The static set: a textured room (Scene Rig) or LED-panel cylinder (Face Rig), calibration targets,
a colour chart, emitters, and the lighting model. Everything Lambertian, so the set's radiance is
baked into its texture maps (flat surfaces under a normal-only lighting model have constant
irradiance).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from hardware.rig import Rig
from volcap_core.synth import textures as tx
from volcap_core.synth.geometry import (PinholeCamera, intersect_box_inside, intersect_cylinder_inside,
                                        intersect_rect)

WHITE_LED = np.array([1.0, 0.97, 0.92], np.float32)


@dataclass(frozen=True)
class Lighting:
    """Irradiance for a surface normal n: ``ambient + sky * (1 + n_z) / 2 + key * max(0, n . key_dir)``.

    Lambertian radiance = albedo * irradiance (+ emission). View independent.
    """

    ambient: float
    sky: float
    key: float
    key_dir: tuple[float, float, float]

    def irradiance(self, n: np.ndarray) -> np.ndarray:
        n = np.asarray(n, np.float32)
        kd = np.asarray(self.key_dir, np.float32)
        kd = kd / np.linalg.norm(kd)
        return (self.ambient + self.sky * (1 + n[..., 2]) / 2
                + self.key * np.maximum(0, n @ kd)).astype(np.float32)

    def to_json(self) -> dict:
        kd = np.asarray(self.key_dir, np.float64)
        return {"model": "radiance = albedo * (ambient + sky*(1+n_z)/2 + key*max(0, n.key_dir)) + emission",
                "ambient": self.ambient, "sky": self.sky, "key": self.key,
                "key_dir": (kd / np.linalg.norm(kd)).round(6).tolist()}


SCENE_LIGHTING = Lighting(ambient=0.35, sky=0.45, key=0.4, key_dir=(0.4, 0.25, 1.0))
FACE_LIGHTING = Lighting(ambient=0.7, sky=0.3, key=0.0, key_dir=(1.0, 0.0, 0.0))


@dataclass
class Plane:
    """A flat surface ``origin + a*eu + b*ev`` (0 <= a <= size[0], 0 <= b <= size[1]), front normal
    eu x ev. ``texture`` holds baked radiance in (a, b) metres."""

    name: str
    origin: np.ndarray
    eu: np.ndarray
    ev: np.ndarray
    size: tuple[float, float]
    texture: tx.Texture | None
    back_radiance: np.ndarray = field(default_factory=lambda: np.full(3, 0.05, np.float32))
    # analytic black/white cell pattern (calibration targets): exact edges at any resolution
    pattern: np.ndarray | None = None            # (rows, cols) of 0/1, row 0 at the top
    pattern_origin: tuple[float, float] = (0.0, 0.0)   # (a, b) of the pattern's bottom-left corner
    pattern_cell: tuple[float, float] = (1.0, 1.0)
    pattern_radiance: tuple[float, float] = (0.03, 0.8)  # black, white (albedo * irradiance)

    def front_radiance(self, a, b, footprint) -> np.ndarray:
        if self.pattern is None:
            return self.texture.sample(a, b, footprint)
        nr, nc = self.pattern.shape
        j = np.floor((a - self.pattern_origin[0]) / self.pattern_cell[0]).astype(np.int64)
        i = (nr - 1) - np.floor((b - self.pattern_origin[1]) / self.pattern_cell[1]).astype(np.int64)
        inside = (i >= 0) & (i < nr) & (j >= 0) & (j < nc)
        val = np.where(inside, self.pattern[np.clip(i, 0, nr - 1), np.clip(j, 0, nc - 1)], 1.0)
        lo, hi = self.pattern_radiance
        return np.repeat((lo + (hi - lo) * val).astype(np.float32)[:, None], 3, axis=1)

    @property
    def normal(self) -> np.ndarray:
        return np.cross(self.eu, self.ev)

    def point(self, a, b) -> np.ndarray:
        return self.origin + np.multiply.outer(a, self.eu) + np.multiply.outer(b, self.ev)

    @property
    def centre(self) -> np.ndarray:
        return self.point(self.size[0] / 2, self.size[1] / 2)

    @property
    def corners(self) -> np.ndarray:
        """Top-left, top-right, bottom-right, bottom-left as seen from the front (b up, a right)."""
        w, h = self.size
        return np.array([self.point(0, h), self.point(w, h), self.point(w, 0), self.point(0, 0)])


# --------------------------------------------------------------------------- backgrounds

class RoomBackground:
    """The inside of a box room; surfaces 0..5 = x-min, x-max, y-min, y-max walls, floor, ceiling."""

    FLOOR = 4

    def __init__(self, lo, hi, planes: list[Plane]):
        self.lo = np.asarray(lo, np.float64)
        self.hi = np.asarray(hi, np.float64)
        self.planes = planes

    def trace(self, o, d):
        return intersect_box_inside(o, d, self.lo, self.hi)

    def shade(self, o, d, t, sid, pix_angle):
        p = np.asarray(o, np.float32) + t[..., None] * d
        out = np.empty(p.shape, np.float32)
        for k, pl in enumerate(self.planes):
            m = sid == k
            if not m.any():
                continue
            rel = p[m] - pl.origin.astype(np.float32)
            cos = np.abs(d[m] @ pl.normal.astype(np.float32))
            fp = t[m] * pix_angle / np.maximum(cos, 0.15)
            out[m] = pl.texture.sample(rel @ pl.eu.astype(np.float32), rel @ pl.ev.astype(np.float32), fp)
        return out

    def lidar(self, rng, spacing):
        pts, nrm = [], []
        for pl in self.planes:
            p, n = _sample_plane(rng, pl, spacing)
            pts.append(p)
            nrm.append(n)
        return np.concatenate(pts), np.concatenate(nrm)

    def describe(self) -> dict:
        return {"kind": "room", "min_m": self.lo.round(6).tolist(), "max_m": self.hi.round(6).tolist(),
                "surfaces": [pl.name for pl in self.planes]}


class CylinderBackground:
    """Inside of a capped cylinder about the z axis: 0 wall, 1 floor, 2 ceiling.

    Wall texture coordinates: a = radius * ((-theta) mod 2 pi) (increasing clockwise seen from
    above, so the wall reads unmirrored from inside), b = z. Caps: a = x - (-r), b = y - (-r).
    """

    FLOOR = 1

    def __init__(self, radius, z0, z1, wall: tx.Texture, floor: tx.Texture, ceiling: tx.Texture):
        self.radius, self.z0, self.z1 = float(radius), float(z0), float(z1)
        self.wall, self.floor, self.ceiling = wall, floor, ceiling

    def trace(self, o, d):
        return intersect_cylinder_inside(o, d, self.radius, self.z0, self.z1)

    def shade(self, o, d, t, sid, pix_angle):
        p = np.asarray(o, np.float32) + t[..., None] * d
        out = np.empty(p.shape, np.float32)
        m = sid == 0
        if m.any():
            q = p[m]
            theta = np.arctan2(q[:, 1], q[:, 0])
            a = self.radius * np.mod(-theta, 2 * np.pi)
            nrm = -np.stack([q[:, 0], q[:, 1], np.zeros_like(q[:, 0])], 1) / self.radius
            cos = np.abs(np.einsum("ij,ij->i", d[m], nrm))
            out[m] = self.wall.sample(a, q[:, 2] - self.z0, t[m] * pix_angle / np.maximum(cos, 0.15))
        for k, tex in ((1, self.floor), (2, self.ceiling)):
            m = sid == k
            if m.any():
                q = p[m]
                cos = np.abs(d[m][:, 2])
                out[m] = tex.sample(q[:, 0] + self.radius, q[:, 1] + self.radius,
                                    t[m] * pix_angle / np.maximum(cos, 0.15))
        return out

    def lidar(self, rng, spacing):
        r = self.radius
        circ = 2 * math.pi * r
        n_wall = int(circ * (self.z1 - self.z0) / spacing ** 2)
        th = rng.uniform(0, 2 * math.pi, n_wall)
        z = rng.uniform(self.z0, self.z1, n_wall)
        wall = np.stack([r * np.cos(th), r * np.sin(th), z], 1)
        wall_n = np.stack([-np.cos(th), -np.sin(th), np.zeros_like(th)], 1)
        n_cap = int(math.pi * r * r / spacing ** 2)
        caps, caps_n = [], []
        for zc, nz in ((self.z0, 1.0), (self.z1, -1.0)):
            rr = r * np.sqrt(rng.uniform(0, 1, n_cap))
            a = rng.uniform(0, 2 * math.pi, n_cap)
            caps.append(np.stack([rr * np.cos(a), rr * np.sin(a), np.full(n_cap, zc)], 1))
            caps_n.append(np.tile([0.0, 0.0, nz], (n_cap, 1)))
        return np.concatenate([wall] + caps), np.concatenate([wall_n] + caps_n)

    def describe(self) -> dict:
        return {"kind": "cylinder", "radius_m": self.radius, "z_min_m": self.z0, "z_max_m": self.z1,
                "surfaces": ["wall", "floor", "ceiling"]}


def _sample_plane(rng, pl: Plane, spacing):
    n = max(1, int(pl.size[0] * pl.size[1] / spacing ** 2))
    a = rng.uniform(0, pl.size[0], n)
    b = rng.uniform(0, pl.size[1], n)
    return pl.point(a, b), np.tile(pl.normal, (n, 1))


# --------------------------------------------------------------------------- the static scene

@dataclass
class StaticScene:
    background: RoomBackground | CylinderBackground
    boards: list[Plane]
    lighting: Lighting
    targets: list[dict]          # ground-truth descriptions of calibration targets
    chart: dict                  # ground-truth description of the colour chart
    emitters: list[dict]
    stage_size_m: tuple[float, float, float]

    timed_boards: list[tuple[Plane, float]] = field(default_factory=list)   # (board, visible until s)
    props: list[dict] = field(default_factory=list)                        # ground truth of props

    def render(self, cam: PinholeCamera, dirs: np.ndarray, ss: int):
        """Radiance (Hs, Ws, 3), distance t (Hs, Ws) and background surface id (-1 on boards) of
        the permanent set (timed boards are drawn per frame by :meth:`draw_timed`)."""
        o = cam.centre
        pix_angle = 1.0 / (cam.fx * ss)
        t, sid = self.background.trace(o, dirs)
        rad = self.background.shade(o, dirs, t, sid, pix_angle)
        sid = sid.astype(np.int16)
        for board in self.boards:
            draw_board(board, cam, dirs, ss, t, rad, sid)
        return rad, t, sid

    def draw_timed(self, cam: PinholeCamera, dirs: np.ndarray, ss: int, t_sec: float, tbuf, rad) -> None:
        for board, until in self.timed_boards:
            if t_sec < until:
                draw_board(board, cam, dirs, ss, tbuf, rad, None)

    def lidar(self, rng: np.random.Generator, spacing: float, noise_m: float = 0.003):
        p, n = self.background.lidar(rng, spacing)
        pts, nrm = [p], [n]
        for board in self.boards:
            bp, bn = _sample_plane(rng, board, spacing / 2)
            pts.append(bp)
            nrm.append(bn)
        p = np.concatenate(pts)
        n = np.concatenate(nrm)
        p = p + n * rng.normal(0, noise_m, (len(p), 1)) + rng.normal(0, noise_m / 3, p.shape)
        return p.astype(np.float32), n.astype(np.float32)


def draw_board(board: Plane, cam: PinholeCamera, dirs, ss, t, rad, sid) -> None:
    """Z-buffer a board into (t, rad[, sid]) in place."""
    rect = cam.sphere_rect(board.centre, 0.5 * math.hypot(*board.size) + 0.01, ss)
    if rect is None:
        return
    o = cam.centre
    pix_angle = 1.0 / (cam.fx * ss)
    y0, y1, x0, x1 = rect
    d = dirs[y0:y1, x0:x1]
    tb, a, b = intersect_rect(o, d, board.origin, board.eu, board.ev, *board.size)
    m = tb < t[y0:y1, x0:x1]
    if not m.any():
        return
    cosn = d[m] @ board.normal.astype(np.float32)
    front = cosn < 0
    vals = np.empty((int(m.sum()), 3), np.float32)
    fp = tb[m] * pix_angle / np.maximum(np.abs(cosn), 0.15)
    if front.any():
        vals[front] = board.front_radiance(a[m][front], b[m][front], fp[front])
    vals[~front] = board.back_radiance
    t[y0:y1, x0:x1][m] = tb[m]
    rad[y0:y1, x0:x1][m] = vals
    if sid is not None:
        sid[y0:y1, x0:x1][m] = -1


def _baked(albedo: np.ndarray, lighting: Lighting, normal, emission: np.ndarray | None = None):
    e = float(lighting.irradiance(np.asarray(normal, np.float32)))
    rad = albedo * e
    if emission is not None:
        rad = rad + emission
    return rad


def _board(name, centre, normal, width, height, albedo_img, texel, lighting, up=(0.0, 0.0, 1.0)):
    """A board standing at ``centre`` facing ``normal`` (its a axis horizontal, b axis 'up')."""
    n = np.asarray(normal, np.float64)
    n /= np.linalg.norm(n)
    up = np.asarray(up, np.float64)
    eu = np.cross(up, n)
    if np.linalg.norm(eu) < 1e-6:
        eu = np.array([1.0, 0.0, 0.0])
    eu /= np.linalg.norm(eu)
    ev = np.cross(n, eu)
    origin = np.asarray(centre, np.float64) - eu * width / 2 - ev * height / 2
    rad = _baked(albedo_img, lighting, n)
    back = np.full(3, 0.08, np.float32) * float(lighting.irradiance(-n.astype(np.float32)))
    return Plane(name, origin, eu, ev, (width, height), tx.Texture(rad, texel), back)


def _chart(name, centre, normal, patch_m, gap_m, lighting, texel):
    img, centres_ab = tx.chart_texture(patch_m, gap_m, texel)
    h, w = img.shape[0] * texel, img.shape[1] * texel
    board = _board(name, centre, normal, w, h, img, texel, lighting)
    refl = tx.colorchecker_linear()
    e = float(lighting.irradiance(board.normal.astype(np.float32)))
    patches = []
    for k in range(24):
        a, b = centres_ab[k]
        patches.append({"index": k, "name": tx.COLORCHECKER_NAMES[k],
                        "centre_m": board.point(a, b).round(6).tolist(),
                        "reflectance_linear": refl[k].round(6).tolist(),
                        "radiance_linear": (refl[k] * e).round(6).tolist()})
    gt = {"kind": "colorchecker24", "layout": "6 columns x 4 rows, row 0 at the top (dark skin first)",
          "primaries": "linear Rec.709 / sRGB, D65",
          "corners_m": board.corners.round(6).tolist(), "corner_order": "TL, TR, BR, BL seen from the front",
          "normal": board.normal.round(6).tolist(), "patch_size_m": patch_m, "gap_m": gap_m,
          "irradiance": round(e, 6), "patches": patches}
    return board, gt


def _target_gt(kind: str, name: str, plane_point, u0, v0, w, h, extra: dict) -> dict:
    corners = [plane_point(u0, v0 + h), plane_point(u0 + w, v0 + h), plane_point(u0 + w, v0),
               plane_point(u0, v0)]
    gt = {"name": name, "kind": kind, "size_m": [w, h],
          "corners_m": np.array(corners).round(6).tolist(),
          "corner_order": "TL, TR, BR, BL of the pattern as seen from the front "
                          "(ArUco corner order of cv2.aruco.detectMarkers)"}
    gt.update(extra)
    return gt


def _pattern_board(name, origin, eu, ev, cells, u0, v0, width, height, lighting, margin_cells=1.0,
                   offset_m=0.002) -> Plane:
    """A flat target on a surface (origin, eu, ev): ``cells`` over [u0, u0+width] x [v0, v0+height]
    surface metres with a white quiet zone, lifted ``offset_m`` off the surface towards its front."""
    origin, eu, ev = (np.asarray(x, np.float64) for x in (origin, eu, ev))
    nr, nc = cells.shape
    mu, mv = margin_cells * width / nc, margin_cells * height / nr
    normal = np.cross(eu, ev)
    e = float(lighting.irradiance(normal.astype(np.float32)))
    return Plane(name, origin + (u0 - mu) * eu + (v0 - mv) * ev + offset_m * normal, eu, ev,
                 (width + 2 * mu, height + 2 * mv), None,
                 back_radiance=np.full(3, 0.05, np.float32), pattern=cells.astype(np.float32),
                 pattern_origin=(mu, mv), pattern_cell=(width / nc, height / nr),
                 pattern_radiance=(0.03 * e, 0.8 * e))


def _add_aruco(boards, targets, surface, name, marker_id, u0, v0, size, lighting):
    origin, eu, ev = surface
    board = _pattern_board(name, origin, eu, ev, tx.aruco_cells(marker_id), u0, v0, size, size, lighting)
    boards.append(board)
    a0, b0 = board.pattern_origin
    targets.append(_target_gt("aruco", name, board.point, a0, b0, size, size,
                              {"dictionary": "DICT_4X4_50", "marker_id": int(marker_id)}))


def _add_checker(boards, targets, surface, name, cols, rows, square, u0, v0, lighting):
    origin, eu, ev = surface
    board = _pattern_board(name, origin, eu, ev, tx.checker_cells(cols, rows), u0, v0, cols * square,
                           rows * square, lighting)
    boards.append(board)
    a0, b0 = board.pattern_origin
    inner = [board.point(a0 + i * square, b0 + (rows - j) * square)
             for j in range(1, rows) for i in range(1, cols)]
    targets.append(_target_gt("checkerboard", name, board.point, a0, b0, cols * square, rows * square,
                              {"squares": [cols, rows], "square_m": square,
                               "inner_corners_m": np.array(inner).round(6).tolist(),
                               "inner_corner_order": "row-major from the top-left, as "
                                                     "cv2.findChessboardCorners reports them"}))


# stage props (crates and pillars) in units of the stage half-size: (x, y, width, depth, height m, yaw deg)
PROPS = [(-0.85, 0.65, 0.35, 0.35, 2.4, 10.0), (-0.55, -1.15, 0.3, 0.3, 1.9, -20.0),
         (-0.8, 0.05, 0.9, 0.6, 0.55, 5.0), (-1.3, -0.4, 0.7, 0.7, 1.2, -35.0)]


def _add_box(boards, rng, name, centre_xy, width, depth, height, yaw_deg, lighting, texel=0.01) -> dict:
    """A textured box standing on the floor: four sides and a top, as boards."""
    c = np.array([centre_xy[0], centre_xy[1], height / 2])
    a = math.radians(yaw_deg)
    ex = np.array([math.cos(a), math.sin(a), 0.0])
    ey = np.array([-math.sin(a), math.cos(a), 0.0])
    up = np.array([0.0, 0.0, 1.0])
    base = tx.random_palette(rng, 1, 0.15, 0.6)[0]
    faces = [(ex, width / 2, depth), (-ex, width / 2, depth), (ey, depth / 2, width), (-ey, depth / 2, width)]
    for k, (n, half, face_w) in enumerate(faces):
        eu = np.cross(up, n)
        fc = c + n * half
        img = tx.surface_texture(rng, face_w, height, texel, base, shapes_per_m2=40, size_m=(0.03, 0.35),
                                 contrast=0.6)
        boards.append(Plane(f"{name}_side{k}", fc - eu * face_w / 2 - up * height / 2, eu, up.copy(),
                            (face_w, height), tx.Texture(_baked(img, lighting, n), texel)))
    img = tx.surface_texture(rng, width, depth, texel, base, shapes_per_m2=40, size_m=(0.03, 0.35), contrast=0.6)
    boards.append(Plane(f"{name}_top", c + up * height / 2 - ex * width / 2 - ey * depth / 2, ex, ey,
                        (width, depth), tx.Texture(_baked(img, lighting, up), texel)))
    return {"name": name, "kind": "box", "centre_m": np.round(c, 6).tolist(), "size_m": [width, depth, height],
            "yaw_deg": yaw_deg, "x_axis": np.round(ex, 6).tolist()}


def build_room_stage(rig: Rig, rng: np.random.Generator, texel: float = 0.015) -> StaticScene:
    """A room around the rig's stage: walls just beyond the farthest camera, textured floor with a
    marked stage, ArUco markers and checkerboards on walls and floor, LED strips, a colour chart."""
    pos = np.array([c.mount.position_m for c in rig.cameras])
    sx, sy, _ = rig.stage_size_m
    # each wall 1.5 m behind the farthest camera on its side, and at least 1.5 m off the stage edge
    # (a rig with cameras on one side only gets a near back wall, which fills its views)
    x0 = min(pos[:, 0].min() - 1.5, -sx / 2 - 1.5)
    x1 = max(pos[:, 0].max() + 1.5, sx / 2 + 1.5)
    y0 = min(pos[:, 1].min() - 1.5, -sy / 2 - 1.5)
    y1 = max(pos[:, 1].max() + 1.5, sy / 2 + 1.5)
    H = max(pos[:, 2].max() + 0.7, 4.0)
    lo, hi = np.array([x0, y0, 0.0]), np.array([x1, y1, H])
    W_x, W_y = x1 - x0, y1 - y0
    lighting = SCENE_LIGHTING
    X, Y, Z = np.eye(3)
    specs = [  # name, origin, eu, ev, size   (eu so that each wall reads unmirrored from inside)
        ("wall_x_min", [x0, y0, 0], Y, Z, (W_y, H)),
        ("wall_x_max", [x1, y1, 0], -Y, Z, (W_y, H)),
        ("wall_y_min", [x1, y0, 0], -X, Z, (W_x, H)),
        ("wall_y_max", [x0, y1, 0], X, Z, (W_x, H)),
        ("floor", [x0, y0, 0], X, Y, (W_x, W_y)),
        ("ceiling", [x1, y0, H], -X, Y, (W_x, W_y)),
    ]
    targets: list[dict] = []
    emitters: list[dict] = []
    planes: list[Plane] = []
    boards: list[Plane] = []
    marker_id = 0
    for name, origin, eu, ev, size in specs:
        origin = np.asarray(origin, np.float64)
        normal = np.cross(eu, ev)
        w, h = size

        if name.startswith("wall"):
            base = tx.random_palette(rng, 1, 0.2, 0.5)[0]
            # dense mid-sized shapes: the most SIFT inliers between demo views 25-30 degrees apart
            img = tx.surface_texture(rng, w, h, texel, base, shapes_per_m2=40, size_m=(0.08, 0.5), contrast=0.7)
            # ArUco markers at two heights and a checkerboard, spread along the wall
            n_mark = max(2, int(w // 3.5))
            for k in range(n_mark):
                size_m = 0.8
                u0 = (k + 0.5) * w / n_mark - size_m / 2 + rng.uniform(-0.4, 0.4)
                v0 = (1.1 if k % 2 == 0 else 2.2) + rng.uniform(-0.1, 0.1)
                v0 = min(v0, h - 1.5)
                _add_aruco(boards, targets, (origin, eu, ev), f"{name}_aruco{marker_id}", marker_id, u0, v0,
                           size_m, lighting)
                marker_id += 1
            cu = w * rng.uniform(0.3, 0.7)
            _add_checker(boards, targets, (origin, eu, ev), f"{name}_checker", 8, 6, 0.12, cu, 0.25, lighting)
            emission = np.zeros_like(img)
            z0, z1 = h - 0.45, h - 0.38
            emission[int(z0 / texel):int(z1 / texel)] = 5.0 * WHITE_LED
            emitters.append({"kind": "led_strip", "surface": name, "z_m": [round(z0, 4), round(z1, 4)],
                             "radiance": (5.0 * WHITE_LED).round(4).tolist()})
            tex_texel = texel
        elif name == "floor":
            img = tx.surface_texture(rng, w, h, texel, np.array([0.10, 0.11, 0.13]), shapes_per_m2=12,
                                     size_m=(0.08, 0.9), contrast=0.6)
            stage = tx.surface_texture(rng, sx + 0.2, sy + 0.2, texel, np.array([0.33, 0.31, 0.28]),
                                       shapes_per_m2=20, contrast=0.45, size_m=(0.05, 0.5))
            j0 = int(round((-x0 - sx / 2 - 0.1) / texel))
            i0 = int(round((-y0 - sy / 2 - 0.1) / texel))
            img[i0:i0 + stage.shape[0], j0:j0 + stage.shape[1]] = stage
            # white tape: stage outline and centre cross (5 cm wide)
            tape = 0.75
            for (a0, a1, b0, b1) in [(-sx / 2, sx / 2, -sy / 2 - .025, -sy / 2 + .025),
                                     (-sx / 2, sx / 2, sy / 2 - .025, sy / 2 + .025),
                                     (-sx / 2 - .025, -sx / 2 + .025, -sy / 2, sy / 2),
                                     (sx / 2 - .025, sx / 2 + .025, -sy / 2, sy / 2),
                                     (-0.3, 0.3, -0.025, 0.025), (-0.025, 0.025, -0.3, 0.3)]:
                img[int((b0 - y0) / texel):int((b1 - y0) / texel) + 1,
                    int((a0 - x0) / texel):int((a1 - x0) / texel) + 1] = tape
            # ArUco markers just outside the stage corners, a checkerboard beside the stage
            for k, (cx_, cy_) in enumerate([(-1, -1), (1, -1), (1, 1), (-1, 1)]):
                size_m = 0.6
                u = cx_ * (sx / 2 + 0.5) - x0 - size_m / 2
                v = cy_ * (sy / 2 + 0.5) - y0 - size_m / 2
                _add_aruco(boards, targets, (origin, eu, ev), f"floor_aruco{marker_id}", marker_id, u, v, size_m,
                           lighting)
                marker_id += 1
            _add_checker(boards, targets, (origin, eu, ev), "floor_checker", 8, 6, 0.1, -x0 + sx / 2 + 0.4,
                         -y0 - 0.3, lighting)
            emission = None
            tex_texel = texel
        else:  # ceiling: coarser texture, LED strip lines every 2 m
            tex_texel = 2 * texel
            img = tx.surface_texture(rng, w, h, tex_texel, np.array([0.12, 0.12, 0.12]), shapes_per_m2=6,
                                     size_m=(0.1, 0.8))
            emission = np.zeros_like(img)
            for a in np.arange(1.0, w - 0.5, 2.0):
                emission[:, int(a / tex_texel):int((a + 0.1) / tex_texel)] = 6.0 * WHITE_LED
            emitters.append({"kind": "led_strips", "surface": name, "every_m": 2.0, "width_m": 0.1,
                             "radiance": (6.0 * WHITE_LED).round(4).tolist()})
        rad = _baked(img, lighting, normal, emission)
        planes.append(Plane(name, origin, np.asarray(eu, float), np.asarray(ev, float), size,
                            tx.Texture(rad, tex_texel)))
    # the colour chart: a large board on a stand at the far side of the stage, facing the static
    # cameras (so it is seen behind the actors, never in front of them)
    static_pos = np.array([c.mount.position_m for c in rig.cameras if not c.role.tracks])
    look = static_pos[:, :2].mean(axis=0)
    dirn = look / np.linalg.norm(look) if np.linalg.norm(look) > 1.0 else np.array([1.0, 0.0])
    perp = np.array([-dirn[1], dirn[0]])
    ccentre = np.zeros(3)
    ccentre[:2] = -0.35 * sx * dirn - 0.3 * sy * perp
    patch = 0.16 if min(sx, sy) >= 3.5 else 0.1
    board_h = 4 * patch + 5 * patch * 0.2
    ccentre[2] = 0.55 + board_h / 2
    chart, chart_gt = _chart("chart", ccentre, [dirn[0], dirn[1], 0.0], patch, patch * 0.2, lighting, 0.005)
    chart_gt["visible_until_s"] = None     # stays for the whole take
    # props around the actors' area give the set depth (SfM needs more than the back wall's plane)
    props = []
    prng = np.random.default_rng(rng.integers(1 << 63))
    for k, (px, py, w, d, h, yaw) in enumerate(PROPS):
        props.append(_add_box(boards, prng, f"prop{k}", (px * sx / 2, py * sy / 2), w, d, h, yaw, lighting))
    return StaticScene(RoomBackground(lo, hi, planes), boards + [chart], lighting, targets, chart_gt, emitters,
                       tuple(rig.stage_size_m), props=props)


def _disc(img, texel, a, b, radius, value):
    """Paint a disc of ``radius`` metres centred at (a, b) metres (texel centres inside it)."""
    i0, i1 = max(0, int((b - radius) / texel) - 1), min(img.shape[0], int((b + radius) / texel) + 2)
    j0, j1 = max(0, int((a - radius) / texel) - 1), min(img.shape[1], int((a + radius) / texel) + 2)
    yy, xx = np.ogrid[i0:i1, j0:j1]
    m = ((xx + 0.5) * texel - a) ** 2 + ((yy + 0.5) * texel - b) ** 2 < radius ** 2
    img[i0:i1, j0:j1][m] = value


def build_face_stage(rig: Rig, rng: np.random.Generator, texel: float = 0.006,
                     chart_until_s: float = 0.2) -> StaticScene:
    """The Face Rig: a capped cylinder of black LED panels with white lights, a few small ArUco
    boards on the wall and a small colour chart held in front of the face until ``chart_until_s``."""
    sx, sy, H = rig.stage_size_m
    r = sx / 2
    lighting = FACE_LIGHTING
    circ = 2 * math.pi * r
    rows, cols = int(round(H / texel)), int(round(circ / texel))
    wall = np.full((rows, cols, 3), 0.03, np.float32)
    wall *= (1 + 0.35 * tx.value_noise(rng, rows, cols, 0.4 / texel, octaves=5))[..., None]
    # 16 columns x 5 rows of panels: dark seams 2 cm wide
    seam = int(round(0.02 / texel))
    for k in range(16):
        j = int(round(k * cols / 16))
        wall[:, max(0, j - seam // 2):j + seam // 2 + 1] = 0.006
    for k in range(1, 5):
        i = int(round(k * rows / 5))
        wall[i - seam // 2:i + seam // 2 + 1] = 0.006
    emission = np.zeros_like(wall)
    emitters: list[dict] = []
    light_r = 0.035
    n_wall_lights = 80
    for k in range(n_wall_lights):    # 16 columns x 5 rows, at panel corners shifted by half a panel
        cc, rr = k % 16, k // 16
        a = (cc + 0.5) * circ / 16 + (0.12 if rr % 2 else -0.12)
        b = (rr + 0.5) * H / 5
        _disc(emission, texel, a, b, light_r, 8.0 * WHITE_LED)
    emitters.append({"kind": "led_discs", "surface": "wall", "count": n_wall_lights, "radius_m": light_r,
                     "radiance": (8.0 * WHITE_LED).round(4).tolist()})
    # caps
    n_cap = int(round(2 * r / texel))
    caps = []
    for name, n_lights, base in (("floor", 0, 0.04), ("ceiling", 30, 0.03)):
        img = np.full((n_cap, n_cap, 3), base, np.float32)
        img *= (1 + 0.35 * tx.value_noise(rng, n_cap, n_cap, 0.4 / texel, octaves=5))[..., None]
        em = np.zeros_like(img)
        for k in range(n_lights):
            ring = 0.45 if k < 10 else 1.0
            idx = k if k < 10 else k - 10
            ang = 2 * math.pi * idx / (10 if k < 10 else 20)
            a, b = r + ring * math.cos(ang), r + ring * math.sin(ang)
            _disc(em, texel, a, b, light_r, 8.0 * WHITE_LED)
        if n_lights:
            emitters.append({"kind": "led_discs", "surface": name, "count": n_lights, "radius_m": light_r,
                             "radiance": (8.0 * WHITE_LED).round(4).tolist()})
        normal = (0, 0, 1) if name == "floor" else (0, 0, -1)
        caps.append(tx.Texture(_baked(img, lighting, normal, em), texel))
    wall_tex = tx.Texture(_baked(wall, lighting, (1.0, 0.0, 0.0), emission), texel)
    wall_tex.wrap = (True, False)
    background = CylinderBackground(r, 0.0, H, wall_tex, caps[0], caps[1])
    # small ArUco boards 3 cm in front of the wall, facing the centre, at about head height
    boards: list[Plane] = []
    targets: list[dict] = []
    for k in range(6):
        ang = math.radians(-150 + 60 * k + 30)
        size = 0.2
        centre = np.array([(r - 0.03) * math.cos(ang), (r - 0.03) * math.sin(ang), 1.45 + 0.25 * (k % 2)])
        n = -np.array([math.cos(ang), math.sin(ang), 0.0])
        ev = np.array([0.0, 0.0, 1.0])
        eu = np.cross(ev, n)
        _add_aruco(boards, targets, (centre - eu * size / 2 - ev * size / 2, eu, ev), f"aruco_board{k}",
                   40 + k, 0.0, 0.0, size, lighting)
    # the chart is held up in front of the face at the start of the take (a colour slate), then
    # taken away: it is visible while t < chart_until_s
    chart, chart_gt = _chart("chart", (0.24, 0.0, 1.68), (1.0, 0.0, 0.15), 0.04, 0.008, lighting, 0.002)
    chart_gt["visible_until_s"] = chart_until_s
    return StaticScene(background, boards, lighting, targets, chart_gt, emitters, tuple(rig.stage_size_m),
                       timed_boards=[(chart, chart_until_s)])
