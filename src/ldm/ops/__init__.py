"""Running the LDM: `metrics` (one HTTP server for /metrics, /healthz and /readyz, for
ldm and laas), `logs` (text or JSON lines), `passwd` (Mosquitto password files), `hops`
(when each message passed each point, for `laas bench`), `process` (a long-running
process's operator options, metrics server, broker settings and stop signal)."""

__all__: list[str] = []
