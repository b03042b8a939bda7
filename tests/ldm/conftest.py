"""Fixtures for the LDM tests: real brokers (embedded amqtt and Mosquitto), no mocks."""

from __future__ import annotations

from ldm.local.pytest_plugin import broker_factory, broker_kind, mqtt_broker

__all__ = ["broker_factory", "broker_kind", "mqtt_broker"]
