"""deploy/: every file checked by what consumes it, as far as a machine without a container engine
or a cluster can go.

- ``docker-compose.yml``: interpolated as Compose does, validated against the Compose
  Specification's JSON schema (shipped by check-jsonschema), its references resolved, its server
  matched with ``Dockerfile.server``.
- ``Dockerfile.gpu`` / ``Dockerfile.server``: parsed by BuildKit's own parser (the ``dockerfile``
  package); every variable declared where it is used, every COPY source present in the build context
  and not dropped by the .dockerignore, what ``pip install -e .`` needs copied before it, the pins
  equal to the project's (pyproject, Makefile), the torch index's CUDA equal to the base image's.
- ``k8s/gpu-job-template.json``: rendered by prefect-kubernetes' own job configuration (what the
  Kubernetes worker submits), with the ``train-segment`` deployment's job variables, and the Job
  validated against the Kubernetes JSON schema of its kind and apiVersion (kubernetes-validate,
  strict: unknown fields are errors) for the oldest and newest Kubernetes it ships.
- ``prefect.yaml``: loaded by ``prefect deploy``'s own loader, every entrypoint loaded as a flow, its
  parameters and job variables checked against the flow's parameter schema and the pools' variables,
  and the parameters the production flow sends to ``train-segment`` against that flow's schema.
- ``setup-pool.sh``, ``prefect deploy``, ``worker.sh``: run against a Prefect server on loopback
  (slow): pools, limits and automation as the script says; the server accepts the deployments and
  enforces their parameter schemas; worker.sh's workers register and poll, each with its GPU, and
  stop cleanly on SIGTERM or when one of them dies.

Each check is a function returning the problems it finds, run on the real file (no problem) and on
deliberately broken copies (the expected problem), so no check passes by finding nothing to check.
"""

from __future__ import annotations

import asyncio
import copy
import json
import os
import re
import shlex
import shutil
import signal
import socket
import subprocess
import time
import tomllib
import urllib.error
import urllib.request
import uuid
from datetime import datetime, timezone
from importlib import resources
from pathlib import Path, PurePosixPath

import dockerfile
import jsonschema
import pydantic
import pytest
import yaml
from packaging.requirements import InvalidRequirement, Requirement
from packaging.version import Version

REPO = Path(__file__).resolve().parents[2]
DEPLOY = REPO / "deploy"
PYPROJECT = tomllib.loads((REPO / "pyproject.toml").read_text())


def load_yaml(name: str):
    return yaml.safe_load((DEPLOY / name).read_text())


def _pyproject_requirement(name: str, extra: str | None = None) -> Requirement:
    reqs = PYPROJECT["project"]["optional-dependencies"][extra] if extra else PYPROJECT["project"]["dependencies"]
    (req,) = [Requirement(r) for r in reqs if Requirement(r).name.lower() == name]
    return req


def _pinned(req: Requirement) -> Version:
    (spec,) = req.specifier
    assert spec.operator == "==", f"{req} is not a pin"
    return Version(spec.version)


# =================================================================================================
# docker-compose.yml
# =================================================================================================

COMPOSE_SCHEMA = json.loads(
    (resources.files("check_jsonschema.builtin_schemas.vendor") / "compose-spec.json").read_text())
_COMPOSE_VAR = re.compile(r"\$\$|\$\{([A-Za-z_][A-Za-z0-9_]*)(?:(:?[-?])([^}]*))?\}|\$([A-Za-z_][A-Za-z0-9_]*)")


class InterpolationError(ValueError):
    pass


def compose_interpolate(value, env: dict[str, str]):
    """Compose's variable interpolation: ``$$``, ``$VAR``, ``${VAR}``, ``${VAR:-default}``,
    ``${VAR-default}``, ``${VAR:?error}``, ``${VAR?error}``; an unset plain variable is an error
    here (Compose warns and substitutes the empty string)."""
    if isinstance(value, dict):
        return {k: compose_interpolate(v, env) for k, v in value.items()}
    if isinstance(value, list):
        return [compose_interpolate(v, env) for v in value]
    if not isinstance(value, str):
        return value

    def sub(m: re.Match) -> str:
        if m.group(0) == "$$":
            return "$"
        name, op, arg = m.group(1) or m.group(4), m.group(2), m.group(3)
        val = env.get(name)
        missing = val is None or (op is not None and op.startswith(":") and val == "")
        if op in ("-", ":-"):
            return arg if missing else val
        if missing:
            raise InterpolationError(f"{name}: {arg}" if op in ("?", ":?") else f"{name} is not set")
        return val

    return _COMPOSE_VAR.sub(sub, value)


def _compose_schema_errors(doc) -> list[str]:
    cls = jsonschema.validators.validator_for(COMPOSE_SCHEMA)
    cls.check_schema(COMPOSE_SCHEMA)
    errors = [jsonschema.exceptions.best_match([e]) for e in cls(COMPOSE_SCHEMA).iter_errors(doc)]  # the
    # innermost reason of a oneOf / anyOf failure
    return [f"{'.'.join(map(str, e.absolute_path)) or '<root>'}: {e.message}" for e in errors]


def compose_problems(doc: dict, env: dict[str, str], folder: Path = DEPLOY) -> list[str]:
    """What ``docker compose config`` would refuse: interpolation, the Compose schema, then the
    references the schema cannot see (build context and Dockerfile, depends_on, named volumes)."""
    try:
        doc = compose_interpolate(doc, env)
    except InterpolationError as exc:
        return [f"interpolation: {exc}"]
    problems = _compose_schema_errors(doc)
    if problems:
        return problems
    services = doc.get("services", {})
    for name, svc in services.items():
        build = svc.get("build")
        if build is not None:
            build = {"context": build} if isinstance(build, str) else build
            context = folder / build.get("context", ".")
            if not context.is_dir():
                problems.append(f"{name}: build context {context} is not a folder")
            elif not (context / build.get("dockerfile", "Dockerfile")).is_file():
                problems.append(f"{name}: no Dockerfile {build.get('dockerfile', 'Dockerfile')} in {context}")
        deps = svc.get("depends_on", {})
        for dep, cond in (deps.items() if isinstance(deps, dict) else ((d, {}) for d in deps)):
            if dep not in services:
                problems.append(f"{name}: depends_on unknown service {dep!r}")
            elif cond.get("condition") == "service_healthy" and "healthcheck" not in services[dep]:
                problems.append(f"{name}: waits for {dep} to be healthy, but {dep} has no healthcheck")
        for vol in svc.get("volumes", []):
            source = vol.split(":", 1)[0] if isinstance(vol, str) else vol.get("source", "")
            named = source and not source.startswith((".", "/", "~", "$"))
            if named and source not in (doc.get("volumes") or {}):
                problems.append(f"{name}: volume {source!r} is not declared under volumes:")
    return problems


COMPOSE_ENV = {"POSTGRES_PASSWORD": "not-a-real-password"}


def test_compose_file_is_valid_compose():
    doc = load_yaml("docker-compose.yml")
    assert compose_problems(doc, COMPOSE_ENV) == []
    # the password has no default: without it Compose stops before starting anything
    assert compose_problems(doc, {}) == ["interpolation: POSTGRES_PASSWORD: set POSTGRES_PASSWORD in "
                                         "the environment or deploy/.env"]
    # PREFECT_UI_API_URL defaults to localhost and can be overridden
    server = compose_interpolate(doc, {**COMPOSE_ENV, "PREFECT_UI_API_URL": "http://h:4200/api"})
    assert server["services"]["prefect-server"]["environment"]["PREFECT_UI_API_URL"] == "http://h:4200/api"


