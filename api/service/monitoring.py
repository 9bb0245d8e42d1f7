"""``GET /metrics``: service figures in the Prometheus text exposition format (version 0.0.4)."""

from __future__ import annotations

from slamreplay.api.service.store import JOB_STATUSES, Store

CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"
DURATION_BUCKETS_S = (0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0, 300.0, 900.0, 3600.0)


def prometheus_text(store: Store, workers: int) -> str:
    """Jobs by status, queue length, workers, recordings, and a histogram of job durations by final status."""
    counts = store.count_by_status()
    lines = ["# HELP slamreplay_jobs Jobs in the store, by status.", "# TYPE slamreplay_jobs gauge"]
    lines += [f'slamreplay_jobs{{status="{s}"}} {counts[s]}' for s in JOB_STATUSES]
    lines += ["# HELP slamreplay_queue_length Jobs waiting for a worker.", "# TYPE slamreplay_queue_length gauge",
              f"slamreplay_queue_length {counts['queued']}",
              "# HELP slamreplay_workers Jobs that can run at once.", "# TYPE slamreplay_workers gauge",
              f"slamreplay_workers {workers}",
              "# HELP slamreplay_recordings Stored recordings.", "# TYPE slamreplay_recordings gauge",
              f"slamreplay_recordings {store.count_recordings()}",
              "# HELP slamreplay_job_duration_seconds Wall time of ended jobs, from start to end, by final status.",
              "# TYPE slamreplay_job_duration_seconds histogram"]
    by_status: dict[str, list[float]] = {}
    for status, seconds in store.durations():
        by_status.setdefault(status, []).append(seconds)
    for status, values in sorted(by_status.items()):
        for le in DURATION_BUCKETS_S:
            lines.append(f'slamreplay_job_duration_seconds_bucket{{status="{status}",le="{le:g}"}} '
                         f"{sum(v <= le for v in values)}")
        lines.append(f'slamreplay_job_duration_seconds_bucket{{status="{status}",le="+Inf"}} {len(values)}')
        lines.append(f'slamreplay_job_duration_seconds_sum{{status="{status}"}} {sum(values):.6f}')
        lines.append(f'slamreplay_job_duration_seconds_count{{status="{status}"}} {len(values)}')
    return "\n".join(lines) + "\n"
