"""The LDM core, one per cluster: `Core` links a cluster broker to the backbone."""

from ldm.core.core import Core, CoreStats

__all__ = ["Core", "CoreStats"]
