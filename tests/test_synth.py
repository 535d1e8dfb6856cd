"""Synthetic capture: layout, photometric and lens-encoder realism, determinism, camera convention."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest

from hardware.rig import load_rig
from volcap_core.capture import FRAME_FILE_RE, CaptureDescription
from volcap_core.synth import read_exr, read_ply, synthesize_capture, synthesize_face_capture

FRAMES = 3


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("synth") / "cap"
    calls = []
    path = synthesize_capture(out, rig="demo_scene", seed=3, frames=FRAMES, supersample=1,
                              progress=lambda d, n: calls.append((d, n)))
    assert path == out / "capture.json"
    assert calls and calls[-1][0] == calls[-1][1] and [c[0] for c in calls] == list(range(1, len(calls) + 1))
    return out


def _gt(root: Path, name: str) -> dict:
    return json.loads((root / "ground_truth" / name).read_text())


def _project(frame: dict, points) -> tuple[np.ndarray, np.ndarray]:
    m = np.array(frame["world_to_camera"])
    pc = np.asarray(points, float) @ m[:3, :3].T + m[:3, 3]
    uv = np.stack([frame["fx"] * pc[:, 0] / pc[:, 2] + frame["cx"],
                   frame["fy"] * pc[:, 1] / pc[:, 2] + frame["cy"]], 1)
    return uv, pc[:, 2]


def _image(root: Path, desc: CaptureDescription, cam_id: str, take_index: int) -> np.ndarray:
    cam = next(c for c in desc.cameras if c.id == cam_id)
    n = take_index - desc.take_offset(cam)
    return read_exr(root / cam.path / f"{n:06d}.exr")


def test_layout_and_capture_json(scene):
    desc = CaptureDescription.model_validate_json((scene / "capture.json").read_text())
    rig = load_rig(desc.rig)
    assert desc.take.frame_count == FRAMES and desc.fps == 24 and desc.take.start_timecode == "01:00:00:00"
    assert [c.id for c in desc.cameras] == rig.camera_ids
    assert desc.ground_truth == "ground_truth"
    offsets = {c.id: desc.take_offset(c) for c in desc.cameras}
    early = [cid for cid, o in offsets.items() if o < 0]
    assert 1 <= len(early) <= 2 and all(o <= 0 for o in offsets.values())
    assert any(rig.camera(cid).role.tracks for cid in early)       # encoder re-indexing exercised
    for cam in desc.cameras:
        files = sorted((scene / cam.path).iterdir())
        numbers = sorted(int(FRAME_FILE_RE.match(f.name).group("number")) for f in files)
        assert numbers == list(range(FRAMES - offsets[cam.id]))          # no stray temporary files
        take_indices = [n + offsets[cam.id] for n in numbers]
        assert set(range(FRAMES)) <= set(take_indices)
        rc = rig.camera(cam.id)
        if rc.role.tracks:
            assert [s.frame for s in cam.lens_encoder] == numbers
        else:
            assert cam.lens_encoder is None
    for name in ("cameras.json", "scene.json", "lidar.ply"):
        assert (scene / "ground_truth" / name).is_file()


def test_images_are_finite_linear_hdr(scene):
    desc = CaptureDescription.model_validate_json((scene / "capture.json").read_text())
    rig = load_rig(desc.rig)
    peak = 0.0
    for cam in desc.cameras:
        img = _image(scene, desc, cam.id, 0)
        s = rig.camera(cam.id).sensor
        assert img.shape == (s.height_px, s.width_px, 3)
        assert np.isfinite(img).all()
        assert img.mean() > 0.02
        peak = max(peak, float(img.max()))
    assert peak > 1.5          # LED strips are brighter than diffuse white


def test_exposures_differ_between_cameras(scene):
    cams = _gt(scene, "cameras.json")["cameras"]
    gains = [c["photometric"]["gain"] for c in cams.values()]
    blacks = np.array([c["photometric"]["black_offset"] for c in cams.values()])
    assert np.std(np.log(gains)) > 0.1
    assert np.ptp(blacks, axis=0).min() > 1e-3
    assert all(c["photometric"]["glare_fraction"] > 0 for c in cams.values() if c["role"] != "static")
    assert all(c["photometric"]["glare_fraction"] == 0 for c in cams.values() if c["role"] == "static")
    # the same world seen through different gains: the chart's white patch differs in level
    desc = CaptureDescription.model_validate_json((scene / "capture.json").read_text())
    chart = _gt(scene, "scene.json")["chart"]
    white = chart["patches"][18]["centre_m"]
    levels = {}
    for cid, c in cams.items():
        if c["role"] != "static":
            continue
        uv, z = _project(c["frames"][0], [white])
        u, v = np.round(uv[0]).astype(int)
        if z[0] > 0 and 0 <= u < c["width"] and 0 <= v < c["height"]:
            px = _image(scene, desc, cid, 0)[v, u]
            levels[cid] = (float(px.mean()), c["photometric"]["gain"])
    assert len(levels) >= 3
    obs = np.array([v[0] for v in levels.values()])
    assert obs.max() / obs.min() > 1.15


def test_static_cameras_are_fixed(scene):
    cams = _gt(scene, "cameras.json")["cameras"]
    for c in cams.values():
        assert [f["take_index"] for f in c["frames"]] == list(range(FRAMES))
        if c["role"] == "static":
            first = c["frames"][0]
            for f in c["frames"][1:]:
                assert f["world_to_camera"] == first["world_to_camera"] and f["fx"] == first["fx"]


def test_tracking_cameras_zoom_and_follow_heads(scene):
    cams = _gt(scene, "cameras.json")["cameras"]
    actors = _gt(scene, "scene.json")["actors"]
    rig = load_rig("demo_scene")
    tracking = {cid: c for cid, c in cams.items() if c["role"] != "static"}
    assert len(tracking) == 4
    for cid, c in tracking.items():
        lens = rig.camera(cid).lens
        focals = np.array([f["focal_mm"] for f in c["frames"]])
        assert (focals >= lens.focal_min_mm).all() and (focals <= lens.focal_max_mm).all()
        assert np.ptp(focals) > 1e-3 * focals.mean()                    # zooms smoothly over time
        # the pose changes too: the head turns to follow
        assert c["frames"][0]["world_to_camera"] != c["frames"][-1]["world_to_camera"]
        actor = actors[c["tracking"]["actor"]]
        for f, a in zip(c["frames"], actor["frames"]):
            uv, z = _project(f, [a["head_centre_m"]])
            assert z[0] > 0
            off = np.abs(uv[0] - [(c["width"] - 1) / 2, (c["height"] - 1) / 2]) / [c["width"], c["height"]]
            if c["tracking"]["target"] == "head":
                assert off.max() < 0.2, (cid, off)
            else:
                assert off.max() < 0.5, (cid, off)                          # head inside the frame


def test_lens_encoder_near_truth_but_noisy(scene):
    desc = CaptureDescription.model_validate_json((scene / "capture.json").read_text())
    cams = _gt(scene, "cameras.json")["cameras"]
    rel = []
    for cam in desc.cameras:
        gt = cams[cam.id]
        if gt["role"] == "static":
            continue
        by_frame = {s.frame: s for s in cam.lens_encoder}
        for f in gt["frames"]:
            s = by_frame[f["frame"]]                   # keyed by the camera's own frame number
            rel.append(s.focal_mm / f["focal_mm"] - 1)
            assert s.focus_m > 0
    rel = np.abs(rel)
    assert rel.max() < 0.06
    assert rel.min() > 0 and rel.mean() > 5e-4


def test_chart_projects_where_it_is_rendered(scene):
    """The ground-truth camera convention: projected chart patches land on the rendered patches."""
    desc = CaptureDescription.model_validate_json((scene / "capture.json").read_text())
    cams = _gt(scene, "cameras.json")["cameras"]
    chart = _gt(scene, "scene.json")["chart"]
    centres = np.array([p["centre_m"] for p in chart["patches"]])
    refl = np.array([p["reflectance_linear"] for p in chart["patches"]])
    normal = np.array(chart["normal"])
    good = 0
    for cid, c in cams.items():
        f = c["frames"][0]
        uv, z = _project(f, centres)
        m = np.array(f["world_to_camera"])
        centre_cam = -m[:3, :3].T @ m[:3, 3]
        facing = (centre_cam - centres.mean(0)) @ normal > 0
        inside = (z > 0).all() and (uv >= 2).all() and (uv[:, 0] < c["width"] - 2).all() \
            and (uv[:, 1] < c["height"] - 2).all()
        if not (inside and facing):
            continue
        img = _image(scene, desc, cid, 0)
        vals = np.array([img[int(round(v)), int(round(u))] for u, v in uv])
        corr = np.corrcoef(vals.ravel(), refl.ravel())[0, 1]
        white, black = vals[18].mean(), vals[23].mean()
        if corr > 0.95 and white > 4 * black:
            good += 1
    assert good >= 3


def test_lidar_scan_is_static_set(scene):
    pts, nrm = read_ply(scene / "ground_truth" / "lidar.ply")
    assert pts.dtype == np.float32 and pts.shape[1] == 3 and len(pts) > 10_000
    assert np.allclose(np.linalg.norm(nrm, axis=1), 1, atol=1e-4)
    room = _gt(scene, "scene.json")["stage"]["set"]
    lo, hi = np.array(room["min_m"]), np.array(room["max_m"])
    assert (pts > lo - 0.05).all() and (pts < hi + 0.05).all()
    # no actors: nothing floats in the middle of the stage
    mid = (np.abs(pts[:, 0]) < 1.0) & (np.abs(pts[:, 1]) < 1.0) & (pts[:, 2] > 0.3) & (pts[:, 2] < 1.8)
    assert not mid.any()


def test_deterministic_by_seed(tmp_path):
    kw = dict(frames=1, supersample=1, cameras=["S002", "S009"], lidar_spacing_m=0.2, write_depth=True)
    a = synthesize_capture(tmp_path / "a", seed=5, **kw).parent
    b = synthesize_capture(tmp_path / "b", seed=5, **kw).parent
    c = synthesize_capture(tmp_path / "c", seed=6, **kw).parent
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert len(files) >= 6
    assert Path("ground_truth/masks/S009/000000.exr") in files and Path("ground_truth/depth/S002/000000.exr") in files
    assert files == sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    for rel in files:
        assert (a / rel).read_bytes() == (b / rel).read_bytes(), rel
    assert (a / "ground_truth/scene.json").read_bytes() != (c / "ground_truth/scene.json").read_bytes()


def _part_surface_distance(points: np.ndarray, parts: list[dict]) -> np.ndarray:
    """Per point, roughly how far it is from the nearest actor part's surface (metres)."""
    best = np.full(len(points), np.inf)
    for p in parts:
        if p["kind"] == "capsule":
            a, b = np.array(p["a_m"]), np.array(p["b_m"])
            ab = b - a
            s = np.clip((points - a) @ ab / max(ab @ ab, 1e-12), 0, 1)
            d = np.abs(np.linalg.norm(points - (a + s[:, None] * ab), axis=1) - p["radius_m"])
        else:
            semi = np.array(p["semi_axes_m"])
            local = (points - np.array(p["centre_m"])) @ np.array(p["rotation"])
            d = np.abs(np.linalg.norm(local / semi, axis=1) - 1) * semi.min()
        best = np.minimum(best, d)
    return best


