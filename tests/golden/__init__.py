"""Golden fingerprints of the examples: behaviour pinned while the core is refactored."""
