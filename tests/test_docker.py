"""The deployment files refer to things that exist: settings, volumes, services, commands.

There is no container engine here; these checks read ``docker/compose.yaml`` and
``docker/Dockerfile`` and run the commands they name, from this installation.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path
from urllib.parse import urlsplit

import pytest
import yaml

from mapbuilder.settings import Settings as StoreSettings
from service.settings import ServiceSettings

REPO = Path(__file__).resolve().parents[1]
DOCKER = REPO / "docker"
BIN = Path(sys.executable).parent


@pytest.fixture(scope="module")
def compose() -> dict:
    return yaml.safe_load((DOCKER / "compose.yaml").read_text())


@pytest.fixture(scope="module")
def dockerfile() -> str:
    return (DOCKER / "Dockerfile").read_text()


def _instructions(dockerfile: str) -> list[tuple[str, str]]:
    text = re.sub(r"\\\n\s*", " ", dockerfile)
    out = []
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            word, _, rest = line.partition(" ")
            out.append((word.upper(), rest.strip()))
    return out


def _known_settings() -> set[str]:
    names = set(ServiceSettings.model_fields) | set(StoreSettings.model_fields)
    return {f"LANEMAP_{n.upper()}" for n in names}


def _interpolate(value: str) -> str:
    """``${VAR:-default}`` -> default, ``${VAR:?msg}`` -> VAR (as compose would with VAR set)."""
    value = re.sub(r"\$\{(\w+):-([^}]*)\}", r"\2", str(value))
    return re.sub(r"\$\{(\w+):\?[^}]*\}", lambda m: m.group(1).lower(), value)


def test_compose_services_and_shared_imagery_volume(compose):
    services = compose["services"]
    assert set(services) == {"db", "api", "scheduler", "worker"}
    assert services["worker"]["deploy"]["replicas"] == 2
    declared = set(compose["volumes"])
    mounts = {}
    for name, svc in services.items():
        for spec in svc.get("volumes", []):
            source, target, *mode = spec.split(":")
            assert source in declared, f"{name} mounts undeclared volume {source}"
            mounts[name] = mounts.get(name, []) + [(source, target, mode)]
        for dep in svc.get("depends_on", {}):
            assert dep in services, f"{name} depends on unknown service {dep}"
    # Build tasks carry paths: the workers must see the API's imagery at the same place.
    api_env = services["api"]["environment"]
    data_dir = api_env["LANEMAP_DATA_DIR"]
    assert ("imagery", data_dir, []) in mounts["api"]
    assert ("imagery", data_dir, ["ro"]) in mounts["worker"]
    assert any(t == "/var/lib/postgresql/data" for _, t, _ in mounts["db"])


def test_compose_configuration_is_lanemap_settings_only(compose, dockerfile):
    known = _known_settings()
    readme = (REPO / "README.md").read_text()
    services = compose["services"]
    used = set()
    for name, svc in services.items():
        for key in svc.get("environment", {}):
            if key.startswith("LANEMAP_"):
                used.add(key)
    image_only = {"LANEMAP_WORKERS"}  # read by the image's entry point, not by the settings
    assert used - known <= image_only, used - known
    for var in image_only & used:
        assert "${" + var + "}" in dockerfile
    for var in used | set(re.findall(r"\bLANEMAP_\w+", dockerfile)):
        assert f"`{var}`" in readme, f"{var} is not documented in README.md"

    api = services["api"]["environment"]
    db = services["db"]
    url = urlsplit(_interpolate(api["LANEMAP_DATABASE_URL"]))
    assert url.scheme == "postgresql" and url.hostname == "db" and url.port == 5432
    assert url.username == db["environment"]["POSTGRES_USER"]
    assert url.path.lstrip("/") == db["environment"]["POSTGRES_DB"]
    assert url.password == "postgres_password"  # the same ${POSTGRES_PASSWORD} as the database's

    sched = urlsplit(api["LANEMAP_DASK_SCHEDULER"])
    sched_cmd = services["scheduler"]["entrypoint"]
    assert sched.hostname == "scheduler" and str(sched.port) == sched_cmd[sched_cmd.index("--port") + 1]
    assert services["worker"]["entrypoint"][2] == api["LANEMAP_DASK_SCHEDULER"]
    ports = services["api"]["ports"]
    assert any(_interpolate(p).endswith(":8000") for p in ports)


def _help(*args: str) -> str:
    out = subprocess.run([*args, "--help"], capture_output=True, text=True, timeout=120,
                         env={**os.environ, "COLUMNS": "200"})  # fmt: skip
    assert out.returncode == 0, out.stderr
    return out.stdout


def test_compose_commands_exist_with_their_options(compose):
    for name in ("scheduler", "worker"):
        cmd = compose["services"][name]["entrypoint"]
        assert cmd[0] == "dask"
        text = _help(str(BIN / "dask"), cmd[1])
        for opt in (a for a in cmd[2:] if a.startswith("--")):
            assert opt in text, f"dask {cmd[1]} has no option {opt}"


def test_dockerfile_runs_lanemap_serve_as_non_root_with_a_health_check(dockerfile):
    ins = _instructions(dockerfile)
    words = [w for w, _ in ins]
    assert words.count("FROM") == 2 and all("slim" in r for w, r in ins if w == "FROM")
    user = [r for w, r in ins if w == "USER"][-1]
    assert user.split(":")[0] not in ("root", "0")
    health = [r for w, r in ins if w == "HEALTHCHECK"]
    assert len(health) == 1 and "/health" in health[0] and "--timeout" in health[0]
    entry = json.loads([r for w, r in ins if w == "ENTRYPOINT"][-1])
    assert entry[:2] == ["/bin/sh", "-c"] and "lanemap serve" in entry[2]
    # The package is installed with its default model (package data).
    for w, r in ins:
        if w == "COPY" and not r.startswith("--from"):
            for src in shlex.split(r)[:-1]:
                assert (REPO / src).exists(), src
    assert (REPO / "mapbuilder" / "data" / "marking_svm.onnx").is_file()
    # The build context keeps what the image installs.
    ignore = (DOCKER / "Dockerfile.dockerignore").read_text()
    for src in ("mapbuilder", "localizer", "service", "migrations", "pyproject.toml"):
        assert f"!{src}" in ignore

    # The entry point's shell line hands LANEMAP_WORKERS and extra arguments to `lanemap serve`.
    env = {**os.environ, "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}", "LANEMAP_WORKERS": "3",
           "PYTHONPATH": str(REPO), "COLUMNS": "200"}  # fmt: skip
    script = entry[2].replace("exec lanemap", "exec echo lanemap")
    out = subprocess.run([entry[0], "-c", script, entry[3], "--demo"], capture_output=True, text=True, env=env)
    assert out.stdout.split() == ["lanemap", "serve", "--host", "0.0.0.0", "--port", "8000", "--workers", "3", "--demo"]
    serve_help = _help(str(BIN / "lanemap"), "serve")
    for opt in ("--host", "--port", "--workers", "--demo"):
        assert opt in serve_help


def test_the_images_python_build_steps_run_here(dockerfile):
    """``python -c`` steps of the image build (compiling the localizer's kernels) work on this installation."""
    steps = [m for w, r in _instructions(dockerfile) if w == "RUN"
             for m in re.findall(r'python -c "([^"]+)"', r)]  # fmt: skip
    assert any("localizer.warm_up()" in m for m in steps)
    for code in steps:
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
        assert out.returncode == 0, out.stderr


def test_hadolint_finds_nothing_in_the_dockerfile():
    hadolint = BIN / "hadolint"
    out = subprocess.run([str(hadolint), "--no-color", str(DOCKER / "Dockerfile")],
                         capture_output=True, text=True, timeout=60)  # fmt: skip
    assert out.returncode == 0, out.stdout + out.stderr
    # It does lint: a Dockerfile with a known fault is reported.
    bad = subprocess.run([str(hadolint), "--no-color", "-"], input="FROM debian\nRUN cd /tmp && apt-get install curl\n",
                         capture_output=True, text=True, timeout=60)  # fmt: skip
    assert bad.returncode != 0 and "DL3006" in bad.stdout
