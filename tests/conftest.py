"""Shared pytest configuration: a report header with the versions that matter, and a last
line that counts the Mosquitto tests skipped because Mosquitto is not installed."""

from __future__ import annotations

import numpy
import pyproj
import pytest
import shapely

_mosquitto_skipped: set[str] = set()
_NO_MOSQUITTO = "mosquitto is not installed"  # the reason `need_mosquitto` skips with


def pytest_report_header() -> list[str]:
    return [
        f"numpy {numpy.__version__}, shapely {shapely.__version__} "
        f"(GEOS {shapely.geos_version_string}), "
        f"pyproj {pyproj.__version__} (PROJ {pyproj.proj_version_str})"
    ]


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    """Count a test skipped for want of Mosquitto, marked `mosquitto` or not (a test may
    call `need_mosquitto` itself); the reason is the third item of a skip's report."""
    longrepr = report.longrepr
    if report.skipped and isinstance(longrepr, tuple) and _NO_MOSQUITTO in str(longrepr[2]):
        _mosquitto_skipped.add(report.nodeid)


def pytest_unconfigure(config: pytest.Config) -> None:
    """After pytest's own final line: how many tests need Mosquitto, and how to run them."""
    reporter = config.pluginmanager.get_plugin("terminalreporter")
    count = len(_mosquitto_skipped)
    if reporter is not None and count:
        tests = "test" if count == 1 else "tests"
        reporter.write_line(
            f"{count} {tests} skipped: Mosquitto is not installed; run "
            "`apt-get install -y mosquitto mosquitto-clients` and then `bash scripts/test` "
            "to run them",
            yellow=True,
        )


@pytest.fixture(scope="session")
def hamburg_map():  # -> HdMap (imported here, so this stays an append to the file)
    """The bundled Hamburg map (`maps/messe-hamburg.geojson`), loaded once per session;
    found by `bundled_map`, so it does not depend on the current directory."""
    from laas.map.bundled import bundled_map
    from laas.map.geojson import read_geojson_file

    return read_geojson_file(bundled_map("messe-hamburg"))


@pytest.fixture(scope="session")
def ci_suite(tmp_path_factory: pytest.TempPathFactory):  # -> tests.ci_suite.CiSuite
    """The `ci` suite, answered once per test run (tests/test_accuracy.py scores it,
    tests/test_same_answers.py takes its recorded cases' batched answers from it), also
    when pytest-xdist runs the two files in different processes: they share the run's
    temporary directory (a worker's is a directory in it)."""
    import os

    from tests.ci_suite import ci_suite

    base = tmp_path_factory.getbasetemp()
    shared = base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base
    return ci_suite(shared / "ci-suite.pickle")
