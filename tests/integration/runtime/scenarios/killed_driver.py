"""Run as a script: join the running cluster at argv[1], launch a group, print its crash logs and
rank pids, then wait to be killed (SIGKILL: no shutdown, no cleanup of any kind)."""

import json
import sys
import time

from infinirl.runtime import Cluster, Worker, WorkerGroup


class Idle(Worker):
    pass


def main():
    Cluster(address=sys.argv[1], log_to_driver=False).start()
    group = WorkerGroup.launch(Idle, "orphaned", num_ranks=2)
    result = {"logs": [info["crash_log"] for info in group.rank_info], "pids": group.pids()}
    print("RESULT " + json.dumps(result), flush=True)
    time.sleep(600)


if __name__ == "__main__":
    main()
