"""A small Prefect studio on loopback, for tests and benchmarks: a ``prefect server`` with a
temporary home (SQLite), the volcap pools, limits and deployments, and worker processes.

``Cluster(tmp, s3_env)`` holds the environment every process gets (the S3 server's credentials,
``PREFECT_API_URL``, ``VOLCAP_HOME`` = this checkout, one CPU thread); ``stop()`` kills every process
it started and their children (SIGKILL), whatever state they are in.
"""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def descendants(pid: int) -> list[int]:
    """Every process below ``pid`` (from /proc; children of children too)."""
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        ppid = int(stat.rsplit(")", 1)[1].split()[1])
        children.setdefault(ppid, []).append(int(entry.name))
    out, frontier = [], [pid]
    while frontier:
        nxt = [c for p in frontier for c in children.get(p, [])]
        out += nxt
        frontier = nxt
    return out


def kill_tree(proc: subprocess.Popen) -> None:
    for pid in [*descendants(proc.pid), proc.pid]:
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        pass


class Cluster:
    """The processes of a small studio; ``stop()`` kills them all."""

    def __init__(self, tmp: Path, s3_env: dict[str, str]):
        self.tmp = tmp
        self.port = free_port()
        self.env = {**os.environ, **s3_env,
                    "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}",
                    "PREFECT_HOME": str(tmp / "prefect-home"),
                    "PREFECT_API_URL": f"http://127.0.0.1:{self.port}/api",
                    "PREFECT_SERVER_ANALYTICS_ENABLED": "false", "DO_NOT_TRACK": "1",
                    "PREFECT_LOGGING_LEVEL": "INFO",
                    "PREFECT_WORKER_QUERY_SECONDS": "2", "PREFECT_WORKER_PREFETCH_SECONDS": "2",
                    "PREFECT_FLOWS_HEARTBEAT_FREQUENCY": "30",
                    "VOLCAP_HOME": str(REPO), "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
                    "OMP_WAIT_POLICY": "PASSIVE",
                    "PYTHONPATH": str(REPO)}
        self.env.pop("PREFECT_PROFILES_PATH", None)
        self.procs: dict[str, subprocess.Popen] = {}

    def log(self, name: str) -> Path:
        return self.tmp / f"{name}.log"

    def start(self, name: str, args: list[str]) -> subprocess.Popen:
        out = open(self.log(name), "wb")
        proc = subprocess.Popen(args, cwd=REPO, env=self.env, stdout=out, stderr=subprocess.STDOUT,
                                start_new_session=True)
        self.procs[name] = proc
        return proc

    def run(self, args: list[str], timeout: float = 120, check: bool = True) -> subprocess.CompletedProcess:
        res = subprocess.run(args, cwd=REPO, env=self.env, capture_output=True, text=True, timeout=timeout)
        if check and res.returncode != 0:
            raise AssertionError(f"{' '.join(args)} -> {res.returncode}\n{res.stdout[-3000:]}\n{res.stderr[-3000:]}")
        return res

    def start_server(self) -> None:
        self.start("server", [str(BIN / "prefect"), "server", "start", "--host", "127.0.0.1",
                              "--port", str(self.port)])
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{self.port}/api/health", timeout=2) as r:
                    if r.status == 200:
                        return
            except OSError:
                time.sleep(0.5)
            if self.procs["server"].poll() is not None:
                break
        raise AssertionError("prefect server did not start:\n" + self.log("server").read_text()[-3000:])

    def stop(self) -> None:
        for proc in self.procs.values():
            kill_tree(proc)

    def api(self, path: str, body: dict | None = None) -> object:
        req = urllib.request.Request(f"http://127.0.0.1:{self.port}/api/{path}",
                                     data=json.dumps(body or {}).encode(), method="POST",
                                     headers={"Content-Type": "application/json"})
        with urllib.request.urlopen(req, timeout=30) as r:
            return json.loads(r.read())

    def segment_runs(self) -> list[dict]:
        runs = self.api("flow_runs/filter", {"flow_runs": {"tags": {"all_": ["segment"]}}, "limit": 200})
        return list(runs)


def submissions(log: Path) -> list[str]:
    """Flow-run ids a worker's log says it started."""
    text = log.read_text(errors="replace") if log.exists() else ""
    return re.findall(r"[Ss]ubmitting flow run '([0-9a-f-]{36})'", text)


def set_up_studio(cluster: Cluster, gpus: int, zombie_within_s: float | None = None,
                  heartbeat_s: int | None = None) -> None:
    """Server, pools and ``gpu-slots`` (deploy/setup-pool.sh), the deployments (deploy/prefect.yaml),
    and the zombie automation (its window shortened to ``zombie_within_s`` when given). With
    ``heartbeat_s`` the deployments' flow runs send heartbeats that often instead of every 60 s
    (deployed from a copy of deploy/prefect.yaml; Prefect refuses fewer than 30 s), so a shorter
    zombie window still spans more than one heartbeat."""
    cluster.start_server()
    # (seven `prefect` commands, seconds each on a quiet machine, over 2 minutes at a load of 25)
    cluster.run(["bash", "deploy/setup-pool.sh", "--gpus", str(gpus)], timeout=600)
    if zombie_within_s is not None:
        automation = yaml.safe_load((REPO / "deploy/automations/crash-zombie-flows.yaml").read_text())
        automation["trigger"]["within"] = zombie_within_s
        automation["actions"][0]["message"] = f"No heartbeat for {zombie_within_s} s (test window)."
        short = cluster.tmp / "zombie.yaml"
        short.write_text(yaml.safe_dump({**automation, "name": "volcap test: crash zombie flow runs"}))
        cluster.run([str(BIN / "prefect"), "automation", "delete", "volcap: crash zombie flow runs"], check=False)
        cluster.run([str(BIN / "prefect"), "automation", "create", "--from-file", str(short)])
    prefect_file = "deploy/prefect.yaml"
    if heartbeat_s is not None:
        doc = yaml.safe_load((REPO / prefect_file).read_text())
        for deployment in doc["deployments"]:
            deployment["work_pool"]["job_variables"]["env"]["PREFECT_FLOWS_HEARTBEAT_FREQUENCY"] = str(heartbeat_s)
        prefect_file = str(cluster.tmp / "prefect.yaml")
        Path(prefect_file).write_text(yaml.safe_dump(doc, sort_keys=False))
    cluster.run([str(BIN / "prefect"), "--no-prompt", "deploy", "--all", "--prefect-file", prefect_file], timeout=600)


def start_gpu_workers(cluster: Cluster, names: list[str]) -> None:
    for name in names:
        cluster.start(name, [str(BIN / "volcap"), "worker", "--pool", "gpu", "--name", name, "--limit", "1"])
