"""Rasterizer back-end resolution: an explicit request that cannot run is an error naming its cause,
"auto" says what it chose and why (a WARNING when CUDA tensors fall back to torch), once per
process, and training records the back-end it used.

No CUDA is needed: the CUDA cases pass ``device="cuda"`` to the resolver (it only reads the device
type) and replace the cached gsplat probe with a known outcome.
"""

import importlib
import logging
import sys
import types
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))  # _splat_scenes, any import mode

from _splat_scenes import moving_scene, random_gaussians, ring_cameras, single_thread  # noqa: E402, F401

from volcap_core.reconstruction import SegmentModel  # noqa: E402
from volcap_core.splat.model import Poly4DGSConfig  # noqa: E402
from volcap_core.splat.render import (  # noqa: E402
    BackendChoice,
    BackendUnavailable,
    GsplatProbe,
    probe_gsplat,
    render,
    resolve_backend,
)
from volcap_core.splat.train import SegmentData, TrainConfig, View, train_segment  # noqa: E402

LOGGER = "volcap_core.splat.render"
# the module, not the function volcap_core.splat re-exports under the same name
render_mod = importlib.import_module("volcap_core.splat.render")


@pytest.fixture(autouse=True)
def fresh_backend_state(monkeypatch):
    """Each test starts with no cached probe and nothing logged yet (both are per process)."""
    monkeypatch.setattr(render_mod, "_announced", set())
    probe_gsplat.cache_clear()
    yield
    probe_gsplat.cache_clear()


def _fake_probe(monkeypatch, probe: GsplatProbe) -> list[int]:
    calls = []
    monkeypatch.setattr(render_mod, "probe_gsplat", lambda: calls.append(1) or probe)
    return calls


def _records(caplog, level=None):
    return [r for r in caplog.records if r.name == LOGGER and (level is None or r.levelno == level)]


