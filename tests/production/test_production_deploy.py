"""deploy/: the files parse, match Prefect 3.8's schemas, request GPUs, and hold no secrets."""

import json
import re
import subprocess
from pathlib import Path

import pytest
import yaml

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"


def load_yaml(name):
    return yaml.safe_load((DEPLOY / name).read_text())


def test_prefect_yaml_matches_prefect_schema():
    from prefect.cli.deploy._models import DeploymentConfig, PrefectYamlModel, WorkPoolConfig

    raw = load_yaml("prefect.yaml")
    model = PrefectYamlModel.model_validate(raw)
    # the models ignore unknown keys: a typo would be dropped silently, so check the keys too
    top = set(PrefectYamlModel.model_fields) | {"prefect-version"}
    assert set(raw) <= top, set(raw) - top
    for dep in raw["deployments"]:
        assert set(dep) <= set(DeploymentConfig.model_fields), set(dep) - set(DeploymentConfig.model_fields)
        assert set(dep["work_pool"]) <= set(WorkPoolConfig.model_fields)
    assert model.prefect_version.startswith("3.8.")
    deps = {d.name: d for d in model.deployments}
    assert set(deps) == {"production", "train-segment"}
    assert deps["production"].entrypoint == "flows/production.py:production_flow"
    assert deps["train-segment"].entrypoint == "flows/production.py:train_segment_flow"
    assert deps["train-segment"].work_pool.name == "gpu"
    assert deps["production"].work_pool.name == "control"   # never holds a GPU slot while waiting
    assert model.pull == [{"prefect.deployments.steps.set_working_directory":
                           {"directory": "{{ $VOLCAP_HOME }}"}}]
    for d in model.deployments:
        assert d.work_pool.job_variables["env"]["PREFECT_FLOWS_HEARTBEAT_FREQUENCY"] == "60"


def test_compose_runs_a_pinned_server_on_postgres():
    compose = load_yaml("docker-compose.yml")
    services = compose["services"]
    assert set(services) == {"postgres", "prefect-server"}
    server = services["prefect-server"]
    url = server["environment"]["PREFECT_API_DATABASE_CONNECTION_URL"]
    assert url.startswith("postgresql+asyncpg://prefect:${POSTGRES_PASSWORD}@postgres:5432/")
    assert services["postgres"]["environment"]["POSTGRES_PASSWORD"].startswith("${POSTGRES_PASSWORD:?")
    assert server["depends_on"]["postgres"]["condition"] == "service_healthy"
    dockerfile = (DEPLOY / server["build"]["dockerfile"]).read_text()
    assert re.search(r'"prefect==3\.8\.\d+"', dockerfile) and '"fastapi<=0.150"' in dockerfile


def test_gpu_dockerfile():
    text = (DEPLOY / "Dockerfile.gpu").read_text()
    assert re.search(r"^ARG CUDA_IMAGE=nvidia/cuda:[\d.]+-cudnn-devel-", text, re.M)
    assert "--index-url \"${TORCH_INDEX}\"" in text and "download.pytorch.org/whl/cu" in text
    assert "gsplat==${GSPLAT_VERSION}" in text and "pip install -e ." in text
    assert text.index("torch==") < text.index("gsplat==") < text.index("pip install -e .")


def test_kubernetes_template_requests_one_gpu_per_run():
    from prefect.server.schemas.actions import validate_base_job_template
    from prefect.utilities.templating import apply_values

    template = json.loads((DEPLOY / "k8s" / "gpu-job-template.json").read_text())
    validate_base_job_template(template)                 # every placeholder is a declared variable
    props = template["variables"]["properties"]
    defaults = {k: v["default"] for k, v in props.items() if "default" in v}
    defaults["command"] = "prefect flow-run execute"
    job = apply_values(template["job_configuration"], defaults)
    manifest = job["job_manifest"]
    assert (manifest["apiVersion"], manifest["kind"]) == ("batch/v1", "Job")
    pod = manifest["spec"]["template"]["spec"]
    assert (pod["parallelism"], pod["completions"], pod["restartPolicy"]) == (1, 1, "Never")
    (container,) = pod["containers"]
    assert container["name"] == "prefect-job"           # what the Kubernetes worker requires
    assert container["resources"]["limits"]["nvidia.com/gpu"] == 1
    assert container["resources"]["requests"]["nvidia.com/gpu"] == 1
    assert container["envFrom"] == [{"secretRef": {"name": "volcap-store", "optional": False}}]
    assert container["image"] == "volcap-gpu:latest"
    assert manifest["spec"]["backoffLimit"] == 0        # Prefect retries, not Kubernetes


def test_zombie_automation_is_valid():
    from prefect.events.schemas.automations import AutomationCore

    automation = AutomationCore.model_validate(load_yaml("automations/crash-zombie-flows.yaml"))
    assert automation.actions[0].type == "change-flow-run-state"
    assert "prefect.flow-run.heartbeat" in automation.trigger.after


@pytest.mark.parametrize("script", ["setup-pool.sh", "worker.sh"])
def test_scripts_parse(script):
    subprocess.run(["bash", "-n", str(DEPLOY / script)], check=True)


def test_scripts_do_what_the_docs_say():
    setup = (DEPLOY / "setup-pool.sh").read_text()
    assert 'prefect gcl create gpu-slots --limit "$GPUS"' in setup
    assert 'prefect work-pool set-concurrency-limit gpu "$GPUS"' in setup
    assert "--base-job-template \"$HERE/k8s/gpu-job-template.json\"" in setup
    worker = (DEPLOY / "worker.sh").read_text()
    assert 'CUDA_VISIBLE_DEVICES="$gpu" "${WORKER[@]}" --pool gpu' in worker
    assert "volcap worker" in worker


def test_no_credentials_in_deploy_files():
    secret = re.compile(r"(SECRET|PASSWORD|TOKEN|API_KEY)[A-Z_]*\s*[:=]\s*['\"]?(?!\$\{)[^\s'\"$]{6,}")
    for path in DEPLOY.rglob("*"):
        if path.is_file():
            for line in path.read_text().splitlines():
                if line.lstrip().startswith("#"):
                    continue
                assert not secret.search(line), f"{path.name}: {line}"