def _break(doc: dict, path: str, value) -> dict:
    """A copy of ``doc`` with ``value`` at the dotted ``path`` (``None``: the key removed)."""
    doc = copy.deepcopy(doc)
    *parents, last = path.split(".")
    node = doc
    for key in parents:
        node = node[int(key)] if isinstance(node, list) else node[key]
    if value is None:
        del node[last]
    else:
        node[int(last) if isinstance(node, list) else last] = value
    return doc


@pytest.mark.parametrize("path, value, expected", [
    # wrong types and values the schema knows
    ("services.prefect-server.ports", "4200:4200", "is not of type 'array'"),
    ("services.prefect-server.depends_on.postgres.condition", "service_ready", "is not one of"),
    ("services.postgres.healthcheck.test", 5, "5 is not valid under any of the given schemas"),
    ("services.prefect-server.environment", ["PREFECT_LOGGING_LEVEL"], None),  # a list is valid too
    # a misspelt key is not silently ignored
    ("services.prefect-server.dependson", {"postgres": {"condition": "service_healthy"}}, "'dependson' was unexpected"),
    # references the schema cannot check
    ("services.prefect-server.build.dockerfile", "Dockerfile.serverr", "no Dockerfile Dockerfile.serverr"),
    ("services.postgres.healthcheck", None, "postgres has no healthcheck"),
    ("volumes", {"prefect-data": None}, "volume 'prefect-db' is not declared"),
])
def test_compose_checks_reject_broken_copies(path, value, expected):
    problems = compose_problems(_break(load_yaml("docker-compose.yml"), path, value), COMPOSE_ENV)
    if expected is None:
        assert problems == []
    else:
        assert any(expected in p for p in problems), problems


# =================================================================================================
# Dockerfiles
# =================================================================================================

INSTRUCTIONS = {"ADD", "ARG", "CMD", "COPY", "ENTRYPOINT", "ENV", "EXPOSE", "FROM", "HEALTHCHECK", "LABEL",
                "MAINTAINER", "ONBUILD", "RUN", "SHELL", "STOPSIGNAL", "USER", "VOLUME", "WORKDIR"}
#: variables a base image defines (the only ones used without an ARG / ENV of ours)
BASE_IMAGE_ENV = {"PATH", "HOME"}
_DF_VAR = re.compile(r"\$\{([A-Za-z_][A-Za-z0-9_]*)(?::[-+][^}]*)?\}|\$([A-Za-z_][A-Za-z0-9_]*)")


def dockerignore_excludes(ignore_text: str):
    """``path -> bool``: whether the .dockerignore drops ``path`` (relative to the context) from the
    build context: Docker's rules (``*``, ``?``, ``**``, ``!`` exceptions, the last match wins, a
    folder's exclusion covers its contents)."""
    rules = []
    for line in ignore_text.splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        negate = line.startswith("!")
        pattern = str(PurePosixPath("/" + line.lstrip("!").strip()))[1:]
        rx, i = "", 0
        while i < len(pattern):
            if pattern.startswith("**/", i):
                rx, i = rx + "(?:.*/)?", i + 3
            elif pattern.startswith("**", i):
                rx, i = rx + ".*", i + 2
            elif pattern[i] == "*":
                rx, i = rx + "[^/]*", i + 1
            elif pattern[i] == "?":
                rx, i = rx + "[^/]", i + 1
            else:
                rx, i = rx + re.escape(pattern[i]), i + 1
        rules.append((re.compile(rx + "(?:/.*)?"), negate))

    def excluded(path: str) -> bool:
        path = str(PurePosixPath("/" + path))[1:]
        out = False
        for rx, negate in rules:
            if rx.fullmatch(path):
                out = not negate
        return out

    return excluded


def pip_installs(run: str) -> list[list[str]]:
    """The arguments of every ``pip install`` in a RUN's shell command (split as a shell would:
    at ``&&``, ``||``, ``;``, ``|`` outside quotes)."""
    lexer = shlex.shlex(run, posix=True, punctuation_chars=True)
    lexer.whitespace_split = True
    commands: list[list[str]] = [[]]
    for token in lexer:
        if token in ("&&", "||", ";", "|", "&"):
            commands.append([])
        else:
            commands[-1].append(token)
    out = []
    for words in commands:
        while words and re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*=.*", words[0]):  # VAR=value prefixes
            words = words[1:]
        if words[:2] == ["pip", "install"] or words[1:3] == ["-m", "pip"] and words[3:4] == ["install"]:
            out.append(words[words.index("install") + 1:])
    return out


def _requirements(args: list[str]) -> list[Requirement]:
    reqs, skip = [], False
    for a in args:
        if skip:
            skip = False
        elif a in ("--index-url", "-i", "--extra-index-url", "--no-binary", "--only-binary", "-c", "-r"):
            skip = True
        elif not a.startswith("-") and a != ".":
            try:
                reqs.append(Requirement(a))
            except InvalidRequirement:
                pass        # e.g. an undeclared ${VAR} left in it: Image.problems names that
    return reqs


class Image:
    """A Dockerfile walked instruction by instruction, as BuildKit's parser reads it: variables in
    scope, the working directory, what each COPY puts where, the RUNs. ``problems`` collects what a
    build would get wrong."""

    def __init__(self, text: str, context: Path, ignore_text: str = ""):
        self.context = context
        self.excluded = dockerignore_excludes(ignore_text)
        self.problems: list[str] = []
        self.commands = dockerfile.parse_string(text)
        self.base = ""
        self.workdir = "/"
        self.env: dict[str, str] = {}
        self.copies: list[tuple[int, str, str]] = []    # (instruction index, destination, source)
        self.runs: list[tuple[int, str, str]] = []      # (index, working directory, shell command)
        self.cmd: tuple[str, tuple[str, ...]] | None = None   # (working directory, command)
        self.expose: list[int] = []
        global_args: dict[str, str | None] = {}
        args: dict[str, str | None] | None = None       # None before the first FROM
        for i, c in enumerate(self.commands):
            where = f"line {c.start_line} ({c.cmd})"
            if c.cmd not in INSTRUCTIONS:
                self.problems.append(f"{where}: unknown instruction")
                continue
            # FROM sees the ARGs declared before the first FROM; the rest, the stage's ARGs and ENVs
            scope, allowed = (global_args, set()) if c.cmd == "FROM" else ({**(args or {}), **self.env}, BASE_IMAGE_ENV)
            if c.cmd != "ARG":
                for v in c.value:
                    for m in _DF_VAR.finditer(v):
                        name = m.group(1) or m.group(2)
                        if name not in scope and name not in allowed:
                            self.problems.append(f"{where}: ${name} is not declared (ARG/ENV) before it is used")
            if c.cmd == "FROM":
                self.base = self.expand(c.value[0], global_args)
                args, self.env, self.workdir = {}, {}, "/"
            elif c.cmd == "ARG":
                for decl in c.value:
                    name, _, default = decl.partition("=")
                    value = default.strip('"') if "=" in decl else None
                    if args is None:
                        global_args[name] = value
                    else:
                        args[name] = value if value is not None else global_args.get(name)
            elif c.cmd == "ENV":
                for name, value in zip(c.value[::2], c.value[1::2]):
                    self.env[name] = self.expand(value, {**(args or {}), **self.env})
            elif c.cmd == "WORKDIR":
                self.workdir = str(PurePosixPath(self.workdir) / self.expand(c.value[0], {**(args or {}), **self.env}))
            elif c.cmd in ("COPY", "ADD"):
                if any(f.startswith("--from") for f in c.flags):
                    continue
                *sources, dest = c.value
                dest_abs = str(PurePosixPath(self.workdir) / dest)
                for src in sources:
                    if not (context / src).exists():
                        self.problems.append(f"{where}: {src} is not in the build context {context}")
                    elif self.excluded(src):
                        self.problems.append(f"{where}: {src} is excluded by the .dockerignore")
                    # a folder's contents go to dest; a file goes into dest/ (or several sources), else to dest
                    into = not (context / src).is_dir() and (dest.endswith("/") or len(sources) > 1)
                    self.copies.append((i, str(PurePosixPath(dest_abs) / PurePosixPath(src).name) if into
                                        else dest_abs, src))
            elif c.cmd == "RUN":
                self.runs.append((i, self.workdir, self.expand(" ".join(c.value), {**(args or {}), **self.env},
                                                               keep=True)))
            elif c.cmd == "CMD":
                self.cmd = (self.workdir, c.value)
            elif c.cmd == "EXPOSE":
                self.expose += [int(p.split("/")[0]) for p in c.value]

    @staticmethod
    def expand(text: str, values: dict, keep: bool = False) -> str:
        def sub(m):
            name = m.group(1) or m.group(2)
            return values[name] if values.get(name) is not None else (m.group(0) if keep else "")
        return _DF_VAR.sub(sub, text)

    def has(self, path: str, before: int) -> bool:
        """Whether the image holds ``path`` (absolute) once the instructions before ``before`` ran."""
        for i, dest, src in self.copies:
            if i >= before:
                continue
            if path == dest or path.startswith(dest.rstrip("/") + "/"):
                rel = PurePosixPath(path).relative_to(dest)
                source = str(PurePosixPath(src) / rel)
                if (self.context / source).exists() and not self.excluded(source):
                    return True
        return False

    def installs(self) -> list[tuple[int, str, list[str]]]:
        return [(i, wd, args) for i, wd, run in self.runs for args in pip_installs(run)]