def _part_spheres(parts: list[dict]) -> tuple[np.ndarray, np.ndarray]:
    """Bounding spheres (centres [N, 3], radii [N]) of the actor parts."""
    centres, radii = [], []
    for p in parts:
        if p["kind"] == "capsule":
            a, b = np.array(p["a_m"]), np.array(p["b_m"])
            centres.append((a + b) / 2)
            radii.append(np.linalg.norm(b - a) / 2 + p["radius_m"])
        else:
            centres.append(np.array(p["centre_m"]))
            radii.append(max(p["semi_axes_m"]))
    return np.array(centres), np.array(radii)


def test_performer_masks(tmp_path):
    """ground_truth/masks: per take frame, the actor coverage; 1 on actor surfaces, 0 away from them."""
    from volcap_core.synth.ground_truth import backproject_depth, performer_mask

    frames = 2
    root = synthesize_capture(tmp_path / "m", seed=3, frames=frames, supersample=2, cameras=["S003", "S010"],
                              write_depth=True, lidar_spacing_m=0.3).parent
    cams = _gt(root, "cameras.json")["cameras"]
    actors = _gt(root, "scene.json")["actors"]
    assert any(c["take_offset"] < 0 for c in cams.values())       # pre-roll frames get no mask
    for cid, c in cams.items():
        files = sorted((root / "ground_truth" / "masks" / cid).iterdir())
        assert [f.name for f in files] == [f"{k:06d}.exr" for k in range(frames)]
        for k in range(frames):
            mask = performer_mask((root / "ground_truth" / "masks" / cid / f"{k:06d}.exr").read_bytes())
            assert mask.dtype == np.float32 and mask.shape == (c["height"], c["width"])
            assert mask.min() >= 0 and mask.max() <= 1
            assert set(np.unique(mask)) <= {0.0, 0.25, 0.5, 0.75, 1.0}     # 2x2 sub-sample coverage
            assert (mask == 1).sum() > 200, (cid, k)                      # both see an actor
            assert ((mask > 0) & (mask < 1)).any()                        # soft silhouette edges
            f = c["frames"][k]
            parts = [p for a in actors for p in a["frames"][k]["parts"]]
            depth = read_exr(root / "ground_truth" / "depth" / cid / f"{k:06d}.exr")
            K = np.array([[f["fx"], 0, f["cx"]], [0, f["fy"], f["cy"]], [0, 0, 1]])
            w2c = np.array(f["world_to_camera"])
            # full coverage: the visible surface is an actor part's
            full = np.where(mask == 1, depth, np.nan)
            xyz, _ = backproject_depth(full, np.zeros((*mask.shape, 3), np.float32), K, w2c)
            d = _part_surface_distance(xyz.astype(np.float64), parts)
            assert len(d) == (mask == 1).sum() and np.percentile(d, 95) < 0.015 and d.max() < 0.04, (cid, k)
            # no coverage: the set (only where feet touch the floor is it within 1 cm of a part)
            none = np.where(mask == 0, depth, np.nan)
            xyz, _ = backproject_depth(none, np.zeros((*mask.shape, 3), np.float32), K, w2c)
            assert (_part_surface_distance(xyz.astype(np.float64), parts) < 0.01).mean() < 0.01, (cid, k)
            # no coverage anywhere off the parts' projected bounding spheres (only the set there)
            centres, radii = _part_spheres(parts)
            uv, z = _project(f, centres)
            assert (z > radii).all()
            r_px = 1.5 * f["fx"] * radii / np.sqrt(z ** 2 - radii ** 2) + 3     # generous: off-axis ellipses
            v, u = np.mgrid[0:c["height"], 0:c["width"]]
            near = np.zeros(mask.shape, bool)
            for (uc, vc), r in zip(uv, r_px):
                near |= (u - uc) ** 2 + (v - vc) ** 2 <= r ** 2
            assert (~near).sum() > 0.3 * mask.size
            assert (mask[~near] == 0).all(), (cid, k)


