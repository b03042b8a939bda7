"""The LDM core, one per cluster: `Core` links a cluster broker to the backbone.

core        Core: lifecycle, the dispatch thread's work, the participants' boundary
admission   Admission: participant messages charged to their budgets on paho's threads
budgets     the token buckets a participant's messages are charged to
sessions    Sessions: grants, pseudonyms, rotation, expiry
services    Catalog: the services of every cluster and the signed service list
notices     Notices: signed notices to participants, refusals within their budget
routing     Router: ciphertext between clusters and back, batched per destination
state       the records those objects hold
stats       CoreStats: every message ends in one counter
"""

from ldm.core.core import Core
from ldm.core.stats import CoreStats

__all__ = ["Core", "CoreStats"]
