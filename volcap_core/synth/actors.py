"""Animated actors: rigid ellipsoid and capsule parts driven by a tiny walk cycle, with a textured
head whose eyes, brows and mouth follow an expression track.

Body frame: x forward, y left, z up; the root stands on the floor. All functions of time are smooth
and defined for negative times too (cameras that start before the take render those frames).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from volcap_core.synth import textures as tx

#: the head centre's height over the actor's root at rest, per unit of ``Actor.scale`` (metres):
#: pelvis 0.95 + chest 0.29 + neck 0.18 + 0.12 + head 0.08 (``Actor._pose``)
HEAD_CENTRE_HEIGHT = 1.62


def rot_x(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def rot_y(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rot_z(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def frame_from_z(z, x_hint) -> np.ndarray:
    """Rotation (columns x, y, z) with z along ``z`` and x as close as possible to ``x_hint``."""
    z = np.asarray(z, np.float64)
    z = z / np.linalg.norm(z)
    x = np.asarray(x_hint, np.float64) - z * (z @ x_hint)
    if np.linalg.norm(x) < 1e-6:
        x = np.array([1.0, 0.0, 0.0]) - z * z[0]
        if np.linalg.norm(x) < 1e-6:
            x = np.array([0.0, 1.0, 0.0]) - z * z[1]
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], axis=1)


@dataclass
class Prim:
    """One rigid part at one instant. ``R`` maps part-local to world (columns = local axes)."""

    name: str
    kind: str                      # "ellipsoid" | "capsule"
    material: str                  # shirt | trousers | skin | shoes | head
    actor: int
    R: np.ndarray
    centre: np.ndarray             # ellipsoid centre / capsule mid-point
    semi: np.ndarray | None = None      # ellipsoid semi-axes along R's columns
    a: np.ndarray | None = None         # capsule end points and radius
    b: np.ndarray | None = None
    radius: float = 0.0
    uv_offset: tuple[float, float] = (0.0, 0.0)
    expression: dict | None = None      # head only: the expression at this instant

    @property
    def bound_radius(self) -> float:
        if self.kind == "ellipsoid":
            return float(np.max(self.semi))
        return float(np.linalg.norm(self.b - self.a) / 2 + self.radius)

    def to_json(self) -> dict:
        d = {"name": self.name, "kind": self.kind, "material": self.material,
             "rotation": np.round(self.R, 6).tolist(), "centre_m": np.round(self.centre, 6).tolist()}
        if self.kind == "ellipsoid":
            d["semi_axes_m"] = np.round(self.semi, 6).tolist()
        else:
            d.update(a_m=np.round(self.a, 6).tolist(), b_m=np.round(self.b, 6).tolist(),
                     radius_m=round(self.radius, 6))
        return d


def _smooth_track(rng, n_terms=3, f_lo=0.2, f_hi=0.9):
    freqs = rng.uniform(f_lo, f_hi, n_terms)
    phases = rng.uniform(0, 2 * math.pi, n_terms)
    amps = rng.uniform(0.5, 1.0, n_terms)
    amps /= amps.sum()

    def f(t):
        return float(sum(a * math.sin(2 * math.pi * fr * t + ph) for a, fr, ph in zip(amps, freqs, phases)))
    return f


def _motion_tracks(rng: np.random.Generator) -> dict:
    """An actor's smooth head, face and sway tracks (each a function of time in seconds) and its
    blink timing (period, phase in seconds): its performance, apart from the walk."""
    tracks: dict = {}
    for key in ("yaw", "pitch", "roll", "mouth", "smile", "brow", "gaze_x", "gaze_y", "sway"):
        tracks[key] = _smooth_track(rng, f_lo=0.25 if key != "mouth" else 0.6,
                                    f_hi=0.8 if key != "mouth" else 2.0)
    tracks["blink"] = (float(rng.uniform(2.0, 3.5)), float(rng.uniform(0, 3.0)))
    return tracks


@dataclass
class Actor:
    index: int
    scale: float
    colours: dict[str, list[float]]
    path_centre: tuple[float, float]
    path_radii: tuple[float, float]
    path_phase: float
    path_dir: float                   # +1 counter-clockwise, -1 clockwise
    speed: float                      # metres per second along the loop (approx.)
    walking: bool
    facing: float = 0.0               # yaw when not walking
    textures: dict[str, tx.Texture] = field(default_factory=dict, repr=False)
    freckles: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)), repr=False)
    _tracks: dict = field(default_factory=dict, repr=False)
    _pose_cache: dict = field(default_factory=dict, repr=False)
    expressive: float = 1.0
    #: height of what the actor stands on (metres): the root is at this z, not on the floor. The
    #: Face Rig stands a Scene Rig actor on a riser so the head is where its cameras look.
    riser_m: float = 0.0

    STRIDE = 1.4   # metres per gait cycle

    @staticmethod
    def random(index: int, rng: np.random.Generator, centre, radii, walking: bool = True,
               expressive: float = 1.0) -> "Actor":
        skin = np.array([0.62, 0.42, 0.32]) * rng.uniform(0.35, 1.1)
        colours = {
            "shirt": tx.random_palette(rng, 1, 0.08, 0.6)[0].tolist(),
            "trousers": tx.random_palette(rng, 1, 0.04, 0.35)[0].tolist(),
            "shoes": (np.full(3, rng.uniform(0.03, 0.5)) * rng.uniform(0.8, 1.0, 3)).tolist(),
            "skin": np.clip(skin, 0.05, 0.8).tolist(),
            "hair": (np.array([0.12, 0.08, 0.05]) * rng.uniform(0.3, 3.0)).clip(0.01, 0.6).tolist(),
            "iris": (tx.random_palette(rng, 1, 0.03, 0.2)[0]).tolist(),
        }
        a = Actor(index=index, scale=float(rng.uniform(0.93, 1.06)), colours=colours,
                  path_centre=tuple(float(c) for c in centre), path_radii=tuple(float(r) for r in radii),
                  path_phase=float(rng.uniform(0, 2 * math.pi)), path_dir=float(rng.choice([-1.0, 1.0])),
                  speed=float(rng.uniform(0.8, 1.2)) if walking else 0.0, walking=walking,
                  expressive=expressive)
        a.textures = {name: _cloth_texture(rng, np.array(colours[name]), kind)
                      for name, kind in (("shirt", "print"), ("trousers", "weave"), ("shoes", "weave"),
                                         ("skin", "skin"), ("hair", "hair"))}
        nf = int(rng.integers(6, 12))
        a.freckles = np.stack([rng.uniform(-1.2, 1.2, nf), rng.uniform(-0.6, 0.35, nf),
                               rng.uniform(0.012, 0.03, nf)], 1)
        a._tracks = _motion_tracks(rng)
        return a

    def restaged(self, index: int, rng: np.random.Generator, centre, *, expressive: float,
                 riser_m: float = 0.0) -> "Actor":
        """The same person in another take: this actor's identity (scale, colours, textures,
        freckles: the same arrays) standing still at ``centre`` (x, y metres) facing +x on a riser
        ``riser_m`` high, with head turns, expressions, blinks and sway of its own, drawn from
        ``rng`` (how :meth:`random` draws them). ``index``: its place in the new world's actors."""
        a = Actor(index=index, scale=self.scale, colours=self.colours,
                  path_centre=tuple(float(c) for c in centre), path_radii=(0.0, 0.0), path_phase=0.0,
                  path_dir=1.0, speed=0.0, walking=False, textures=self.textures, freckles=self.freckles,
                  expressive=expressive, riser_m=float(riser_m))
        a._tracks = _motion_tracks(rng)
        return a

    # ---- motion
    def _omega(self) -> float:
        rx, ry = self.path_radii
        return self.speed / max(0.5 * (rx + ry), 1e-6)

    def root(self, t: float) -> tuple[np.ndarray, float]:
        """Root position on the floor (3,) and body yaw (radians)."""
        cx, cy = self.path_centre
        if not self.walking:
            s = self._tracks["sway"](t)
            return (np.array([cx + 0.02 * s, cy + 0.015 * self._tracks["roll"](t + 3.0), self.riser_m]),
                    self.facing)
        rx, ry = self.path_radii
        ang = self.path_phase + self.path_dir * self._omega() * t
        p = np.array([cx + rx * math.cos(ang), cy + ry * math.sin(ang), self.riser_m])
        tangent = self.path_dir * np.array([-rx * math.sin(ang), ry * math.cos(ang)])
        return p, math.atan2(tangent[1], tangent[0])

    def expression(self, t: float) -> dict[str, float]:
        e = self.expressive
        period, phase = self._tracks["blink"]
        x = ((t + phase) % period) / period * period          # seconds since the last blink start
        blink = math.exp(-((x - 0.08) / 0.05) ** 2)
        return {
            "mouth_open": float(np.clip(0.35 + 0.65 * e * self._tracks["mouth"](t), 0.0, 1.0)),
            "smile": float(np.clip(e * 1.2 * self._tracks["smile"](t), -0.6, 1.0)),
            "brow_raise": float(np.clip(e * 1.3 * self._tracks["brow"](t), -0.8, 1.0)),
            "eye_open": float(np.clip(1.0 - blink, 0.0, 1.0)),
            "gaze_x": 0.06 * self._tracks["gaze_x"](t),
            "gaze_y": 0.03 * self._tracks["gaze_y"](t),
        }

    def head_rotation_local(self, t: float) -> np.ndarray:
        k = 0.6 if self.walking else 1.0
        return rot_z(0.5 * k * self._tracks["yaw"](t)) @ rot_y(0.2 * k * self._tracks["pitch"](t)) @ \
            rot_x(0.1 * k * self._tracks["roll"](t))

    def pose(self, t: float) -> list[Prim]:
        """All parts at time t (cached: every camera renders the same instants; do not mutate)."""
        key = (float(t), self.scale)
        cached = self._pose_cache.get(key)
        if cached is None:
            if len(self._pose_cache) > 512:
                self._pose_cache.clear()
            cached = self._pose_cache[key] = self._pose(t)
        return cached

    def _pose(self, t: float) -> list[Prim]:
        s = self.scale
        root, yaw = self.root(t)
        Rb = rot_z(yaw)
        gait = 2 * math.pi * self.speed * t / self.STRIDE if self.walking else 0.0
        amp = 1.0 if self.walking else 0.0
        bob = 0.02 * amp * math.cos(2 * gait)
        lean = 0.06 * amp + (0.0 if self.walking else 0.03 * self._tracks["pitch"](t + 5.0))
        twist = 0.12 * amp * math.sin(gait)

        def W(p_local):  # body-local -> world
            return root + Rb @ np.asarray(p_local, np.float64)

        prims: list[Prim] = []
        uid = 0

        def ell(name, material, centre, R, semi):
            nonlocal uid
            uid += 1
            prims.append(Prim(name, "ellipsoid", material, self.index, R, np.asarray(centre),
                              semi=np.asarray(semi, np.float64) * s, uv_offset=(0.37 * uid, 0.61 * uid)))

        def cap(name, material, a, b, r, x_hint):
            nonlocal uid
            uid += 1
            a, b = np.asarray(a), np.asarray(b)
            prims.append(Prim(name, "capsule", material, self.index, frame_from_z(b - a, x_hint), (a + b) / 2,
                              a=a, b=b, radius=r * s, uv_offset=(0.29 * uid, 0.53 * uid)))

        fwd = Rb[:, 0]
        R_torso = Rb @ rot_z(twist) @ rot_y(lean)
        pelvis_c = W([0, 0, 0.95 * s + bob])
        ell("pelvis", "trousers", pelvis_c, Rb @ rot_z(-0.5 * twist), [0.11, 0.17, 0.12])
        chest_c = pelvis_c + R_torso @ np.array([0, 0, 0.29 * s])
        ell("chest", "shirt", chest_c, R_torso, [0.125, 0.19, 0.25])
        neck_a = chest_c + R_torso @ np.array([0, 0, 0.18 * s])
        neck_b = neck_a + R_torso @ np.array([0.005, 0, 0.12 * s])
        cap("neck", "skin", neck_a, neck_b, 0.05, fwd)
        R_head = R_torso @ self.head_rotation_local(t)
        head_c = neck_b + R_head @ np.array([0.01 * s, 0, 0.08 * s])
        ell("head", "head", head_c, R_head, [0.10, 0.08, 0.115])
        prims[-1].expression = self.expression(t)
        ell("nose", "skin", head_c + R_head @ (np.array([0.096, 0, -0.012]) * s), R_head, [0.028, 0.016, 0.032])
        for side, sign in ((0, 1.0), (1, -1.0)):       # left (+y), right (-y)
            ph = gait + side * math.pi
            # leg
            hip = pelvis_c + Rb @ np.array([0, 0.09 * sign * s, -0.03 * s])
            alpha = 0.42 * amp * math.sin(ph)
            beta = 0.65 * amp * max(0.0, math.sin(ph + 0.5 * math.pi)) ** 2
            thigh_dir = Rb @ np.array([math.sin(alpha), 0.02 * sign, -math.cos(alpha)])
            knee = hip + 0.44 * s * thigh_dir
            shin_dir = Rb @ np.array([math.sin(alpha - beta), 0.0, -math.cos(alpha - beta)])
            ankle = knee + 0.41 * s * shin_dir
            cap(f"thigh_{'lr'[side]}", "trousers", hip, knee, 0.075, fwd)
            cap(f"shin_{'lr'[side]}", "trousers", knee, ankle, 0.055, fwd)
            ell(f"foot_{'lr'[side]}", "shoes", ankle + Rb @ np.array([0.06 * s, 0, -0.035 * s]), Rb,
                [0.12, 0.05, 0.045])
            # arm (swings against the same-side leg)
            shoulder = chest_c + R_torso @ np.array([0, 0.205 * sign * s, 0.15 * s])
            gam = -0.35 * amp * math.sin(ph) + (0.0 if self.walking else 0.05 * self._tracks["sway"](t + side))
            eps = 0.13
            ua_dir = R_torso @ np.array([math.sin(gam) * math.cos(eps), sign * math.sin(eps),
                                         -math.cos(gam) * math.cos(eps)])
            elbow = shoulder + 0.29 * s * ua_dir
            delta = 0.3 + 0.25 * amp * (1 + math.sin(ph)) / 2
            fa_dir = R_torso @ np.array([math.sin(gam + delta) * math.cos(eps), sign * math.sin(eps),
                                         -math.cos(gam + delta) * math.cos(eps)])
            wrist = elbow + 0.26 * s * fa_dir
            cap(f"upper_arm_{'lr'[side]}", "shirt", shoulder, elbow, 0.048, fwd)
            cap(f"forearm_{'lr'[side]}", "skin", elbow, wrist, 0.04, fwd)
            ell(f"hand_{'lr'[side]}", "skin", wrist + 0.07 * s * fa_dir, frame_from_z(fa_dir, fwd),
                [0.045, 0.025, 0.08])
        return prims

    def head(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Head centre and rotation (local x = facing direction) at time t."""
        for p in self.pose(t):
            if p.name == "head":
                return p.centre, p.R
        raise AssertionError("no head")

    def describe(self) -> dict:
        d = {"index": self.index, "height_scale": round(self.scale, 6),
             "nominal_height_m": round(1.86 * self.scale, 4),
             "colours_linear": {k: np.round(v, 6).tolist() for k, v in self.colours.items()},
             "walking": self.walking,
             "path": {"kind": "ellipse", "centre_m": list(self.path_centre),
                      "radii_m": list(self.path_radii), "phase_rad": round(self.path_phase, 6),
                      "direction": self.path_dir, "speed_mps": round(self.speed, 6)}}
        if self.riser_m:      # (absent on the floor: scene.json files stay as they were)
            d["riser_m"] = round(self.riser_m, 6)
        return d

    # ---- appearance
    def albedo(self, prim: Prim, local: np.ndarray, footprint: np.ndarray) -> np.ndarray:
        """Albedo at hit points given in the part's local frame ((N, 3), metres, unscaled)."""
        if prim.material == "head":
            return self._face_albedo(prim, local, footprint)
        if prim.kind == "ellipsoid":
            q = local / prim.semi
            u = np.arctan2(q[:, 1], q[:, 0]) * float(np.mean(prim.semi[:2]))
            v = np.arcsin(np.clip(q[:, 2], -1, 1)) * float(prim.semi[2])
        else:
            u = np.arctan2(local[:, 1], local[:, 0]) * prim.radius
            v = local[:, 2]
        tex = self.textures[prim.material]
        return tex.sample(u + prim.uv_offset[0], v + prim.uv_offset[1], footprint)

    def _face_albedo(self, prim: Prim, local: np.ndarray, footprint: np.ndarray) -> np.ndarray:
        ex = prim.expression
        q = local / prim.semi
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        lon = np.arctan2(q[:, 1], q[:, 0])
        lat = np.arcsin(np.clip(q[:, 2], -1, 1))
        out = self.textures["skin"].sample(lon * 0.09 + prim.uv_offset[0], lat * 0.115, footprint)
        # cheeks
        for sgn in (1, -1):
            g = np.exp(-(((lon - sgn * 0.55) / 0.22) ** 2 + ((lat + 0.18) / 0.15) ** 2))
            out *= (1 + 0.25 * g[:, None] * np.array([0.6, -0.2, -0.2], np.float32))
        # freckles / moles
        for fl, fa, fr in self.freckles:
            m = (lon - fl) ** 2 + (lat - fa) ** 2 < fr ** 2
            out[m] *= 0.45
        # hair: hairline at lat 0.55 in front, down to -0.35 at the back
        hairline = 0.55 - 0.9 * ((1 - np.cos(lon)) / 2) ** 1.5
        hair = lat > hairline
        if hair.any():
            out[hair] = self.textures["hair"].sample(lon[hair] * 0.09, lat[hair] * 0.115, footprint[hair])
        # eyes, brows and mouth live on the front of the head: work on that subset only
        fi = np.flatnonzero((np.abs(lon) < 0.75) & (lat > -0.65) & (lat < 0.5))
        if fi.size:
            out[fi] = self._features(ex, lon[fi], lat[fi], out[fi])
        return out

    def _features(self, ex: dict, lon: np.ndarray, lat: np.ndarray, out: np.ndarray) -> np.ndarray:
        eo = ex["eye_open"]
        for sgn in (1, -1):
            le, la = sgn * 0.36, 0.1
            ew, eh = 0.15, 0.065 * eo + 0.004
            r2 = ((lon - le) / ew) ** 2 + ((lat - la) / eh) ** 2
            lid = (((lon - le) / (ew * 1.1)) ** 2 + ((lat - la) / (eh + 0.022)) ** 2 < 1) & (r2 >= 1)
            out[lid] = np.array([0.05, 0.035, 0.03], np.float32)
            eye = r2 < 1
            out[eye] = np.array([0.72, 0.7, 0.66], np.float32)
            ir = (lon - le - ex["gaze_x"]) ** 2 + (lat - la - ex["gaze_y"]) ** 2
            out[eye & (ir < 0.055 ** 2)] = np.asarray(self.colours["iris"], np.float32)
            out[eye & (ir < 0.024 ** 2)] = 0.01
            # eyebrow
            lb = la + 0.17 + 0.06 * ex["brow_raise"] + 0.03 * (1 - ((lon - le) / 0.2) ** 2)
            brow = (np.abs(lat - lb) < 0.025) & (np.abs(lon - le) < 0.2)
            out[brow] = np.asarray(self.colours["hair"], np.float32) * 0.8
        # mouth
        smile, mo = ex["smile"], ex["mouth_open"]
        wm = 0.24 * (1 + 0.22 * smile)
        xr = np.clip(lon / wm, -1, 1)
        lat_c = -0.42 + 0.09 * smile * (xr ** 2 - 0.3)
        open_h = 0.09 * mo * (1 - xr ** 2)
        inside = np.abs(lon) < wm
        lips = inside & (np.abs(lat - lat_c) < open_h + 0.03 * (1 - 0.5 * xr ** 2))
        out[lips] = np.asarray(self.colours["skin"], np.float32) * np.array([0.95, 0.45, 0.45], np.float32)
        hole = inside & (np.abs(lat - lat_c) < open_h)
        out[hole] = np.array([0.06, 0.015, 0.015], np.float32)
        teeth = hole & (lat - lat_c > 0.35 * open_h) & (np.abs(lon) < 0.7 * wm)
        out[teeth] = np.array([0.62, 0.6, 0.55], np.float32)
        return out


def _cloth_texture(rng: np.random.Generator, colour: np.ndarray, kind: str, texel: float = 0.004,
                   size_px: int = 256) -> tx.Texture:
    n = size_px
    if kind == "skin":
        g = 1 + 0.08 * tx.value_noise(rng, n, n, 24, octaves=4, wrap=True)
        img = colour[None, None, :] * g[..., None]
    elif kind == "hair":
        g = tx.value_noise(rng, n, n, 48, octaves=5, wrap=True)
        streak = np.sin(np.arange(n)[None, :] * 0.9 + 3 * g) * 0.5 + 0.5
        img = colour[None, None, :] * (0.7 + 0.5 * streak * (1 + 0.3 * g))[..., None]
    else:
        g = tx.value_noise(rng, n, n, 64, octaves=5, wrap=True)
        img = colour[None, None, :] * (1 + 0.35 * g)[..., None]
        pal = np.clip(tx.random_palette(rng, 6, 0.05, 0.85) * 0.5 + colour * 0.5, 0, 1)
        if kind == "print":
            count, size = 90, (6, 40)
        else:
            count, size = 160, (3, 14)
        img = np.ascontiguousarray(img, np.float32)
        tx.draw_shapes(img, rng, count, size, pal)
    return tx.Texture(np.clip(img, 0.005, 0.95).astype(np.float32), texel, wrap=True, levels=5)
