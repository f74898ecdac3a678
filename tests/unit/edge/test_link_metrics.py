"""The trainer's link metrics: the hub's counters and the edge's outage counters, so an outage at the
edge shows in the run's metrics."""

from infinirl.edge.trainer_link import link_metrics


def test_connected_hub_counters_and_the_edges_outages():
    hub = {"edges": ["edge-0"], "connects": 2, "episodes": 14, "duplicates": 1, "episode_bytes": 5000,
           "weight_bytes": 900, "weight_pushes_full": 1, "weight_pushes_delta": 3, "refusals": 0}
    edge = {"steps": 400, "link_outages": 1, "link_offline_s": 3.5, "link_episodes_spooled_offline": 2,
            "offline_holds": 0, "spool_refused": 0}
    metrics = link_metrics(hub, "edge-0", edge)
    assert metrics["link/connected"] == 1.0 and metrics["link/connects"] == 2.0
    assert metrics["link/episodes"] == 14.0 and metrics["link/duplicates"] == 1.0
    assert metrics["link/weight_pushes_delta"] == 3.0 and metrics["link/refused"] == 0.0  # absent counters read 0
    assert metrics["edge/outages"] == 1.0 and metrics["edge/offline_s"] == 3.5
    assert metrics["edge/episodes_spooled_offline"] == 2.0 and metrics["edge/offline_hold_s"] == 0.0
    assert "edge/steps" not in metrics  # the robot's own counters are logged elsewhere


def test_an_edge_not_connected_now_reads_zero():
    assert link_metrics({"edges": ["edge-1"]}, "edge-0", {})["link/connected"] == 0.0