def test_face_capture(tmp_path):
    path = synthesize_face_capture(tmp_path / "face", frames=2, supersample=1, cameras=["F002", "F003", "F007"])
    root = path.parent
    desc = CaptureDescription.model_validate_json(path.read_text())
    assert desc.rig == "demo_face" and desc.take.frame_count == 2
    scene = _gt(root, "scene.json")
    assert scene["kind"] == "face" and len(scene["actors"]) == 1
    ex = [f["expression"] for f in scene["actors"][0]["frames"]]
    assert ex[0] != ex[1]
    head = np.array(scene["actors"][0]["frames"][0]["head_centre_m"])
    assert abs(head[2] - 1.7) < 0.08 and np.linalg.norm(head[:2]) < 0.1
    cams = _gt(root, "cameras.json")["cameras"]
    # the colour chart is held in front of the face at the start: the frontal camera sees it
    chart = scene["chart"]
    assert chart["visible_until_s"] > 0
    f = cams["F003"]["frames"][0]
    uv, z = _project(f, [p["centre_m"] for p in chart["patches"]])
    img = _image(root, desc, "F003", 0)
    vals = np.array([img[int(round(v)), int(round(u))] for u, v in uv])
    refl = np.array([p["reflectance_linear"] for p in chart["patches"]])
    assert np.corrcoef(vals.ravel(), refl.ravel())[0, 1] > 0.95
    for cid in cams:
        assert np.isfinite(_image(root, desc, cid, 1)).all()


