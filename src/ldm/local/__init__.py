"""Brokers on this machine, for tests, demos and benchmarks: `embedded` (amqtt in
process), `brokers` (Mosquitto and the embedded broker as processes), `nats` (a NATS
cluster with MQTT), `pytest_plugin` (fixtures for real brokers on free ports) and
`floodbench` (the fair-intake benchmark)."""

__all__: list[str] = []
