"""Run as a script: a 3-node Ray cluster on one machine; placement pins ranks to the right nodes."""

import json
import sys

import ray
from ray.cluster_utils import Cluster as RayTestCluster

from infinirl.runtime import Cluster, Worker, WorkerGroup, place


class WhereAmI(Worker):
    def node(self):
        return ray.get_runtime_context().get_node_id()


def main():
    fake = RayTestCluster(initialize_head=True, head_node_args={"num_cpus": 1})
    fake.add_node(num_cpus=2)
    fake.add_node(num_cpus=2)
    cluster = Cluster(address=fake.address, wait_for_nodes=3, log_to_driver=False,
                      robot_plugins={"simulated": {"count": 1, "kind": "arm"}}).start()
    inv = cluster.inventory
    plan = place(inv, {"actor": "node:1:0-1", "env": "node:2", "robot": "robot:2"})
    groups = {name: WorkerGroup.launch(WhereAmI, name, placement=plan.ranks(name))
              for name in ("actor", "env", "robot")}
    out = {
        "num_nodes": inv.num_nodes,
        "cpus": [n.num_cpus for n in inv.nodes],
        "robots": inv.num_robots,
        "expected": {name: [p.node_id for p in plan.ranks(name)] for name in groups},
        "actual": {name: g.node().wait(timeout=120) for name, g in groups.items()},
    }
    for g in groups.values():
        g.shutdown()
    cluster.shutdown()
    fake.shutdown()
    print("RESULT " + json.dumps(out))


if __name__ == "__main__":
    sys.exit(main())
