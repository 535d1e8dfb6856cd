"""train_segment on a tiny synthetic multi-view capture: learns, holds cameras out, checkpoints
and resumes bit-exactly."""

import math
import sys
from pathlib import Path

import pytest
import torch
from safetensors.torch import load as st_load

sys.path.insert(0, str(Path(__file__).resolve().parent))  # _splat_scenes, any import mode

from _splat_scenes import moving_scene, single_thread  # noqa: E402, F401  (fixture)

from volcap_core.splat.model import Poly4DGSConfig  # noqa: E402
from volcap_core.splat.train import SegmentData, TrainConfig, View, train_segment  # noqa: E402

pytestmark = pytest.mark.usefixtures("single_thread")


def _config(**kw):
    base = dict(model=Poly4DGSConfig.paper(sh_degree=0), grid_size=4,
                checkpoint_every=0, held_out_cameras=["3"],
                mcmc=dict(refine_start=60, refine_every=40, refine_stop=10_000, cap_max=600))
    base.update(kw)
    return TrainConfig(**base)


def test_training_improves_held_out_psnr_substantially():
    data, points, _ = moving_scene()
    seen = []
    res = train_segment(data, points, _config(steps=240, eval_every=120), seed=0,
                        progress=lambda s, n, info: seen.append((s, info["num_gaussians"])))
    first, last = res.history[0], res.history[-1]
    print("held-out PSNR/SSIM vs wall time:", [(e.step, round(e.wall_s, 2), round(e.psnr, 2),
                                                round(e.ssim, 4)) for e in res.history])
    assert [e.step for e in res.history] == [0, 120, 240]
    assert first.wall_s == 0 and res.history[1].wall_s < last.wall_s
    assert last.psnr > first.psnr + 6.0 and last.psnr > 26.0
    assert last.ssim > first.ssim
    assert seen[-1][0] == 240 and seen[-1][1] > seen[0][1]  # MCMC grew the model
    assert all(torch.isfinite(v).all() for v in res.model.params.values())


def test_resume_from_checkpoint_is_bit_identical():
    data, points, _ = moving_scene(n=12, frames=(0, 2), size=16, cameras=4)
    cfg = _config(steps=12, checkpoint_every=5, eval_every=0, held_out_cameras=[],
                  mcmc=dict(refine_start=4, refine_every=4, refine_stop=100, cap_max=200))
    blobs = {}
    full = train_segment(data, points, cfg, seed=7,
                         checkpoint=lambda b, s: blobs.__setitem__(s, b))
    assert sorted(blobs) == [5, 10, 12]
    tensors = st_load(blobs[5])  # plain safetensors, no pickle
    assert "rng" in tensors and any(k.startswith("adam/m/") for k in tensors)
    resumed = train_segment(data, [], cfg, seed=7, resume_from=blobs[5])
    assert resumed.steps == 12 and len(resumed.model) == len(full.model)
    for k, v in full.model.params.items():
        assert torch.equal(v, resumed.model.params[k]), k
    assert torch.equal(full.grids.exposure, resumed.grids.exposure)
    assert torch.equal(full.grids.black, resumed.grids.black)


def test_held_out_cameras_are_never_trained_on():
    data, points, _ = moving_scene(n=12, frames=(0, 2), size=16, cameras=4)
    poisoned = [View(v.camera_id, v.frame, v.time, v.camera,
                     torch.full((16, 16, 3), float("nan")) if v.camera_id == "2" else v.image)
                for v in data.views]
    res = train_segment(SegmentData(data.frames, poisoned), points,
                        _config(steps=30, eval_every=0, held_out_cameras=["2"]), seed=0)
    assert all(torch.isfinite(v).all() for v in res.model.params.values())
    assert res.grids.camera_ids == ["0", "1", "3"]
    assert math.isnan(res.history[-1].psnr)  # only evaluation saw the NaN images


def test_static_3dgs_on_one_frame_and_4d_rotor_configs_train():
    data, points, _ = moving_scene(n=12, frames=(0, 1), size=16, cameras=4)
    res = train_segment(data, points, _config(model=Poly4DGSConfig.static(sh_degree=1), steps=20,
                                              eval_every=0, held_out_cameras=[]), seed=0)
    assert set(res.model.params) == {"means", "quats", "scales", "opacities", "sh0", "shN"}
    data, points, _ = moving_scene(n=12, frames=(0, 2), size=16, cameras=4)
    res = train_segment(data, points, _config(model=Poly4DGSConfig.rotor4d(sh_degree=0),
                                              steps=20, eval_every=0, held_out_cameras=[]), seed=0)
    assert res.model.params["means_t"].shape[1:] == (1, 3) and "quats_t" not in res.model.params


def test_segment_data_builds_lazily_with_frame_times():
    loads = []
    data, _, cams = moving_scene(n=4, frames=(3, 5), size=8, cameras=2, fps=25.0)
    built = SegmentData.build(frames=(3, 5), camera_ids=["0", "1"], fps=25.0,
                              load_image=lambda c, f: loads.append((c, f)) or torch.zeros(8, 8, 3),
                              camera_for=lambda c, f: cams[int(c)])
    assert loads == [] and len(built.views) == 4
    assert built.times == [3 / 25.0, 4 / 25.0]
    built.views[0].load()
    assert loads == [("0", 3)]
    with pytest.raises(ValueError):
        View("0", 0, 0.0, cams[0], torch.zeros(4, 4, 3)).load()


def test_a_non_finite_loss_stops_training_with_the_view_that_caused_it():
    data, points, _ = moving_scene(n=12, frames=(0, 2), size=16, cameras=4)
    poisoned = [View(v.camera_id, v.frame, v.time, v.camera,
                     torch.full((16, 16, 3), float("nan")) if v.camera_id == "1" else v.image)
                for v in data.views]
    with pytest.raises(FloatingPointError, match=r"on view 1@\d.*target has NaN/Inf pixels"):
        train_segment(SegmentData(data.frames, poisoned), points,
                      _config(steps=30, eval_every=0, held_out_cameras=[]), seed=0)


@pytest.mark.gpu
def test_training_on_cuda_with_gsplat_learns_as_the_cpu_run_does():
    """The production path on a GPU: the same run as the CPU test above, on CUDA through gsplat's
    kernels (MCMC, grids and Adam on CUDA tensors); it must learn as much as the CPU back-end."""
    from volcap_core.splat.render import gsplat_available

    if not gsplat_available():
        pytest.skip("needs CUDA and gsplat")
    data, points, _ = moving_scene()
    cpu = train_segment(data, points, _config(steps=240, eval_every=120), seed=0, device="cpu")
    gpu = train_segment(data, points, _config(steps=240, eval_every=120, backend="gsplat"), seed=0,
                        device="cuda")
    print("held-out PSNR cpu/torch:", [round(e.psnr, 2) for e in cpu.history],
          "cuda/gsplat:", [round(e.psnr, 2) for e in gpu.history], gpu.backend)
    assert gpu.backend.name == "gsplat"
    first, last = gpu.history[0], gpu.history[-1]
    assert last.psnr > first.psnr + 6.0 and last.psnr > 26.0
    assert abs(last.psnr - cpu.history[-1].psnr) < 2.0
    assert all(torch.isfinite(v).all() and v.is_cuda for v in gpu.model.params.values())
