"""The segment fan-out (``flows/segment_runs.py``) as the facerig_pairs flow uses it.

The Face Rig HQ and LQ models of each sub-sequence are ``train-segment`` jobs like a production's
segments: in-process task runs (``local``; the slow flow test of tests/enhance/test_splat_pairs.py),
or runs of the ``train-segment`` deployment (``deployment``). The whole cluster path (workers,
S3, a killed worker) is tests/production/test_production_cluster.py; here, without a worker, only
what the coordinator sends and how it refuses: a deployment registered on the session's
temporary Prefect server with ``train_segment_flow``'s parameter schema enforced, whose runs a
thread marks Failed as a worker whose training failed would.
"""

from __future__ import annotations

import threading

import pytest

from flows.facerig_pairs import face_model_jobs, facerig_pairs_flow
from flows.segment_runs import SEGMENT_DEPLOYMENT, SegmentJob, train_segment_flow
from tasks.contract import task_cache_key
from tasks.reconstruct import train_segment_task
from volcap_core.production.presets import named_preset
from volcap_core.records import ArtifactRef
from volcap_core.splat.train import TrainConfig

FACE_CAMS = ["F000", "F002", "F004", "F006"]   # four static cameras: one is held out of every model


def _ref(c: str) -> ArtifactRef:
    return ArtifactRef(digest="blake3:" + c * 64, size=1)


def test_face_model_jobs_are_an_hq_and_an_lq_segment_per_subsequence_at_per_frame_budgets():
    q = named_preset("test").with_overrides(face_hq_gaussians_per_frame=1000)
    windows, lq = [[0, 1, 2, 3], [6, 7, 8, 9]], [150, 220]
    jobs = face_model_jobs(_ref("a"), _ref("b"), _ref("c"), windows, q, ["F000"], lq, seed=3)
    assert [j.frames for j in jobs] == [(0, 4), (0, 4), (6, 10), (6, 10)]
    assert [j.config.mcmc.cap_max for j in jobs] == [4000, 600, 4000, 880]      # per frame x 4 frames
    assert all(j.config == q.train_config(held_out=["F000"], max_gaussians=j.config.mcmc.cap_max) for j in jobs)
    assert all(j.seed == 3 and (j.capture, j.calibration, j.points) == (_ref("a"), _ref("b"), _ref("c"))
               for j in jobs)
    # one model, one cache key: the key the flow's in-process map of train-segment always had
    store = "file:///nonexistent/store"
    keys = [task_cache_key(train_segment_task, store, **j.task_inputs()) for j in jobs]
    assert len(set(keys)) == 4
    assert keys[1] == task_cache_key(train_segment_task, store, capture=_ref("a"), calibration=_ref("b"),
                                     points=_ref("c"), frames=[0, 4],
                                     config=q.train_config(held_out=["F000"], max_gaussians=600), seed=3)
    with pytest.raises(ValueError, match="1 LQ count"):
        face_model_jobs(_ref("a"), _ref("b"), _ref("c"), windows, q, ["F000"], [150])


def test_deployment_mode_without_the_deployment_is_refused_before_any_work(prefect_api, tmp_path):
    # the store holds nothing: the refusal comes before the capture is read
    with pytest.raises(ValueError, match=f"segment_runs='deployment' but the Prefect server at .* has no "
                                         f"deployment '{SEGMENT_DEPLOYMENT}': run `env -u VOLCAP_HOME prefect deploy"):
        facerig_pairs_flow(store=f"file://{tmp_path}/store", capture="no-such-capture", actor="anna",
                           quality="test", ground_truth=True, segment_runs="deployment")


@pytest.fixture(scope="module")
def face_capture(tmp_path_factory, prefect_api):
    from flows.ingest import ingest_flow
    from volcap_core.synth import synthesize_face_capture

    root = tmp_path_factory.mktemp("face_fanout")
    folder = synthesize_face_capture(root / "cap", frames=2, supersample=1, cameras=FACE_CAMS, write_depth=True)
    store = f"file://{root}/store"
    return store, ingest_flow(store=store, capture_dir=str(folder.parent))


def test_in_deployment_mode_the_face_rig_models_are_runs_of_the_train_segment_deployment(face_capture):
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import DeploymentFilter, DeploymentFilterId
    from prefect.states import Failed
    from prefect.utilities.callables import parameter_schema

    store, cap = face_capture
    quality = named_preset("test").with_overrides(face_subsequences=1, face_subsequence_frames=2,
                                                  face_hq_gaussians_per_frame=500, face_lq_gaussians=(100, 250))
    flow_name, name = SEGMENT_DEPLOYMENT.split("/")
    with get_client(sync_client=True) as client:
        dep = client.create_deployment(
            flow_id=client.create_flow_from_name(flow_name), name=name, enforce_parameter_schema=True,
            parameter_openapi_schema=parameter_schema(train_segment_flow).model_dump_for_openapi())
        stop = threading.Event()
        only_ours = DeploymentFilter(id=DeploymentFilterId(any_=[dep]))

        def fail_runs() -> None:   # a worker whose training failed
            with get_client(sync_client=True) as c:
                while not stop.wait(0.2):
                    for run in c.read_flow_runs(deployment_filter=only_ours):
                        if run.state is not None and run.state.is_scheduled():
                            c.set_flow_run_state(run.id, Failed(message="no GPU here"), force=True)

        thread = threading.Thread(target=fail_runs, daemon=True)
        thread.start()
        try:
            with pytest.raises(RuntimeError, match=r"segment \[0, 2\): run .* ended Failed: no GPU here"):
                facerig_pairs_flow(store=store, capture=cap.digest, actor="anna", quality=quality, ground_truth=True,
                                   segment_runs="deployment", max_attempts=1, poll_interval_s=0.2)
            runs = client.read_flow_runs(deployment_filter=only_ours)
        finally:
            stop.set()
            thread.join()
            client.delete_deployment(dep)   # later tests of this session find no deployment again

    # one run per model, HQ and LQ of the one sub-sequence, each keyed by its segment's cache key
    assert len(runs) == 2
    jobs = [SegmentJob(capture=ArtifactRef.model_validate(r.parameters["capture"]),
                       calibration=ArtifactRef.model_validate(r.parameters["calibration"]),
                       points=ArtifactRef.model_validate(r.parameters["points"]), frames=tuple(r.parameters["frames"]),
                       config=TrainConfig.model_validate(r.parameters["config"]), seed=r.parameters["seed"])
            for r in runs]
    assert {r.idempotency_key for r in runs} == {f"{task_cache_key(train_segment_task, store, **j.task_inputs())}"
                                                 "/attempt-0" for j in jobs}
    assert all(r.parameters["store"] == store and j.capture.digest == cap.digest and j.frames == (0, 2) for r, j in zip(runs, jobs))
    assert sorted(j.config.mcmc.cap_max for j in jobs)[1] == 500 * 2               # the HQ
    assert 100 * 2 <= sorted(j.config.mcmc.cap_max for j in jobs)[0] <= 250 * 2    # the LQ, from the range
    assert all(j.config.held_out_cameras for j in jobs)                              # the preset's held-out camera