def _project_packages() -> list[str]:
    patterns = PYPROJECT["tool"]["setuptools"]["packages"]["find"]["include"]
    return sorted(p.name for p in REPO.iterdir() if (p / "__init__.py").is_file()
                  and any(re.fullmatch(pat.replace(".", r"\.").replace("*", ".*"), p.name) for pat in patterns))


def gpu_image_problems(text: str, ignore_text: str) -> list[str]:
    """Dockerfile.gpu, built from the repository root with Dockerfile.gpu.dockerignore."""
    img = Image(text, REPO, ignore_text)
    problems = list(img.problems)
    # the base image compiles gsplat's CUDA extension: it needs nvcc (a -devel image)
    m = re.fullmatch(r"nvidia/cuda:(\d+)\.(\d+)\.\d+-(?:cudnn-)?devel-.+", img.base)
    if not m:
        return problems + [f"base image {img.base!r} is not an nvidia/cuda -devel image"]
    cuda_tag = f"cu{m[1]}{m[2]}"
    torch = gsplat = project = None
    for i, wd, args in img.installs():
        names = {r.name for r in _requirements(args)}
        if "torch" in names:
            torch = (i, args)
        if "gsplat" in names:
            gsplat = (i, args)
        if "-e" in args and "." in args:
            project = (i, wd)
    if not (torch and gsplat and project):
        return problems + [f"missing a pip install: torch {torch}, gsplat {gsplat}, the project {project}"]
    # torch: the version the CPU suite runs (Makefile), from the index of the base image's CUDA
    (torch_req,) = [r for r in _requirements(torch[1]) if r.name == "torch"]
    make_torch = Requirement(re.search(r"^TORCH\s*\?=\s*(\S+)", (REPO / "Makefile").read_text(), re.M)[1])
    if torch_req.specifier != make_torch.specifier:
        problems.append(f"torch {torch_req.specifier} in the image, {make_torch.specifier} in the Makefile")
    if not _requirement_allows(_pyproject_requirement("torch"), _pinned(torch_req)):
        problems.append(f"torch {torch_req.specifier} outside pyproject's {_pyproject_requirement('torch')}")
    index = torch[1][torch[1].index("--index-url") + 1] if "--index-url" in torch[1] else ""
    if not index.rstrip("/").endswith("/" + cuda_tag):
        problems.append(f"torch index {index!r} is not the {cuda_tag} build of the base image's CUDA")
    # gsplat: the version the tests check against (test extra), compiled from source
    (gsplat_req,) = [r for r in _requirements(gsplat[1]) if r.name == "gsplat"]
    if gsplat_req.specifier != _pyproject_requirement("gsplat", "test").specifier:
        problems.append(f"gsplat {gsplat_req.specifier} in the image, "
                        f"{_pyproject_requirement('gsplat', 'test').specifier} in pyproject's test extra")
    if not torch[0] < gsplat[0] < project[0]:
        problems.append("install order: torch (CUDA index), then gsplat against it, then the project")
    # pip install -e . needs the project's metadata, readme and packages copied before it runs
    i, wd = project
    for rel in ["pyproject.toml", PYPROJECT["project"]["readme"],
                *(f"{p}/__init__.py" for p in _project_packages())]:
        if not img.has(f"{wd}/{rel}", before=i):
            problems.append(f"pip install -e . in {wd} runs without {rel} (not copied before it)")
    # the default command's script is in the image, and VOLCAP_HOME is where the code is
    if img.cmd is None:
        problems.append("no CMD")
    else:
        wd, cmd = img.cmd
        scripts = [a for a in cmd if a.endswith(".sh")]
        for s in scripts:
            if not img.has(str(PurePosixPath(wd) / s), before=len(img.commands)):
                problems.append(f"CMD runs {s}, which is not in the image")
        if img.env.get("VOLCAP_HOME") != wd:
            problems.append(f"VOLCAP_HOME={img.env.get('VOLCAP_HOME')} but the code is in {wd}")
    return problems


def _requirement_allows(req: Requirement, version: Version) -> bool:
    return req.specifier.contains(version, prereleases=True)


def server_image_problems(text: str, compose: dict) -> list[str]:
    """Dockerfile.server against pyproject's pins and the compose service that runs it."""
    img = Image(text, DEPLOY)
    problems = list(img.problems)
    reqs = {r.name: r for _, _, args in img.installs() for r in _requirements(args)}
    prefect = reqs.get("prefect")
    if prefect is None:
        return problems + ["the image installs no prefect"]
    version = _pinned(prefect)
    if not _requirement_allows(_pyproject_requirement("prefect"), version):
        problems.append(f"prefect {version} outside pyproject's {_pyproject_requirement('prefect')}")
    if "fastapi" not in reqs or reqs["fastapi"].specifier != _pyproject_requirement("fastapi").specifier:
        problems.append(f"fastapi {reqs.get('fastapi')} differs from pyproject's {_pyproject_requirement('fastapi')}")
    if str(version) != str(load_yaml("prefect.yaml")["prefect-version"]):
        problems.append(f"prefect {version} in the server image, {load_yaml('prefect.yaml')['prefect-version']} "
                        "in prefect.yaml")
    svc = compose["services"]["prefect-server"]
    if not svc["image"].endswith(f":{version}"):
        problems.append(f"compose tags the server image {svc['image']}, it installs prefect {version}")
    driver = re.match(r"postgresql\+(\w+)://", svc["environment"]["PREFECT_API_DATABASE_CONNECTION_URL"])
    if driver and driver[1] not in reqs:
        problems.append(f"the database URL uses the {driver[1]} driver, which the image does not install")
    # one port everywhere: EXPOSE, the server's --port, the published port, the healthcheck
    command = svc.get("command") or list(img.cmd[1])
    port = int(command[command.index("--port") + 1])
    published = {int(str(p).rsplit(":", 1)[1]) for p in svc["ports"]}
    health = {int(p) for p in re.findall(r"127\.0\.0\.1:(\d+)/api/health", " ".join(svc["healthcheck"]["test"]))}
    if {port} != set(img.expose) or {port} != published or {port} != health:
        problems.append(f"ports: --port {port}, EXPOSE {img.expose}, published {published}, healthcheck {health}")
    return problems


