"""A real multi-node Ray cluster on 127.0.0.1, in a child process, for tests and benchmarks.

``ray.cluster_utils.Cluster`` starts a head and worker nodes (each its own raylet and object
store) on this machine. It runs in a child process, not in the test's: the API server under test
is then a plain Ray driver that connects over TCP, as it does in a deployment, and a node can be
killed on request (``kill_node``) while the test's process stays out of the cluster.

Every process binds to loopback: ``node_ip_address="127.0.0.1"`` for each node, and
``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0`` so that Ray does not rewrite ``127.0.0.1`` to the
machine's interface address (``server.ray_executor.import_ray``).

Protocol on the child's stdin/stdout, one JSON object a line: it prints
``{"address": ..., "nodes": [...]}`` once up; ``kill ID`` removes that worker node at once (no
graceful stop) and answers ``{"killed": ID}``; ``quit`` (or EOF) shuts the cluster down.
"""

from __future__ import annotations

import json
import os
import select
import signal
import subprocess
import sys
import time
from dataclasses import dataclass

START_TIMEOUT_S = 180.0


@dataclass(frozen=True)
class ClusterInfo:
    address: str
    """GCS ``127.0.0.1:port``."""
    nodes: tuple[str, ...]
    """Worker node ids (the head has no CPUs, so sessions run on these)."""


class LocalRayCluster:
    """``with LocalRayCluster(nodes=2, cpus=2) as cluster: cluster.info.address``."""

    def __init__(self, nodes: int = 2, cpus: float = 2.0) -> None:
        self.nodes, self.cpus = nodes, cpus
        self._process: subprocess.Popen | None = None
        self.info: ClusterInfo | None = None

    def __enter__(self) -> "LocalRayCluster":
        env = dict(os.environ, RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER="0")
        self._process = subprocess.Popen(
            [sys.executable, __file__, str(self.nodes), str(self.cpus)], stdin=subprocess.PIPE,
            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, env=env, text=True, start_new_session=True)
        reply = self._read(START_TIMEOUT_S)
        self.info = ClusterInfo(address=reply["address"], nodes=tuple(reply["nodes"]))
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def kill_node(self, node_id: str, timeout_s: float = 60.0) -> None:
        """Remove a worker node at once: its raylet and the workers on it die."""
        self._process.stdin.write(f"kill {node_id}\n")
        self._process.stdin.flush()
        self._read(timeout_s)

    def close(self) -> None:
        process = self._process
        if process is None or process.poll() is not None:
            return
        try:
            process.stdin.write("quit\n")
            process.stdin.flush()
            process.wait(timeout=60)
        except (OSError, subprocess.TimeoutExpired):
            os.killpg(process.pid, signal.SIGKILL)  # its own session: only the cluster's processes
            process.wait(timeout=10)

    def _read(self, timeout_s: float) -> dict:
        deadline = time.monotonic() + timeout_s
        stdout = self._process.stdout
        while time.monotonic() < deadline:
            ready, _, _ = select.select([stdout], [], [], max(0.0, deadline - time.monotonic()))
            if not ready:
                break
            line = stdout.readline()
            if not line:
                raise RuntimeError("the Ray cluster process ended")
            if line.startswith("{"):
                return json.loads(line)
        self.close()
        raise TimeoutError(f"no answer from the Ray cluster process within {timeout_s:.0f} s")


def _serve(nodes: int, cpus: float) -> None:
    from ray.cluster_utils import Cluster

    cluster = Cluster(initialize_head=True, head_node_args={
        "node_ip_address": "127.0.0.1", "num_cpus": 0, "include_dashboard": False})
    workers = {}
    for _ in range(nodes):
        node = cluster.add_node(num_cpus=cpus, node_ip_address="127.0.0.1")
        workers[node.node_id] = node
    print(json.dumps({"address": cluster.address, "nodes": list(workers)}), flush=True)
    for line in sys.stdin:
        command, _, argument = line.strip().partition(" ")
        if command == "kill" and argument in workers:
            cluster.remove_node(workers.pop(argument), allow_graceful=False)
            print(json.dumps({"killed": argument}), flush=True)
        elif command == "quit":
            break
    cluster.shutdown()


if __name__ == "__main__":
    _serve(int(sys.argv[1]), float(sys.argv[2]))
