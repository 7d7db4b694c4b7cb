"""Where episodes ran: container ids from /proc texts, manifest fields, throughput per node (fast, fake episodes)."""

from __future__ import annotations

import socket

import pytest

from cosim.batch.job import container_id_in
from cosim.batch.report import node_label, throughput
from cosim.io.manifest import latest_records
from tests.helpers import run_fake_batch as run
from tests.helpers import six_plan

CID = "3f1c0a9be2d84c6f8a7d5e4b3c2a1908f7e6d5c4b3a29180f7e6d5c4b3a29180"


@pytest.mark.parametrize("text", [
    f"12:memory:/docker/{CID}\n11:cpu,cpuacct:/docker/{CID}\n",  # cgroup v1
    f"0::/system.slice/docker-{CID}.scope\n",  # cgroup v2 with the systemd driver
    f"612 590 0:52 /var/lib/docker/containers/{CID}/hostname /etc/hostname rw - ext4 /dev/sda1 rw\n",  # mountinfo
])
def test_container_id_is_read_from_cgroup_and_mountinfo(text):
    assert container_id_in(text) == CID


@pytest.mark.parametrize("text", ["12:memory:/user.slice\n0::/init.scope\n", "0::/\n",
                                  f"12:memory:/docker/{CID[:40]}\n"])
def test_no_container_id_on_a_plain_host(text):
    assert container_id_in(text) is None


def test_local_batch_records_host_and_no_node(tmp_path):
    out = tmp_path / "out"
    assert run(six_plan(tmp_path), out).ok
    records = latest_records(out)
    assert len(records) == 6
    assert {r["host"] for r in records.values()} == {socket.gethostname()}
    assert all(r["node"] is None for r in records.values())  # no Ray here
    nodes = throughput(list(records.values()))
    [(label, t)] = nodes.items()
    assert label == node_label(next(iter(records.values())))
    assert t["episodes"] == 6
    assert t["sim_s"] == pytest.approx(sum(r["duration_s"] for r in records.values()))


def test_throughput_per_node_from_records():
    def rec(host, node, end, wall, duration=10.0, status="done"):
        return {"host": host, "node": node, "container": None, "time_unix": end, "wall_time_s": wall,
                "duration_s": duration, "status": status}

    records = [rec("a", "n1" * 10, 100.0, 20.0), rec("a", "n1" * 10, 110.0, 20.0),  # two workers: 90..110
               rec("b", "n2" * 10, 50.0, 10.0), rec("b", "n2" * 10, 60.0, 10.0, status="failed")]
    nodes = throughput(records)
    a, b = nodes["a ray:n1n1n1n1n1n1"], nodes["b ray:n2n2n2n2n2n2"]
    assert (a["episodes"], a["sim_s"], a["busy_s"], a["span_s"]) == (2, 20.0, 40.0, 30.0)
    assert a["sim_per_wall"] == pytest.approx(20.0 / 30.0)
    assert (b["episodes"], b["span_s"], b["sim_per_wall"]) == (1, 10.0, 1.0)  # failed attempts do not count