def _read(name: str) -> str:
    return (DEPLOY / name).read_text()


def test_gpu_dockerfile():
    assert gpu_image_problems(_read("Dockerfile.gpu"), _read("Dockerfile.gpu.dockerignore")) == []


def test_server_dockerfile():
    assert server_image_problems(_read("Dockerfile.server"), load_yaml("docker-compose.yml")) == []


@pytest.mark.parametrize("old, new, expected", [
    ("COPY flows flows", "COPY flow flows", "flow is not in the build context"),
    ("COPY deploy deploy", "COPY deploy deploy\nCOPY tests tests", "tests is excluded by the .dockerignore"),
    ("COPY hardware hardware\n", "", "runs without hardware/__init__.py"),
    ("COPY pyproject.toml README.md ./", "COPY pyproject.toml ./", "runs without README.md"),
    ("COPY deploy deploy\n", "", "CMD runs deploy/worker.sh, which is not in the image"),
    ('"torch==${TORCH_VERSION}"', '"torch==${TORCH_VER}"', "$TORCH_VER is not declared"),
    ("ARG GSPLAT_VERSION=1.5.3", "ARG GSPLAT_VERSION=1.5.2", "gsplat ==1.5.2 in the image"),
    ("ARG TORCH_VERSION=2.13.0", "ARG TORCH_VERSION=2.12.0", "torch ==2.12.0 in the image"),
    ("whl/cu128", "whl/cu126", "is not the cu128 build"),
    ("cudnn-devel-ubuntu", "cudnn-runtime-ubuntu", "is not an nvidia/cuda -devel image"),
    ("VOLCAP_HOME=/opt/volcap", "VOLCAP_HOME=/srv/volcap", "VOLCAP_HOME=/srv/volcap but the code is in /opt/volcap"),
    ("WORKDIR /opt/volcap", "WORKDIRR /opt/volcap", "unknown instruction"),
])
def test_gpu_dockerfile_checks_reject_broken_copies(old, new, expected):
    text = _read("Dockerfile.gpu")
    assert old in text
    problems = gpu_image_problems(text.replace(old, new, 1), _read("Dockerfile.gpu.dockerignore"))
    assert any(expected in p for p in problems), problems


def test_gpu_dockerignore_rules():
    excluded = dockerignore_excludes(_read("Dockerfile.gpu.dockerignore"))
    for path in [".git/config", ".venv/bin/python", "flows/__pycache__/x.pyc", "deploy/.env", "tests/x.py",
                 "volcap.egg-info/PKG-INFO", "hardware/rigs/a.env"]:
        assert excluded(path), path
    for path in ["flows/production.py", "deploy/worker.sh", "hardware/rigs/demo_scene.json", "pyproject.toml"]:
        assert not excluded(path), path
    assert not dockerignore_excludes("tests\n!tests/keep.py")("tests/keep.py")


@pytest.mark.parametrize("old, new, expected", [
    ('"prefect==3.8.8"', '"prefect==3.9.0"', "outside pyproject's prefect"),
    ('"fastapi<=0.150"', '"fastapi"', "fastapi fastapi differs"),
    (' "asyncpg>=0.29"', "", "uses the asyncpg driver"),
    ("EXPOSE 4200", "EXPOSE 8080", "ports:"),
])
def test_server_dockerfile_checks_reject_broken_copies(old, new, expected):
    text = _read("Dockerfile.server")
    assert old in text
    problems = server_image_problems(text.replace(old, new), load_yaml("docker-compose.yml"))
    assert any(expected in p for p in problems), problems


# =================================================================================================
# k8s/gpu-job-template.json
# =================================================================================================

#: fields prefect-kubernetes requires in the pod spec of every Job it submits (its manifest check
#: refuses a template without them); Kubernetes does not know them there and drops them with a
#: warning. The only exception to the strict schema; test_pod_spec_fields_prefect_requires keeps
#: it honest.
PREFECT_POD_SPEC_FIELDS = {"parallelism": 1, "completions": 1}


class _NoClient:
    """from_template_and_values wants a Prefect client only to resolve block and variable
    references, which the template has none of: any use of this one fails the test."""


def render_gpu_job(template: dict, job_variables: dict) -> dict:
    """The Job the Kubernetes worker submits for a flow run: prefect-kubernetes' job
    configuration from the pool's template and the deployment's job variables, prepared for a run."""
    from prefect.client.schemas.objects import FlowRun
    from prefect_kubernetes.worker import KubernetesWorkerJobConfiguration

    config = asyncio.run(KubernetesWorkerJobConfiguration.from_template_and_values(
        copy.deepcopy(template), copy.deepcopy(job_variables), client=_NoClient()))
    config.prepare_for_flow_run(FlowRun(id=uuid.uuid4(), name="brave-otter", flow_id=uuid.uuid4()),
                                worker_name="k8s-worker")
    return config.job_manifest


def job_schema_problems(manifest: dict, kubernetes_version: str) -> list[str]:
    """Validate against the strict JSON schema of the manifest's kind and apiVersion."""
    import kubernetes_validate

    manifest = copy.deepcopy(manifest)
    pod = manifest.get("spec", {}).get("template", {}).get("spec", {})
    for key, value in PREFECT_POD_SPEC_FIELDS.items():
        if pod.get(key) == value:
            del pod[key]
    try:
        kubernetes_validate.validate(manifest, kubernetes_version, strict=True)
    except kubernetes_validate.ValidationError as exc:
        return [f"{'.'.join(map(str, exc.path))}: {exc.message} (Kubernetes {exc.version})"]
    return []


def _kubernetes_versions() -> list[str]:
    from kubernetes_validate.utils import all_versions

    versions = all_versions()
    return [versions[0], versions[-1]]


def _gpu_template() -> dict:
    return json.loads((DEPLOY / "k8s" / "gpu-job-template.json").read_text())


def _train_segment_job_variables() -> dict:
    configs, _, _ = load_prefect_yaml(DEPLOY / "prefect.yaml")
    (dep,) = [d for d in configs if d["name"] == "train-segment"]
    return dep["work_pool"]["job_variables"]


@pytest.mark.parametrize("kubernetes_version", _kubernetes_versions())
def test_kubernetes_job_is_a_valid_job(kubernetes_version):
    manifest = render_gpu_job(_gpu_template(), _train_segment_job_variables())
    assert (manifest["apiVersion"], manifest["kind"]) == ("batch/v1", "Job")
    assert job_schema_problems(manifest, kubernetes_version) == []


