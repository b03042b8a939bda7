"""The live map of a running worker: a web page over HTTP and server-sent events.

    server = DashboardServer(service, provider, port=0)   # laas worker --http 0
    print(server.url)
    ...
    server.stop()

`server` is the HTTP server, `feed` the fan-out of the worker's answered fixes to the
pages (bounded per page, off the dispatch thread), `views` the JSON the page draws (the
map's lanes, answered fixes, common-error areas), and ``static/index.html`` the page
itself, self-contained. The page shows pseudonyms only: the worker knows no identity.
"""

from laas.worker.dashboard.feed import Client, Feed
from laas.worker.dashboard.server import DashboardServer
from laas.worker.dashboard.views import AreaSnapshot, area_views, lanes_geojson, observation_view

__all__ = [
    "AreaSnapshot",
    "Client",
    "DashboardServer",
    "Feed",
    "area_views",
    "lanes_geojson",
    "observation_view",
]
