"""The Face Rig's Gaussian-splat pairs (issue 29): LQ counts, renders along a camera path (pixel
alignment, the colour matrix, the exact flow), the pair dataset's split and its loader.

The fast tests use a hand-made moving Poly4DGS (a textured blob of Gaussians drifting sideways)
seen by a dollying camera; the HQ is the whole blob, the LQ a fifth of its Gaussians made larger,
as a Gaussian budget cut leaves a model. The slow test runs the ``facerig_pairs`` flow end to end
on a 4-camera, 4-frame synthetic Face Rig capture.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from volcap_core.calibration.colour import apply_colour_matrix
from volcap_core.calibration.colour_step import ChartView, ColourMatrixRecord
from volcap_core.enhance.metrics import warp_error
from volcap_core.enhance.production import (PairDataset, SplatPairSequence, decode_splat_pair_sequence,
                                            load_pair_sets, pair_record, split_subsequences)
from volcap_core.enhance.temporal import DisFlow
from volcap_core.records import MEDIA_EXR, ArtifactRef
from volcap_core.view import ViewSpec
from volcap_core.splat.camera import look_at
from volcap_core.splat.model import Poly4DGS, Poly4DGSConfig
from volcap_core.splat_pairs import (encode_flow_frame, encode_frames, encode_pair_frame, lq_gaussians_per_frame,
                                     render_path)
from volcap_core.store import ArtifactStore

FPS = 24.0
SIZE = 64


# ---------------------------------------------------------------------------------------------
# LQ counts and the split


def test_lq_counts_are_drawn_inside_the_range_seeded_per_subsequence():
    counts = [lq_gaussians_per_frame((50_000, 200_000), 0, i) for i in range(40)]
    assert all(50_000 <= c <= 200_000 for c in counts)
    assert len(set(counts)) > 30                                           # drawn, not one value
    assert counts == [lq_gaussians_per_frame((50_000, 200_000), 0, i) for i in range(40)]
    assert counts != [lq_gaussians_per_frame((50_000, 200_000), 1, i) for i in range(40)]
    assert lq_gaussians_per_frame((300, 300), 5, 2) == 300
    with pytest.raises(ValueError, match="0 < low <= high"):
        lq_gaussians_per_frame((500, 200), 0, 0)


@pytest.mark.parametrize("count", [1, 2, 3, 10, 60])
def test_the_split_is_by_subsequence_disjoint_and_seeded(count):
    split = split_subsequences(count, seed=3)
    parts = [set(split[k]) for k in ("train", "validation", "test")]
    assert set().union(*parts) == set(range(count))
    assert sum(len(p) for p in parts) == count                            # disjoint
    assert split["train"]                                                  # something to train on
    if count >= 2:
        assert split["test"]                                               # something held out
    assert split == split_subsequences(count, seed=3)
    if count == 60:
        assert len(split["test"]) == 6 and len(split["validation"]) == 6
        assert split != split_subsequences(count, seed=4)


# ---------------------------------------------------------------------------------------------
# Rendering along a path


def blob(n: int, *, seed: int = 0, size_scale: float = 1.0) -> Poly4DGS:
    """``n`` Gaussians in a 0.6 m cube of random colours, drifting at 1.2 m/s along x (~2 px a frame)."""
    g = torch.Generator().manual_seed(seed)
    xyz = (torch.rand(n, 3, generator=g) * 2 - 1) * 0.3
    cfg = Poly4DGSConfig(mean_degree=1, quat_degree=0, scale_degree=0, opacity_degree=1, sh_degree=0)
    model = Poly4DGS.from_points(cfg, xyz, torch.rand(n, 3, generator=g),
                                 scales=torch.full((n,), 0.035 * size_scale), t0=torch.zeros(n), opacity=0.9,
                                 lifespan_s=float("inf"))
    model.params["means_t"][:, 0] = torch.tensor([1.2, 0.0, 0.0])
    return model


def lq_of(hq: Poly4DGS, keep: int = 5) -> Poly4DGS:
    """Every ``keep``-th Gaussian of ``hq``, ``sqrt(keep)`` times larger: a smaller budget's model."""
    params = {k: v[::keep].clone() for k, v in hq.params.items()}
    params["scales"] = params["scales"] + 0.5 * float(np.log(keep))
    return Poly4DGS(hq.config, params)


