"""The Local Dynamic Map (LDM): a generic service architecture over MQTT.

Clusters (a broker and a core each), joined by an inter-cluster broker; retained
service lists for discovery; rotating pseudonyms and end-to-end encryption between
participants and services. The LDM knows nothing about positioning.
"""

__all__: list[str] = []
