"""Running the LDM: `metrics` (one HTTP server for /metrics, /healthz and /readyz, for
ldm and laas), `logs` (text or JSON lines), `passwd` (Mosquitto password files),
`process` (a long-running process's operator options, metrics server, broker settings
and stop signal)."""

__all__: list[str] = []
