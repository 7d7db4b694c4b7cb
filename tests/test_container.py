"""The Docker image, built and run: one episode inside a container, then a 3-way shard matrix.

Skipped with the reason when no Docker daemon answers (CI's ``.ci/run`` starts one as root). The
image is built the offline way (README, "Containers"): a base made by ``docker/base.sh``
(debootstrap + ``docker import``, no registry) and the dependency wheels from the host. Both are
cached outside the clone: the base as a Docker image tagged with the hash of ``docker/base.sh``,
the wheels in ``$COSIM_CI_CACHE`` (default ``~/.cache/cosim-ci``) keyed by the hash of
``pyproject.toml``'s dependency lists. Containers run as the test's own user, so bind-mounted output stays removable.
Deselect with ``-m "not container"``.

The Docker daemon's storage outlives a CI run, so the fixtures clean up after the runs before them: a
source change leaves the previous image and its build stage untagged (about 2 GB each), a changed
``docker/base.sh`` or dependency list a stale base image or wheelhouse. Everything this module builds is
labelled ``cosim-ci=1``; only untagged images with that label, base images of other hashes and other
wheelhouses are removed. Then, when the daemon's disk has less room than one build takes, the tests skip
and say how much is free (a full disk fails every other test running beside the build).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import subprocess
import sys
import sysconfig
import time
import tomllib
import uuid
from pathlib import Path

import pytest

from cosim.batch.report import build_report
from cosim.io.manifest import deterministic_view, latest_records, sha256_file, verify
from cosim.io.validate import validate_episode
from tests.helpers import REPO, run_cli

pytestmark = [pytest.mark.container, pytest.mark.integration, pytest.mark.timeout(3600)]
log = logging.getLogger(__name__)

CACHE = Path(os.environ.get("COSIM_CI_CACHE", Path.home() / ".cache" / "cosim-ci"))
BUILD_CONTEXT = ("Dockerfile", ".dockerignore", "pyproject.toml", "README.md", "cosim", "sensors", "exporters",
                 "scenarios", "sweeps")
SMOKE = REPO / "sweeps" / "smoke.yaml"
LABEL = "cosim-ci=1"
# One build's peak on the daemon's disk: the context's wheels (0.7 GB) copied into the build stage, the
# environment installed from them (2.1 GB), that environment copied into the final image (2.1 GB), the
# context itself while it is sent, and room for the episodes the tests write.
BUILD_NEEDS_BYTES = 8e9
EPISODE_ARGS = ("scenarios/default.yaml", "--duration", "2", "--no-sensors", "--set", "map.size_m=300",
                "--set", "traffic.density_veh_per_km=6", "-q")


def _hash(*paths: Path) -> str:
    h = hashlib.sha256()
    for p in paths:
        h.update(p.read_bytes())
    return h.hexdigest()[:16]


def docker(*args: str, timeout: float = 120, check: bool = True) -> subprocess.CompletedProcess:
    r = subprocess.run(["docker", *args], capture_output=True, text=True, timeout=timeout)
    if check and r.returncode != 0:
        raise AssertionError(f"docker {' '.join(args[:3])} ... failed ({r.returncode}): {r.stderr[-3000:]}")
    return r


def _daemon_problem() -> str | None:
    if shutil.which("docker") is None:
        return "no docker client on PATH (CI's .ci/run installs docker.io as root)"
    try:
        r = subprocess.run(["docker", "info", "--format", "{{.ServerVersion}}"], capture_output=True, text=True,
                           timeout=30)
    except subprocess.TimeoutExpired:
        return "docker info did not answer within 30 s"
    if r.returncode != 0 or not r.stdout.strip():
        return f"no Docker daemon reachable: {(r.stderr.strip().splitlines() or ['?'])[-1]}"
    return None


@pytest.fixture(scope="module")
def base_image() -> str:
    problem = _daemon_problem()
    if problem:
        pytest.skip(problem)
    tag = f"cosim-base:bookworm-{_hash(REPO / 'docker' / 'base.sh')}"
    _remove_stale_images(keep_base=tag)
    problem = _disk_problem()
    if problem:
        pytest.skip(problem)
    if docker("image", "inspect", tag, check=False).returncode == 0:
        return tag
    if os.geteuid() != 0 or shutil.which("debootstrap") is None:
        pytest.skip(f"no base image {tag}, and making one needs root and debootstrap (docker/base.sh)")
    started = time.monotonic()
    r = subprocess.run(["nice", "-n", "10", str(REPO / "docker" / "base.sh"), tag], capture_output=True,
                       text=True, timeout=1800)
    assert r.returncode == 0, f"docker/base.sh failed: {r.stderr[-3000:]}"
    log.warning("base image %s made in %.0f s", tag, time.monotonic() - started)
    return tag


def _remove_stale_images(keep_base: str) -> None:
    """Untagged images of earlier builds here (superseded final images and build stages), exited
    containers of earlier runs and base images made from another ``docker/base.sh``."""
    docker("container", "prune", "-f", "--filter", f"label={LABEL}", check=False)
    docker("image", "prune", "-f", "--filter", f"label={LABEL}", check=False)  # dangling ones only
    bases = docker("images", "cosim-base", "--format", "{{.Repository}}:{{.Tag}}", check=False).stdout.split()
    stale = [b for b in bases if b != keep_base and b.startswith("cosim-base:bookworm-")]
    if stale:
        docker("rmi", *stale, check=False)
        log.warning("removed stale base images %s", stale)


def _disk_problem() -> str | None:
    root = docker("info", "--format", "{{.DockerRootDir}}", check=False).stdout.strip()
    try:
        free = shutil.disk_usage(root).free
    except OSError:  # a remote daemon, or a root directory this user cannot see: nothing to measure
        return None
    if free < BUILD_NEEDS_BYTES:
        return (f"only {free / 1e9:.1f} GB free under Docker's {root}; building the image takes about "
                f"{BUILD_NEEDS_BYTES / 1e9:.0f} GB")
    return None


#: Packaging tools: the build stage brings its own (the project's build-system.requires), never the host's.
UNPINNED = {"cosim", "pip", "setuptools", "wheel"}


def host_pins() -> str:
    """The host environment's distributions as pip constraints (``name==version``, one a line): the image is
    built from the very versions the host runs, so that an episode made in it can equal the host's byte for
    byte. Pinning by the dependency list alone let a wheelhouse cached from older releases (numpy, numba)
    give last-digit differences in float results after the host's environment moved on."""
    from importlib import metadata

    # The environment's own site-packages, not whatever sys.path holds now: importing Ray puts its vendored
    # packages (colorama) on sys.path, which gave the whole suite (whose collection imports Ray) another key
    # than a run of this file alone, and each switch rebuilt the wheelhouse and the image's dependency layer.
    paths = sorted({sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]})
    pins = {(d.metadata["Name"] or "").lower().replace("_", "-"): d.version
            for d in metadata.distributions(path=paths)}
    return "".join(f"{name}=={version}\n" for name, version in sorted(pins.items())
                   if name and name not in UNPINNED)


