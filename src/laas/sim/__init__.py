"""Offline traces for the engine: simulated scenarios (plan, kinematics, simulate,
builtin, scenario, family, roam), trace files (trace, truth, foreign), and replay, which
answers a trace in batches as the live worker takes them (batches). Judging the answers
is `laas.evaluation`'s; nothing here imports it."""
