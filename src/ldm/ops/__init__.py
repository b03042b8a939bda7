"""Running the LDM: `metrics` (one HTTP server for /metrics, /healthz and /readyz, for
ldm and laas), `logs` (text or JSON lines), `passwd` (Mosquitto password files), `hops`
(when each message passed each point, for `laas bench`)."""

__all__: list[str] = []
