"""Offline research tools over the engine: simulated scenarios, traces, replay, scores,
evaluation and plots. They drive the same `Engine` as the live worker."""