def path(frames: int = 4) -> list[ViewSpec]:
    """A camera dollying in and sliding, aimed at the blob, one view per frame at 24 fps."""
    views = []
    for k in range(frames):
        cam = look_at((0.1 * k, -2.2 + 0.08 * k, 0.2), (0.0, 0.0, 0.0), fov_x_deg=40, width=SIZE, height=SIZE)
        views.append(ViewSpec(K=tuple(tuple(float(v) for v in r) for r in cam.K.tolist()),
                              world_to_camera=tuple(tuple(float(v) for v in r) for r in cam.world_to_camera.tolist()),
                              width=SIZE, height=SIZE, time_s=k / FPS))
    return views


@pytest.fixture(scope="module")
def rendered():
    torch.set_num_threads(1)
    hq, lq = blob(1500), lq_of(blob(1500))
    views = path()
    hq_rgba, _ = render_path(hq, views)
    lq_rgba, lq_flow = render_path(lq, views, flow=True)
    return hq, lq, views, hq_rgba, lq_rgba, lq_flow


def test_lq_and_hq_renders_of_one_path_are_pixel_aligned(rendered):
    hq, lq, views, hq_rgba, lq_rgba, _ = rendered
    assert hq_rgba.shape == lq_rgba.shape == (4, SIZE, SIZE, 4)
    again, none = render_path(hq, views)
    assert none is None and np.array_equal(again, hq_rgba)                # same camera, same time: same pixels
    def centre(alpha: np.ndarray) -> np.ndarray:
        ys, xs = np.mgrid[:alpha.shape[0], :alpha.shape[1]]
        return np.array([(alpha * xs).sum(), (alpha * ys).sum()]) / alpha.sum()

    for t in range(4):                                                     # the same footprint, frame by frame
        a, b = hq_rgba[t, ..., 3] > 0.5, lq_rgba[t, ..., 3] > 0.5
        assert (a & b).sum() / (a | b).sum() > 0.65
        assert np.abs(centre(hq_rgba[t, ..., 3]) - centre(lq_rgba[t, ..., 3])).max() < 0.5
    # the LQ one frame off is ~2 px away: the alignment is in time too
    off, _ = render_path(lq, [v.model_copy(update={"time_s": v.time_s + 1 / FPS}) for v in views])
    assert np.abs(centre(hq_rgba[0, ..., 3]) - centre(off[0, ..., 3])).max() > 1.0


def test_the_lq_is_worse_than_the_hq_where_both_draw(rendered):
    _, _, _, hq_rgba, lq_rgba, _ = rendered
    again = render_path(lq_of(blob(1500)), path())[0]
    assert np.array_equal(again, lq_rgba)
    assert np.abs(lq_rgba - hq_rgba).mean() > 0.01