def test_kubernetes_job_runs_one_segment_on_one_gpu():
    from prefect.server.schemas.actions import validate_base_job_template

    template = _gpu_template()
    validate_base_job_template(template)                 # the server's rule: every placeholder declared
    manifest = render_gpu_job(template, _train_segment_job_variables())
    pod = manifest["spec"]["template"]["spec"]
    (container,) = pod["containers"]
    assert container["name"] == "prefect-job"
    assert container["args"] == ["prefect", "flow-run", "execute"]
    assert container["resources"]["limits"]["nvidia.com/gpu"] == 1
    assert container["resources"]["requests"]["nvidia.com/gpu"] == 1
    assert {"key": "nvidia.com/gpu", "operator": "Exists", "effect": "NoSchedule"} in pod["tolerations"]
    assert container["envFrom"] == [{"secretRef": {"name": "volcap-store", "optional": False}}]
    assert container["image"] == "volcap-gpu:latest"
    env = {e["name"]: e["value"] for e in container["env"]}
    # the pull step cds to VOLCAP_HOME: where Dockerfile.gpu puts the code
    gpu_image = Image(_read("Dockerfile.gpu"), REPO, _read("Dockerfile.gpu.dockerignore"))
    assert env["VOLCAP_HOME"] == gpu_image.workdir == gpu_image.env["VOLCAP_HOME"]
    assert env["PREFECT_FLOWS_HEARTBEAT_FREQUENCY"] == "60"
    # backoffLimit 0: Kubernetes never retries; an evicted pod's run is rescheduled by Prefect
    assert manifest["spec"]["backoffLimit"] == 0
    assert env["PREFECT_FLOW_RUN_EXECUTE_SIGTERM_BEHAVIOR"] == "reschedule"
    assert manifest["spec"]["ttlSecondsAfterFinished"] == 86400
    assert manifest["metadata"]["namespace"] == "volcap"
    mounts = {m["name"]: m["mountPath"] for m in container["volumeMounts"]}
    assert mounts == {"dshm": "/dev/shm"} and pod["volumes"][0]["emptyDir"]["medium"] == "Memory"
    # every pod label of the template survives the worker's own labels
    template_labels = template["job_configuration"]["job_manifest"]["spec"]["template"]["metadata"]["labels"]
    assert template_labels.items() <= manifest["spec"]["template"]["metadata"]["labels"].items()
    # job variables reach the Job
    two = render_gpu_job(template, {"gpus": 2, "image": "registry.studio/volcap-gpu:abc123", "namespace": "render"})
    (c2,) = two["spec"]["template"]["spec"]["containers"]
    assert c2["resources"]["limits"]["nvidia.com/gpu"] == 2 and c2["image"] == "registry.studio/volcap-gpu:abc123"
    assert two["metadata"]["namespace"] == "render"


def _template_with(path: str, value) -> dict:
    template = _gpu_template()
    return {**template, "job_configuration": {**template["job_configuration"], "job_manifest": _break(
        template["job_configuration"]["job_manifest"], path, value)}}


@pytest.mark.parametrize("template, expected", [
    # a misspelt field (strict: unknown fields are errors, Kubernetes would drop it)
    (lambda t: _template_with("spec.template.spec.toleration", [{"key": "nvidia.com/gpu", "operator": "Exists"}]),
     "'toleration' was unexpected"),
    # a wrong type: resources.limits as a list
    (lambda t: _template_with("spec.template.spec.containers.0.resources.limits", [{"nvidia.com/gpu": 1}]),
     "is not of type 'object'"),
    # a variable of the wrong type: the Job's TTL as words
    (lambda t: _break(t, "variables.properties.finished_job_ttl.default", "one day"), "is not of type 'integer'"),
])
def test_kubernetes_checks_reject_broken_copies(template, expected):
    for version in _kubernetes_versions():
        problems = job_schema_problems(render_gpu_job(template(_gpu_template()), {}), version)
        assert any(expected in p for p in problems), problems


def test_pod_spec_fields_prefect_requires():
    """The one allowance of the strict check is still needed: prefect-kubernetes refuses a template
    without these fields (if it ever stops, remove them from the template and the allowance)."""
    template = _gpu_template()
    pod = template["job_configuration"]["job_manifest"]["spec"]["template"]["spec"]
    assert {k: pod[k] for k in PREFECT_POD_SPEC_FIELDS} == PREFECT_POD_SPEC_FIELDS
    for key in PREFECT_POD_SPEC_FIELDS:
        del pod[key]
    with pytest.raises(ValueError, match="missing required attributes"):
        render_gpu_job(template, {})


# =================================================================================================
# prefect.yaml
# =================================================================================================


def load_prefect_yaml(path: Path) -> tuple[list[dict], dict, str]:
    """``prefect deploy``'s loader: the deployment configs, the build/push/pull actions, and what it
    printed (it prints and skips the whole file when the file does not validate)."""
    from prefect.cli.deploy._config import _load_deploy_configs_and_actions
    from rich.console import Console

    console = Console(record=True, width=200)
    configs, actions = _load_deploy_configs_and_actions(path, console=console)
    return configs, actions, console.export_text()


@pytest.fixture(scope="module")
def flows_of_entrypoints():
    """Entrypoint -> flow, loaded as ``prefect deploy`` loads them (from the repository root)."""
    from prefect.flows import load_flow_from_entrypoint

    cache: dict[str, object] = {}

    def load(entrypoint: str):
        if entrypoint not in cache:
            cwd = os.getcwd()
            os.chdir(REPO)
            try:
                cache[entrypoint] = load_flow_from_entrypoint(entrypoint)
            except Exception as exc:  # noqa: BLE001 - a problem to report, not a crash
                cache[entrypoint] = exc
            finally:
                os.chdir(cwd)
        return cache[entrypoint]

    return load


def _pool_variables(pool: str) -> list[dict]:
    """The job-variable schemas a deployment of ``pool`` may meet: `control` is a process pool,
    `gpu` a process or a kubernetes pool (deploy/setup-pool.sh --type)."""
    from prefect.workers.process import ProcessWorker

    process = ProcessWorker.get_default_base_job_template()["variables"]
    return [process] if pool == "control" else [process, _gpu_template()["variables"]]


