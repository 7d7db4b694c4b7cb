"""A two-node Ray cluster of separate ``ray start`` processes runs ``cosim batch --backend ray --address``.

The head listens on 127.0.0.1 and the second node on 127.0.0.2 (two raylets, two object stores, on
loopback; both see the same output folder, as nodes of a real cluster see a shared filesystem). The
batch must use both nodes (the manifest names each episode's Ray node), reproduce the files of a local
batch, and survive the second node being killed mid-episode: the lost attempt is retried on the head.
Every process of the cluster is found by its temp dir or as a child of its raylets and killed in
teardown, whatever the test's outcome; nothing else on the machine is touched.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import psutil
import pytest

from cosim.io.manifest import deterministic_view, latest_records, read_records, sha256_file, verify
from tests.helpers import REPO

pytest.importorskip("ray")
pytestmark = [pytest.mark.cluster, pytest.mark.integration, pytest.mark.resource("ray"), pytest.mark.timeout(1200)]

SMOKE = REPO / "sweeps" / "smoke.yaml"
HEAD_IP, NODE_IP = "127.0.0.1", "127.0.0.2"
OBJECT_STORE_BYTES = 200 * 1024 * 1024
START_TIMEOUT_S = 180
# The head declares a node dead after about 5 missed health checks of 1 s (default: 30 s or more). The
# nodes run their workers at niceness 0, as README's "A Ray cluster" says to where nodes do other work too
# (here: the rest of the suite), not Ray's 15.
RAY_ENV = {"RAY_health_check_period_ms": "1000", "RAY_health_check_failure_threshold": "5",
           "RAY_health_check_timeout_ms": "2000", "RAY_USAGE_STATS_ENABLED": "0", "RAY_worker_niceness": "0",
           # Explicit: a head started where ~/.ray/auth_token exists would otherwise turn token auth on.
           "RAY_AUTH_MODE": "disabled"}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _ray_start(*args: str, temp_dir: Path) -> str | None:
    """One node; every port it listens on chosen free (defaults would collide with the other node or other Rays).

    Returns None, or why it failed: Ray gives a raylet a fixed 30 s to register, which a loaded machine misses."""
    ports = {f"--{name}": str(_free_port()) for name in ("dashboard-agent-listen-port", "dashboard-agent-grpc-port",
                                                          "metrics-export-port", "runtime-env-agent-port",
                                                          "object-manager-port")}
    cmd = [sys.executable, "-m", "ray.scripts.scripts", "start", "--num-cpus", "1", "--object-store-memory",
           str(OBJECT_STORE_BYTES), "--disable-usage-stats", "--log-style", "record",
           *(x for kv in ports.items() for x in kv), *args]
    env = {**os.environ, **RAY_ENV, "RAY_TMPDIR": str(temp_dir)}
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=START_TIMEOUT_S, env=env)
    return None if r.returncode == 0 else f"ray start failed:\n{r.stdout[-1500:]}\n{r.stderr[-1500:]}"


def _start_node(args: list[str], raylet_ports: list[int], temp_dir: Path, attempts: int = 3) -> int:
    """Start a node, again on fresh ports after a start-up timeout (the failed one's processes killed)."""
    failures = []
    for _ in range(attempts):
        port = _free_port()
        raylet_ports.append(port)
        failure = _ray_start(*args, "--node-manager-port", str(port), temp_dir=temp_dir)
        if failure is None:
            return port
        failures.append(failure)
        raylet = _raylet(port)
        _kill([raylet, *raylet.children(recursive=True)] if raylet else [])
    raise AssertionError("\n".join(failures))


PROBE = """
import json, sys, time, ray
ray.init(address=sys.argv[1], log_to_driver=False)
end = time.monotonic() + float(sys.argv[2])
while True:
    alive = [(n["NodeManagerAddress"], n["NodeID"]) for n in ray.nodes() if n["Alive"]]
    if len(alive) == int(sys.argv[3]) or time.monotonic() > end:
        break
    time.sleep(1)
print(json.dumps(alive))
"""


def _alive_nodes(address: str, expect: int, timeout_s: float = 120) -> dict[str, list[str]]:
    """IP -> ids of the alive nodes, once there are ``expect`` of them (a killed failed start may linger)."""
    r = subprocess.run([sys.executable, "-c", PROBE, address, str(timeout_s), str(expect)], capture_output=True,
                       text=True, timeout=timeout_s + 120, env={**os.environ, **RAY_ENV})
    assert r.returncode == 0, r.stderr[-2000:]
    by_ip: dict[str, list[str]] = {}
    for ip, node in json.loads(r.stdout.strip().splitlines()[-1]):
        by_ip.setdefault(ip, []).append(node)
    return by_ip


def _processes_of(temp_dir: Path, raylet_ports: list[int]) -> list[psutil.Process]:
    """Every process of this cluster: anything naming its temp dir or one of its raylet ports, and children."""
    marks = [str(temp_dir), *(f"--node_manager_port={p}" for p in raylet_ports)]
    found: dict[int, psutil.Process] = {}
    for proc in psutil.process_iter(["pid", "cmdline", "environ"]):
        with contextlib.suppress(psutil.Error):
            text = " ".join(proc.info["cmdline"] or [])
            env_tmp = (proc.info["environ"] or {}).get("RAY_TMPDIR", "")
            if proc.pid != os.getpid() and (any(m in text for m in marks) or env_tmp == str(temp_dir)):
                found[proc.pid] = proc
                for child in proc.children(recursive=True):
                    found[child.pid] = child
    return list(found.values())


def _kill(procs: list[psutil.Process]) -> None:
    for p in procs:
        with contextlib.suppress(psutil.Error):
            p.send_signal(signal.SIGKILL)
    psutil.wait_procs(procs, timeout=30)


def _raylet(port: int) -> psutil.Process | None:
    for proc in psutil.process_iter(["cmdline"]):
        with contextlib.suppress(psutil.Error):
            cmd = proc.info["cmdline"] or []
            if cmd and cmd[0].endswith("raylet") and f"--node_manager_port={port}" in cmd:
                return proc
    return None


@pytest.fixture(scope="module")
def cluster():
    """(address, {"head"|"second": node id}, second node's raylet port); torn down whatever happens."""
    temp_dir = Path(tempfile.mkdtemp(prefix="rayc-", dir="/tmp"))  # short: Ray's socket paths must fit
    gcs_port = _free_port()
    address = f"{HEAD_IP}:{gcs_port}"
    raylet_ports: list[int] = []
    try:
        _start_node(["--head", "--node-ip-address", HEAD_IP, "--port", str(gcs_port), "--include-dashboard",
                     "false", "--temp-dir", str(temp_dir), "--min-worker-port", "0", "--max-worker-port", "0"],
                    raylet_ports, temp_dir, attempts=1)
        node_raylet = _start_node(["--address", address, "--node-ip-address", NODE_IP, "--min-worker-port", "0",
                                   "--max-worker-port", "0"], raylet_ports, temp_dir)
        by_ip = _alive_nodes(address, expect=2)
        # Ray may register the head under the machine's address rather than loopback.
        assert len(by_ip) == 2 and len(by_ip.get(NODE_IP, [])) == 1, by_ip
        nodes = {"second": by_ip.pop(NODE_IP)[0], "head": next(iter(by_ip.values()))[0]}
        yield address, nodes, node_raylet
    finally:
        _kill(_processes_of(temp_dir, raylet_ports))
        subprocess.run(["rm", "-rf", str(temp_dir)], check=False, timeout=60)


def _done_on(out: Path, node_id: str) -> int:
    return sum(r.get("status") == "done" and r.get("node") == node_id
               for path in out.glob("manifest*.jsonl") for r in read_records(path))


def _running_task(raylet: psutil.Process | None) -> bool:
    """A worker of this raylet is executing an episode (Ray titles it after the task function)."""
    if raylet is None:
        return False
    with contextlib.suppress(psutil.Error):
        return any("ray::_task" in " ".join(c.cmdline()) for c in raylet.children(recursive=True))
    return False


def test_batch_spans_two_nodes_and_survives_losing_one(cluster, smoke_batch, tmp_path):
    address, nodes, node_raylet_port = cluster
    out = tmp_path / "shared"
    cmd = [sys.executable, "-m", "cosim.cli", "batch", str(SMOKE), "--out", str(out), "--backend", "ray",
           "--address", address, "--retries", "2", "-q"]
    batch = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO,
                             env={**os.environ, **RAY_ENV}, start_new_session=True)
    killed = False
    try:
        # Kill the second node once it has finished an episode and is running another.
        raylet = _raylet(node_raylet_port)
        deadline = time.monotonic() + 900
        while batch.poll() is None and time.monotonic() < deadline:
            if _done_on(out, nodes["second"]) >= 1 and _running_task(raylet):
                _kill([raylet, *raylet.children(recursive=True)])
                killed = True
                break
            time.sleep(0.2)
        stdout, stderr = batch.communicate(timeout=900)
    finally:
        if batch.poll() is None:
            os.killpg(batch.pid, signal.SIGKILL)
            batch.wait(timeout=30)
    assert killed, f"the second node never ran a second episode; batch output:\n{stdout[-2000:]}"
    assert batch.returncode == 0, f"{stdout[-2000:]}\n{stderr[-3000:]}"

    final, local = latest_records(out), latest_records(smoke_batch)
    assert len(final) == 6 and all(verify(out, rec) for rec in final.values())
    assert deterministic_view(final.values()) == deterministic_view(local.values())
    for rec in local.values():
        assert sha256_file(out / rec["file"]) == sha256_file(smoke_batch / rec["file"])
    ran_on = {rec["node"] for rec in final.values()}
    assert ran_on == {nodes["head"], nodes["second"]}  # both nodes delivered episodes
    lost = [r for path in out.glob("manifest*.jsonl") for r in read_records(path)
            if r["status"] == "failed" and r.get("retrying")]
    assert lost, "killing the node mid-episode left no failed attempt"
    for rec in lost:  # the lost episode was finished afterwards by the surviving head
        assert final[rec["episode"]]["node"] == nodes["head"]
        assert final[rec["episode"]]["attempts"] > rec["attempts"]
