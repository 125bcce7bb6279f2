"""The project's Dockerfile built and run with podman, on a stand-in for its base image.

No Docker and no registry here: the base image ``python:3.11-slim`` is, when missing, a
minimal Debian 12 root file system (``mmdebstrap``) with Debian's Python 3.11, imported under
that name (as ``../shared/tools/docker-check`` makes it); podman runs rootful, with rlimits
this machine allows when its defaults are refused (a container's ``nofile`` above the hard
limit needs CAP_SYS_RESOURCE), and with runc where crun refuses the host's cgroups. Built with
``--format docker``, which keeps ``HEALTHCHECK``.
"""

from __future__ import annotations

import os
import resource
import shutil
import subprocess
import tempfile
from pathlib import Path

BASE = "python:3.11-slim"
IMAGE = "motiond-ci"
PACKAGES = "ca-certificates,python3,python3-venv,python3-pip,python3-dev,python-is-python3"
SUITE, MIRROR = "bookworm", "http://deb.debian.org/debian"
HOST_CA = Path("/etc/ssl/certs/ca-certificates.crt")


def podman(*args: str, timeout_s: float = 120, check: bool = False,
           env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["podman", *args], capture_output=True, text=True, check=check,
                          timeout=timeout_s, env={**os.environ, **(env or {})})


def settings(folder: Path) -> dict[str, str]:
    """The environment podman needs here: none, or a containers.conf with allowed rlimits, and
    runc where podman's crun refuses the host's cgroups (crun 1.8: "cgroups in hybrid mode not
    supported"), as ``../shared/tools/docker-check`` tries them."""
    if probe({}).returncode == 0:
        return {}
    nofile = resource.getrlimit(resource.RLIMIT_NOFILE)[1]
    nproc = min(resource.getrlimit(resource.RLIMIT_NPROC)[1],
                int(Path("/proc/sys/kernel/pid_max").read_text()))
    conf = folder / "containers.conf"
    env = {"CONTAINERS_CONF": str(conf)}
    errors = []
    for engine in ("", '[engine]\nruntime = "runc"\n'):
        conf.write_text(f'[containers]\ndefault_ulimits = ["nofile={nofile}:{nofile}", '
                        f'"nproc={nproc}:{nproc}"]\n{engine}')
        tried = probe(env)
        if tried.returncode == 0:
            return env
        errors.append(tried.stderr[-300:])
    raise AssertionError(f"podman cannot run a container here: {' / '.join(errors)}")


def probe(env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    """A container of the base image that does nothing (never pulled: it is made here)."""
    return podman("run", "--rm", "--pull=never", "--network", "none", BASE, "true", env=env)


def ensure_base() -> None:
    """The stand-in base image, made once (about 100 s) when no image has its name."""
    if podman("image", "exists", BASE).returncode == 0:
        return
    assert shutil.which("mmdebstrap"), "mmdebstrap makes the stand-in (scripts/system-packages)"
    with tempfile.TemporaryDirectory() as scratch:
        rootfs = Path(scratch) / "rootfs"
        subprocess.run(
            ["mmdebstrap", "--variant=minbase", "--aptopt=APT::Install-Recommends \"false\"",
             f"--include={PACKAGES}", SUITE, str(rootfs), f"deb {MIRROR} {SUITE} main"],
            check=True, capture_output=True, timeout=900)
        tar = subprocess.Popen(["tar", "-C", str(rootfs), "-c", "."], stdout=subprocess.PIPE)
        subprocess.run(
            ["podman", "import", "--change",
             "ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin",
             "--change", "ENV LANG=C.UTF-8", "--change", 'CMD ["python3"]', "-", BASE],
            stdin=tar.stdout, check=True, capture_output=True, timeout=300)
        tar.wait()


def build(project: Path, env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    """``podman build --format docker`` of the project as it is (its .dockerignore applies)."""
    volume = ["-v", f"{HOST_CA}:{HOST_CA}:ro"] if HOST_CA.is_file() else []
    return podman("build", "--format", "docker", "--network", "host", *volume, "-t", IMAGE,
                  str(project), timeout_s=1200, env=env)
