"""Bridges: devices that speak their own formats take part in LaaS as LDM participants.

Each bridge runs in the user cluster and turns every device it serves into its own
`ldm.Participant` (`DevicePool`): OwnTracks phones (`owntracks`), GNSS receivers through
gpsd or NMEA (`gpsd`, `nmea`) and ETSI CAM stations in its-client JSON (`cam`).
docs/bridges.md describes the mappings.
"""

from laas.bridges.pool import DevicePool, LogLimiter, Malformed, PoolConfig, PoolStats, device_name

__all__ = ["DevicePool", "LogLimiter", "Malformed", "PoolConfig", "PoolStats", "device_name"]