def test_bad_arguments(tmp_path):
    with pytest.raises(ValueError, match="no camera"):
        synthesize_capture(tmp_path / "x", frames=1, cameras=["S000", "NOPE"])
    with pytest.raises(ValueError, match="actors"):
        synthesize_capture(tmp_path / "y", frames=1, actors=4)
    with pytest.raises(ValueError, match="face rig"):
        synthesize_capture(tmp_path / "z", rig="demo_face", frames=1)


def test_lens_calibration_error_sets_how_far_the_true_lens_is_from_the_rigs(tmp_path):
    """A rig with measured intrinsics renders each unit through them plus the lens calibration's
    error (``lens_calibration_error``): none of it renders the measured lens itself, a larger
    principal-point error moves the true principal point by the same draw scaled."""
    rig = load_rig("demo_scene_distorted")
    measured = rig.measured_intrinsics("S003")

    def truth(name: str, error: dict | None) -> dict:
        synthesize_capture(tmp_path / name, rig="demo_scene_distorted", frames=1, cameras=["S003"], supersample=1,
                           lens_calibration_error=error)
        return json.loads((tmp_path / name / "ground_truth/cameras.json").read_text())["cameras"]["S003"]["frames"][0]

    exact = truth("exact", {"focal_rel": 0.0, "centre_px": 0.0, "k": 0.0, "p": 0.0})
    assert (exact["fx"], exact["fy"], exact["cx"], exact["cy"]) == pytest.approx(
        (measured.fx, measured.fy, measured.cx, measured.cy), abs=1e-9)
    assert exact["distortion"]["params"] == pytest.approx(list(measured.params), abs=1e-12)
    base, double = truth("base", None), truth("double", {"centre_px": 0.6})
    off = np.array([base["cx"] - measured.cx, base["cy"] - measured.cy])
    assert 0 < np.abs(off).max() < 1.5                                   # 0.3 px sigma
    assert [double["cx"] - measured.cx, double["cy"] - measured.cy] == pytest.approx(2 * off, abs=1e-9)
    with pytest.raises(ValueError, match="unknown keys"):
        synthesize_capture(tmp_path / "bad", rig="demo_scene_distorted", frames=1, lens_calibration_error={"cx": 1})


@pytest.mark.slow
def test_demo_capture_renders_within_a_minute(tmp_path):
    t0 = time.perf_counter()
    synthesize_capture(tmp_path / "demo")
    elapsed = time.perf_counter() - t0
    print(f"demo capture (12 cameras, 320x180, 24 frames, 2x2 supersampling): {elapsed:.1f} s")
    assert elapsed < 60
