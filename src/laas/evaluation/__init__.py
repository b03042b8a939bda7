"""Judging the engine's answers to offline traces: score, integrity, evaluate, suite,
regional (one worker against N), plots, and the attacks (liar; linker and privacy, on
pseudonyms). The traces come from `laas.sim`, and the answers from the same `Engine` as
the live worker's."""
