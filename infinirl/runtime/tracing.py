"""Spans of every group call, a Chrome/Perfetto trace, and per-device busy ratio (1 - bubble).

Workers record one span per executed method (component, rank, method, start, end, ok). The
``Tracer`` pulls them from groups, writes a trace that chrome://tracing and ui.perfetto.dev open
(one process row per component, one thread row per rank), and computes, for each device, the
fraction of the traced window in which some component was busy on it: the idle remainder is the
pipeline bubble that the execution modes are meant to remove.
"""

from __future__ import annotations

import json
from collections import defaultdict
from collections.abc import Iterable

from infinirl.utils.atomic import atomic_open


class Tracer:
    def __init__(self):
        self.spans: list[tuple] = []
        self.device_of: dict[tuple[str, int], list[str]] = {}

    def collect(self, *groups) -> None:
        for group in groups:
            self.spans.extend(group.pop_spans())
            for ctx in group.contexts:
                node = ctx.node_ip or ctx.node_id or "local"
                if ctx.local_devices:
                    keys = [f"{node}:gpu{d}" for d in ctx.local_devices]
                else:
                    keys = [f"{node}:cpu{s}" for s in (ctx.cpu_slots or (ctx.rank,))]
                self.device_of[(ctx.component, ctx.rank)] = keys

    def add(self, component: str, rank: int, method: str, start: float, end: float, ok: bool = True) -> None:
        self.spans.append((component, rank, method, start, end, ok))

    def write_chrome_trace(self, path: str) -> str:
        """Write the spans as Chrome trace-event JSON, atomically."""
        components = sorted({s[0] for s in self.spans})
        pid_of = {c: i + 1 for i, c in enumerate(components)}
        t0 = min((s[3] for s in self.spans), default=0.0)
        events = [
            {"name": "process_name", "ph": "M", "pid": pid_of[c], "args": {"name": c}} for c in components
        ]
        for component, rank, method, start, end, ok in self.spans:
            events.append(
                {
                    "name": method,
                    "cat": component,
                    "ph": "X",
                    "pid": pid_of[component],
                    "tid": rank,
                    "ts": (start - t0) * 1e6,
                    "dur": max(0.0, end - start) * 1e6,
                    "args": {"ok": ok},
                }
            )
        with atomic_open(path, "w") as handle:
            json.dump({"traceEvents": events, "displayTimeUnit": "ms"}, handle)
        return path

    def busy_ratio(self, window: tuple[float, float] | None = None) -> dict[str, float]:
        """Per device: union of busy intervals / window length (1.0 = never idle)."""
        if not self.spans:
            return {}
        start = min(s[3] for s in self.spans) if window is None else window[0]
        end = max(s[4] for s in self.spans) if window is None else window[1]
        per_device: dict[str, list[tuple[float, float]]] = defaultdict(list)
        for component, rank, _, s, e, _ in self.spans:
            for device in self.device_of.get((component, rank), [f"{component}:{rank}"]):
                per_device[device].append((max(s, start), min(e, end)))
        length = max(end - start, 1e-12)
        return {device: union_length(iv) / length for device, iv in per_device.items()}


def union_length(intervals: Iterable[tuple[float, float]]) -> float:
    total, cur_start, cur_end = 0.0, None, None
    for s, e in sorted(i for i in intervals if i[1] > i[0]):
        if cur_end is None or s > cur_end:
            if cur_end is not None:
                total += cur_end - cur_start
            cur_start, cur_end = s, e
        else:
            cur_end = max(cur_end, e)
    if cur_end is not None:
        total += cur_end - cur_start
    return total
