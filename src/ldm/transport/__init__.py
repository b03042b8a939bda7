"""The MQTT transport: paho-mqtt lives here and nowhere else.

- `mqtt`: `Transport` (one reconnecting connection, fail-over across a cluster's
  addresses), `ClientLoop` (many connections on one thread), and the LDM's own
  `Message`/`Connected` events, converted from paho's at one place;
- `dispatch`: the thread hand-off, a `Dispatcher` whose thread takes everything that
  waited;
- `intake`: `FairQueue`, per-sender FIFOs served round-robin;
- `hops`: `Hops`, when each message passed each point of the LDM (`laas bench`).
"""

from ldm.transport.mqtt import ClientLoop, Connected, Event, Message, Transport, Will

__all__ = ["ClientLoop", "Connected", "Event", "Message", "Transport", "Will"]
