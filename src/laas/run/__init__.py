"""Live tools: a whole deployment on this machine, its road users as participants, the
demo and the benchmarks."""
