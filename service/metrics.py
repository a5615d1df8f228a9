"""A small Prometheus text-format registry: request counts and latency histograms."""

from __future__ import annotations

import threading
from collections import defaultdict

_BUCKETS_S = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0)


class Metrics:
    def __init__(self):
        self._lock = threading.Lock()
        self._requests: dict[tuple, int] = defaultdict(int)
        self._histogram: dict[tuple, list[float]] = {}
        self._counters: dict[str, float] = defaultdict(float)

    def observe(self, method: str, path: str, status: int, seconds: float) -> None:
        with self._lock:
            self._requests[(method, path, status)] += 1
            h = self._histogram.setdefault((method, path), [0.0] * (len(_BUCKETS_S) + 2))
            for i, bound in enumerate(_BUCKETS_S):
                if seconds <= bound:
                    h[i] += 1
            h[-2] += 1
            h[-1] += seconds

    def count(self, name: str, amount: float = 1.0) -> None:
        with self._lock:
            self._counters[name] += amount

    def render(self) -> str:
        lines = ["# TYPE passive_locator_requests_total counter"]
        with self._lock:
            for (method, path, status), n in sorted(self._requests.items()):
                lines.append(f'passive_locator_requests_total{{method="{method}",path="{path}",status="{status}"}} {n}')
            lines.append("# TYPE passive_locator_request_seconds histogram")
            for (method, path), h in sorted(self._histogram.items()):
                labels = f'method="{method}",path="{path}"'
                for bound, n in zip(_BUCKETS_S, h):
                    lines.append(f'passive_locator_request_seconds_bucket{{{labels},le="{bound}"}} {n:.0f}')
                lines.append(f'passive_locator_request_seconds_bucket{{{labels},le="+Inf"}} {h[-2]:.0f}')
                lines.append(f"passive_locator_request_seconds_count{{{labels}}} {h[-2]:.0f}")
                lines.append(f"passive_locator_request_seconds_sum{{{labels}}} {h[-1]:.6f}")
            for name, value in sorted(self._counters.items()):
                lines.append(f"# TYPE passive_locator_{name} counter")
                lines.append(f"passive_locator_{name} {value:g}")
        return "\n".join(lines) + "\n"
