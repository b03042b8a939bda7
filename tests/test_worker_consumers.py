"""The worker's work beyond the engine is paid only when someone consumes it: the live
map's views and events only with a page connected, area notes only with a neighbour."""

from __future__ import annotations

import time

from laas.map.hdmap import HdMap
from laas.models import GpsMeasurement
from laas.worker.dashboard.feed import Feed
from laas.worker.regions import split
from laas.worker.service import LaasService, Observation
from ldm.provider.provider import Request
from tests.operations import hamburg_fixes


def _request(m: GpsMeasurement, k: int) -> Request:
    return Request("p1", f"c{k}", m.model_dump(mode="json"), time.time(), k == 0)


def test_the_feed_makes_no_events_for_nobody_and_shows_a_new_page_all_it_kept(
    hamburg_map: HdMap,
) -> None:
    service = LaasService(hamburg_map)
    feed = Feed(service)  # not started: its thread's work is called here, in order
    fixes = hamburg_fixes(hamburg_map, 3)
    answers = service.engine.process_many([("p1", m) for m in fixes])
    seen = [Observation("p1", m, a) for m, a in zip(fixes, answers, strict=True) if a]
    published: list[bytes] = []
    feed._publish = published.append  # type: ignore[method-assign, assignment]
    feed._batch(time.time(), seen, 0.001, [])
    assert published == []  # no page: no views, no events
    client = feed.subscribe()
    hello = client.next(0.1)
    assert hello is not None and b'"pseudonym":"p1"' in hello
    feed._batch(time.time(), seen[-1:], 0.001, None)
    assert len(published) == 1 and published[0].startswith(b"event: batch")


def test_a_region_of_one_sends_no_area_notes(hamburg_map: HdMap) -> None:
    sent: list[bytes] = []
    for regions, expected in ((split(hamburg_map, 1), 0), (split(hamburg_map, 2), 1)):
        sent.clear()
        service = LaasService(hamburg_map, region=regions[0])
        service.notes = sent.append
        fixes = hamburg_fixes(hamburg_map, 5)
        service.handle_many([_request(m, k) for k, m in enumerate(fixes)])
        assert len(sent) == expected, (len(regions), len(sent))


def test_the_feed_thread_is_woken_for_a_batch_only_with_a_page_connected(
    hamburg_map: HdMap,
) -> None:
    service = LaasService(hamburg_map)
    feed = Feed(service)  # not started: only the dispatch thread's side is called
    fixes = hamburg_fixes(hamburg_map, 2)
    answers = service.engine.process_many([("p1", m) for m in fixes])
    seen = [Observation("p1", m, a) for m, a in zip(fixes, answers, strict=True) if a]
    feed.observe(seen)
    assert not feed._wake.is_set()  # nobody watches: taken at the next stats tick
    feed.subscribe()
    feed.observe(seen)
    assert feed._wake.is_set()