def _dependencies_key(pins: str) -> str:
    project = tomllib.loads((REPO / "pyproject.toml").read_text())
    deps = [project["build-system"]["requires"], project["project"]["dependencies"], pins]
    return hashlib.sha256(json.dumps(deps).encode()).hexdigest()[:16]


@pytest.fixture(scope="module")
def wheelhouse() -> Path:
    """Every dependency as a wheel, at the host's versions, built once per dependency list and set of host
    versions (the network is needed only then)."""
    pins = host_pins()
    path = CACHE / f"wheelhouse-{_dependencies_key(pins)}"
    for old in CACHE.glob("wheelhouse-*"):  # made for another dependency list
        if old != path:
            shutil.rmtree(old, ignore_errors=True)
    if (path / ".complete").exists():
        return path
    tmp = CACHE / f".wheelhouse-{uuid.uuid4().hex[:8]}"
    tmp.mkdir(parents=True)
    (tmp / "constraints.txt").write_text(pins)
    try:
        r = subprocess.run(["nice", "-n", "10", sys.executable, "-m", "pip", "wheel", "--quiet", "--wheel-dir",
                            str(tmp), "-c", str(tmp / "constraints.txt"), str(REPO), "setuptools>=77", "wheel"],
                           capture_output=True, text=True, timeout=1800)
        assert r.returncode == 0, f"pip wheel failed: {r.stderr[-3000:]}"
        for w in tmp.glob("cosim-*.whl"):
            w.unlink()  # the project itself is built from the context, the wheelhouse holds dependencies
        (tmp / ".complete").touch()
        shutil.rmtree(path, ignore_errors=True)
        tmp.rename(path)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return path