def prefect_yaml_problems(path: Path, load_flow) -> list[str]:
    """What ``prefect deploy --all`` or the server would refuse, or silently drop."""
    from prefect.cli.deploy._config import _merge_with_default_deploy_config, _pick_deploy_configs
    from prefect.cli.deploy._models import DeploymentConfig, PrefectYamlModel, WorkPoolConfig
    from prefect.utilities.callables import parameter_schema
    from prefect.utilities.schema_tools import validate
    from rich.console import Console

    configs, actions, printed = load_prefect_yaml(path)
    if printed.strip():
        return [f"prefect deploy's loader: {printed.strip()}"]
    problems = []
    # the models ignore unknown keys: a misspelt key would vanish without a word
    raw = yaml.safe_load(path.read_text())
    top = {f.alias or n for n, f in PrefectYamlModel.model_fields.items()} | set(PrefectYamlModel.model_fields)
    problems += [f"unknown top-level key {k!r}" for k in set(raw) - top]
    for dep in raw.get("deployments", []):
        problems += [f"{dep.get('name')}: unknown key {k!r}" for k in set(dep) - set(DeploymentConfig.model_fields)]
        problems += [f"{dep.get('name')}: unknown work_pool key {k!r}"
                     for k in set(dep.get("work_pool") or {}) - set(WorkPoolConfig.model_fields)]
    picked = _pick_deploy_configs(configs, [], True, console=Console(), is_interactive=lambda: False)
    if [c["name"] for c in picked] != [c["name"] for c in configs] or not configs:
        problems.append(f"--all picks {[c.get('name') for c in picked]} of {[c.get('name') for c in configs]}")
    if actions["pull"] != [{"prefect.deployments.steps.set_working_directory": {"directory": "{{ $VOLCAP_HOME }}"}}]:
        problems.append(f"pull steps {actions['pull']}: workers must cd to their VOLCAP_HOME")
    for config in picked:
        config = _merge_with_default_deploy_config(config)
        name = config["name"]
        flow = load_flow(config["entrypoint"])
        if isinstance(flow, Exception):
            problems.append(f"{name}: entrypoint {config['entrypoint']}: {type(flow).__name__}: {flow}")
            continue
        schema = parameter_schema(flow).model_dump_for_openapi()
        params = config["parameters"]
        problems += [f"{name}: parameter {k!r} is not a parameter of {flow.name}"
                     for k in set(params) - set(schema["properties"])]
        problems += [f"{name}: parameters: {e.message}"
                     for e in validate(params, schema, raise_on_error=False, ignore_required=True)]
        job_variables = config["work_pool"]["job_variables"]
        for variables in _pool_variables(config["work_pool"]["name"]):
            problems += [f"{name}: job variable {k!r} is not a variable of the pool's template"
                         for k in set(job_variables) - set(variables["properties"])]
            problems += [f"{name}: job variables: {e.message}"
                         for e in validate(job_variables, variables, raise_on_error=False, ignore_required=True)]
    return problems


def test_prefect_yaml_loads_through_prefect_deploy(flows_of_entrypoints):
    assert prefect_yaml_problems(DEPLOY / "prefect.yaml", flows_of_entrypoints) == []
    configs, _, _ = load_prefect_yaml(DEPLOY / "prefect.yaml")
    deps = {d["name"]: d for d in configs}
    assert set(deps) == {"production", "train-segment"}
    assert deps["train-segment"]["work_pool"]["name"] == "gpu"
    assert deps["production"]["work_pool"]["name"] == "control"    # never holds a GPU slot while waiting
    assert all(d["enforce_parameter_schema"] for d in configs)
    assert all(d["work_pool"]["job_variables"]["env"]["PREFECT_FLOWS_HEARTBEAT_FREQUENCY"] == "60" for d in configs)


def test_segment_runs_match_the_train_segment_deployment(flows_of_entrypoints):
    """What the production flow sends to ``train-segment`` is what that deployment's flow takes:
    the name it calls it by, and parameters valid against its schema (checked as the server does
    for enforce_parameter_schema)."""
    from prefect.utilities.callables import parameter_schema
    from prefect.utilities.schema_tools import validate

    from flows.segment_runs import SEGMENT_DEPLOYMENT, SegmentJob
    from volcap_core.records import ArtifactRef
    from volcap_core.splat.train import TrainConfig

    configs, _, _ = load_prefect_yaml(DEPLOY / "prefect.yaml")
    deps = {d["name"]: d for d in configs}
    flow = flows_of_entrypoints(deps["train-segment"]["entrypoint"])
    assert f"{flow.name}/train-segment" == SEGMENT_DEPLOYMENT
    ref = ArtifactRef(digest="blake3:" + "0" * 64, size=1)
    params = SegmentJob(capture=ref, calibration=ref, points=ref, frames=(0, 3), config=TrainConfig()
                        ).deployment_parameters("s3://studio/store")
    schema = parameter_schema(flow).model_dump_for_openapi()
    assert validate(params, schema, raise_on_error=False) == []
    assert validate({**params, "frames": "0-3"}, schema, raise_on_error=False)      # the check can fail
    production = flows_of_entrypoints(deps["production"]["entrypoint"])
    assert validate({"spec": "/shared/productions/ep3.yaml"},  # docs/operations.md, 6.
                    parameter_schema(production).model_dump_for_openapi(), raise_on_error=False) == []


@pytest.mark.parametrize("edit, expected", [
    (lambda d: d["deployments"][1].update(entrypoint="flows/production.py:no_such_flow"), "entrypoint"),
    (lambda d: d["deployments"][0].update(entrypoint="flows/no_such_file.py:production_flow"), "entrypoint"),
    (lambda d: d["deployments"][0].update(parameters={"spec_path": "x.yaml"}), "'spec_path' is not a parameter"),
    (lambda d: d["deployments"][1].update(parameters={"seed": "zero"}), "is not of type 'integer'"),
    (lambda d: d["deployments"][1]["work_pool"].update(job_variables=["env"]), "prefect deploy's loader"),
    (lambda d: d["deployments"][1]["work_pool"]["job_variables"].update(envv={}), "'envv' is not a variable"),
    (lambda d: d["deployments"][1]["work_pool"]["job_variables"].update(env=["A=1"]), "is not of type 'object'"),
    (lambda d: d["deployments"][0].update(entry_point="flows/production.py:production_flow"), "unknown key"),
    (lambda d: d.update(pull=None), "pull steps"),
])
def test_prefect_yaml_checks_reject_broken_copies(edit, expected, tmp_path, flows_of_entrypoints):
    doc = load_yaml("prefect.yaml")
    edit(doc)
    broken = tmp_path / "prefect.yaml"
    broken.write_text(yaml.safe_dump(doc))
    problems = prefect_yaml_problems(broken, flows_of_entrypoints)
    assert any(expected in p for p in problems), problems


# =================================================================================================
# the automation, secrets
# =================================================================================================


def test_zombie_automation_is_valid():
    from prefect.events.schemas.automations import AutomationCore

    raw = load_yaml("automations/crash-zombie-flows.yaml")
    automation = AutomationCore.model_validate(raw)
    assert set(raw) <= set(AutomationCore.model_fields)
    assert automation.actions[0].type == "change-flow-run-state"
    assert "prefect.flow-run.heartbeat" in automation.trigger.after
    with pytest.raises(pydantic.ValidationError, match="state"):
        AutomationCore.model_validate(_break(raw, "actions.0.state", "EXPLODED"))


def test_no_credentials_in_deploy_files():
    secret = re.compile(r"(SECRET|PASSWORD|TOKEN|API_KEY)[A-Z_]*\s*[:=]\s*['\"]?(?!\$\{)[^\s'\"$]{6,}")
    for path in DEPLOY.rglob("*"):
        if path.is_file():
            for line in path.read_text().splitlines():
                if line.lstrip().startswith("#"):
                    continue
                assert not secret.search(line), f"{path.name}: {line}"


# =================================================================================================
# the scripts: their refusals (no server)
# =================================================================================================


BASH = shutil.which("bash")


def _script(args: list[str], env: dict[str, str]) -> subprocess.CompletedProcess:
    base = {k: v for k, v in os.environ.items() if k not in ("PREFECT_API_URL", "VOLCAP_HOME")}
    return subprocess.run([BASH, *args], cwd=REPO, env={**base, **env}, capture_output=True, text=True,
                          timeout=30)


