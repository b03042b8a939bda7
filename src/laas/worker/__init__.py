"""The worker: the LaaS engine offered as the LDM service `laas`, one process per area.

service     `LaasService` (decode, check, correct, answer), `start_worker`, the
            limits on its input (`WorkerConfig`) and what it did (`WorkerStats`)
regions     the map cut into strips, one regional worker each (``laas-1of2`` ...)
metrics     its Prometheus collector (`watch_worker`)
asyncapi    the AsyncAPI document of its messages
processes   several workers of one map, one process each (`laas worker --processes`)
dashboard   its live map: a web page over HTTP and server-sent events
serve       a worker process's whole life (`serve_worker`): standby, region, metrics,
            live map, stop
"""

from laas.worker.regions import Region, parse_region, split
from laas.worker.serve import ServeOptions, serve_worker
from laas.worker.service import (
    SERVICE_NAME,
    LaasService,
    Observation,
    WorkerConfig,
    WorkerStats,
    service_spec,
    start_worker,
)

__all__ = [
    "SERVICE_NAME",
    "LaasService",
    "Observation",
    "Region",
    "ServeOptions",
    "WorkerConfig",
    "WorkerStats",
    "parse_region",
    "serve_worker",
    "service_spec",
    "split",
    "start_worker",
]
