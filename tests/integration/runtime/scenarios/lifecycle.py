"""Run as a script: start a local cluster, run a group, shut down; print the pids to check later."""

import json

import psutil

from infinirl.runtime import Cluster, Worker, WorkerGroup


class Pid(Worker):
    def pid(self):
        import os

        return os.getpid()


def main():
    cluster = Cluster(num_cpus=2, log_to_driver=False).start()
    group = WorkerGroup.launch(Pid, "p", num_ranks=2)
    worker_pids = group.pid().wait()
    me = psutil.Process()
    ray_pids = [p.pid for p in me.children(recursive=True)]
    group.shutdown()
    cluster.shutdown()
    print("RESULT " + json.dumps({"workers": worker_pids, "ray": ray_pids}))


if __name__ == "__main__":
    main()