@pytest.mark.parametrize("args, env, code, message", [
    (["deploy/setup-pool.sh", "--gpus", "0"], {}, 2, "--gpus must be a positive integer"),
    (["deploy/setup-pool.sh", "--gpus", "2", "--type", "docker"], {}, 2, "--type is process or kubernetes"),
    (["deploy/setup-pool.sh", "--gpus", "2"], {}, 1, "set PREFECT_API_URL"),
    (["deploy/setup-pool.sh", "--pools"], {}, 2, "unknown argument: --pools"),
    (["deploy/worker.sh", "--gpus", "0"], {"VOLCAP_HOME": "/x"}, 1, "set PREFECT_API_URL"),
    (["deploy/worker.sh", "--gpus", "0"], {"PREFECT_API_URL": "http://h/api"}, 1, "set VOLCAP_HOME"),
    (["deploy/worker.sh", "--gpus", "0;1"], {"PREFECT_API_URL": "http://h/api", "VOLCAP_HOME": "/x"}, 2,
     "--gpus is a comma-separated list"),
    (["deploy/worker.sh", "--gpu", "0"], {}, 2, "unknown argument: --gpu"),
])
def test_scripts_refuse_bad_invocations(args, env, code, message):
    res = _script(args, env)
    assert (res.returncode, message in res.stderr) == (code, True), res.stderr


def test_worker_sh_without_gpus_or_nvidia_smi(tmp_path):
    res = _script(["deploy/worker.sh"], {"PREFECT_API_URL": "http://h/api", "VOLCAP_HOME": str(tmp_path),
                                         "PATH": str(tmp_path)})      # no nvidia-smi on this PATH
    assert res.returncode == 2 and "give --gpus" in res.stderr, res.stderr
    assert "deploy/worker.sh --gpus 0,1" in _script(["deploy/worker.sh", "--help"], {}).stdout


def test_workers_and_deployments_run_one_openmp_thread_per_process(tmp_path):
    """CPU runs are one OpenMP thread per process (flows/runtime.py reproducible_cpu_defaults), set
    before a flow run imports torch: by worker.sh for whatever worker command it starts (a choice
    already made wins), and by each deployment's job environment (process and Kubernetes pools)."""
    fake = tmp_path / "fake-worker"
    fake.write_text('#!/usr/bin/env bash\necho "$OMP_NUM_THREADS $MKL_NUM_THREADS" > "$VOLCAP_HOME/threads"\n')
    fake.chmod(0o755)
    base = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "MKL_NUM_THREADS")}
    for chosen, threads in (({}, ["1", "1"]), ({"OMP_NUM_THREADS": "4"}, ["4", "1"])):
        env = {**base, **chosen, "PREFECT_API_URL": "http://h/api", "VOLCAP_HOME": str(tmp_path),
               "VOLCAP_WORKER_CMD": str(fake)}
        res = subprocess.run([BASH, "deploy/worker.sh", "--gpus", "0"], cwd=REPO, env=env, capture_output=True,
                             text=True, timeout=30)
        assert res.returncode == 0, res.stderr
        assert (tmp_path / "threads").read_text().split() == threads
    for deployment in load_yaml("prefect.yaml")["deployments"]:
        env = deployment["work_pool"]["job_variables"]["env"]
        assert (env["OMP_NUM_THREADS"], env["MKL_NUM_THREADS"]) == ("1", "1"), deployment["name"]


# =================================================================================================
# against a Prefect server (slow: a server, several `prefect` commands, worker processes)
# =================================================================================================


@pytest.fixture(scope="module")
def studio(tmp_path_factory):
    from tests.prefect_cluster import Cluster

    cluster = Cluster(tmp_path_factory.mktemp("studio"), {})
    try:
        cluster.start_server()
        yield cluster
    finally:
        cluster.stop()


def http(cluster, method: str, path: str, body: dict | None = None):
    """(status, JSON) of one call to the test server's API."""
    req = urllib.request.Request(f"http://127.0.0.1:{cluster.port}/api/{path}", method=method,
                                 data=None if body is None else json.dumps(body).encode(),
                                 headers={"Content-Type": "application/json"})
    try:
        with urllib.request.urlopen(req, timeout=30) as r:
            text = r.read()
            return r.status, (json.loads(text) if text else None)
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read().decode(errors="replace")


def _ok(cluster, method, path, body=None):
    status, out = http(cluster, method, path, body)
    assert 200 <= status < 300, (method, path, status, out)
    return out


def _check_studio(cluster, gpu_type: str, gpus: int) -> None:
    """What deploy/setup-pool.sh --gpus GPUS --type GPU_TYPE says it makes."""
    control, gpu = _ok(cluster, "GET", "work_pools/control"), _ok(cluster, "GET", "work_pools/gpu")
    assert control["type"] == "process"
    assert (gpu["type"], gpu["concurrency_limit"]) == (gpu_type, gpus)
    if gpu_type == "kubernetes":
        assert gpu["base_job_template"] == _gpu_template()
    assert _ok(cluster, "GET", "v2/concurrency_limits/gpu-slots")["limit"] == gpus
    names = [a["name"] for a in _ok(cluster, "POST", "automations/filter", {})]
    assert names.count("volcap: crash zombie flow runs") == 1


@pytest.fixture
def process_pools(studio):
    """The studio with process pools (deploy/setup-pool.sh --gpus 2), made when missing."""
    status, gpu = http(studio, "GET", "work_pools/gpu")
    if status != 200 or gpu["type"] != "process":
        http(studio, "DELETE", "work_pools/gpu")
        studio.run(["bash", "deploy/setup-pool.sh", "--gpus", "2"])
    return studio


@pytest.mark.slow
def test_setup_pool_makes_what_it_says(studio):
    """Kubernetes pool, then the refusal to change a pool's type, then process pools (the limit
    updated, the automation kept)."""
    http(studio, "DELETE", "work_pools/gpu")
    studio.run(["bash", "deploy/setup-pool.sh", "--gpus", "3", "--type", "kubernetes"])
    _check_studio(studio, "kubernetes", 3)
    refused = studio.run(["bash", "deploy/setup-pool.sh", "--gpus", "2"], check=False)
    assert refused.returncode == 1 and "cannot change type" in refused.stderr, refused.stderr
    _check_studio(studio, "kubernetes", 3)
    _ok(studio, "DELETE", "work_pools/gpu")
    out = studio.run(["bash", "deploy/setup-pool.sh", "--gpus", "2"]).stdout
    assert "exists" in out                                   # the automation is not made twice
    _check_studio(studio, "process", 2)