@pytest.fixture(scope="module")
def image(base_image: str, wheelhouse: Path, tmp_path_factory) -> str:
    """The repository's Dockerfile built from a copy of the sources plus the wheelhouse (no network)."""
    ctx = tmp_path_factory.mktemp("docker-context")
    ignore = shutil.ignore_patterns("__pycache__", "*.mcap", "*.partial")
    for name in BUILD_CONTEXT:
        src = REPO / name
        if src.is_dir():
            shutil.copytree(src, ctx / name, ignore=ignore)
        else:
            shutil.copy2(src, ctx / name)
    (ctx / "wheelhouse").mkdir()
    for whl in wheelhouse.glob("*.whl"):
        try:
            os.link(whl, ctx / "wheelhouse" / whl.name)
        except OSError:
            shutil.copy2(whl, ctx / "wheelhouse" / whl.name)
    tag = "cosim-ci:test"
    started = time.monotonic()
    # The build stage is tagged too, so that only the stages of earlier builds are untagged (and removed
    # by the next run's clean-up) while this one stays the layer cache of the next build.
    for target, name in (("build", "cosim-ci:build-stage"), (None, tag)):
        r = subprocess.run(["nice", "-n", "10", "docker", "build", "--build-arg", f"BASE={base_image}",
                            "--label", LABEL, "-t", name, *(["--target", target] if target else []), str(ctx)],
                           capture_output=True, text=True, timeout=1800)
        assert r.returncode == 0, f"docker build failed:\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
    size = docker("image", "inspect", tag, "--format", "{{.Size}}").stdout.strip()
    log.warning("image %s built in %.0f s, %.0f MB", tag, time.monotonic() - started, int(size) / 1e6)
    shutil.rmtree(ctx, ignore_errors=True)
    return tag


#: Environment variables that choose numeric kernels: OpenBLAS (numpy's BLAS) picks its kernel by the CPU
#: unless OPENBLAS_CORETYPE names one, and a dot product of another kernel differs in the last digit (the
#: drones' poses). They are part of "the same machine": a container runs with the host's.
NUMERIC_PREFIXES = ("OPENBLAS_", "GOTO_", "OMP_", "MKL_")


def run_container(image: str, out: Path, *args: str, detach: bool = False, timeout: float = 600) -> str:
    """``docker run`` as the calling user with ``out`` mounted at /out; returns stdout (the id if detached).

    A detached container is kept after it exits (for its status and log): remove it with ``docker rm``."""
    out.mkdir(parents=True, exist_ok=True)
    cmd = ["run", "-u", f"{os.getuid()}:{os.getgid()}", "-v", f"{out}:/out", "--label", LABEL]
    for name in sorted(k for k in os.environ if k.startswith(NUMERIC_PREFIXES)):
        cmd += ["-e", name]  # the host's value, as docker reads it from this process's environment
    cmd.append("-d" if detach else "--rm")
    r = docker(*cmd, image, *args, timeout=timeout)
    return r.stdout.strip()


def objects_of(path: Path) -> list[tuple[int, bytes]]:
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        return [(m.log_time, m.data) for _s, _c, m in make_reader(f).iter_messages(topics=["/labels/objects"])]


def test_the_image_runs_the_hosts_version_of_every_package_it_has(image):
    """What makes the image's episodes equal the host's: the same releases (a numpy or numba of another
    release may differ in the last digit of a float)."""
    listing = ("import importlib.metadata as m; "
               "print('\\n'.join(sorted(f\"{d.metadata['Name'].lower().replace('_', '-')}=={d.version}\" "
               "for d in m.distributions())))")
    r = docker("run", "--rm", "--entrypoint", "python", image, "-c", listing, timeout=120)
    inside = dict(line.split("==", 1) for line in r.stdout.split())
    host = dict(line.split("==", 1) for line in host_pins().split())
    assert {"numpy", "numba", "open3d-cpu", "libsumo", "mcap"} <= inside.keys()
    differ = {name: (version, host.get(name)) for name, version in inside.items()
              if name not in UNPINNED and host.get(name) != version}
    assert not differ, f"image against host versions: {differ}"


