"""Brokers on this machine, for tests, demos and benchmarks: `embedded` (amqtt in
process), `brokers` (Mosquitto and the embedded broker as processes), `nats` (a NATS
cluster with MQTT), `pytest_plugin` (fixtures for real brokers on free ports) and
the benchmarks `ldm bench` runs: `floodbench` (others' latency under a flood) and
`corebench` (the LDM's own cost)."""

__all__: list[str] = []