@pytest.mark.slow
def test_prefect_deploy_registers_deployments_that_enforce_their_schemas(process_pools):
    from tests.prefect_cluster import BIN

    from flows.segment_runs import SEGMENT_DEPLOYMENT, SegmentJob
    from volcap_core.records import ArtifactRef
    from volcap_core.splat.train import TrainConfig

    studio = process_pools
    deploy = [str(BIN / "prefect"), "--no-prompt", "deploy", "--all", "--prefect-file", "deploy/prefect.yaml"]
    # `prefect deploy` fills in {{ $VOLCAP_HOME }} when it is set where it runs: the deploying
    # machine's checkout would be every worker's (why the docs deploy with it unset)
    studio.run(deploy)
    pull = _ok(studio, "GET", "deployments/name/production-flow/production")["pull_steps"]
    assert pull == [{"prefect.deployments.steps.set_working_directory": {"directory": studio.env["VOLCAP_HOME"]}}]
    # as the docs say: `env -u VOLCAP_HOME prefect deploy ...`, each worker resolves its own
    res = subprocess.run(deploy, cwd=REPO, env={k: v for k, v in studio.env.items() if k != "VOLCAP_HOME"},
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    production = _ok(studio, "GET", "deployments/name/production-flow/production")
    segment = _ok(studio, "GET", f"deployments/name/{SEGMENT_DEPLOYMENT}")
    assert production["pull_steps"] == segment["pull_steps"] == load_yaml("prefect.yaml")["pull"]
    assert (production["work_pool_name"], segment["work_pool_name"]) == ("control", "gpu")
    assert production["global_concurrency_limit"]["limit"] == 4        # concurrency_limit: 4
    assert segment["global_concurrency_limit"] is None
    assert segment["enforce_parameter_schema"] and production["enforce_parameter_schema"]

    ref = ArtifactRef(digest="blake3:" + "0" * 64, size=1)
    params = SegmentJob(capture=ref, calibration=ref, points=ref, frames=(0, 3), config=TrainConfig()
                        ).deployment_parameters("s3://studio/store")
    later = {"type": "SCHEDULED", "state_details": {"scheduled_time": "2099-01-01T00:00:00Z"}}  # no worker takes it
    run = _ok(studio, "POST", f"deployments/{segment['id']}/create_flow_run", {"parameters": params, "state": later})
    _ok(studio, "DELETE", f"flow_runs/{run['id']}")
    for bad in ({**params, "frames": "0-3"}, {k: v for k, v in params.items() if k != "store"}):
        status, detail = http(studio, "POST", f"deployments/{segment['id']}/create_flow_run",
                              {"parameters": bad, "state": later})
        assert status == 409 and "Validation failed" in detail, (status, detail)


def _worker_processes(root_pid: int) -> dict[str, dict]:
    """Worker name -> its process's pid, arguments and environment (from /proc)."""
    from tests.prefect_cluster import descendants

    out = {}
    for pid in descendants(root_pid):
        try:
            argv = Path(f"/proc/{pid}/cmdline").read_bytes().decode().split("\0")[:-1]
            environ = Path(f"/proc/{pid}/environ").read_bytes().decode().split("\0")
            env = dict(e.split("=", 1) for e in environ if "=" in e)
        except OSError:
            continue
        if argv[1:5] == ["-m", "prefect", "worker", "start"]:
            opts = {argv[i]: argv[i + 1] for i in range(5, len(argv) - 1) if argv[i].startswith("--")}
            out[opts["--name"]] = {"pid": pid, "opts": opts, "env": env}
    return out


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def _start_worker_sh(studio, args: list[str], logs: Path) -> subprocess.Popen:
    """worker.sh started with SIGINT *ignored*, as a background job of a non-interactive shell or a
    CI runner may start it (bash cannot un-ignore a signal ignored at its start): its workers must
    still stop gracefully (``volcap worker`` resets SIGINT before it becomes the Prefect worker).
    Before that reset the tests passed alone and failed in the suite, after some earlier test of
    the same process had left SIGINT ignored: the workers never stopped."""
    env = {**studio.env, "VOLCAP_WORKER_LOGS": str(logs)}
    env.pop("PREFECT_FLOWS_HEARTBEAT_FREQUENCY")           # worker.sh's default applies
    return subprocess.Popen(["bash", "deploy/worker.sh", *args], cwd=REPO, env=env, start_new_session=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))


def _wait_for_workers(studio, proc, pools: dict[str, str], since: datetime, timeout: float = 150) -> dict:
    """Until every worker named in ``pools`` (name -> pool) has sent a heartbeat since ``since`` and
    every pool's default queue was polled since then."""
    deadline = time.monotonic() + timeout
    seen: dict[str, dict] = {}
    while time.monotonic() < deadline:
        assert proc.poll() is None, f"worker.sh exited {proc.returncode}: {proc.communicate()}"
        seen = {w["name"]: w for pool in set(pools.values())
                for w in _ok(studio, "POST", f"work_pools/{pool}/workers/filter", {})}
        beat = all(n in seen and seen[n]["status"] == "ONLINE"
                   and datetime.fromisoformat(seen[n]["last_heartbeat_time"]) >= since for n in pools)
        polled = all((q := _ok(studio, "GET", f"work_pools/{pool}/queues/default"))["last_polled"]
                     and datetime.fromisoformat(q["last_polled"]) >= since for pool in set(pools.values()))
        if beat and polled:
            return seen
        time.sleep(1)
    raise AssertionError(f"workers {pools} did not all register and poll; seen {list(seen)}")


@pytest.mark.slow
def test_worker_sh_starts_one_worker_per_gpu_and_stops_them_when_one_dies(process_pools, tmp_path):
    studio, host = process_pools, socket.gethostname().split(".")[0]
    assert subprocess.run(["hostname", "-s"], capture_output=True, text=True).stdout.strip() == host
    names = {f"{host}-gpu0": "gpu", f"{host}-gpu1": "gpu", f"{host}-control": "control"}
    since = datetime.now(timezone.utc)
    proc = _start_worker_sh(studio, ["--gpus", "0,1", "--control"], tmp_path)
    try:
        _wait_for_workers(studio, proc, names, since)
        workers = _worker_processes(proc.pid)
        assert set(workers) == set(names)
        for gpu in ("0", "1"):
            w = workers[f"{host}-gpu{gpu}"]
            assert (w["opts"]["--pool"], w["opts"]["--limit"], w["env"]["CUDA_VISIBLE_DEVICES"]) == ("gpu", "1", gpu)
        control = workers[f"{host}-control"]
        assert control["opts"]["--pool"] == "control" and "--limit" not in control["opts"]
        assert control["env"]["CUDA_VISIBLE_DEVICES"] == ""
        for w in workers.values():
            assert w["env"]["PREFECT_FLOWS_HEARTBEAT_FREQUENCY"] == "60" and w["env"]["DO_NOT_TRACK"] == "1"
            assert w["env"]["PREFECT_API_URL"] == studio.env["PREFECT_API_URL"]
        # one worker dies: worker.sh stops the others (gracefully) and exits with its status
        os.kill(workers[f"{host}-gpu1"]["pid"], signal.SIGKILL)
        # (generous; a shutdown takes seconds: the suite's earlier timeouts here were an ignored
        # SIGINT, not a slow machine: see _start_worker_sh)
        assert proc.wait(timeout=240) == 128 + signal.SIGKILL
        assert "a worker exited (status 137); stopping the others" in proc.stderr.read()
        assert not any(_alive(w["pid"]) for w in workers.values())
        for name in (f"{host}-gpu0", f"{host}-control"):
            assert f"Worker '{name}' stopped!" in (tmp_path / f"{name}.log").read_text(), name
    finally:
        from tests.prefect_cluster import kill_tree

        kill_tree(proc)


@pytest.mark.slow
def test_worker_sh_stops_its_workers_on_sigterm(process_pools, tmp_path):
    studio, host = process_pools, socket.gethostname().split(".")[0]
    since = datetime.now(timezone.utc)
    proc = _start_worker_sh(studio, ["--gpus", "0"], tmp_path)
    try:
        _wait_for_workers(studio, proc, {f"{host}-gpu0": "gpu"}, since)
        workers = _worker_processes(proc.pid)
        assert set(workers) == {f"{host}-gpu0"}
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)                     # what systemd's stop sends
        assert proc.wait(timeout=240) == 128 + signal.SIGTERM
        assert time.monotonic() - t0 < 30
        assert not _alive(workers[f"{host}-gpu0"]["pid"])
        assert f"Worker '{host}-gpu0' stopped!" in (tmp_path / f"{host}-gpu0.log").read_text()
    finally:
        from tests.prefect_cluster import kill_tree

        kill_tree(proc)