def test_episode_in_a_container_validates_and_matches_the_host(image, tmp_path):
    inside, host = tmp_path / "inside", tmp_path / "host"
    run_container(image, inside, "run", *EPISODE_ARGS, "--out", "/out")
    r = run_cli("run", *EPISODE_ARGS, "--out", str(host), timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    [episode] = list(inside.glob("*.mcap"))
    assert episode.stat().st_uid == os.getuid()  # written as the caller, not as the container's root
    report = validate_episode(episode, pixels=False)
    assert report.ok, report.problems[:5]
    inside_objects = objects_of(episode)
    assert len(inside_objects) == 10  # 2 s at 5 Hz
    assert inside_objects == objects_of(host / episode.name)
    # Every message equal, every drone's flight included (the default rig hovers, patrols and escorts), and
    # every metadata field but the versions (Debian's Python 3.11.2 in the image may differ from the host's).
    (ours, our_meta), (theirs, their_meta) = messages_and_metadata(episode), messages_and_metadata(host / episode.name)
    assert ours == theirs, "messages differ between the image and the host"
    for meta in (our_meta, their_meta):
        meta["episode"].pop("versions")
    assert our_meta == their_meta


def messages_and_metadata(path: Path) -> tuple[list[tuple[str, int, bytes]], dict[str, dict[str, str]]]:
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        reader = make_reader(f)
        messages = [(c.topic, m.log_time, m.data) for _s, c, m in reader.iter_messages()]
        return messages, {m.name: dict(m.metadata) for m in reader.iter_metadata()}


def test_three_shard_containers_fill_one_folder_like_a_local_batch(image, tmp_path):
    # Byte for byte, the shards are compared with one unsharded batch in the same image (the host's own
    # episodes equal the image's message for message: the test above). Not with the suite's smoke_batch: that
    # fixture would tie the image's build and the Ray tests that read it to one worker, one after the other.
    smoke_batch = tmp_path / "local"
    run_container(image, smoke_batch, "batch", "smoke", "--out", "/out", "--workers", "2", "-q", timeout=900)
    out = tmp_path / "matrix"
    ids = [run_container(image, out, "batch", "smoke", "--out", "/out", "--shard", f"{i}/3", "-q", detach=True)
           for i in range(3)]
    try:
        for cid in ids:
            status = docker("wait", cid, timeout=900).stdout.strip()
            logs = docker("logs", "--tail", "30", cid, check=False)
            assert status == "0", f"shard container {cid[:12]} exited {status}:\n{logs.stdout}\n{logs.stderr}"
    finally:
        docker("rm", "-f", *ids, check=False)
    assert sorted(p.name for p in out.glob("manifest*.jsonl")) == [f"manifest.shard{i:03d}of003.jsonl"
                                                                    for i in range(3)]
    union, local = latest_records(out), latest_records(smoke_batch)
    assert len(union) == len(local) == 6
    assert all(verify(out, rec) for rec in union.values())
    assert deterministic_view(union.values()) == deterministic_view(local.values())
    for rec in local.values():
        assert sha256_file(out / rec["file"]) == sha256_file(smoke_batch / rec["file"])
    # Where each episode ran: the three containers, each id being one the test started.
    assert {rec["container"] for rec in union.values()} == set(ids)
    assert all(rec["host"] == rec["container"][:12] for rec in union.values())
    assert len({rec["container"] for rec in local.values()}) == 1  # the unsharded batch's one container
    nodes = build_report(out, md_path=tmp_path / "report.md").stats["nodes"]
    assert sorted(n["episodes"] for n in nodes.values()) == [2, 2, 2]
    assert all(n["sim_per_wall"] > 0 for n in nodes.values())


FAKE_DOCKER = """#!/bin/sh
echo "$*" >> "$FAKE_DOCKER_LOG"
case "$1 $2" in
  "info --format") echo "$FAKE_DOCKER_ROOT" ;;
  "images cosim-base") printf 'cosim-base:bookworm-old\\ncosim-base:bookworm-new\\ncosim-base:other\\n' ;;
esac
"""


def test_host_pins_are_the_environments_whatever_sys_path_holds(tmp_path, monkeypatch):
    before = host_pins()
    assert "numpy==" in before and "\ncosim==" not in "\n" + before
    fake = tmp_path / "vendored_thing-1.0.dist-info"
    fake.mkdir()
    (fake / "METADATA").write_text("Metadata-Version: 2.1\nName: vendored-thing\nVersion: 1.0\n")
    monkeypatch.syspath_prepend(str(tmp_path))  # as importing Ray does with its vendored packages
    from importlib import metadata

    assert any(d.metadata["Name"] == "vendored-thing" for d in metadata.distributions())
    assert host_pins() == before


def test_clean_up_removes_earlier_builds_only_and_a_full_disk_skips_with_the_free_space(tmp_path, monkeypatch):
    # A stand-in `docker` on PATH (no daemon needed): the clean-up's calls, and the disk check's answer.
    bin_dir, calls = tmp_path / "bin", tmp_path / "calls.log"
    bin_dir.mkdir()
    (bin_dir / "docker").write_text(FAKE_DOCKER)
    (bin_dir / "docker").chmod(0o755)
    monkeypatch.setenv("PATH", f"{bin_dir}{os.pathsep}{os.environ['PATH']}")
    monkeypatch.setenv("FAKE_DOCKER_LOG", str(calls))
    monkeypatch.setenv("FAKE_DOCKER_ROOT", str(tmp_path))

    _remove_stale_images(keep_base="cosim-base:bookworm-new")
    assert calls.read_text().splitlines() == [
        "container prune -f --filter label=cosim-ci=1",
        "image prune -f --filter label=cosim-ci=1",
        "images cosim-base --format {{.Repository}}:{{.Tag}}",
        "rmi cosim-base:bookworm-old",  # neither the base in use nor an image this module did not make
    ]

    free = shutil.disk_usage(tmp_path).free
    monkeypatch.setattr(sys.modules[__name__], "BUILD_NEEDS_BYTES", free / 2)
    assert _disk_problem() is None
    monkeypatch.setattr(sys.modules[__name__], "BUILD_NEEDS_BYTES", free * 2 + 1e9)
    problem = _disk_problem()
    assert problem is not None and f"under Docker's {tmp_path}" in problem and " GB free " in problem
