"""The paper's deployment (its Fig. 1) on one machine, for the demo, tests and the bench.

    participants -> user broker <- user core -> inter-cluster broker <- service core
                                                                  service broker <- laas worker

Three brokers (Mosquitto processes when `mosquitto` is installed, else the embedded
broker), two LDM cores and the worker, each with its own MQTT connections.
"""

from __future__ import annotations

from types import TracebackType
from typing import Literal

from laas.config import EngineConfig
from laas.map.hdmap import HdMap
from laas.service import LaasService, start_worker
from ldm import Core, Provider
from ldm.brokers import BrokerKind, RunningBroker, find_mosquitto, start_broker

__all__ = ["BrokerChoice", "LocalDeployment"]

BrokerChoice = Literal["auto", "embedded", "embedded-process", "mosquitto"]


class LocalDeployment:
    """Start with `with LocalDeployment(hdmap) as d:`; participants connect to `d.user_url`."""

    def __init__(
        self,
        hdmap: HdMap,
        config: EngineConfig | None = None,
        *,
        brokers: BrokerChoice = "auto",
        rotation_period: float = 120.0,
        data_qos: int = 0,
    ) -> None:
        self.hdmap = hdmap
        self.config = config
        self.kind: BrokerKind = (
            ("mosquitto" if find_mosquitto() else "embedded") if brokers == "auto" else brokers
        )
        self.rotation_period = rotation_period
        self.data_qos = data_qos
        self.brokers: dict[str, RunningBroker] = {}
        self.cores: dict[str, Core] = {}
        self.provider: Provider | None = None
        self.service: LaasService | None = None

    @property
    def user_url(self) -> str:
        return self.brokers["user"].url

    def start(self) -> LocalDeployment:
        try:
            for name in ("user", "backbone", "service"):
                self.brokers[name] = start_broker(self.kind)
            backbone = self.brokers["backbone"].url
            for name in ("user", "service"):
                self.cores[name] = Core.create(
                    name,
                    self.brokers[name].url,
                    backbone,
                    rotation_period=self.rotation_period,
                    data_qos=self.data_qos,
                ).start()
            self.provider, self.service = start_worker(
                self.brokers["service"].url, self.hdmap, self.config
            )
        except BaseException:
            self.stop()
            raise
        return self

    def stop(self) -> None:
        if self.provider is not None:
            self.provider.stop()
            self.provider = None
        for core in self.cores.values():
            core.stop()
        self.cores.clear()
        for broker in self.brokers.values():
            broker.stop()
        self.brokers.clear()

    def __enter__(self) -> LocalDeployment:
        return self.start()

    def __exit__(
        self,
        _type: type[BaseException] | None,
        _value: BaseException | None,
        _tb: TracebackType | None,
    ) -> None:
        self.stop()
