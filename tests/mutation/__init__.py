"""Mutation testing of the safety rules (``make mutate``): hand-listed single-point mutants."""