def test_explicit_gsplat_on_cpu_tensors_raises_naming_the_cause(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    calls = _fake_probe(monkeypatch, GsplatProbe(None, "1.5.3"))
    with pytest.raises(BackendUnavailable, match=r"'gsplat' needs CUDA tensors, these are on cpu; "
                                                 r"CUDA is not available"):
        resolve_backend("gsplat", "cpu")
    # the same through render(): no silent torch fallback for an explicit request
    with pytest.raises(BackendUnavailable, match="needs CUDA tensors"):
        render(random_gaussians(4), ring_cameras(1, size=8)[0], backend="gsplat")
    assert calls == []  # the device alone decided: gsplat was not even imported


def test_explicit_gsplat_with_unusable_gsplat_raises_with_its_exception(monkeypatch):
    error = ImportError("libcudart.so.12: cannot open shared object file: No such file or directory")
    _fake_probe(monkeypatch, GsplatProbe(error))
    with pytest.raises(BackendUnavailable) as info:
        resolve_backend("gsplat", "cuda:0")
    assert "gsplat cannot be used: ImportError: libcudart.so.12: cannot open shared object" in str(info.value)
    assert info.value.__cause__ is error  # the original exception (and its traceback) is kept


def test_torch_is_always_honoured_and_unknown_names_fail():
    assert resolve_backend("torch", "cpu") == BackendChoice("torch", "requested")
    assert resolve_backend("torch", "cuda") == BackendChoice("torch", "requested")
    with pytest.raises(ValueError, match="unknown backend 'cuda'"):
        resolve_backend("cuda", "cpu")


AUTO_CPU = BackendChoice("numba", "auto: float32 CPU tensors, the compiled compositor")


def test_auto_on_cpu_picks_numba_logs_once_and_never_probes_gsplat(monkeypatch, caplog):
    calls = _fake_probe(monkeypatch, GsplatProbe(None, "1.5.3"))
    caplog.set_level(logging.DEBUG, logger=LOGGER)
    g, cam = random_gaussians(6), ring_cameras(1, size=8)[0]
    for _ in range(3):
        choice = resolve_backend("auto", torch.device("cpu"))
        out = render(g, cam)  # auto
    assert choice == AUTO_CPU
    assert torch.allclose(out["rgb"], render(g, cam, backend="numba")["rgb"])
    assert calls == []
    logged = _records(caplog)
    assert len(logged) == 1 and logged[0].levelno == logging.INFO
    assert "'numba'" in logged[0].getMessage() and "float32 CPU tensors" in logged[0].getMessage()


def test_auto_on_cpu_renders_float64_through_torch(caplog):
    """The compiled compositor takes float32: a float64 render (a reference) goes to torch."""
    caplog.set_level(logging.DEBUG, logger=LOGGER)
    choice = resolve_backend("auto", "cpu", torch.float64)
    assert choice.name == "torch" and "float64" in choice.reason
    g, cam = random_gaussians(6), ring_cameras(1, size=8)[0]
    g64 = type(g)(**{f: getattr(g, f).double() if getattr(g, f).is_floating_point() else getattr(g, f)
                     for f in ("means", "quats", "scales", "opacities", "sh", "ids")}, colour_space=g.colour_space)
    out = render(g64, cam)                                    # auto: no error, torch in float64
    assert out["rgb"].dtype == torch.float64
    assert torch.allclose(out["rgb"].float(), render(g, cam, backend="torch")["rgb"], atol=1e-5)


def test_auto_on_cpu_without_numba_warns_and_picks_torch(monkeypatch, caplog):
    error = ImportError("No module named 'numba'")

    def unavailable():
        raise BackendUnavailable("numba cannot be imported") from error
    monkeypatch.setattr(render_mod, "_numba_compositor", unavailable)
    caplog.set_level(logging.DEBUG, logger=LOGGER)
    choice = resolve_backend("auto", "cpu")
    assert choice.name == "torch" and "numba cannot be imported" in choice.reason
    [record] = _records(caplog, logging.WARNING)
    assert record.exc_info[1] is error


def test_auto_on_cuda_with_unusable_gsplat_warns_with_the_reason_and_picks_torch(monkeypatch, caplog):
    error = RuntimeError("Error building extension 'gsplat_cuda'\n[1/20] nvcc ... failed")
    calls = _fake_probe(monkeypatch, GsplatProbe(error))
    caplog.set_level(logging.DEBUG, logger=LOGGER)
    choices = {resolve_backend("auto", d) for d in ("cuda", "cuda:0", torch.device("cuda", 0))}
    assert len(choices) == 1
    (choice,) = choices
    assert choice.name == "torch"
    # the reason names gsplat's exception (its first line: the compiler log stays in the traceback)
    assert "RuntimeError: Error building extension 'gsplat_cuda'" in choice.reason
    assert "nvcc" not in choice.reason
    warnings = _records(caplog, logging.WARNING)
    assert len(warnings) == 1 and len(_records(caplog)) == 1   # once per process, not per call
    msg = warnings[0].getMessage()
    assert "'torch'" in msg and "gsplat is unusable" in msg and "Error building extension" in msg
    assert warnings[0].exc_info[1] is error   # the full exception, logged with the warning
    assert len(calls) == 3  # the resolver asks the (cached) probe each time, never re-imports itself


def test_auto_on_cuda_with_usable_gsplat_picks_gsplat(monkeypatch, caplog):
    _fake_probe(monkeypatch, GsplatProbe(None, "1.5.3"))
    caplog.set_level(logging.DEBUG, logger=LOGGER)
    assert resolve_backend("auto", "cuda") == BackendChoice("gsplat", "auto: CUDA tensors, gsplat 1.5.3")
    assert resolve_backend("gsplat", "cuda") == BackendChoice("gsplat", "requested, gsplat 1.5.3")
    assert [r.levelno for r in _records(caplog)] == [logging.INFO]


def test_probe_keeps_the_import_error_and_is_cached(monkeypatch):
    monkeypatch.setitem(sys.modules, "gsplat", None)  # `import gsplat` now raises ImportError
    first = probe_gsplat()
    assert not first.usable and isinstance(first.error, ImportError)
    assert first.cause == f"{type(first.error).__name__}: {first.error}" and "gsplat" in first.cause
    monkeypatch.delitem(sys.modules, "gsplat")
    assert probe_gsplat() is first  # cached with its exception: not re-imported per call


def test_probe_reports_a_cuda_extension_that_did_not_load(monkeypatch):
    # gsplat imports (a pure-Python wheel) but its CUDA extension is None: what gsplat 1.5 leaves
    # when there is no prebuilt extension and no CUDA toolkit to build one
    pytest.importorskip("gsplat", reason="the gsplat package is not installed")
    backend = types.ModuleType("gsplat.cuda._backend")
    backend._C = None
    monkeypatch.setitem(sys.modules, "gsplat.cuda._backend", backend)
    probe = probe_gsplat()
    assert not probe.usable and probe.version
    assert "CUDA extension did not load" in probe.cause and "CUDA toolkit" in probe.cause


def test_probe_cause_is_one_bounded_line():
    long = GsplatProbe(RuntimeError("x" * 2000 + "\nsecond line"))
    assert len(long.cause) == 500 and long.cause.endswith("...") and "second" not in long.cause
    assert GsplatProbe(ImportError()).cause == "ImportError"
    assert GsplatProbe(None, "1.5.3").cause == ""


def _tiny_config(**kw):
    base = dict(model=Poly4DGSConfig.paper(sh_degree=0), grid_size=4, steps=3, eval_every=0,
                checkpoint_every=0, held_out_cameras=[],
                mcmc=dict(refine_start=100, refine_every=100, refine_stop=1000, cap_max=200))
    base.update(kw)
    return TrainConfig(**base)


def test_training_records_the_backend_it_used(single_thread):
    data, points, _ = moving_scene(n=12, frames=(0, 2), size=16, cameras=3)
    res = train_segment(data, points, _tiny_config(), seed=0, device="cpu")
    assert res.backend == AUTO_CPU
    res = train_segment(data, points, _tiny_config(backend="torch"), seed=0, device="cpu")
    assert res.backend == BackendChoice("torch", "requested")


def test_training_with_an_impossible_backend_fails_before_any_work():
    data, _, _ = moving_scene(n=4, frames=(0, 1), size=8, cameras=2)
    loads = []
    views = [View(v.camera_id, v.frame, v.time, v.camera, lambda v=v: loads.append(v) or v.load())
             for v in data.views]
    # no initial points: initialisation would raise ValueError if it ran first
    with pytest.raises(BackendUnavailable, match="needs CUDA tensors"):
        train_segment(SegmentData(data.frames, views), [], _tiny_config(backend="gsplat"), device="cpu")
    assert loads == []


def test_segment_records_without_a_backend_still_load():
    ref = {"digest": "blake3:" + "0" * 64, "size": 1}
    old = {"capture": ref, "calibration": ref, "frames": [0, 2], "fps": 10.0, "model": ref,
           "gaussians": 5, "steps": 3, "wall_s": 1.0, "config": {}}
    rec = SegmentModel.model_validate(old)
    assert rec.backend is None and rec.backend_reason is None
    new = SegmentModel.model_validate({**old, "backend": "torch", "backend_reason": "requested"})
    assert SegmentModel.from_json_bytes(new.to_canonical_json()).backend == "torch"
    with pytest.raises(ValueError):
        SegmentModel.model_validate({**old, "backend": "opengl"})
