"""The face region of a synthetic actor in a capture camera (volcap_core.synth.ground_truth)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from volcap_core.synth import read_exr, synthesize_capture
from volcap_core.synth.ground_truth import (
    FACE_MARGIN_M,
    backproject_depth,
    face_region,
    head_at,
    head_region,
    performer_mask,
)


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """One take frame of the demo rig's head-framing tracking camera S008 and a static camera,
    with depth maps and performer masks (~3 s)."""
    root = synthesize_capture(tmp_path_factory.mktemp("face") / "cap", seed=3, frames=1, supersample=1,
                              cameras=["S003", "S008"], write_depth=True, lidar_spacing_m=0.3).parent
    gt = root / "ground_truth"
    return root, json.loads((gt / "cameras.json").read_text()), json.loads((gt / "scene.json").read_text())


def _inside(xyz: np.ndarray, head: dict, grow: float) -> np.ndarray:
    R = np.asarray(head["rotation"])
    local = (xyz - np.asarray(head["centre_m"])) @ R / (np.asarray(head["semi_axes_m"]) + grow)
    return (local ** 2).sum(-1) <= 1.0


@pytest.mark.parametrize("cid", ["S008", "S003"])
def test_face_region_covers_the_head_pixels_of_the_performer_mask(capture, cid):
    root, cams, scene = capture
    c = cams["cameras"][cid]
    f = c["frames"][0]
    K = np.array([[f["fx"], 0, f["cx"]], [0, f["fy"], f["cy"]], [0, 0, 1.0]])
    w2c = np.array(f["world_to_camera"])
    mask = performer_mask((root / "ground_truth" / "masks" / cid / "000000.exr").read_bytes())
    depth = read_exr(root / "ground_truth" / "depth" / cid / "000000.exr")
    face = face_region(scene, 0.0, K, w2c, c["width"], c["height"], coverage=mask)
    assert face.dtype == bool and face.shape == mask.shape
    assert not (face & (mask < 0.5)).any()                              # only where a performer is
    # the pixels whose visible surface is a head (the true depth back-projected into one of the
    # actors' head ellipsoids): the face region holds every one of them
    full = np.where(mask == 1, depth, np.nan)
    v, u = np.nonzero(np.isfinite(full) & (full > 0))
    xyz, _ = backproject_depth(full, np.zeros((*mask.shape, 3), np.float32), K, w2c)
    heads = [head_at(a, 0.0) for a in scene["actors"]]
    on_head = np.any([_inside(xyz.astype(np.float64), h, 0.002) for h in heads], axis=0)
    assert on_head.sum() > (400 if cid == "S008" else 10), on_head.sum()    # S008 frames a head
    assert face[v[on_head], u[on_head]].all()
    # and it is the head: its pixels' surfaces lie within the grown ellipsoid (the nose: 2.4 cm out)
    in_face = face[v, u]
    near_head = np.any([_inside(xyz.astype(np.float64), h, FACE_MARGIN_M + 0.005) for h in heads], axis=0)
    assert near_head[in_face].mean() > 0.97


def test_head_region_is_the_projected_ellipsoid():
    """A sphere of radius r at distance d straight ahead covers the disc of radius f·r/sqrt(d²-r²)."""
    head = {"centre_m": [0.0, 0.0, 2.0], "rotation": np.eye(3).tolist(), "semi_axes_m": [0.1, 0.1, 0.1]}
    K = np.array([[200.0, 0, 50], [0, 200.0, 40], [0, 0, 1]])
    m = head_region(head, K, np.eye(4), 100, 80)
    r_px = 200 * 0.1 / np.sqrt(4 - 0.01)
    assert abs(m.sum() - np.pi * r_px ** 2) < 2 * np.pi * r_px    # within a pixel ring
    assert m[40, 50] and not m[40, 50 + int(r_px) + 2]
    grown = head_region(head, K, np.eye(4), 100, 80, margin_m=0.05)
    assert grown.sum() > 2 * m.sum() and (grown | m).sum() == grown.sum()
    behind = dict(head, centre_m=[0.0, 0.0, -2.0])
    assert not head_region(behind, K, np.eye(4), 100, 80).any()


def test_head_at_interpolates_between_take_frames():
    frame = lambda k, x: {"take_index": k, "time_s": k / 24, "parts": [  # noqa: E731
        {"name": "head", "kind": "ellipsoid", "centre_m": [x, 0, 1.6], "rotation": np.eye(3).tolist(),
         "semi_axes_m": [0.1, 0.08, 0.115]}]}
    actor = {"index": 0, "frames": [frame(0, 0.0), frame(1, 0.24)]}
    assert head_at(actor, 0.5 / 24)["centre_m"][0] == pytest.approx(0.12)
    assert head_at(actor, 5.0)["centre_m"][0] == pytest.approx(0.24)      # held after the last frame
    with pytest.raises(ValueError, match="actor 0 take frame 0: no 'head' ellipsoid"):
        head_at({"index": 0, "frames": [{"take_index": 0, "time_s": 0.0, "parts": []}]}, 0.0)