def test_the_colour_matrix_maps_premultiplied_rgb_and_keeps_alpha(rendered):
    hq, _, views, hq_rgba, _, _ = rendered
    M = np.diag([2.0, 1.0, 0.5])
    b = np.array([0.1, 0.0, 0.0])
    out, _ = render_path(hq, views[:1], colour=(M, b))
    np.testing.assert_allclose(out[0, ..., 3], hq_rgba[0, ..., 3])
    np.testing.assert_allclose(out[0, ..., 0], 2 * hq_rgba[0, ..., 0] + 0.1 * hq_rgba[0, ..., 3], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(out[0, ..., 2], 0.5 * hq_rgba[0, ..., 2], rtol=1e-5, atol=1e-6)


def test_the_colour_matrix_on_the_device_is_the_host_s_bit_for_bit(rendered):
    """render_path maps each frame on the model's device before its copy to the host: the values
    are apply_colour_matrix's on the host's copy of the same render, to the bit (so the pair EXRs'
    bytes did not change when the matrix moved), and a transparent pixel stays 0 with an offset."""
    hq, _, views, hq_rgba, _, _ = rendered
    record = colour_record(((1.0341, -0.0412, 0.0123), (0.0231, 0.9812, -0.0045), (-0.0187, 0.0521, 1.0771)),
                           (0.0031, -0.0012, 0.0007))
    out, _ = render_path(hq, views, colour=record)
    assert out.dtype == np.float32
    np.testing.assert_array_equal(out, apply_colour_matrix(hq_rgba, record, premultiplied=True))
    empty = hq_rgba[..., 3] == 0
    assert empty.sum() > 100 and not out[empty].any()                   # transparent black, offset or not
    assert (out[..., :3] != hq_rgba[..., :3]).any()                      # the matrix did map the rest


def test_a_path_s_encodes_on_threads_come_back_in_the_frames_order(rendered):
    _, lq, views, _, lq_rgba, lq_flow = rendered
    attributes = [{"volcap.frame": k} for k in range(len(views))]
    one = list(encode_frames(encode_pair_frame, lq_rgba, views, attributes, workers=1))
    assert list(encode_frames(encode_pair_frame, lq_rgba, views, attributes, workers=3)) == one
    assert len(set(one)) == len(views)                                   # four different frames, in order
    flows = list(encode_frames(encode_flow_frame, lq_flow, workers=2))
    assert flows == [encode_flow_frame(f) for f in lq_flow]
    with pytest.raises(ValueError, match="does not match channels"):    # an encode's error reaches the caller
        list(encode_frames(encode_pair_frame, lq_rgba[..., :3], views, attributes, workers=2))


def test_the_rendered_flow_warps_the_previous_frame_better_than_zero_flow_and_dis(rendered):
    """Frame ``t - 1`` warped onto ``t``, over the pixels the LQ draws at ``t`` (where a flow is
    defined: an empty pixel's flow is 0 by the renderer's convention). Training warps the previous
    *HQ* frame with the LQ's flow: there the exact flow beats DIS run on the LQ frames (the flow the
    enhancer would otherwise have) by about 2x. On the LQ itself DIS, which fits the LQ's own
    appearance changes, is within ~20 % of it either way (docs/enhancer.md)."""
    _, _, _, hq_rgba, lq_rgba, lq_flow = rendered
    assert lq_flow.shape == (3, SIZE, SIZE, 2)
    lq = torch.from_numpy(lq_rgba).permute(0, 3, 1, 2).contiguous()
    hq = torch.from_numpy(hq_rgba).permute(0, 3, 1, 2).contiguous()
    flow = torch.from_numpy(lq_flow).permute(0, 3, 1, 2).contiguous()
    assert float(flow.abs().amax()) > 1.0                                   # the scene does move
    drawn = (lq[1:, 3:4] > 0.5).float()
    dis = DisFlow()
    dis_flow = torch.stack([dis(lq[t, :3], lq[t + 1, :3]) for t in range(len(lq) - 1)])
    zero = torch.zeros_like(flow)
    assert warp_error(lq, flow, drawn) < 0.05 * warp_error(lq, zero, drawn)
    assert warp_error(lq, flow, drawn) < 1.3 * warp_error(lq, dis_flow, drawn)
    exact_hq, dis_hq = warp_error(hq, flow, drawn), warp_error(hq, dis_flow, drawn)
    assert exact_hq < 0.05 * warp_error(hq, zero, drawn) and exact_hq < 0.7 * dis_hq, (exact_hq, dis_hq)


def walled(n: int) -> Poly4DGS:
    """:func:`blob` (the head: a 0.6 m cube at the origin, drifting along x) with a static wall of
    ~1 000 dark Gaussians 1.2 m in front of it (the plane y = -1.2, 2.4 m × 1.6 m): the Face Rig
    room's wall when a path camera stands beyond it."""
    head = blob(n)
    gx, gz = np.meshgrid(np.arange(-1.2, 1.2, 0.06), np.arange(-0.8, 0.8, 0.06))
    xyz = torch.tensor(np.stack([gx.ravel(), np.full(gx.size, -1.2), gz.ravel()], 1), dtype=torch.float32)
    wall = Poly4DGS.from_points(head.config, xyz, torch.full((len(xyz), 3), 0.03), scales=torch.full((len(xyz),), 0.02),
                                t0=torch.zeros(len(xyz)), opacity=0.9, lifespan_s=float("inf"))
    return Poly4DGS(head.config, {k: torch.cat([head.params[k], wall.params[k]]) for k in head.params})


def test_a_path_view_s_near_plane_hides_what_stands_between_the_camera_and_the_head():
    """A face path's camera 1.7 m from the head, past a wall 1.2 m from it (the Face Rig's full run:
    a long lens beyond the room's wall): its near plane drops the wall, so the pair frames and the
    LQ's flow are the head's alone, as if the wall were not there; without it the wall veils the
    head and its flow (static, seen moving by parallax) is mixed into the head's."""
    from volcap_core.production.face_paths import FacePathDistribution, face_camera_paths

    torch.set_num_threads(1)
    r = 0.3                                 # the blob's head sphere
    dist = FacePathDistribution(focal_mm=(50.0, 50.0), zoom=1.0, head_fraction=(0.5, 0.5), azimuth_deg=0.0,
                                orbit_deg=30.0, elevation_deg=(0.0, 0.0), tilt_deg=0.0, aim_offset=0.0, roll_deg=0.0)
    [p] = face_camera_paths((0.0, 0.0, 0.0), r, np.arange(3) / FPS, 1, width=SIZE, height=SIZE, seed=2,
                            facing=(0.0, -1.0, 0.0), distribution=dist)
    views = p.views                         # orbiting 14 degrees in 3 frames: the wall moves by parallax
    d = p.params["distance_m_start"]
    assert d > 1.2 + 0.3 and all(v.near_m == pytest.approx(d - 3 * r) for v in views)   # the wall is between
    head_rgba, head_flow = render_path(blob(1500), views, flow=True)
    rgba, flow = render_path(walled(1500), views, flow=True)
    np.testing.assert_allclose(rgba, head_rgba, atol=1e-5)                 # the head, unveiled
    np.testing.assert_allclose(flow, head_flow, atol=1e-4)                 # and the head's motion
    assert np.abs(head_flow[..., 0]).max() > 1.0                           # which does move
    # the same views without their near plane: the wall veils the frame and drags the flow
    bare = [v.model_copy(update={"near_m": None}) for v in views]
    veiled, veiled_flow = render_path(walled(1500), bare, flow=True)
    head = head_rgba[..., 3] > 0.5
    assert veiled[..., 3].mean() > 0.5 and np.abs(veiled - head_rgba)[head].mean() > 0.1
    assert np.abs(veiled_flow - head_flow)[head[1:]].mean() > 5.0         # px: the wall's parallax, not the head's


def colour_record(matrix, offset) -> ColourMatrixRecord:
    """A Face Rig -> Scene Rig colour-matrix record of ``matrix`` and ``offset`` (its chart views
    are placeholders: only the matrix and offset are applied)."""
    chart = ChartView(rig="face", image=ArtifactRef(digest="blake3:" + "c" * 64, size=1), patches_px=((1.0, 2.0),) * 4)
    return ColourMatrixRecord(source_rig="face", reference_rig="scene", source=chart,
                              reference=chart.model_copy(update={"rig": "scene"}), matrix=matrix, offset=offset,
                              patches_used=(0, 1, 2, 3), before={}, after={}, delta_e2000=())


def test_a_path_of_views_of_two_sizes_is_refused():
    views = path(2)
    views[1] = views[1].model_copy(update={"width": SIZE + 1})
    with pytest.raises(ValueError, match="share one size"):
        render_path(blob(10), views)


# ---------------------------------------------------------------------------------------------
# The dataset record and its loader


def _sequence(s: ArtifactStore, rendered, subsequence: int) -> SplatPairSequence:
    _, _, views, hq_rgba, lq_rgba, lq_flow = rendered
    put = lambda data: s.put_bytes(data, MEDIA_EXR)  # noqa: E731
    model = ArtifactRef(digest="blake3:" + "a" * 64, size=1)
    return SplatPairSequence(
        name=f"s{subsequence:03d}-p000", subsequence=subsequence, path=0, frames=(0, 1, 2, 3), width=SIZE,
        height=SIZE, lq=tuple(put(encode_pair_frame(x, v, {"volcap.pair": "lq"})) for x, v in zip(lq_rgba, views)),
        hq=tuple(put(encode_pair_frame(x, v, {"volcap.pair": "hq"})) for x, v in zip(hq_rgba, views)),
        flow=tuple(put(encode_flow_frame(f)) for f in lq_flow), path_params={"focal_mm": 85.0},
        lq_gaussians=300, hq_gaussians=1500, lq_model=model, hq_model=model)


def test_a_pair_dataset_loads_its_training_split_only_and_round_trips(tmp_path, rendered):
    _, _, _, hq_rgba, lq_rgba, lq_flow = rendered
    s = ArtifactStore(f"file://{tmp_path}/store")
    seqs = tuple(_sequence(s, rendered, i) for i in range(3))
    split = split_subsequences(3, seed=0)
    ref0 = ArtifactRef(digest="blake3:" + "b" * 64, size=1)
    ds = PairDataset(actor="anna", group="anna", capture=ref0, calibration=ref0, colour=None, method="splat",
                     lq_range=(200, 500), lq_range_source="preset", resolution=SIZE, parameters={}, split=split,
                     sequences=seqs)
    ref = s.put_record(ds)
    assert pair_record(ref, s.get_bytes) == ds
    train = load_pair_sets([pair_record(ref, s.get_bytes)], s.get_bytes)
    assert [p.name for p in train] == [f"anna/s{i:03d}-p000" for i in split["train"]]
    test = load_pair_sets([ds], s.get_bytes, split="test")
    assert {p.name for p in test} == {f"anna/s{i:03d}-p000" for i in split["test"]}
    assert not {p.name for p in train} & {p.name for p in test}             # no test sub-sequence trains
    p = train[0]
    assert p.group == "anna" and p.lq.shape == (4, 4, SIZE, SIZE) and p.flow.shape == (3, 2, SIZE, SIZE)
    np.testing.assert_array_equal(p.lq.permute(0, 2, 3, 1).numpy(), lq_rgba.astype(np.float16).astype(np.float32))
    np.testing.assert_array_equal(p.hq.permute(0, 2, 3, 1).numpy(), hq_rgba.astype(np.float16).astype(np.float32))
    np.testing.assert_array_equal(p.flow.permute(0, 2, 3, 1).numpy(), lq_flow)    # flow stays float32
    with pytest.raises(ValueError, match="unknown split"):
        load_pair_sets([ds], s.get_bytes, split="holdout")
    with pytest.raises(ValueError, match="not a pair set"):
        pair_record(s.put_bytes(b"{}", "application/json"), s.get_bytes)


def test_a_frame_of_the_wrong_size_is_named(tmp_path, rendered):
    s = ArtifactStore(f"file://{tmp_path}/store")
    seq = _sequence(s, rendered, 0).model_copy(update={"width": SIZE * 2})
    with pytest.raises(ValueError, match="pair sequence s000-p000: LQ frame 0: 64x64"):
        decode_splat_pair_sequence(seq, s.get_bytes)


# ---------------------------------------------------------------------------------------------
# The render-pairs task


def test_render_pairs_stores_each_path_s_frames_in_order_colour_mapped(tmp_path, monkeypatch):
    """render-pairs on a tiny store (the blob HQ and its LQ, two 3-frame paths, one with a near
    plane, a colour matrix), its EXR encodes on three threads: every stored frame is the path's
    render_path frame encoded as encode_pair_frame / encode_flow_frame encode it, in the frames'
    order, the record's refs what one thread stored."""
    import volcap_core.splat_pairs as splat_pairs
    from tasks.facerig import render_pairs
    from volcap_core.reconstruction import SegmentModel
    from volcap_core.splat.model import save_model

    torch.set_num_threads(1)
    monkeypatch.setattr(splat_pairs, "host_threads", lambda: 3)
    s = ArtifactStore(f"file://{tmp_path}/store")
    some = ArtifactRef(digest="blake3:" + "a" * 64, size=1)
    hq, lq = blob(1500), lq_of(blob(1500))
    models = [s.put_record(SegmentModel(capture=some, calibration=some, frames=(4, 7), fps=FPS, gaussians=len(m),
                                        model=s.put_bytes(save_model(m)), steps=1, wall_s=0.0, config={}))
              for m in (hq, lq)]
    paths = [path(3), [v.model_copy(update={"near_m": 2.0}) for v in path(3)]]   # the second cuts the blob
    paths_ref = s.put_json({"paths": [{"views": [v.model_dump(mode="json") for v in p], "params": {"k": k}}
                                      for k, p in enumerate(paths)]})
    record = colour_record(((1.0341, -0.0412, 0.0123), (0.0231, 0.9812, -0.0045), (-0.0187, 0.0521, 1.0771)),
                           (0.0031, -0.0012, 0.0007))
    refs = render_pairs.fn(s.url, *models, paths_ref, 2, [4, 5, 6], 300, 1500, colour=s.put_record(record))
    assert len(refs) == 2
    for k, (ref, views) in enumerate(zip(refs, paths)):
        q = s.get_record(ref, SplatPairSequence)
        assert q.name == f"s002-p{k:03d}" and q.frames == (4, 5, 6) and q.path_params == {"k": k}
        hq_rgba, _ = render_path(hq, views, colour=record)
        lq_rgba, lq_flow = render_path(lq, views, colour=record, flow=True)
        for label, rgba, stored in (("hq", hq_rgba, q.hq), ("lq", lq_rgba, q.lq)):
            assert [s.get_bytes(r) for r in stored] == [
                encode_pair_frame(x, v, {"volcap.pair": label, "volcap.sequence": q.name, "volcap.frame": f})
                for x, v, f in zip(rgba, views, (4, 5, 6))], (q.name, label)
        assert [s.get_bytes(r) for r in q.flow] == [encode_flow_frame(f, {"volcap.sequence": q.name, "volcap.frame": t})
                                                     for f, t in zip(lq_flow, (5, 6))]


# ---------------------------------------------------------------------------------------------
# The tasks' cache keys (tests/test_cache_keys.py's rules, for the Face Rig pair tasks)


def test_the_pair_tasks_keys_see_what_their_output_depends_on():
    from tasks.contract import task_identity
    from tasks.facerig import pair_dataset, render_pairs
    from tests.test_cache_keys import assert_key_behaviour, ref, settings_read

    for task in (render_pairs, pair_dataset):
        assert settings_read(task) == []
        assert task_identity(task)                                          # every library has a release
    base = dict(hq=ref("a"), lq=ref("b"), paths=ref("e"), subsequence=0, frames=[0, 1], lq_gaussians=300,
                hq_gaussians=2000)
    assert_key_behaviour(
        render_pairs, base,
        misses={"the HQ model": {"hq": ref("c")}, "the LQ model": {"lq": ref("c")}, "the paths": {"paths": ref("f")},
                "the sub-sequence": {"subsequence": 1}, "the colour matrix": {"colour": ref("d")}},
        hits={"no colour matrix, spelled out": {"colour": None}})
    base = dict(sequences=[ref("a")], actor="anna", capture=ref("b"), calibration=ref("c"), subsequences=3,
                lq_range=[200, 500], lq_range_source="preset", resolution=128, parameters={}, seed=0)
    assert_key_behaviour(
        pair_dataset, base,
        misses={"the sequences": {"sequences": [ref("a"), ref("d")]}, "the seed": {"seed": 1},
                "the LQ range": {"lq_range": [100, 500]}, "its source": {"lq_range_source": "measured"},
                "the test fraction": {"test": 0.2}},
        hits={"the default fractions, spelled out": {"validation": 0.1, "test": 0.1}})


# ---------------------------------------------------------------------------------------------
# The facerig_pairs flow end to end (slow: eight tiny segment trainings)

FACE_CAMS = ["F000", "F002", "F004", "F006"]   # four static cameras: one is held out of every model


@pytest.fixture(scope="module")
def pair_flow(tmp_path_factory, prefect_api):
    from flows.facerig_pairs import facerig_pairs_flow
    from flows.ingest import ingest_flow
    from flows.runtime import run_flow
    from volcap_core.production.presets import named_preset
    from volcap_core.synth import synthesize_face_capture

    root = tmp_path_factory.mktemp("facerig_pairs")
    folder = synthesize_face_capture(root / "cap", frames=8, supersample=1, cameras=FACE_CAMS, write_depth=True)
    store = f"file://{root}/store"
    cap = ingest_flow(store=store, capture_dir=str(folder.parent))
    # the test preset's schedule at half resolution; two 4-frame sub-sequences, two paths each, 64 px
    quality = named_preset("test").with_overrides(train_scale=0.5, sh_degree=1, face_camera_paths=2,
                                                  face_hq_gaussians_per_frame=1000, face_lq_gaussians=(100, 250),
                                                  pair_resolution=64)
    args = dict(store=store, capture=cap.digest, actor="anna", quality=quality, ground_truth=True)
    first = run_flow(facerig_pairs_flow, **args)
    again = run_flow(facerig_pairs_flow, **args)
    return store, quality, first, again


@pytest.mark.slow
def test_the_flow_makes_a_split_pair_dataset_and_a_rerun_is_cached(pair_flow):
    store, quality, first, again = pair_flow
    s = ArtifactStore(store)
    out = first.result
    ds = s.get_record(out["dataset"], PairDataset)
    assert ds.actor == ds.group == "anna" and ds.resolution == 64 and ds.lq_range == (100, 250)
    assert ds.lq_range_source == "preset" and ds.colour is None
    assert [sub["frames"] for sub in out["subsequences"]] == [[0, 1, 2, 3], [4, 5, 6, 7]]
    assert len(ds.sequences) == out["sequences"] == 2 * 2
    for q in ds.sequences:
        assert len(q.lq) == len(q.hq) == 4 and len(q.flow) == 3 and (q.width, q.height) == (64, 64)
        assert 100 <= q.lq_gaussians <= 250 and q.hq_gaussians == 1000
        assert 35 <= q.path_params["focal_mm_start"] <= 200
    train_subs, test_subs = set(ds.split["train"]), set(ds.split["test"])
    assert train_subs | test_subs == {0, 1} and not train_subs & test_subs
    # train-enhancer's loader reads the training split only
    train = load_pair_sets([pair_record(out["dataset"], s.get_bytes)], s.get_bytes)
    assert {p.name.split("/")[1][:4] for p in train} == {f"s{i:03d}" for i in ds.split["train"]}
    assert again.tasks_run == 0 and again.tasks_cached > 0
    assert again.result["dataset"] == out["dataset"]


@pytest.mark.slow
def test_the_flow_s_lq_and_hq_are_aligned_and_its_flow_warps(pair_flow):
    from volcap_core.reconstruction import SegmentModel
    from volcap_core.splat import load_model

    store, _, first, _ = pair_flow
    s = ArtifactStore(store)
    ds = s.get_record(first.result["dataset"], PairDataset)
    exact, zero = [], []
    for q in ds.sequences:
        p = decode_splat_pair_sequence(q, s.get_bytes)
        # the HQ model rendered again from the stored frames' cameras gives the stored pixels
        views = [ViewSpec(K=tuple(map(tuple, json_of(ref, s, "volcap.K"))),
                          world_to_camera=tuple(map(tuple, json_of(ref, s, "volcap.world_to_camera"))),
                          width=q.width, height=q.height, time_s=float(np.ravel(header_of(ref, s)["volcap.time_s"])[0]),
                          near_m=float(np.ravel(header_of(ref, s)["volcap.near_m"])[0]))
                 for ref in q.hq]
        hq = load_model(s.get_bytes(s.get_record(q.hq_model, SegmentModel).model))
        again, _ = render_path(hq, views)
        np.testing.assert_array_equal(again.astype(np.float16).astype(np.float32), p.hq.permute(0, 2, 3, 1).numpy())
        a, b = p.hq[:, 3] > 0.5, p.lq[:, 3] > 0.5
        assert a.any() and (a & b).sum() / (a | b).sum() > 0.5, q.name     # the same head, in the same place
        drawn = (p.lq[1:, 3:4] > 0.5).float()
        exact.append(warp_error(p.lq, p.flow, drawn))
        zero.append(warp_error(p.lq, torch.zeros_like(p.flow), drawn))
    # over the dataset the LQ's own flow warps its previous frame better than none (per sequence
    # not always, with 20-step models: a 170 mm close-up of one is a few huge Gaussians; the strict
    # per-frame check is the fast test's, on a model that renders like a trained one)
    assert np.mean(exact) < 0.8 * np.mean(zero), (exact, zero)


def header_of(ref, s) -> dict:
    import io

    import OpenEXR

    return dict(OpenEXR.File(io.BytesIO(s.get_bytes(ref))).header())


def json_of(ref, s, key: str):
    import json

    return json.loads(header_of(ref, s)[key])


# ---------------------------------------------------------------------------------------------
# In a production: the preset's pair method


def test_face_pairs_steps_carry_the_pair_method_and_interim_plans_keep_their_fingerprint():
    from flows.production import STEP_KINDS
    from volcap_core.production.presets import named_preset
    from volcap_core.production.steps import FacePairs, Step

    assert named_preset("test").pair_method == named_preset("demo").pair_method == "interim"
    assert named_preset("preview").pair_method == named_preset("production").pair_method == "splat"
    interim = FacePairs.for_actor("anna", "anna_face", named_preset("test"))
    assert interim.method == "interim" and "method" not in interim.as_json()   # as before the field existed
    splat = FacePairs.for_actor("anna", "anna_face", named_preset("test").with_overrides(pair_method="splat"))
    assert splat.as_json()["method"] == "splat"
    source = STEP_KINDS["face-pairs"].source
    assert source(None, Step(id="face-pairs:anna", parameters=interim)) == {}
    tasks = source(None, Step(id="face-pairs:anna", parameters=splat))["splat_tasks"]
    assert {"train-segment", "face-paths", "render-pairs", "pair-dataset"} <= set(tasks)


@pytest.mark.slow
def test_train_enhancer_trains_on_the_dataset_s_training_split(pair_flow):
    from prefect import flow

    from tasks.enhance import actor_prompt, train_enhancer_task
    from volcap_core.enhance.production import EnhancerModel

    store, quality, first, _ = pair_flow
    dataset = first.result["dataset"]

    @flow
    def train() -> ArtifactRef:
        arch = quality.enhancer_config()
        prompt = actor_prompt(store, "anna", arch)
        return train_enhancer_task(store, [dataset], {"anna": prompt},
                                   quality.enhancer_train_config().model_copy(update={"steps": 4, "vae_steps": 4,
                                                                                      "checkpoint_every": 0}),
                                   architecture=arch)

    s = ArtifactStore(store)
    model = s.get_record(train(), EnhancerModel)
    assert model.pair_sets == (dataset,) and model.groups == ("anna",) and model.steps == 4
    assert len(model.losses) == 4 and all(np.isfinite(model.losses))
