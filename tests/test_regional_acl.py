"""`laas worker --processes 2` behind the shipped service-cluster ACL on Mosquitto: its
two regional workers (laas-1of2, laas-2of2) are announced, and a car that drives from
one region into the other is answered by them throughout."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from laas.bridges.pool import Answer, DevicePool, PoolConfig
from laas.map.bundled import bundled_map
from laas.map.hdmap import HdMap
from laas.models import CorrectedPosition
from laas.sim.scenario import ErrorModel, hamburg_scenario, simulate
from laas.worker.regions import split
from ldm import Core, Participant
from ldm.config import BrokerSettings
from ldm.local.brokers import MosquittoBroker, wait_for
from ldm.local.pytest_plugin import need_mosquitto
from tests.ldm.deployment import has_service

ROOT = Path(__file__).resolve().parent.parent
SECURITY = ROOT / "deploy" / "security"
CORE = {"rotation_period": 60.0, "grace": 1.0, "idle_timeout": 3.0, "service_ttl": 3.0}
LIMITS = {"rate": 1000.0, "burst": 200}  # the car sends its 101 fixes at once


@pytest.mark.mosquitto
@pytest.mark.timeout(180)
def test_two_worker_processes_are_announced_and_answer_on_the_shipped_acl(
    hamburg_map: HdMap,
) -> None:
    need_mosquitto()
    acl = (SECURITY / "acl-user-cluster").read_text()
    acl += (SECURITY / "acl-service-cluster").read_text()
    broker = MosquittoBroker(allow_anonymous=False, acl=acl)
    passwd = broker.directory / "passwd"
    passwords = {"ldm-core-user": "core-pw", "laas-worker": "worker-pw", "car": "car-pw"}
    subprocess.run(
        ["bash", str(SECURITY / "make-passwd.sh"), str(passwd), "-"],
        input="".join(f"{u}={p}\n" for u, p in passwords.items()),
        check=True,
        capture_output=True,
        text=True,
        env={"PATH": f"{Path(sys.executable).parent}:/usr/bin:/bin", "MODE": "0644"},
    )
    # one broker for both clusters; no use_username_as_clientid, as on broker-service:
    # the two worker processes share the account laas-worker
    broker.config_file.write_text(broker.config_file.read_text() + f"password_file {passwd}\n")
    trace = simulate(hamburg_map, hamburg_scenario(), ErrorModel(), 0)
    car = [f.measurement for f in trace.fixes if f.user == "car"]
    first, second = split(hamburg_map, 2)
    border = (max(y for _, y in first.coverage) + min(y for _, y in second.coverage)) / 2
    latitudes = [f.latitude for f in car]
    assert min(latitudes) < border < max(latitudes), "the car must cross between the regions"
    shift = int(time.time() * 1000) - 20_000 - car[0].timestamp
    fixes = [f.model_copy(update={"timestamp": f.timestamp + shift}) for f in car]

    def account(user: str) -> BrokerSettings:
        return BrokerSettings(url=broker.url, username=user, password=passwords[user])

    with broker:
        core = Core.create("single", account("ldm-core-user"), None, **CORE, **LIMITS).start(
            timeout=5
        )
        workers = subprocess.Popen(
            [sys.executable, "-m", "laas.cli", "worker", "--processes", "2",
             "--cluster", broker.url, "--username", "laas-worker",
             "--map", str(bundled_map("messe-hamburg")), "--max-speedup", "100"],
            env={**os.environ, "LAAS_PASSWORD": passwords["laas-worker"]},
            stdout=subprocess.DEVNULL,
        )  # fmt: skip
        try:
            with Participant.create(account("car"), client_id="car") as probe:
                listed = wait_for(
                    lambda: all(has_service(probe, n)() for n in ("laas-1of2", "laas-2of2")), 30
                )
            assert listed, "the regional workers were not announced through the ACL"
            answers: list[Answer] = []
            done = threading.Event()

            def on_answer(answer: Answer) -> None:
                answers.append(answer)
                if len(answers) == len(fixes):
                    done.set()

            pool = DevicePool(
                PoolConfig(cluster=account("car"), device_accounts=True, core_key=core.public_key)
            )
            with pool:
                for fix in fixes:
                    pool.submit("car", fix, on_answer)
                assert done.wait(60), (len(answers), pool.stats)
        finally:
            workers.terminate()
            workers.communicate(timeout=30)
            core.stop()
    assert all(isinstance(a, CorrectedPosition) for a in answers), [
        a for a in answers if not isinstance(a, CorrectedPosition)
    ][:3]
