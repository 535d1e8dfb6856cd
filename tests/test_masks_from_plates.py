"""Masks computed against background plates (``volcap masks``) agree with a synthetic capture's
ground-truth masks. The plates are the synthesizer's (``plates=True``: the empty set through each
static camera's own sensor model, rendered as its frames are)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from volcap_core.capture import CaptureFolder
from volcap_core.imageio.read import read_exr_header, read_exr_native
from volcap_core.masks import write_plate_masks
from volcap_core.synth import synthesize_capture

SEED, CAMERAS, FRAMES = 1, ["S000", "S003"], 12


def _iou(root: Path) -> dict[str, float]:
    """Per camera, the mean over take frames of the IoU of mask >= 0.5 with the ground truth's."""
    folder = CaptureFolder.open(root)
    out = {}
    for cam in CAMERAS:
        ious = []
        for i in range(FRAMES):
            truth = read_exr_native(root / "ground_truth" / "masks" / cam / f"{i:06d}.exr")[0][..., 0] >= 0.5
            mask = folder.load_mask(cam, i) >= 0.5
            ious.append((mask & truth).sum() / max((mask | truth).sum(), 1))
        out[cam] = float(np.mean(ious))
    return out


def test_masks_against_plates_agree_with_the_ground_truth(tmp_path):
    """~8 s: 2 static cameras, 12 frames at 320x180."""
    root = synthesize_capture(tmp_path / "cap", rig="demo_scene", seed=SEED, frames=FRAMES, cameras=CAMERAS,
                              supersample=1, write_depth=True, plates=True).parent
    assert sorted(p.name for p in (root / "plates").iterdir()) == [f"{c}.exr" for c in CAMERAS]
    written = write_plate_masks(root, plates=root / "plates")
    assert written == {"S000": FRAMES, "S003": FRAMES}
    assert json.loads((root / "capture.json").read_text())["masks"] == "masks"
    assert CaptureFolder.open(root).mask_cameras == CAMERAS
    with_shadows = _iou(root)
    # the performers' shadows on the floor left out: a better mask (S000 0.871, S003 0.882 against
    # 0.865, 0.779 with them on 2026-11-28: S003 sees the shadows on the floor at length)
    from typer.testing import CliRunner

    from flows import cli
    res = CliRunner().invoke(cli.app, ["masks", str(root), "--plates", str(root / "plates"), "--drop-shadows"])
    assert res.exit_code == 0, res.output
    clean = _iou(root)
    header = read_exr_header(sorted((root / "masks" / "S000").iterdir())[0])
    assert header["volcap.mask_source"] == "plate S000.exr, shadows dropped"
    # no plate given: each camera's median of its take, performers that walk leave it (partly)
    write_plate_masks(root)
    median = _iou(root)
    print("IoU with the ground truth: clean plates", clean, "shadows kept", with_shadows, "median of the take", median)
    assert min(clean.values()) > 0.75
    assert all(clean[c] >= with_shadows[c] for c in CAMERAS)
    assert sum(clean.values()) > sum(with_shadows.values()) + 0.05
    assert min(median.values()) > 0.3


def test_a_shadow_is_the_plate_darkened_with_its_colour_kept():
    """With ``drop_shadows`` a region of the plate at 65 % of its brightness (a shadow) is no
    performer; a region of another colour, or darkened to 20 %, is; by default every difference
    counts."""
    from volcap_core.masks import plate_mask

    rng = np.random.default_rng(0)
    plate = rng.uniform(0.2, 0.8, (30, 30, 3)).astype(np.float32)
    frame = plate.copy()
    frame[:10] *= 0.65                                    # shadow
    frame[10:20] = plate[10:20] * np.array([0.3, 0.9, 0.6], np.float32)   # another colour
    frame[20:] *= 0.2                                     # far darker than a shadow: a performer in black
    mask = plate_mask(frame, plate, drop_shadows=True)
    assert mask[:10].max() == 0.0
    assert mask[10:20].mean() > 0.9 and mask[20:].min() == 1.0
    kept = plate_mask(frame, plate)
    assert kept[:10].min() > 0.5 and np.array_equal(kept[10:], mask[10:])


def test_a_video_cameras_plate_can_come_from_its_whole_recording(tmp_path):
    """A performer who stays put through a short take is its median plate, so the take's masks are
    empty; the median of the whole video, where they were not there most of the time, finds them
    (Pose2Sim's 3-frame takes of a 100-frame video: docs/poly4dgs.md, "Real footage"). ~11 s at load 27,
    most of it the first imports."""
    from tests.test_ingest_video import write_capture, write_video

    grey, white = (126, 128, 128), (235, 128, 128)
    root = tmp_path / "capture"
    root.mkdir()
    # the take is video frames 1-3 (the camera starts a frame before it): the performer's white
    write_video(root / "v.mp4", [grey, white, white, white, grey, grey, grey])
    write_capture(root, {"V0": "v.mp4"}, {"V0": (32, 16)}, frame_count=3)
    write_plate_masks(root)
    folder = CaptureFolder.open(root)
    assert all(folder.load_mask("V0", i).max() == 0.0 for i in range(3))
    # as a user asks for it: `volcap masks --whole-recording`
    from typer.testing import CliRunner

    from flows import cli

    res = CliRunner().invoke(cli.app, ["masks", str(root), "--whole-recording", "--json"])
    assert res.exit_code == 0, res.output
    assert json.loads(res.output.strip().splitlines()[-1])["cameras"] == {"V0": 3}
    folder = CaptureFolder.open(root)
    assert all(folder.load_mask("V0", i).min() == 1.0 for i in range(3))


def test_the_synthesizer_writes_plates_for_static_cameras_only(tmp_path):
    """A tracking camera moves, so no plate stands behind it (``volcap masks`` refuses it): ``plates=True``
    writes the static cameras' alone, and a face rig's synthesis refuses ``--plates`` by name."""
    from typer.testing import CliRunner

    import flows.cli as cli

    root = synthesize_capture(tmp_path / "cap", rig="demo_scene", seed=0, frames=1, cameras=["S000", "S008"],
                              supersample=1, plates=True).parent
    assert [p.name for p in (root / "plates").iterdir()] == ["S000.exr"]
    again = synthesize_capture(tmp_path / "cap", rig="demo_scene", seed=0, frames=1, cameras=["S000", "S008"],
                               supersample=1).parent
    assert not (again / "plates").exists()   # a rerun without plates leaves none behind
    res = CliRunner().invoke(cli.app, ["synth", str(tmp_path / "face"), "--rig", "demo_face", "--frames", "1",
                                       "--plates"])
    assert res.exit_code != 0 and "--plates is for scene rigs" in str(res.exception or res.output)
