"""The service's side: `provider` (announce, take input by wildcard, reply in batches)
and `standby` (wait until a service's provider is gone, then serve in its place)."""

from ldm.provider.provider import BatchHandler, Handler, Provider, ProviderStats, Request

__all__ = ["BatchHandler", "Handler", "Provider", "ProviderStats", "Request"]
